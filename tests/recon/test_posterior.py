"""The Gaussian-process reading of the gradient fit (recon.posterior): kernels, evidence, calibrated posterior."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.recon.posterior import (
    GradientGP,
    Hyper,
    fit_hyper,
    frame_posterior,
    gradient_kernel,
    height_gradient_kernel,
)

HYPER = Hyper(smooth_amp=0.01, smooth_len=10.0, broad_amp=2e-6, broad_len=1.0, noise=1e-6)


def test_gradient_kernels_are_derivatives_of_the_height_kernel() -> None:
    from scopetwin.recon.posterior import height_kernel

    rng = np.random.default_rng(0)
    p = rng.uniform(-10, 10, (5, 2))
    r = rng.uniform(-10, 10, (4, 2))
    eps = 1e-4
    kg = height_gradient_kernel(p, r, HYPER)
    for axis in (0, 1):
        dr = np.zeros(2)
        dr[axis] = eps
        fd = (height_kernel(p, r + dr, HYPER) - height_kernel(p, r - dr, HYPER)) / (2 * eps)
        np.testing.assert_allclose(kg[:, axis * 4 : (axis + 1) * 4], fd, rtol=1e-6, atol=1e-14)
    kgg = gradient_kernel(r, Hyper(HYPER.smooth_amp, HYPER.smooth_len, HYPER.broad_amp, HYPER.broad_len, 0.0))
    q = r[:1]
    fd = np.zeros(8)
    for axis in (0, 1):
        dq = np.zeros(2)
        dq[axis] = eps
        fd_row = (height_gradient_kernel(q + dq, r, HYPER) - height_gradient_kernel(q - dq, r, HYPER)) / (2 * eps)
        np.testing.assert_allclose(kgg[axis * 4, :], fd_row[0], rtol=1e-5, atol=1e-12)
    assert np.all(np.isfinite(fd))


def _draw(hyper: Hyper, xy: np.ndarray, extra: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A joint prior draw of gradients at xy and heights at extra (exact, by Cholesky)."""
    from scopetwin.recon.posterior import height_kernel

    kgg = gradient_kernel(xy, Hyper(hyper.smooth_amp, hyper.smooth_len, hyper.broad_amp, hyper.broad_len, 0.0))
    kfg = height_gradient_kernel(extra, xy, hyper)
    kff = height_kernel(extra, extra, hyper)
    full = np.block([[kgg, kfg.T], [kfg, kff]])
    evals, evecs = np.linalg.eigh(full)
    root = evecs * np.sqrt(np.clip(evals, 0.0, None))
    v = root @ np.random.default_rng(seed).standard_normal(len(full))
    g = v[: 2 * len(xy)] + hyper.noise * np.random.default_rng(seed + 1).standard_normal(2 * len(xy))
    return g, v[2 * len(xy) :]


def test_evidence_recovers_the_prior_scale() -> None:
    xx, yy = np.meshgrid(np.linspace(-12, 12, 9), np.linspace(-22, 22, 19))
    xy = np.stack([xx.ravel(), yy.ravel()], axis=-1)
    g, _ = _draw(HYPER, xy, xy[:1], seed=3)
    h = fit_hyper(xy, g[: len(xy)], g[len(xy) :], max_points=400, smooth_starts=(10.0,))
    assert h.smooth_len == pytest.approx(HYPER.smooth_len, rel=0.25)
    assert h.smooth_amp == pytest.approx(HYPER.smooth_amp, rel=0.6)
    # at 2-3 mm data spacing a 1 mm broadband part is white: only its sum with the noise is identifiable
    white = np.hypot(h.noise_pair[0], h.broad_amp / h.broad_len)
    assert white == pytest.approx(np.hypot(HYPER.noise, HYPER.broad_amp / HYPER.broad_len), rel=0.3)


