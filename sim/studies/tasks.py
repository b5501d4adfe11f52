"""Worker tasks shared by the studies: reconstruct a rendered measurement, calibrate a rendered view, compare.

Every task is a module-level function of plain arguments (it runs on a Dask worker) and returns a JSON-ready dict.
"""

from __future__ import annotations

import json
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.geometry import Frame
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap
from scopetwin.sim.datasets.config import merge

THESIS_DEFLECTOMETRY = "thesis-1.10-deflectometry"


def quiet() -> None:
    """Silence warnings in a worker task (the tables report what matters)."""
    warnings.simplefilter("ignore")


def frame_deviation(frame: Frame, truth: Frame) -> dict[str, list[float]]:
    """Differences of origin and axes (ours - truth)."""
    return {
        "r": (frame.origin - truth.origin).tolist(),
        "t_x": (frame.tx - truth.tx).tolist(),
        "t_y": (frame.ty - truth.ty).tolist(),
        "n_z": (frame.nz - truth.nz).tolist(),
    }


def axis_angle(frame: Frame, truth: Frame) -> float:
    """Rotation angle between two frames, rad."""
    r = np.stack([frame.tx, frame.ty, frame.nz]) @ np.stack([truth.tx, truth.ty, truth.nz]).T
    return float(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)))


def measurement_setup(surface_seed: int, spp: int, overrides: dict[str, Any] | None = None) -> Setup:
    """The §1.10 measurement setup with surface seed ``surface_seed`` (render seed 0, ``spp``), plus ``overrides``."""
    from scopetwin.scenes.setup import load_setup

    over = {"substrate": {"surface": {"seed": int(surface_seed)}}, "render": {"spp": spp, "seed": 0}}
    if overrides:
        over = merge(over, overrides)
    return load_setup(THESIS_DEFLECTOMETRY, over)


def reconstruct(
    setup: Setup,
    heights: HeightMap,
    image: NDArray[Any],
    recon_setup: Setup | None = None,
    config: str = "default",
) -> dict[str, Any]:
    """Reconstruct with ``recon_setup`` (default: the same) by the one strategy (markers found with it), compare."""
    from scopetwin.recon.config import ReconstructionConfig
    from scopetwin.recon.strategy import reconstruct
    from scopetwin.recon.substrate import Substrate2D
    from scopetwin.sim.pipeline import roi_errors

    rs = recon_setup or setup
    cfg = None
    if config == "thesis":
        # the thesis's basis (9 x 5 inverse multiquadrics) and criterion (Delta h_max = 0, eq. 1.3), searched by a
        # secant as ``reconstruct --thesis`` does: the thesis's own update (eq. 1.4, H - d_min) has its fixed point
        # where one frame maximum lies on the frame, not at Delta h_max = 0, and stalls (exact markers of surface
        # 1: +0.39 µm after 60 runs; the secant converges in 3)
        cfg = ReconstructionConfig.thesis(literal_axes=False, search="secant")
    elif config.startswith("spacing="):
        cfg = ReconstructionConfig(spacing=float(config.split("=")[1]))
    t0 = time.perf_counter()
    done = reconstruct(image, rs, config=cfg)
    found, res = done.markers, done.result
    errs = roi_errors(res.surface.height, heights, Substrate2D.from_setup(setup))
    return {
        **errs,
        "outer_iterations": res.outer_iterations,
        "inner_iterations": res.inner_iterations,
        "delta_h_max_um": res.delta_h_max_um,
        "markers": int(len(found.ij)),
        "seconds": time.perf_counter() - t0,
    }


CALIB_MODULES = {
    "scopetwin.recon.markers": "marker detection and indexing",
    "scopetwin.recon.bias": "centroid-bias prediction",
    "scopetwin.calib.oneshot": "one-shot camera calibration",
}


def read_sample(folder: str) -> tuple[Any, np.ndarray, dict[str, Any]]:
    """A dataset sample's setup, image and truth."""
    from scopetwin.scenes.io import read_image
    from scopetwin.scenes.setup import setup_from_dict

    p = Path(folder)
    truth = json.loads((p / "truth.json").read_text())
    image, _ = read_image(p / "image.exr")
    return setup_from_dict(truth["setup_json"], str(p)), image, truth


