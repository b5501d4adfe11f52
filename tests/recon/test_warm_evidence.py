"""The posterior's warm start (issue 26): the prior of one frame as the one start of the next frame's evidence
maximisation (:attr:`scopetwin.recon.reconstruct.Reconstructor.evidence_start`).

Truth from elsewhere: two frames of the §1.10 setup's own surface, the exact images of the marker centres
(:func:`scopetwin.sim.truth.marker_truth`) plus independent Gaussian centroid noise; the next frame is reconstructed
cold (two starts) and warm (from the first frame's prior). The warm start must find the same prior within the
evidence's flatness and leave the surface and its uncertainty where the cold start puts them, for a fraction of the
evaluations.
"""

from __future__ import annotations

import numpy as np
import pytest

import scopetwin.recon.posterior as posterior_module
from scopetwin.recon.posterior import Hyper
from scopetwin.recon.reconstruct import MarkerObservations, Reconstructor
from scopetwin.recon.strategy import solve
from scopetwin.recon.substrate import Substrate2D
from scopetwin.scenes.setup import load_setup
from scopetwin.sim.pipeline import roi_errors
from scopetwin.sim.surfaces import surface_for
from scopetwin.sim.truth import marker_truth

NOISE_PX = 0.01  # centroid noise per coordinate, px (a 16 spp render with sensor noise)


def test_hyper_round_trips_through_its_dict() -> None:
    h = Hyper(0.013, 17.0, 6e-7, 0.65, 1.8e-6, 2.2e-7)
    back = Hyper.from_dict(h.as_dict())
    assert np.allclose(
        [back.smooth_amp, back.smooth_len, back.broad_amp, back.broad_len, *back.noise_pair],
        [h.smooth_amp, h.smooth_len, h.broad_amp, h.broad_len, *h.noise_pair],
        rtol=1e-12,
    )


@pytest.fixture(scope="module")
def frames():
    setup = load_setup("thesis-1.10-deflectometry")
    heights = surface_for(setup)
    truth = marker_truth(setup, heights)
    vis = truth.visible
    obs = [
        MarkerObservations(truth.ij[vis], truth.center_px[vis] + NOISE_PX * rng.standard_normal((int(vis.sum()), 2)))
        for rng in (np.random.default_rng([11, k]) for k in (1, 2))
    ]
    return setup, heights, obs


def _solve_counting(setup, obs, start, monkeypatch):
    """A solve of ``obs`` with ``start`` as the evidence's warm start; the result and the evaluations it took."""
    calls = []
    inner = posterior_module._evidence_and_gradient

    def counted(*args):
        calls.append(1)
        return inner(*args)

    monkeypatch.setattr(posterior_module, "_evidence_and_gradient", counted)
    rec = Reconstructor.from_setup(setup)
    rec.evidence_start = start
    res = solve(rec, obs)
    monkeypatch.setattr(posterior_module, "_evidence_and_gradient", inner)
    return res, len(calls)


def test_the_warm_start_finds_the_cold_prior_in_fewer_evaluations(frames, monkeypatch) -> None:
    setup, heights, (first, second) = frames
    sub = Substrate2D.from_setup(setup)
    res1, _ = _solve_counting(setup, first, None, monkeypatch)
    assert res1.uncertainty is not None
    prior = Hyper.from_dict(res1.uncertainty.hyper)
    cold, n_cold = _solve_counting(setup, second, None, monkeypatch)
    warm, n_warm = _solve_counting(setup, second, prior, monkeypatch)
    assert cold.uncertainty is not None and warm.uncertainty is not None
    assert n_warm <= 0.5 * n_cold, (n_warm, n_cold)
    u_cold, u_warm = cold.uncertainty.absolute_um, warm.uncertainty.absolute_um
    assert abs(u_warm - u_cold) <= 0.1 * u_cold, (u_warm, u_cold)
    assert abs(warm.uncertainty.shape_um - cold.uncertainty.shape_um) <= 0.1 * cold.uncertainty.shape_um
    e_cold, e_warm = roi_errors(cold.surface.height, heights, sub), roi_errors(warm.surface.height, heights, sub)
    # the same surface within a fifth of its own standard uncertainty, and the truth within 3 u either way
    assert abs(e_warm["roi_absolute_um"] - e_cold["roi_absolute_um"]) <= 0.2 * u_cold
    assert abs(e_warm["roi_shape_um"] - e_cold["roi_shape_um"]) <= 0.2 * cold.uncertainty.shape_um
    assert abs(e_warm["roi_absolute_um"]) <= 3 * u_warm
