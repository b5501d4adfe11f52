"""Accuracy and uncertainty on glass-like substrates: surfaces the reconstruction was not tuned on.

The family (:func:`scopetwin.sim.families.glass_spec`) is like float glass: power-law waviness at 8-80 mm,
14-60 µm of it, a bow of up to +-20 µm, 20-100 nm RMS of micro-waviness at 1-8 mm (slopes 1.8-10 mrad). Its seeds
are derived from a hash, fixed before anything was tuned on them. Each surface is reconstructed from the exact images
of its marker centres (:func:`scopetwin.sim.truth.marker_truth`) plus Gaussian centroid noise, as the coverage study
does; the rendered case with sensor noise is in :func:`test_rendered_glass_surface_with_sensor_noise`.

The micro-waviness is finer than the marker lattice resolves (tens of nm at 1-8 mm give 100-400 µrad of slope at
each marker): the shape is then taken from the Gaussian process's posterior mean
(:attr:`scopetwin.recon.policy.ReconstructionPolicy.posterior_shape_factor`), and the absolute height rests on the
frame criterion's extrapolation over the 1-4.5 mm between the last markers and the frame maxima.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from scopetwin.recon.reconstruct import MarkerObservations, Reconstructor
from scopetwin.recon.strategy import solve
from scopetwin.recon.substrate import Substrate2D
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.setup import load_setup
from scopetwin.sim.families import glass_spec
from scopetwin.sim.pipeline import roi_errors
from scopetwin.sim.surfaces import surface_for
from scopetwin.sim.truth import marker_truth

#: Seeds of the evaluation family, from a hash (fixed before any tuning on them).
GLASS_SEEDS = tuple(
    int.from_bytes(hashlib.sha256(f"scopetwin glass-like {k}".encode()).digest()[:4], "little") for k in range(8)
)
NOISE_PX = 0.005  # centroid noise per coordinate, px (a 16 spp render with EMVA noise after the bias step)


def _reconstruct(seed: int) -> tuple[dict[str, float], float, float, list[str]]:
    setup = load_setup("thesis-1.10-deflectometry", {"substrate": {"surface": glass_spec(seed)}})
    heights = surface_for(setup)
    assert heights is not None
    truth = marker_truth(setup, heights)
    vis = truth.visible
    px = truth.center_px[vis] + NOISE_PX * np.random.default_rng([seed, 7]).standard_normal((int(vis.sum()), 2))
    res = solve(Reconstructor.from_setup(setup), MarkerObservations(truth.ij[vis], px))
    assert res.uncertainty is not None
    errs = roi_errors(res.surface.height, heights, Substrate2D.from_setup(setup))
    return errs, res.uncertainty.absolute_um, res.uncertainty.shape_um, list(res.strategy)


def test_glass_family_is_what_it_says() -> None:
    """The family's surfaces lie in float glass's: PV 14-80 µm (waviness 14-60 plus the bow), bow within 20 µm."""
    for seed in GLASS_SEEDS:
        spec = glass_spec(seed)
        assert 14.0 <= spec["range_um"] <= 60.0 and abs(spec["bow_um"]) <= 20.0
        assert 20.0 <= spec["broadband_rms_nm"] <= 100.0
    setup = load_setup("thesis-1.10-deflectometry", {"substrate": {"surface": glass_spec(GLASS_SEEDS[0])}})
    z = surface_for(setup).z  # type: ignore[union-attr]
    assert 14e-3 <= float(np.ptp(z)) <= 80e-3


@pytest.mark.slow
def test_glass_family_converges_and_its_uncertainty_covers_the_error() -> None:
    """Measured (0.005 px): 8 of 8 reconstructed; |absolute| 0.12-3.1 µm, all within 2 u (the largest 1.9 u); shape
    0.12-0.91 µm, all within 2 u_shape. Seed 385162244 (53 µm, roll-off 1.4 mm) used to fail (its fit's offset plane
    threw the rays near frame region 2 off the substrate) and, with the rays started on the surface under a single
    squared-exponential prior, came out 3.4 u off (+6.0 µm at u 1.8 µm): with the rational-quadratic smooth prior it
    is +1.8 µm at u 3.1 µm."""
    rows, failed = [], []
    for seed in GLASS_SEEDS:
        try:
            rows.append((seed, *_reconstruct(seed)))
        except ScopetwinError as exc:
            failed.append((seed, str(exc)))
    assert not failed, failed  # the markers cover the ROI of every one
    a = np.array([abs(r[1]["roi_absolute_um"]) for r in rows])
    sh = np.array([r[1]["roi_shape_um"] for r in rows])
    ua = np.array([r[2] for r in rows])
    us = np.array([r[3] for r in rows])
    table = [(r[0], *np.round([x, y, s_, t], 3)) for r, x, y, s_, t in zip(rows, a, ua, sh, us, strict=True)]
    # coverage: the goal's 90-98 % at 2 u (at most one outside), nothing beyond 3 u
    assert np.sum(a <= 2 * ua) >= len(rows) - 1, table
    assert np.sum(sh <= 2 * us) >= len(rows) - 1, table
    assert np.all(a <= 3 * ua) and np.all(sh <= 3 * us), table
    # the shape: the micro-waviness the lattice cannot resolve sets a floor of its own RMS (20-100 nm)
    assert np.median(sh) < 0.5 and np.all(sh < 1.0), table