def test_frame_criterion_posterior_is_calibrated_on_prior_draws() -> None:
    """Draw surfaces from the prior; the true D lies within 2 posterior sd in ~95 % of 24 draws."""
    xx, yy = np.meshgrid(np.linspace(-12, 12, 7), np.linspace(-22, 22, 12))
    xy = np.stack([xx.ravel(), yy.ravel()], axis=-1)
    f1x, f1y = np.meshgrid(np.linspace(-12.6, 12.6, 11), -(24 + np.linspace(0, 4.5, 6)))
    f2x, f2y = np.meshgrid(np.linspace(-12.6, 12.6, 11), 24 + np.linspace(0, 4.5, 6))
    rx, ry = np.linspace(-12.6, 12.6, 7), np.linspace(-24, 24, 13)
    rxx, ryy = np.meshgrid(rx, ry)
    f1 = np.stack([f1x.ravel(), f1y.ravel()], -1)
    f2 = np.stack([f2x.ravel(), f2y.ravel()], -1)
    extra = np.concatenate([f1, f2, np.stack([rxx.ravel(), ryy.ravel()], -1)])
    z = []
    for seed in range(24):
        g, f = _draw(HYPER, xy, extra, seed=100 + 2 * seed)
        d_true = 0.5 * (f[: len(f1)].max() + f[len(f1) : 2 * len(f1)].max()) - f[2 * len(f1) :].mean()
        gp = GradientGP(xy, g[: len(xy)], g[len(xy) :], HYPER)
        post = frame_posterior(
            gp, (-12.6, 12.6), (-28.5, 28.5), 48.0, (rx, ry), frame_step=2.52, node_step=6.0, samples=300
        )
        z.append((d_true - post.d_mean) / post.d_std)
    z = np.abs(np.array(z))
    assert 0.85 <= np.mean(z <= 2) <= 1.0, z
    assert np.max(z) < 4.0, z


def _exact_gradient_covariance(xy: np.ndarray, amp: float, length: float, alpha: float | None) -> np.ndarray:
    """cov of [f_x; f_y] at xy for an isotropic k(s) = amp^2 kappa(s), s = |r - r'|^2, written here in closed form:
    a squared exponential (``alpha`` None) or a rational quadratic (1 + s / (2 alpha l^2))^-alpha; the tilt prior of
    the module (TILT_STD) added. cov(f_x, f_x') = -2 k' - 4 dx^2 k'', cov(f_x, f_y') = -4 dx dy k''."""
    from scopetwin.recon.posterior import TILT_STD

    dx = xy[:, None, 0] - xy[None, :, 0]
    dy = xy[:, None, 1] - xy[None, :, 1]
    s = dx * dx + dy * dy
    if alpha is None:
        e = amp**2 * np.exp(-s / (2 * length**2))
        k1, k2 = -e / (2 * length**2), e / (4 * length**4)
    else:
        base = 1.0 + s / (2 * alpha * length**2)
        k1 = -(amp**2) / (2 * length**2) * base ** -(alpha + 1)
        k2 = amp**2 * (alpha + 1) / (4 * alpha * length**4) * base ** -(alpha + 2)
    n = len(xy)
    k = np.empty((2 * n, 2 * n))
    k[:n, :n] = -2 * k1 - 4 * dx * dx * k2 + TILT_STD**2
    k[n:, n:] = -2 * k1 - 4 * dy * dy * k2 + TILT_STD**2
    k[:n, n:] = k[n:, :n] = -4 * dx * dy * k2
    return k


@pytest.mark.slow  # 8 evidence fits of each shape on 231 points
@pytest.mark.parametrize("alpha", [None, 1.0])
def test_evidence_chooses_the_smooth_parts_shape(alpha: float | None) -> None:
    """Gradients drawn from an exact squared-exponential or rational-quadratic (alpha 1) prior on a marker-like
    lattice (1.3-2.4 mm spacing, 1 µrad noise): the evidence picks the family they came from in at least 3 of 4
    draws, and recovers the length within 35 %."""
    from scopetwin.recon.posterior import SMOOTH_SHAPE

    xx, yy = np.meshgrid(np.linspace(-12, 12, 11), np.linspace(-22, 22, 21))
    xy = np.stack([xx.ravel(), yy.ravel()], axis=-1)
    cov = _exact_gradient_covariance(xy, 0.01, 8.0, alpha)
    root = np.linalg.cholesky(cov + 1e-18 * np.eye(len(cov)))
    chosen, lengths = [], []
    for seed in range(4):
        rng = np.random.default_rng([seed, 41])
        g = root @ rng.standard_normal(len(cov)) + 1e-6 * rng.standard_normal(len(cov))
        h = fit_hyper(xy, g[: len(xy)], g[len(xy) :], max_points=400, smooth_starts=(10.0,), coarse_points=0)
        chosen.append(h.smooth_shape)
        lengths.append(h.smooth_len)
    expected = None if alpha is None else SMOOTH_SHAPE
    assert sum(c == expected for c in chosen) >= 3, (chosen, lengths)
    right = [ln for c, ln in zip(chosen, lengths, strict=True) if c == expected]
    assert np.all(np.abs(np.array(right) / 8.0 - 1.0) < 0.35), (chosen, lengths)