def calibration_view_task(folder: str, fill: float | None = None, noise_seed: int | None = None) -> dict[str, Any]:
    """Centroid and one-shot calibration errors of one calibration-view sample against its truth.

    With ``fill``, the sample is a clean render and this task captures it with the setup's EMVA 1288 sensor
    (:func:`scopetwin.sim.measurement.apply_sensor`) at an exposure that fills ``fill`` of the full well at the peak,
    noise
    seeded by ``noise_seed``: many noise draws of one render (``study noise``) cost no render each. The row's
    ``parameters`` then carry ``exposure_fill`` and ``noise_seed``.
    """
    from scopetwin.calib.oneshot import Prior, calibrate, calibrate_bias_corrected
    from scopetwin.recon.bias import correct_centroids, model_for_setup, spot_bias_model
    from scopetwin.recon.markers import find_markers_for
    from scopetwin.scenes.setup import setup_from_dict
    from scopetwin.sim.measurement import apply_sensor

    quiet()
    setup, image, truth = read_sample(folder)
    params = dict(truth["parameters"])
    try:
        if fill is not None:
            over = {"sensor": {"fill_fraction": float(fill)}}
            setup = setup_from_dict(merge(truth["setup_json"], over), folder)
            image = apply_sensor(setup, image, 0 if noise_seed is None else int(noise_seed))
            params.update(exposure_fill=float(fill), noise_seed=noise_seed)
        found = find_markers_for(image, setup)
    except ScopetwinError as exc:  # e.g. too little light to find the markers: a result, not a crash
        return {"folder": folder, "parameters": params, "error": f"{type(exc).__name__}: {exc}"}
    key = {(m["i"], m["j"]): (m["center_col"], m["center_row"]) for m in truth["markers"]}
    true_px = np.array([key[(int(i), int(j))] for i, j in found.ij], dtype=np.float64)
    corrected, _ = correct_centroids(found.centroids, found.ij, model_for_setup(setup))
    raw_err = np.linalg.norm(found.centroids - true_px, axis=1)
    cor_err = np.linalg.norm(corrected - true_px, axis=1)
    pat = setup.marker_pattern
    xy = pat.centers_local(found.ij)
    prior = Prior.from_camera(setup.camera_model, setup.camera.focal_length, plane=pat.frame)
    cam_t = setup.camera_model
    out = {
        "folder": folder,
        "parameters": params,
        "markers": int(len(found.ij)),
        "raw_rms_px": float(np.sqrt(np.mean(raw_err**2))),
        "raw_max_px": float(raw_err.max()),
        "corrected_rms_px": float(np.sqrt(np.mean(cor_err**2))),
        "corrected_max_px": float(cor_err.max()),
    }
    for label, fn in (
        ("raw", lambda: calibrate(xy, found.centroids, prior)),
        (
            "corrected",
            lambda: calibrate_bias_corrected(xy, found.centroids, prior, spot_bias_model(xy, pat.radii(found.ij)))[0],
        ),
    ):
        try:
            cal = fn()
            cam = cal.to_global(pat.frame)
            out[f"{label}_r_c_um"] = float(np.linalg.norm(cam.center - cam_t.center) * 1e3)
            out[f"{label}_r_c_vec_um"] = ((cam.center - cam_t.center) * 1e3).tolist()
            out[f"{label}_angle_urad"] = axis_angle(cam.frame, cam_t.frame) * 1e6
            out[f"{label}_b_um"] = float((cam.b - cam_t.b) * 1e3)
            out[f"{label}_residual_rms_px"] = cal.residual_rms_px
        except ScopetwinError as exc:
            out[f"{label}_error"] = str(exc)
    return out


def calibration_dataset(
    kind_vary: dict[str, Any], setup: str, count: int, seed: int, noise: bool, spp: int
) -> dict[str, Any]:
    """The config dict of a calibration-view dataset (kind ``calibration``, no previews)."""
    return {
        "dataset": {
            "kind": "calibration",
            "setup": setup,
            "count": count,
            "master_seed": seed,
            "spp": spp,
            "noise": noise,
            "preview": False,
        },
        "vary": kind_vary,
    }


def sample_folders(root: Path) -> list[str]:
    """The finished sample folders of a dataset, in index order."""
    return [str(p) for p in sorted((root / "samples").iterdir()) if p.is_dir() and p.name.isdigit()]
