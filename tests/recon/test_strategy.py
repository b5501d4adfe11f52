"""The one reconstruction strategy (recon.strategy) and its policy (recon.policy): every fallback named, taken in
order, recorded in the result, and one error naming every path when all failed."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.recon.errors import TooFewMarkersError
from scopetwin.recon.policy import DEFAULT_POLICY, ReconstructionPolicy
from scopetwin.recon.reconstruct import MarkerObservations, Reconstructor
from scopetwin.recon.strategy import reconstruct_markers, solve
from scopetwin.scenes.setup import load_setup
from scopetwin.scenes.surface import HeightMap
from scopetwin.sim.surfaces import make_surface
from scopetwin.sim.truth import marker_truth

SETUP = load_setup("thesis-1.10-deflectometry")


@pytest.fixture(scope="module")
def exact() -> tuple[HeightMap, MarkerObservations]:
    """Exact marker images of the preset's §1.9 surface (the truth tracer, no renderer)."""
    heights = make_surface(SETUP.substrate.surface, SETUP.substrate)
    t = marker_truth(SETUP, heights)
    return heights, MarkerObservations(t.ij[t.visible], t.center_px[t.visible])


@pytest.mark.parametrize(
    "changes",
    [
        {"lattice_below": 1.5},
        {"outlier_factor": -1.0},
        {"outlier_max_fraction": 1.0},
        {"slope_range": (5.0, 0.2)},
        {"inverse_starts": ()},
    ],
)
def test_a_policy_out_of_range_is_refused(changes):
    with pytest.raises(ValueError):
        ReconstructionPolicy(**changes)


def test_the_result_says_which_path_it_took(exact):
    heights, obs = exact
    res = reconstruct_markers(SETUP, obs)
    assert res.converged and res.strategy, res.strategy
    assert res.strategy[0].startswith("start-height search, basis scale 12 mm: converged")
    assert any("posterior" in step for step in res.strategy)
    assert res.summary()["strategy"] == res.strategy
    # the result's heights are the surface's, vectorised over any shape
    x, y = np.meshgrid(np.linspace(-10, 10, 3), np.linspace(-20, 20, 4))
    assert res.height_at(x, y).shape == (4, 3)
    assert np.allclose(res.height_at(x, y), res.surface.height(x, y))
    err = res.height_at(x, y) - heights.height(x, y)
    assert np.abs(err - err.mean()).max() < 1e-3  # mm: the shape within a micrometre


def test_the_policy_turns_a_fallback_off(exact):
    _, obs = exact
    off = DEFAULT_POLICY.with_changes(rechoose_scale=False)
    res = solve(Reconstructor.from_setup(SETUP), obs, off)
    assert not any("chosen on the data" in step for step in res.strategy)
    assert {s.sigma_mm for s in res.history} == {12.0}  # the default scale kept throughout


def test_one_error_names_every_path_tried(exact):
    """Markers only in the middle of the substrate: the default scale loses the frame regions, the flat start's
    scale choice cannot help; the one error says both."""
    _, obs = exact
    keep = np.abs(obs.ij[:, 1]) <= 3
    middle = MarkerObservations(obs.ij[keep], obs.px[keep])
    with pytest.raises(TooFewMarkersError) as info:
        reconstruct_markers(SETUP, middle)
    msg = str(info.value)
    assert "frame region" in msg and "[tried: start-height search" in msg and "flat start" in msg


