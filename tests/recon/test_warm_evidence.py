"""The posterior's warm start: the prior of one frame as the one start of the next frame's evidence
maximisation (:attr:`scopetwin.recon.reconstruct.Reconstructor.evidence_start`), for the Gaussian process's prior
(``prior="process"``: the one rough surfaces get) and the finite basis's.

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
from scopetwin.recon.config import ReconstructionConfig
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
    assert back.smooth_shape is None
    assert Hyper.from_dict(Hyper(0.013, 17.0, 6e-7, 0.65, 1.8e-6, 2.2e-7, 1.0).as_dict()).smooth_shape == 1.0


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


def _solve_counting(setup, obs, start, monkeypatch, converged=False):
    """A solve of ``obs`` with ``start`` as the evidence's warm start (``converged``: the search run to the evidence's
    maximum itself, ftol 1e-12 and 400 iterations); the result and the evidence evaluations it took."""
    calls = []
    inner = posterior_module._evidence_and_gradient

    def counted(*args):
        calls.append(1)
        return inner(*args)

    with monkeypatch.context() as patch:
        patch.setattr(posterior_module, "_evidence_and_gradient", counted)
        if converged:
            patch.setattr(posterior_module, "FTOL", 1e-12)
            patch.setattr(posterior_module, "MAXITER", 400)
        rec = Reconstructor.from_setup(setup, ReconstructionConfig(prior="process"))
        rec.evidence_start = start
        res = solve(rec, obs)
    return res, len(calls)


@pytest.mark.slow  # 8 s, two full solves (make test <= 5 min)
def test_the_warm_start_lands_where_the_cold_one_does(frames, monkeypatch) -> None:
    """Both fits stop short of the evidence's maximum somewhere along its flat directions (noise, broadband part); the
    warm one must stop as near to it as the cold one: the absolute height within half a standard uncertainty of
    the maximum's (the spread measured between fits stopping at different points of the flat maximum, 17 surfaces:
    up to 0.48 u, benchmarks/evidence_search.py), the uncertainties within 10 %."""
    setup, heights, (first, second) = frames
    sub = Substrate2D.from_setup(setup)
    res1, _ = _solve_counting(setup, first, None, monkeypatch)
    assert res1.uncertainty is not None
    prior = Hyper.from_dict(res1.uncertainty.hyper)
    best, _ = _solve_counting(setup, second, None, monkeypatch, converged=True)
    cold, n_cold = _solve_counting(setup, second, None, monkeypatch)
    warm, n_warm = _solve_counting(setup, second, prior, monkeypatch)
    assert best.uncertainty is not None and cold.uncertainty is not None and warm.uncertainty is not None
    assert n_warm < n_cold, (n_warm, n_cold)
    u = best.uncertainty.absolute_um
    e_best = roi_errors(best.surface.height, heights, sub)
    for res in (cold, warm):
        assert abs(res.uncertainty.absolute_um - u) <= 0.1 * u, (res.uncertainty.absolute_um, u)
        assert abs(res.uncertainty.shape_um - best.uncertainty.shape_um) <= 0.1 * best.uncertainty.shape_um
        e = roi_errors(res.surface.height, heights, sub)
        assert abs(e["roi_absolute_um"] - e_best["roi_absolute_um"]) <= 0.5 * u, (e, e_best, u)
        assert abs(e["roi_shape_um"] - e_best["roi_shape_um"]) <= 0.2 * best.uncertainty.shape_um
        assert abs(e["roi_absolute_um"]) <= 3 * res.uncertainty.absolute_um


def test_a_held_prior_reads_the_next_frame_without_a_search(frames, monkeypatch) -> None:
    """Reconstructor.held_prior: the next frame's gradients, as plausible a draw of the first frame's prior as that
    frame's own (held_prior_z), are read with it as it is (no evidence evaluation, the path says so); the
    uncertainties stay within 10 % of a frame searched from that prior and the heights within 3 u of the truth. An
    implausible prior (the same one, its amplitudes and noise a hundred times too large) is searched again from."""
    from dataclasses import replace

    from scopetwin.recon.policy import DEFAULT_POLICY
    from scopetwin.recon.uncertainty import HeldPrior

    setup, heights, (first, second) = frames
    sub = Substrate2D.from_setup(setup)
    res1, _ = _solve_counting(setup, first, None, monkeypatch)
    assert res1.uncertainty is not None
    prior = Hyper.from_dict(res1.uncertainty.hyper)
    warm, _ = _solve_counting(setup, second, prior, monkeypatch)
    assert warm.uncertainty is not None
    config = ReconstructionConfig(prior="process").starting_at(float(res1.surface.basis.sigma[0]))
    policy = DEFAULT_POLICY.with_changes(rechoose_scale=False)

    def held(hyper: Hyper) -> tuple:
        calls = []
        inner = posterior_module._evidence_and_gradient
        with monkeypatch.context() as patch:
            patch.setattr(posterior_module, "_evidence_and_gradient", lambda *a: calls.append(1) or inner(*a))
            rec = Reconstructor.from_setup(setup, config)
            rec.evidence_start, rec.held_prior = hyper, HeldPrior(hyper, res1.uncertainty.prior_z)
            return solve(rec, second, policy), len(calls)

    res, n = held(prior)
    assert n == 0
    assert any(step.startswith("prior held") for step in res.strategy), res.strategy
    u, u_warm = res.uncertainty, warm.uncertainty
    assert u is not None
    assert abs(u.absolute_um - u_warm.absolute_um) <= 0.1 * u_warm.absolute_um, (u, u_warm)
    assert abs(u.shape_um - u_warm.shape_um) <= 0.1 * u_warm.shape_um, (u, u_warm)
    e = roi_errors(res.surface.height, heights, sub)
    assert abs(e["roi_absolute_um"]) <= 3 * u.absolute_um, e
    noise_y = None if prior.noise_y is None else 100 * prior.noise_y
    wide = replace(prior, smooth_amp=100 * prior.smooth_amp, broad_amp=100 * prior.broad_amp, noise=100 * prior.noise)
    res, n = held(replace(wide, noise_y=noise_y))
    assert n > 0
    assert any(step.startswith("held prior implausible") for step in res.strategy), res.strategy


def test_a_held_finite_basis_prior_reads_the_next_frame_without_a_search(frames, monkeypatch) -> None:
    """The §1.10 surface reads with the finite-basis prior (its evidence peaks at a basis scale): held for the next
    frame, the gradients are read with it as they are (no basis search, the path says so), the uncertainties within
    10 % of a frame searched from it, the heights within 3 u of the truth; a prior whose noise is a hundred times too
    large is searched again from."""
    from dataclasses import replace

    import scopetwin.recon.basis_posterior as basis_module
    from scopetwin.recon.policy import DEFAULT_POLICY
    from scopetwin.recon.posterior import BasisPrior, prior_from_dict
    from scopetwin.recon.uncertainty import HeldPrior

    setup, heights, (first, second) = frames
    sub = Substrate2D.from_setup(setup)
    res1 = solve(Reconstructor.from_setup(setup), first)
    assert res1.uncertainty is not None
    prior = prior_from_dict(res1.uncertainty.hyper)
    assert isinstance(prior, BasisPrior)
    config = ReconstructionConfig().starting_at(float(res1.surface.basis.sigma[0]))

    def next_frame(hyper: BasisPrior, hold: bool) -> tuple:
        calls = []
        inner = basis_module.fit_basis_prior
        with monkeypatch.context() as patch:
            patch.setattr(basis_module, "fit_basis_prior", lambda *a, **k: calls.append(1) or inner(*a, **k))
            rec = Reconstructor.from_setup(setup, config)
            rec.evidence_start = hyper
            rec.held_prior = HeldPrior(hyper, res1.uncertainty.prior_z) if hold else None
            return solve(rec, second, DEFAULT_POLICY.with_changes(rechoose_scale=False)), len(calls)

    warm, n_warm = next_frame(prior, False)
    res, n = next_frame(prior, True)
    assert n_warm > 0 and n == 0
    assert any(step.startswith("prior held") for step in res.strategy), res.strategy
    u, u_warm = res.uncertainty, warm.uncertainty
    assert u is not None and u_warm is not None
    assert abs(u.absolute_um - u_warm.absolute_um) <= 0.1 * u_warm.absolute_um, (u, u_warm)
    assert abs(u.shape_um - u_warm.shape_um) <= 0.1 * u_warm.shape_um, (u, u_warm)
    e = roi_errors(res.surface.height, heights, sub)
    assert abs(e["roi_absolute_um"]) <= 3 * u.absolute_um, e
    res, n = next_frame(replace(prior, noise=100 * prior.noise, noise_y=100 * prior.noise_y), True)
    assert n > 0
    assert any(step.startswith("held prior implausible") for step in res.strategy), res.strategy


def test_held_prior_z_is_a_standard_score_of_the_whitened_gradients() -> None:
    """held_prior_z: about N(0, 1) for whitened gradients that are standard normal draws (the prior holds), far beyond
    HELD_PRIOR_Z for draws of a prior ten times too wide or narrow."""
    from scopetwin.recon.uncertainty import HELD_PRIOR_Z, held_prior_z

    rng = np.random.default_rng(4)
    z = np.array([held_prior_z(rng.standard_normal(1000)) for _ in range(400)])
    assert abs(z.mean()) < 0.2 and 0.85 < z.std() < 1.15
    assert np.mean(np.abs(z) <= HELD_PRIOR_Z) > 0.99
    v = rng.standard_normal(1000)
    assert held_prior_z(10 * v) > 100 and held_prior_z(0.1 * v) < -20


def test_previous_with_a_second_image_or_the_inverse_method_is_one_clear_error() -> None:
    import scopetwin
    from scopetwin.recon.errors import ReconstructionError

    dummy = object()
    image = np.zeros((4, 4))
    for kwargs in ({"second": image}, {"method": "inverse"}):
        with pytest.raises(ReconstructionError, match="previous= takes one image"):
            scopetwin.reconstruct(image, "thesis-1.10-deflectometry", previous=dummy, **kwargs)  # type: ignore[arg-type]
    with pytest.raises(ReconstructionError, match="give previous="):
        scopetwin.reconstruct(image, "thesis-1.10-deflectometry", hold=True)
    with pytest.raises(ReconstructionError, match="no posterior prior to hold"):
        scopetwin.reconstruct(image, "thesis-1.10-deflectometry", previous=dummy, hold=True)  # type: ignore[arg-type]


def test_a_recorded_prior_is_read_back_and_checked() -> None:
    """recorded_prior: the prior of a reconstruction's JSON (``uncertainty.prior``) as the Hyper it was, and one error
    naming the value for anything that is not a prior."""
    from scopetwin.recon.posterior import PosteriorError, recorded_prior

    h = Hyper(0.013, 17.0, 6e-7, 0.65, 1.8e-6, 2.2e-7, 1.0, 3e-6, 2.5)
    record = {"uncertainty": {"absolute_um": 0.02, "prior": h.as_dict()}}
    back = recorded_prior(record, "r.json")
    assert back.as_dict() == pytest.approx(h.as_dict())
    no_features = {k: v for k, v in Hyper(0.013, 17.0, 6e-7, 0.65, 1.8e-6, 2.2e-7).as_dict().items() if "feat" not in k}
    assert recorded_prior({"uncertainty": {"prior": no_features}}, "r.json").feature_amp == 0.0
    for bad, match in (
        ({}, "holds no uncertainty.prior"),
        ({"uncertainty": None}, "holds no uncertainty.prior"),
        ({"uncertainty": {"prior": [1, 2]}}, "holds no uncertainty.prior"),
        ({"uncertainty": {"prior": {**h.as_dict(), "noise_urad": -1.0}}}, "noise_urad must be a positive number"),
        ({"uncertainty": {"prior": {**h.as_dict(), "smooth_len_mm": float("inf")}}}, "smooth_len_mm must be"),
        ({"uncertainty": {"prior": {**h.as_dict(), "broad_amp_nm": True}}}, "broad_amp_nm must be"),
        ({"uncertainty": {"prior": {**h.as_dict(), "smooth_amp_um": "13"}}}, "smooth_amp_um must be"),
        ({"uncertainty": {"prior": {**h.as_dict(), "feature_amp_nm": -0.1}}}, "feature_amp_nm must be a non-negative"),
        ({"uncertainty": {"prior": {**h.as_dict(), "smooth_shape": 0}}}, "smooth_shape must be a positive"),
        ({"uncertainty": {"prior": {k: v for k, v in h.as_dict().items() if k != "broad_len_mm"}}}, "broad_len_mm"),
    ):
        with pytest.raises(PosteriorError, match=match):
            recorded_prior(bad, "r.json")


def test_cli_previous_is_checked_before_any_work(tmp_path) -> None:
    """``scopetwin reconstruct --previous JSON``: a file that holds no prior, or the option with a second image, the
    inverse method or no posterior, is one clear error before the image is read; nothing is written."""
    import argparse
    import json

    from scopetwin.cli.reconstruct import register
    from scopetwin.scenes.errors import ScopetwinError

    parser = argparse.ArgumentParser(prog="scopetwin")
    register(parser.add_subparsers(dest="command", required=True))
    good, bad = tmp_path / "good.json", tmp_path / "bad.json"
    good.write_text(json.dumps({"uncertainty": {"prior": Hyper(0.013, 17.0, 6e-7, 0.65, 1.8e-6, 2.2e-7).as_dict()}}))
    bad.write_text(json.dumps({"seconds": 1.0}))
    base = ["reconstruct", str(tmp_path / "missing.exr"), "--setup", "thesis-1.10-deflectometry"]
    base += ["--out", str(tmp_path / "h.exr")]
    for extra, match in (
        (["--previous", str(bad)], "holds no uncertainty.prior"),
        (["--previous", str(tmp_path / "none.json")], "does not exist"),
        (["--previous", str(good), "--method", "inverse"], "--previous takes one image"),
        (["--previous", str(good), "--second", str(tmp_path / "b.exr")], "--previous takes one image"),
        (["--previous", str(good), "--posterior", "off"], "--posterior off skips"),
        (["--hold"], "give --previous JSON"),
        (["--previous", str(good), "--hold"], "--hold needs uncertainty.prior_z"),
    ):
        args = parser.parse_args(base + extra)
        with pytest.raises(ScopetwinError, match=match):
            args.func(args)
    scaled = tmp_path / "scaled.json"
    scaled.write_text(json.dumps({**json.loads(good.read_text()), "history": [{"sigma_mm": -3.0}]}))
    args = parser.parse_args(base + ["--previous", str(scaled)])
    with pytest.raises(ScopetwinError, match="sigma_mm must be a basis scale"):
        args.func(args)
    scaled.unlink()
    args = parser.parse_args(base + ["--previous", str(good)])
    with pytest.raises(ScopetwinError, match="does not exist"):  # the prior read, then the image
        args.func(args)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.json", "good.json"]


def test_cli_takes_a_finite_basis_prior_and_the_prior_option(tmp_path) -> None:
    """``--previous`` with a finite-basis prior (``kind`` "basis") is read and checked before the image; ``--prior``
    sets the configuration's prior."""
    import argparse
    import json

    from scopetwin.cli.reconstruct import _config, register
    from scopetwin.recon.posterior import BasisPrior
    from scopetwin.scenes.errors import ScopetwinError

    parser = argparse.ArgumentParser(prog="scopetwin")
    register(parser.add_subparsers(dest="command", required=True))
    prior = tmp_path / "basis.json"
    prior.write_text(json.dumps({"uncertainty": {"prior": BasisPrior(12.0, 3.8e-3, 2e-6, 1e-6).as_dict()}}))
    base = ["reconstruct", str(tmp_path / "missing.exr"), "--setup", "thesis-1.10-deflectometry"]
    base += ["--out", str(tmp_path / "h.exr")]
    args = parser.parse_args([*base, "--previous", str(prior)])
    with pytest.raises(ScopetwinError, match="does not exist"):  # the prior read, then the image
        args.func(args)
    prior.write_text(
        json.dumps({"uncertainty": {"prior": {**BasisPrior(12.0, 3.8e-3, 2e-6, 1e-6).as_dict(), "noise_urad": 0}}})
    )
    with pytest.raises(ScopetwinError, match=r"uncertainty\.prior\.noise_urad must be a positive number"):
        args.func(args)
    assert _config(parser.parse_args([*base, "--prior", "process"])).prior == "process"
    assert _config(parser.parse_args(base)).prior == "auto"


def test_the_next_frame_starts_on_the_scale_the_last_ended_on() -> None:
    from scopetwin.recon.config import ReconstructionConfig

    cfg = ReconstructionConfig()
    assert (
        cfg.starting_at(15.0).sigma == (15.0, 15.0) and cfg.starting_at(15.0).sigma_candidates == cfg.sigma_candidates
    )
    assert cfg.starting_at(None) is cfg
    fixed = ReconstructionConfig(sigma=(6.0, 6.0), sigma_candidates=None)
    assert fixed.starting_at(15.0) is fixed  # a fixed scale stays
    thesis = ReconstructionConfig.thesis()
    assert thesis.starting_at(15.0) is thesis
    with pytest.raises(ValueError, match="positive"):
        cfg.starting_at(0.0)