@pytest.mark.parametrize("depth_um", [pytest.param(2.0, marks=pytest.mark.slow), 0.0])
def test_evidence_admits_local_features_only_where_the_data_hold_them(depth_um: float) -> None:
    """Exact marker images (0.005 px of centroid noise) of the §1.10 surface with a 3 mm wide (FWHM) dimple, the
    local-features part allowed (``ReconstructionConfig.local_features``): with a 2 µm dimple the evidence adds it
    (measured 134 nm at 1.8 mm) and the shape follows the dimple (measured 119 % of its depth; the basis fit alone
    smooths it away); without the dimple the prior is the one without the part, exactly."""
    from scopetwin.recon.config import ReconstructionConfig
    from scopetwin.recon.reconstruct import MarkerObservations, Reconstructor
    from scopetwin.recon.strategy import solve
    from scopetwin.scenes.setup import load_setup
    from scopetwin.sim.families import dimple_depth, dimple_spec
    from scopetwin.sim.surfaces import surface_for
    from scopetwin.sim.truth import marker_truth

    setup = load_setup("thesis-1.10-deflectometry", {"substrate": {"surface": dimple_spec(depth_um=depth_um)}})
    heights = surface_for(setup)
    assert heights is not None
    t = marker_truth(setup, heights)
    px = t.center_px[t.visible] + 0.005 * np.random.default_rng(7).standard_normal((int(t.visible.sum()), 2))
    rec = Reconstructor.from_setup(setup, ReconstructionConfig(local_features=True))
    res = solve(rec, MarkerObservations(t.ij[t.visible], px))
    assert res.uncertainty is not None
    prior = Hyper.from_dict(res.uncertainty.hyper)
    if depth_um == 0.0:
        assert prior.feature_amp == 0.0
        return
    assert prior.feature_amp > 5e-5 and 1.0 <= prior.feature_len < 3.0  # mm
    assert dimple_depth(res.surface.height) >= 0.8 * dimple_depth(heights.height)


def test_frame_posterior_at_its_frame_step_matches_the_dense_frame_grid() -> None:
    """The default frame grid (FRAME_STEP, 0.75 mm) against one of 0.5 mm on gradients drawn from a prior with a
    broadband part on a marker-like lattice (1.2-2.2 mm spacing, the §1.10 substrate's extent): with 4000 draws each
    (Monte-Carlo noise of a spread ~1.1 %), the spreads of D and Delta h_max within 6 % and the means within 0.15 of
    the spread; the contrast map (same nodes) identical."""
    from scopetwin.recon.posterior import FRAME_STEP

    hyper = Hyper(smooth_amp=0.01, smooth_len=12.0, broad_amp=2e-5, broad_len=0.5, noise=1e-6)
    xx, yy = np.meshgrid(np.linspace(-12, 12, 11), np.linspace(-22.5, 22.5, 21))
    xy = np.stack([xx.ravel(), yy.ravel()], axis=-1)
    g, _ = _draw(hyper, xy, xy[:1], seed=7)
    gp = GradientGP(xy, g[: len(xy)], g[len(xy) :], hyper)
    args = ((-12.6, 12.6), (-28.5, 28.5), 48.0)
    coarse = frame_posterior(gp, *args, samples=4000)
    dense = frame_posterior(gp, *args, frame_step=0.5, samples=4000)
    assert FRAME_STEP == 0.75 and len(coarse.frame1) * 2 < len(dense.frame1)
    assert coarse.d_std == pytest.approx(dense.d_std, rel=0.06)
    assert coarse.delta_std == pytest.approx(dense.delta_std, rel=0.06)
    assert abs(coarse.d_mean - dense.d_mean) < 0.15 * dense.d_std
    assert abs(coarse.delta_mean - dense.delta_mean) < 0.15 * dense.delta_std
    np.testing.assert_allclose(coarse.contrast_std, dense.contrast_std, rtol=1e-6)
    np.testing.assert_allclose(coarse.contrast_mean, dense.contrast_mean, rtol=1e-9, atol=1e-12)


def _lattice() -> np.ndarray:
    xx, yy = np.meshgrid(np.linspace(-12, 12, 9), np.linspace(-22.5, 22.5, 16))
    return np.stack([xx.ravel(), yy.ravel()], axis=-1)


