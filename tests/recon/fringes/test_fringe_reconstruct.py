"""The fringe reconstruction chain (recon/fringes) on synthetic phase images of known surfaces (§1.10 setup).

Phase-shift frames (4 steps, periods 64 / 8 / 1 mm, EMVA 1288 noise) of the per-pixel truth of the thesis setup
(4x binned camera, ~26,000 pixels on the ROI) are decoded and reconstructed. Acceptance: the shape error (height minus
truth, ROI means removed) <= 0.1 µm RMS with the frame criterion and <= 0.03 µm with two display positions; the
absolute height within 3 of its reported uncertainty, on a steep bowed sheet too (the frame criterion's D from the
Gaussian-process posterior); a 1.5 mm wide, 2 µm deep dimple recovered to >= 90 % of its
depth; over several noise seeds the reported uncertainties cover the errors (slow test).
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fringe_cases import PERIODS, capture, second_position, thesis_setup, truth  # noqa: E402

from scopetwin.recon.errors import ReconstructionError  # noqa: E402
from scopetwin.recon.fringes.phase import DisplayCoordinates, decode_display  # noqa: E402
from scopetwin.recon.fringes.reconstruct import (  # noqa: E402
    FringeConfig,
    FringeResult,
    distance_left,
    reconstruct_fringes,
)
from scopetwin.sim.families import dimple_spec, steep_spec  # noqa: E402

SHIFT_MM = 10.0


@pytest.fixture(scope="module")
def case():
    setup = thesis_setup()
    heights, maps = truth(setup)
    return setup, heights, maps, second_position(setup, heights, SHIFT_MM)


@pytest.fixture(scope="module")
def steep():
    setup = thesis_setup(steep_spec(9100))
    heights, maps = truth(setup)
    return setup, heights, _decode(setup, maps, 7)


def _decode(setup, maps, seed):
    frames = capture(setup, maps, seed)
    return decode_display(frames.x, frames.y, PERIODS, tuple(setup.pattern.size))


def _errors(result: FringeResult, heights) -> tuple[float, float, np.ndarray, np.ndarray]:
    """(absolute error, shape error RMS, per-node shape error, per-node shape std) over the ROI, mm."""
    gx, gy = result.substrate.roi_grid(0.5)
    est, tru = result.height_at(gx, gy), heights.height(gx, gy)
    shape = (est - est.mean()) - (tru - tru.mean())
    return float(est.mean() - tru.mean()), float(np.sqrt(np.mean(shape**2))), shape, result.shape_std_at(gx, gy)


def test_frame_criterion_gives_shape_and_absolute_height(case):
    setup, heights, maps, _ = case
    result = reconstruct_fringes(setup, _decode(setup, maps, 1))
    abs_err, shape_rms, _, _ = _errors(result, heights)
    assert result.converged and result.method == "frame-criterion"
    assert shape_rms < 1e-4, shape_rms  # 0.1 µm
    assert abs(abs_err) * 1e3 < 3.0 * result.absolute_um, (abs_err, result.absolute_um)
    assert 0.01 < result.absolute_um < 2.0 and 0.005 < result.shape_um < 0.2
    assert result.measured_mask().mean() > 0.9 and result.summary()["observations"] > 20_000


def test_two_display_positions_give_the_absolute_height(case):
    setup, heights, maps, moved = case
    result = reconstruct_fringes(setup, _decode(setup, maps, 2), second=_decode(setup, moved, 3), shift_mm=SHIFT_MM)
    abs_err, shape_rms, _, _ = _errors(result, heights)
    assert result.converged and result.method == "two-positions"
    assert shape_rms < 3e-5, shape_rms  # 0.03 µm
    assert abs(abs_err) * 1e3 < 3.0 * result.absolute_um and result.absolute_um < 0.3, (abs_err, result.absolute_um)


def test_two_positions_leave_out_pixels_far_from_the_surface(case):
    """One pixel in 500 of the second position sees a display point 0.3 mm off (a ghost, an edge pixel): each of them
    triangulates a height micrometres off; H still lands within 3 u with the stated sigmas doubled (the cut is on the
    residuals' robust scale)."""
    setup, heights, maps, moved = case
    first, second = _decode(setup, maps, 2), _decode(setup, moved, 3)
    rng = np.random.default_rng(4)
    bad = second.valid & (rng.random(second.valid.shape) < 2e-3)
    u = np.where(bad, second.u + 0.3, second.u)
    spoilt = replace(second, u=u, u_std=2.0 * second.u_std, v_std=2.0 * second.v_std)
    result = reconstruct_fringes(setup, first, second=spoilt, shift_mm=SHIFT_MM)
    abs_err = _errors(result, heights)[0]
    assert bad.sum() > 20 and abs(abs_err) * 1e3 < 3.0 * result.absolute_um, (abs_err, result.absolute_um)


def test_a_dimple_is_recovered_to_its_depth():
    at = (2.0, 5.0)
    setup = thesis_setup(dimple_spec(depth_um=2.0, width_mm=1.5, at=at))
    heights, maps = truth(setup)
    result = reconstruct_fringes(setup, _decode(setup, maps, 5))
    ang = np.linspace(0.0, 2.0 * np.pi, 64, endpoint=False)
    ring = (at[0] + 2.5 * np.cos(ang), at[1] + 2.5 * np.sin(ang))  # 2.5 mm: beyond the dimple (FWHM 1.5 mm)
    depth_true = float(heights.height(np.array([at[0]]), np.array([at[1]]))[0] - heights.height(*ring).mean())
    depth = float(result.height_at(*at) - result.height_at(*ring).mean())
    assert depth_true < -1.7e-3  # the dimple (on the surface's own curvature)
    assert 0.9 <= depth / depth_true <= 1.1, (depth, depth_true)


def test_frame_criterion_on_a_steep_bowed_sheet_from_the_posterior(steep):
    """A steep sheet (steep_spec: 80-200 µm of waviness, a bow): the spline's fixed curvature prior extrapolates the
    frame maxima microns off; the Gaussian-process posterior's D (prior by evidence) puts the ROI mean height within
    3 of its reported u, and closer to the truth than the spline's extrapolation."""
    setup, heights, coords = steep
    spline = reconstruct_fringes(setup, coords, FringeConfig(frame_posterior=False))
    result = reconstruct_fringes(setup, coords)
    abs_err = _errors(result, heights)[0]
    info = result.frame_posterior
    assert info is not None and info["steps"] >= 1 and info["d_std_um"] > 0
    assert abs(abs_err) * 1e3 < 3.0 * result.absolute_um, (abs_err, result.absolute_um, info)
    assert result.absolute_um < 1.0 and abs(abs_err) < abs(_errors(spline, heights)[0]), (abs_err, info)
    assert result.summary()["frame_posterior"]["correction_um"] == info["correction_um"]


def test_bad_input_is_one_clear_error(case):
    setup, _, maps, _ = case
    coords = DisplayCoordinates.from_arrays(maps["pattern_xy"][:10], 1e-3)
    with pytest.raises(ReconstructionError, match="decoded maps of shape"):
        reconstruct_fringes(setup, coords)
    full = DisplayCoordinates.from_arrays(maps["pattern_xy"], 1e-3, maps["roi"])
    with pytest.raises(ReconstructionError, match="shift_mm"):
        reconstruct_fringes(setup, full, second=full)


@pytest.mark.slow
def test_reported_uncertainties_cover_the_errors_over_noise_seeds(case):
    """Four noise seeds, both methods: every absolute error within 3 u, the normalised absolute errors of unit-order
    spread, and >= 90 % of the ROI nodes' shape errors within 2 of their reported standard deviation."""
    setup, heights, maps, moved = case
    z_abs, inside = [], []
    for seed in range(20, 24):
        first = _decode(setup, maps, seed)
        for result in (
            reconstruct_fringes(setup, first),
            reconstruct_fringes(setup, first, second=_decode(setup, moved, seed + 50), shift_mm=SHIFT_MM),
        ):
            abs_err, _, shape, std = _errors(result, heights)
            z_abs.append(abs_err * 1e3 / result.absolute_um)
            inside.append(np.mean(np.abs(shape) <= 2.0 * std))
    z = np.asarray(z_abs)
    assert np.all(np.abs(z) < 3.0), z
    assert np.sqrt(np.mean(z**2)) < 2.0, z
    assert np.min(inside) >= 0.9, inside


def test_distance_left_sums_the_steps_of_a_contracting_iteration():
    """A fixed-point iteration whose steps shrink by q: the steps still to come sum to the extrapolated distance; no
    distance (infinite) without a last step or where the steps do not shrink."""
    q, first = 0.07, 10.0
    steps = first * q ** np.arange(60)
    for k in (1, 2, 5):
        assert distance_left(steps[k], steps[k - 1]) == pytest.approx(steps[k + 1 :].sum(), rel=1e-12)
    assert distance_left(1.0, float("inf")) == float("inf")
    assert distance_left(1.0, 1.0) == float("inf")
    assert distance_left(2.0, 1.0) == float("inf")


def test_a_small_posterior_step_moves_the_surface_as_the_inner_loop_would(case):
    """The posterior's Newton steps up to LINEAR_STEP_UM move the surface to first order (shift + tilt x step, slopes
    traced anew): for a 0.3 µm step on the thesis case the result lies within 0.002 µm RMS (ROI, mean removed; the
    inner loop's own tolerance) of the inner loop run at the new start height, which moves the shape by far more."""
    from scopetwin.recon.fringes.blocks import block_average, block_size
    from scopetwin.recon.fringes.reconstruct import LINEAR_STEP_UM, FringeReconstructor, _EarlyEvidence
    from scopetwin.recon.fringes.slopes import PixelRays
    from scopetwin.recon.substrate import Substrate2D

    setup, _, maps, _ = case
    sub, cam, cfg = Substrate2D.from_setup(setup), setup.camera_model, FringeConfig()
    coords, _ = block_average(_decode(setup, maps, 3), block_size(cam, sub, cfg.knot_spacing_mm))
    rec = FringeReconstructor(cam, setup.marker_pattern.frame, sub, cfg)
    rays = PixelRays.of(cam, coords.valid, coords.block)
    runs = rec._start_heights(coords, rays, _EarlyEvidence(rec.evidence, wanted=False)).runs
    (h0, inner), (h1, other) = runs[-1], runs[0]
    tilt = (other.surface.coef.ravel() - inner.surface.coef.ravel()) / (h1 - h0)
    tilt -= float(rec.integrator.roi_mean(tilt))
    step = 3e-4
    assert step * 1e3 <= LINEAR_STEP_UM
    moved = rec._moved(inner, step, tilt, coords, rays)
    ran = rec.inner_loop(h0 + step, coords, rays, inner.surface)
    gx, gy = sub.roi_grid(0.5)

    def shape_rms(a, b) -> float:
        d = a.height(gx, gy) - b.height(gx, gy)
        return float(np.sqrt(np.mean((d - d.mean()) ** 2)))

    shifted = inner.surface.with_coef(inner.surface.coef.ravel() + step)
    assert shape_rms(moved.surface, ran.surface) < 2e-6
    assert shape_rms(shifted, ran.surface) > 5 * shape_rms(moved.surface, ran.surface)
    assert len(moved.obs) == len(ran.obs)


def test_the_frame_loop_hands_over_to_the_posterior_near_its_root(case, monkeypatch):
    """With the frame posterior, the loop stops within POSTERIOR_HANDOFF_UM of the fitted criterion's root and the
    posterior's Newton steps take the start height from there: fewer start heights than the loop run to its root,
    the same start height within a few nm (a small part of its uncertainty). Where the posterior cannot be formed
    after a hand-over, the loop goes on to the fitted root: the spline's own result."""
    from scopetwin.recon.fringes import reconstruct as fr

    setup, heights, maps, _ = case
    coords = _decode(setup, maps, 1)
    handed = reconstruct_fringes(setup, coords)
    with monkeypatch.context() as m:
        m.setattr(fr, "POSTERIOR_HANDOFF_UM", 0.0)  # never: to the root
        full = reconstruct_fringes(setup, coords)
    assert handed.converged and full.converged
    assert len(handed.history) < len(full.history), (handed.history, full.history)
    dh_um = abs(handed.start_height_mm - full.start_height_mm) * 1e3
    assert dh_um < 0.005 and dh_um < 0.1 * full.absolute_um, (dh_um, full.absolute_um)
    spline = reconstruct_fringes(setup, coords, FringeConfig(frame_posterior=False))
    monkeypatch.setattr(fr.FringeReconstructor, "posterior_start_height", lambda *args, **kwargs: None)
    fallback = reconstruct_fringes(setup, coords)
    assert fallback.converged and abs(fallback.history[-1].criterion_um) <= FringeConfig().outer_tol_um
    assert fallback.start_height_mm == spline.start_height_mm
    assert fallback.absolute_um == pytest.approx(spline.absolute_um, rel=1e-9)