def test_inverse_start_falls_back_in_order(monkeypatch):
    """The centroid method with its bias step; without it; a coarse fit of the markers; a plane — each taken only
    where the ones before failed, and what failed is said."""
    import scopetwin.recon.markers as markers_mod
    from scopetwin.recon import strategy
    from scopetwin.recon.bias import BiasError
    from scopetwin.recon.errors import TooFewMarkersError
    from scopetwin.recon.reconstruct import Reconstructor

    setup = load_setup("thesis-1.10-deflectometry")
    image = np.zeros((setup.camera_model.ny, setup.camera_model.nx))

    class Result:
        surface = "centroid surface"
        uncertainty = None
        strategy: list[str] = []

    calls: list[object] = []

    def bias_fails(image, setup, config, policy):
        calls.append(policy.bias_step)
        if policy.bias_step:
            raise BiasError("the model's map from pixels to the pattern is singular at a marker")
        return strategy.ImageReconstruction("markers", Result(), None)

    monkeypatch.setattr(strategy, "reconstruct_image", bias_fails)
    start = strategy.inverse_start(image, setup)
    assert start.kind == "centroid-unbiased" and start.holds_height and start.absolute == "start"
    assert calls == [True, False] and "singular" in start.note

    def both_fail(image, setup, config, policy):
        raise TooFewMarkersError("only 0 markers within 6.0 mm of frame region 1")

    class Found:
        ij = np.zeros((0, 2), dtype=np.int64)
        centroids = np.zeros((0, 2))

    monkeypatch.setattr(strategy, "reconstruct_image", both_fail)
    monkeypatch.setattr(markers_mod, "find_markers_for", lambda image, setup, **kw: Found())
    monkeypatch.setattr(Reconstructor, "coarse_surface", lambda self, obs, *a: "coarse surface")
    start = strategy.inverse_start(image, setup)
    assert (start.kind, start.surface, start.holds_height) == ("coarse", "coarse surface", True)
    assert start.note.count("TooFewMarkersError") == 2

    def no_markers(image, setup, **kw):
        raise markers_mod.MarkerError("too few markers left after filtering (0)")

    monkeypatch.setattr(markers_mod, "find_markers_for", no_markers)
    start = strategy.inverse_start(image, setup)
    assert start.kind == "plane" and start.surface is None and "too few markers" in start.note
    assert not start.holds_height and start.absolute == "frame"  # from a plane the height is searched

    # the policy decides which starts there are: without the bias step the biased one is never tried
    calls.clear()
    monkeypatch.setattr(strategy, "reconstruct_image", bias_fails)
    start = strategy.inverse_start(image, setup, policy=strategy.DEFAULT_POLICY.with_changes(bias_step=False))
    assert calls == [False] and start.kind == "centroid"


def test_the_indexing_that_numbered_the_markers_is_on_the_path(monkeypatch, exact):
    """Where the grid's topology numbered the markers instead of the thesis's flood (a fallback of the markers step,
    ``lattice_below``), the result's path says so; the flood's markers add no line."""
    import scopetwin.recon.markers as markers_mod
    from scopetwin.recon import strategy

    _, obs = exact
    image = np.zeros((SETUP.camera_model.ny, SETUP.camera_model.nx))

    class Found:
        ij, centroids, indexing = obs.ij, obs.px, "lattice"

    monkeypatch.setattr(markers_mod, "find_markers_for", lambda image, setup, **kw: Found())
    done = strategy.reconstruct_image(image, SETUP, policy=DEFAULT_POLICY.with_changes(bias_step=False))
    assert done.result.strategy[0].startswith("markers indexed by the grid's topology"), done.result.strategy
    Found.indexing = "flood"
    done = strategy.reconstruct_image(image, SETUP, policy=DEFAULT_POLICY.with_changes(bias_step=False))
    assert not any("topology" in step for step in done.result.strategy)