def _bowed_gradients(xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gradients of a known bowed surface with waviness, f = 4e-5 x^2 - 2e-5 y^2 + 5e-4 sin(0.4 x + 0.2 y) (mm)."""
    x, y = xy[:, 0], xy[:, 1]
    wave = 5e-4 * np.cos(0.4 * x + 0.2 * y)
    return 8e-5 * x + 0.4 * wave, -4e-5 * y + 0.2 * wave


def test_a_frame_model_reads_other_gradients_as_their_own_posterior() -> None:
    """frame_model's reading of gradients g2 at the same positions equals the posterior conditioned on g2 itself
    (the same draws: D's mean and spread, the contrast map)."""
    from scopetwin.recon.posterior import frame_model

    xy = _lattice()
    g1, _ = _draw(HYPER, xy, xy[:1], seed=21)
    g2, _ = _draw(HYPER, xy, xy[:1], seed=41)
    n = len(xy)
    args = ((-12.6, 12.6), (-28.5, 28.5), 48.0)
    model = frame_model(GradientGP(xy, g1[:n], g1[n:], HYPER), *args)
    read = model.read(g2[:n], g2[n:])
    fresh = frame_posterior(GradientGP(xy, g2[:n], g2[n:], HYPER), *args)
    assert abs(read.d_mean - fresh.d_mean) < 1e-6 * fresh.d_std
    assert read.d_std == pytest.approx(fresh.d_std, rel=1e-6)
    assert read.delta_mean == pytest.approx(fresh.delta_mean, rel=1e-6, abs=1e-6 * fresh.delta_std)
    np.testing.assert_allclose(
        read.contrast_mean, fresh.contrast_mean, rtol=1e-6, atol=1e-9 * np.ptp(fresh.contrast_mean)
    )
    np.testing.assert_allclose(read.contrast_std, fresh.contrast_std, rtol=1e-12)


def test_a_frame_model_covers_observations_moved_by_less_than_its_tolerance() -> None:
    """Gradients of a known surface observed at positions moved by up to 0.5 µm (all alike, as a start-height step
    moves them, or each its own way) read with the model of the old positions: D within 0.02 of its spread (7 nm
    here) of the fresh posterior's, its spread within 1e-3; moved by 0.6 µm, or one observation fewer, the model
    does not cover them."""
    from scopetwin.recon.posterior import REUSE_SHIFT_MM, frame_model

    xy = _lattice()
    args = ((-12.6, 12.6), (-28.5, 28.5), 48.0)
    model = frame_model(GradientGP(xy, *_bowed_gradients(xy), HYPER), *args)
    assert REUSE_SHIFT_MM == 5e-4
    for moved in (xy + np.array([5e-5, -4.9e-4]), xy + np.random.default_rng(5).uniform(-4.9e-4, 4.9e-4, xy.shape)):
        assert model.covers(moved)
        read = model.read(*_bowed_gradients(moved))
        fresh = frame_posterior(GradientGP(moved, *_bowed_gradients(moved), HYPER), *args)
        assert abs(read.d_mean - fresh.d_mean) < 0.02 * fresh.d_std
        assert read.d_std == pytest.approx(fresh.d_std, rel=1e-3)
    assert not model.covers(xy + 6e-4)
    assert not model.covers(xy[1:])


def test_read_frame_reuses_the_earlier_model_only_where_it_covers() -> None:
    """recon.uncertainty.read_frame: the earlier reading's model is read again for observations that barely moved
    (its posterior subset kept), a new one is formed where they moved further or their count changed."""
    from types import SimpleNamespace

    from scopetwin.recon.uncertainty import read_frame

    sub = SimpleNamespace(x_range=(-12.6, 12.6), y_range=(-28.5, 28.5), roi_length=48.0)
    axes = (np.linspace(-12.6, 12.6, 7), np.linspace(-24, 24, 13))
    xy = _lattice()
    first = read_frame(sub, axes, (xy, *_bowed_gradients(xy)), HYPER, budget=100)  # type: ignore[arg-type]
    assert len(first.keep) == 100 and first.n_traced == len(xy)
    near = xy + 3e-4
    again = read_frame(sub, axes, (near, *_bowed_gradients(near)), HYPER, 100, first)  # type: ignore[arg-type]
    assert again.model is first.model and np.array_equal(again.keep, first.keep)
    assert again.post.d_mean != first.post.d_mean  # the new gradients were read
    far = xy + 2e-3
    anew = read_frame(sub, axes, (far, *_bowed_gradients(far)), HYPER, 100, first)  # type: ignore[arg-type]
    assert anew.model is not first.model
    fewer = xy[:-1]
    other = read_frame(sub, axes, (fewer, *_bowed_gradients(fewer)), HYPER, 100, first)  # type: ignore[arg-type]
    assert other.model is not first.model


def test_a_frame_model_without_contrasts_reads_the_same_criterion() -> None:
    """frame_model(contrasts=False) (the fringe path reads D alone): the same D and Delta h_max, no contrast map."""
    from scopetwin.recon.posterior import frame_model

    xy = _lattice()
    gp = GradientGP(xy, *_bowed_gradients(xy), HYPER)
    args = ((-12.6, 12.6), (-28.5, 28.5), 48.0)
    full = frame_model(gp, *args).read(*_bowed_gradients(xy))
    bare = frame_model(gp, *args, contrasts=False).read(*_bowed_gradients(xy))
    assert bare.d_mean == pytest.approx(full.d_mean, rel=1e-9)
    assert bare.d_std == pytest.approx(full.d_std, rel=1e-9)
    assert bare.delta_mean == pytest.approx(full.delta_mean, rel=1e-9, abs=1e-9 * full.delta_std)
    assert bare.contrast_mean.size == 0 and bare.contrast_std.size == 0 and full.contrast_std.size > 0


@pytest.mark.parametrize(
    "hyper",
    [Hyper(0.01, 15.0, 1e-6, 0.4, 2e-6, 3e-7, 1.0), Hyper(0.01, 15.0, 1e-6, 0.4, 2e-6, 3e-7, None, 2e-4, 2.0)],
)
def test_a_residual_correction_on_a_grid_is_its_pointwise_value(hyper: Hyper) -> None:
    """The separable evaluation of the correction on a tensor grid (ResidualCorrection.on_grid, taken by height for
    meshgrid arrays) gives the pointwise sum over the observations, with every component (rational-quadratic
    mixture, local features, broadband, tilt), within 1e-9 mm (the pointwise sum's own round-off is ~1e-11)."""
    from scopetwin.recon.posterior import residual_correction

    rng = np.random.default_rng(3)
    xy = np.column_stack([rng.uniform(-12, 12, 300), rng.uniform(-28, 28, 300)])
    ex, ey = rng.normal(0, 1e-6, 300), rng.normal(0, 1e-6, 300)
    corr = residual_correction(xy, ex, ey, hyper, (np.linspace(-10, 10, 41), np.linspace(-24, 24, 97)))
    xx, yy = np.meshgrid(np.linspace(-12.6, 12.6, 37), np.linspace(-28.5, 28.5, 81))
    pointwise = corr.height(xx.ravel(), yy.ravel()).reshape(xx.shape)
    grid = corr.height(xx, yy)
    assert np.abs(pointwise).max() > 1e-6  # mm: a correction of micrometres
    np.testing.assert_allclose(grid, pointwise, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(grid, corr.on_grid(xx[0], yy[:, 0]))
    # not a tensor grid: the pointwise path
    np.testing.assert_allclose(corr.height(xx.T, yy.T), pointwise.T, rtol=0, atol=1e-9)


def test_a_residual_correction_on_a_frame_models_factor_is_the_one_formed_anew() -> None:
    """The residual correction read with the factor a frame model was formed with (same positions, same prior) is the
    correction formed with a factor of its own, bit for bit; a factor of the wrong size is refused."""
    from scopetwin.recon.posterior import GradientGP, frame_model, residual_correction

    hyper = Hyper(0.01, 15.0, 1e-6, 0.4, 2e-6, 3e-7, 1.0)
    rng = np.random.default_rng(5)
    xy = np.column_stack([rng.uniform(-12, 12, 200), rng.uniform(-28, 28, 200)])
    gp = GradientGP(xy, *_bowed_gradients(xy), hyper)
    model = frame_model(gp, (-13.0, 13.0), (-30.0, 30.0), 48.0)
    ex, ey = rng.normal(0, 1e-6, 200), rng.normal(0, 1e-6, 200)
    axes = (np.linspace(-10, 10, 41), np.linspace(-24, 24, 97))
    fresh = residual_correction(xy, ex, ey, hyper, axes)
    reused = residual_correction(xy, ex, ey, hyper, axes, model.chol)
    np.testing.assert_array_equal(reused.alpha, fresh.alpha)
    assert reused.roi_mean == fresh.roi_mean
    with pytest.raises(ValueError, match="a factor of 400 x 400"):
        GradientGP(xy, ex, ey, hyper, model.chol[:-2, :-2])
