"""``--refine-setup`` on a full image: a setup with calibration errors, reconstructed with and without refining it.

The §1.10 measurement (a §1.9 surface, EMVA 1288 sensor noise) is rendered with Mitsuba under the true setup; the
reconstruction is given a setup whose camera and pattern poses are off by errors of a calibration's size (camera
~25 µm / ~70 µrad, pattern ~40 µm / ~70 µrad), carrying those sizes as its ``[calibration]`` uncertainties (as a
setup from ``calibrate-setup`` does). Printed: the shape and absolute errors of the centroid method, of inverse
rendering with the setup as given, and with ``--refine-setup`` (camera and pattern pose fitted too, held near the
setup by the uncertainties); and how far the refined poses moved toward the truth.

Run: ``.venv/bin/python benchmarks/refine_setup.py [--corr 12] [--range 40] [--seed 2] [--spp 16]`` (~5 min on 2
cores).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

#: Pose errors given to the setup: camera shift (mm), rotation vector (rad); pattern shift, rotation vector.
ERRORS = (
    np.array([0.02, -0.015, 0.01]),
    np.array([5e-5, -3e-5, 4e-5]),
    np.array([0.03, 0.02, -0.02]),
    np.array([-4e-5, 5e-5, 2e-5]),
)


def wrong_setup(setup, errors):
    """The setup with its camera and pattern moved by ``errors``, with their sizes as [calibration]."""
    from scopetwin.calib.setup_calibration import set_poses
    from scopetwin.recon.inverse import _pose_update
    from scopetwin.scenes.setup import setup_from_dict

    cam, pat = _pose_update(setup.camera_model, setup.marker_pattern, np.concatenate(errors))
    data = setup.model_dump(exclude_none=True)
    set_poses(data, cam, pat.frame)
    norms = [float(np.linalg.norm(e)) for e in errors]
    data["calibration"] = {
        "camera": {"shift_mm": norms[0], "rotation_rad": norms[1]},
        "pattern": {"shift_mm": norms[2], "rotation_rad": norms[3]},
    }
    return setup_from_dict(data, "setup with calibration errors")


def pose_errors(setup, camera, pattern):
    """|shift| (mm) and |rotation| (rad) of camera and pattern against the setup's."""
    from scipy.spatial.transform import Rotation

    def rot(a, b):
        ma = np.stack([a.tx, a.ty, a.nz], axis=1)
        mb = np.stack([b.tx, b.ty, b.nz], axis=1)
        return float(np.linalg.norm(Rotation.from_matrix(ma @ mb.T).as_rotvec()))

    c0, p0 = setup.camera_model.frame, setup.marker_pattern.frame
    c1, p1 = camera.frame, pattern.frame
    return (
        float(np.linalg.norm(c1.origin - c0.origin)),
        rot(c1, c0),
        float(np.linalg.norm(p1.origin - p0.origin)),
        rot(p1, p0),
    )


def pose_text(e):
    """The four pose errors as text."""
    return f"camera {e[0]:.4f} mm / {e[1] * 1e6:.1f} µrad, pattern {e[2]:.4f} mm / {e[3] * 1e6:.1f} µrad"


def main() -> None:
    from scopetwin.recon.inverse import InverseConfig, InverseReconstructor, pose_sigma_for
    from scopetwin.recon.markers import find_markers_for
    from scopetwin.recon.reconstruct import MarkerObservations, Reconstructor, centroid_bias_step
    from scopetwin.recon.strategy import solve
    from scopetwin.recon.substrate import Substrate2D
    from scopetwin.scenes.setup import load_setup
    from scopetwin.sim.measurement import apply_sensor, render_measurement
    from scopetwin.sim.pipeline import roi_errors
    from scopetwin.sim.studies.tasks import THESIS_DEFLECTOMETRY, quiet
    from scopetwin.sim.surfaces import surface_for

    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--corr", type=float, default=12.0)
    ap.add_argument("--range", type=float, default=40.0)
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--spp", type=int, default=16)
    args = ap.parse_args()
    quiet()
    over = {
        "substrate": {
            "surface": {"kind": "random", "correlation_length": args.corr, "range_um": args.range, "seed": args.seed}
        }
    }
    truth_setup = load_setup(THESIS_DEFLECTOMETRY, over)
    truth = surface_for(truth_setup)
    t0 = time.perf_counter()
    clean, _ = render_measurement(truth_setup, truth, args.spp, 1, False)
    image = apply_sensor(truth_setup, clean, 1)
    print(f"render {time.perf_counter() - t0:.0f} s")
    setup = wrong_setup(truth_setup, ERRORS)
    sub = Substrate2D.from_setup(setup)
    before = pose_errors(truth_setup, setup.camera_model, setup.marker_pattern)
    print(f"pose errors given: {pose_text(before)}")
    found = find_markers_for(image, setup)
    t0 = time.perf_counter()
    centroid = solve(
        Reconstructor.from_setup(setup, None, centroid_bias_step(setup)), MarkerObservations(found.ij, found.centroids)
    )
    e = roi_errors(centroid.surface.height, truth, sub)
    print(
        f"centroid method, setup as given: shape {e['roi_shape_um']:.4f} µm, absolute {e['roi_absolute_um']:+.4f} µm"
        f" ({time.perf_counter() - t0:.0f} s)"
    )
    for refine in (False, True):
        cfg = InverseConfig(refine_setup=refine, pose_sigma=pose_sigma_for(setup))
        out = InverseReconstructor(setup, image, cfg).run(centroid.surface)
        e = roi_errors(out.surface.height, truth, sub)
        label = "inverse, --refine-setup     " if refine else "inverse, setup as given     "
        print(
            f"{label}: shape {e['roi_shape_um']:.4f} µm, absolute {e['roi_absolute_um']:+.4f} µm ({out.seconds:.0f} s)"
        )
        if refine:
            after = pose_errors(truth_setup, out.camera, out.pattern)
            print(f"pose errors after refinement: {pose_text(after)}")


if __name__ == "__main__":
    main()