def test_the_prior_is_searched_beside_the_scale_choice(exact, monkeypatch):
    """The posterior's evidence search starts beside the basis scale's choice on the converged surface
    (uncertainty.PriorAhead). Where nothing changed that surface it is taken as it is: the result is the one of a
    solve that searches its prior afterwards. Where the scale changed it is refined from on the gradients traced
    anew, to the evidence of a cold search on them."""
    import threading

    import scopetwin.recon.uncertainty as uncertainty
    from scopetwin.recon.parallel import available_cpus
    from scopetwin.recon.posterior import GradientGP

    _, obs = exact
    from scopetwin.recon.config import ReconstructionConfig

    process = ReconstructionConfig(prior="process")  # the Gaussian process's evidence (GradientGP below)
    rec = Reconstructor.from_setup(SETUP, process)
    calls: list[tuple[threading.Thread, object]] = []
    searched = uncertainty.evidence_prior

    def counted(cfg, sub, traced, start, **kwargs):
        calls.append((threading.current_thread(), start))
        return searched(cfg, sub, traced, start, **kwargs)

    monkeypatch.setattr(uncertainty, "evidence_prior", counted)
    first = solve(rec, obs)
    assert any("basis scale chosen on the data" in step for step in first.strategy), first.strategy
    # the early search beside the choice, then a search for the new scale's surface (exact images: the noise at its
    # floor, the new scale moved the gradients far beyond the prior's spread of them, so a cold one)
    assert len(calls) == 2 and calls[0][1] is None and calls[1][1] is None
    assert calls[1][0] is threading.main_thread()
    if available_cpus() >= 2:
        assert calls[0][0] is not threading.main_thread()
    calls.clear()
    later = solve(rec, obs)  # the scale stands: the early search's prior as it is
    assert len(calls) == 1
    fresh = Reconstructor.from_setup(SETUP, process)
    fresh.use_basis(rec.basis)
    after = solve(fresh, obs, DEFAULT_POLICY.with_changes(rechoose_scale=False))
    assert len(calls) == 2 and calls[1][0] is threading.main_thread()
    np.testing.assert_array_equal(later.surface.coef, after.surface.coef)
    assert later.surface.offset == after.surface.offset
    assert later.uncertainty.summary() == after.uncertainty.summary()
    # for a surface whose gradients moved within the prior's spread of them (here a start height 0.01 µm off),
    # refined from: the evidence of a cold search on the gradients traced through it; moved beyond it (20 µm), none
    xy, hx, hy, _ = rec.traced_gradients(first.surface, obs)
    ahead = uncertainty.PriorAhead(rec, first.surface, obs, (xy, hx, hy))
    near, far = (later.surface.shifted(first.surface.offset + dz) for dz in (1e-5, 0.02))
    traced = rec.traced_gradients(near, obs)[:3]
    refined = ahead.hyper(rec, near, obs, traced)
    cold = searched(rec.config, rec.sub, traced, None)
    assert refined is not None
    keep = np.linspace(0, len(traced[0]) - 1, rec.config.evidence_points).round().astype(int)
    evidence = [
        GradientGP(traced[0][keep], traced[1][keep], traced[2][keep], h).log_evidence() for h in (refined, cold)
    ]
    assert evidence[0] > evidence[1] - 0.5, evidence
    assert ahead.hyper(rec, far, obs, rec.traced_gradients(far, obs)[:3]) is None
    assert ahead.hyper(rec, near, MarkerObservations(obs.ij, obs.px), traced) is None  # other markers
    assert ahead.hyper(rec, first.surface, obs, (xy, hx, hy)) == searched(rec.config, rec.sub, (xy, hx, hy), None)
    rec.evidence_start = cold  # another warm start than the early search's: not used
    assert ahead.hyper(rec, first.surface, obs, (xy, hx, hy)) is None
    ahead.close()


def test_a_smooth_surface_is_fitted_at_the_scale_its_evidence_chose(exact, monkeypatch) -> None:
    """``scale_by_evidence``: the §1.10 surface (exact images plus 0.005 px of centroid noise) reads with the
    finite-basis prior, so the fit takes that prior's scale and the held-out choice (select_sigma) does not run; the
    heights within 3 u of the truth. Without it, the held-out choice runs as before."""
    import scopetwin.recon.strategy as strategy
    from scopetwin.recon.posterior import BasisPrior, prior_from_dict
    from scopetwin.recon.substrate import Substrate2D
    from scopetwin.sim.pipeline import roi_errors

    heights, obs = exact
    noisy = MarkerObservations(obs.ij, obs.px + 0.005 * np.random.default_rng(5).standard_normal(obs.px.shape))
    calls = []
    inner = strategy.select_sigma
    monkeypatch.setattr(strategy, "select_sigma", lambda *a, **k: calls.append(1) or inner(*a, **k))
    res = solve(Reconstructor.from_setup(SETUP), noisy)
    prior = prior_from_dict(res.uncertainty.hyper)
    assert isinstance(prior, BasisPrior) and not calls
    assert float(res.surface.basis.sigma[0]) == prior.sigma
    e = roi_errors(res.surface.height, heights, Substrate2D.from_setup(SETUP))
    assert abs(e["roi_absolute_um"]) <= 3 * res.uncertainty.absolute_um, e
    assert e["roi_shape_um"] <= 3 * res.uncertainty.shape_um, e
    solve(Reconstructor.from_setup(SETUP), noisy, DEFAULT_POLICY.with_changes(scale_by_evidence=False))
    assert len(calls) == 1
