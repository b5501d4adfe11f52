"""Pixel blocks (recon/fringes/blocks.py) and the integration's normal matrix built straight into its band.

Synthetic display points: an affine field over a 240 x 180 pixel image plus a smooth quadratic term, with the
decoder's stated noise (sigma_dec, varying per pixel) scaled by an unstated factor F = 1.8 (as a render's sampling
error). Acceptance: the block average finds F within 10 %, the block values' (and single pixels') errors against the
noiseless field at the block centres have a mean square of 1 +- 0.1 of their stated variance (and 2.5x that were F
left out), F = 1 within 0.15 when there is no unstated noise; on a map curved at the scale of a few blocks the block
values miss the centre rays' points by under 30 % of the plain means' bias; the rays of a block pass through its
centre; the banded normal matrix equals A^T A + D^T D / kappa^2 of the sparse design matrix to 1e-12 relative.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from scopetwin.recon.fringes.blocks import block_average, block_size, pixel_footprint_mm
from scopetwin.recon.fringes.integration import SlopeIntegrator
from scopetwin.recon.fringes.phase import DisplayCoordinates, FringeDecodingError
from scopetwin.recon.fringes.slopes import PixelRays, SlopeObservations
from scopetwin.recon.substrate import Substrate2D

ROWS, COLS = 180, 240
SIGMA_DEC, FACTOR = 1.5e-3, 1.8  # mm; the true scatter over the decoder's sigma


def _field() -> tuple[np.ndarray, np.ndarray]:
    r, c = np.mgrid[0:ROWS, 0:COLS].astype(float) + 0.5
    return _field_at(r, c)


def _coords(factor: float, seed: int, block: int) -> tuple[DisplayCoordinates, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    u, v = _field()
    sigma = SIGMA_DEC * (1.0 + 0.5 * rng.random((ROWS, COLS)))  # the decoder's per-pixel noise, varying
    noisy = [a + rng.normal(0.0, 1.0, a.shape) * sigma * factor for a in (u, v)]
    valid = np.ones((ROWS, COLS), dtype=bool)
    valid[:7, :] = False  # a partial band of blocks at the top
    valid[100, 50] = False
    uv = np.stack(noisy, axis=-1)
    coords = DisplayCoordinates.from_arrays(np.where(valid[..., None], uv, np.nan), np.stack([sigma, sigma], -1))
    # the noiseless field at the block centres ((c + 0.5) b, (r + 0.5) b)
    rc, cc = (np.mgrid[0 : ROWS // block, 0 : COLS // block] + 0.5) * block
    centre = _field_at(rc, cc)
    return coords, centre[0], centre[1]


def _field_at(r: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    u = -20.0 + 0.15 * c + 0.01 * r + 1e-6 * (c - 120) ** 2
    v = -15.0 + 0.02 * c + 0.16 * r - 1e-6 * (r - 90) ** 2
    return u, v


@pytest.mark.parametrize("block", [3, 4])
def test_block_average_finds_the_unstated_noise_and_covers(block):
    coords, tu, tv = _coords(FACTOR, 7, block)
    avg, noise = block_average(coords, block)
    assert avg.block == block and avg.shape == (ROWS // block, COLS // block)
    assert not avg.valid[: 7 // block + 1].any() or block == 1  # tiles with an undecoded pixel are dropped
    assert not avg.valid[100 // block, 50 // block] and avg.valid.sum() > 0.9 * avg.valid.size
    for found in (noise.factor_u, noise.factor_v):
        assert abs(found / FACTOR - 1.0) < 0.1, found
    ok = avg.valid
    for mean, std, true in ((avg.u, avg.u_std, tu), (avg.v, avg.v_std, tv)):
        z2 = np.mean(((mean[ok] - true[ok]) / std[ok]) ** 2)
        assert abs(z2 - 1.0) < 0.1, z2
        stated_only = std[ok] ** 2 / FACTOR**2  # what the decoder's noise alone would have said
        assert np.mean((mean[ok] - true[ok]) ** 2 / stated_only) > 2.5


def test_single_pixels_carry_the_unstated_noise():
    coords, _, _ = _coords(FACTOR, 10, 1)
    kept, noise = block_average(coords, 1)
    assert kept.block == 1 and np.array_equal(kept.valid, coords.valid)
    assert abs(noise.factor_u / FACTOR - 1.0) < 0.1 and abs(noise.factor_v / FACTOR - 1.0) < 0.1
    u, v = _field()
    ok = kept.valid
    for est, std, true in ((kept.u, kept.u_std, u), (kept.v, kept.v_std, v)):
        z2 = np.mean(((est[ok] - true[ok]) / std[ok]) ** 2)
        assert abs(z2 - 1.0) < 0.05, z2


def test_no_unstated_noise_is_found_where_there_is_none():
    coords, tu, _ = _coords(1.0, 8, 4)
    avg, noise = block_average(coords, 4)
    assert noise.factor_u < 1.15 and noise.factor_v < 1.15
    z2 = np.mean(((avg.u[avg.valid] - tu[avg.valid]) / avg.u_std[avg.valid]) ** 2)
    assert abs(z2 - 1.0) < 0.1, z2


def test_block_values_are_the_centre_rays_display_points_on_a_curved_map():
    """A display-point map curved along the rows as the short-wavelength detail of a glass sheet curves it (a
    sinusoid of 13 pixels, 0.1 mm display amplitude: f_rr up to 23 µm per pixel^2), each pixel the mean of the map
    over its own box (sampled 8 x 8), no noise: the block values lie within 30 % of the plain means' bias from the
    map at the block centres (interior blocks), and the stated variance grows by CENTRE_VARIANCE_FACTOR."""
    from scopetwin.recon.fringes.blocks import CENTRE_VARIANCE_FACTOR

    wave, amp, block = 13.0, 0.1, 3
    k = 2 * np.pi / wave

    def field(r: np.ndarray, c: np.ndarray) -> np.ndarray:
        return 0.05 * r + 0.002 * c + amp * np.sin(k * r)

    sub = (np.arange(8) + 0.5) / 8 - 0.5  # an 8 x 8 grid over each pixel's box
    r, c = np.mgrid[0:ROWS, 0:COLS].astype(float) + 0.5
    pixel = np.mean([field(r + a, c + b) for a in sub for b in sub], axis=0)
    coords = DisplayCoordinates.from_arrays(np.stack([pixel, pixel], -1), 1e-4)
    avg, noise = block_average(coords, block)
    rc, cc = (np.mgrid[0 : ROWS // block, 0 : COLS // block] + 0.5) * block
    truth = field(rc, cc)
    plain = pixel.reshape(ROWS // block, block, COLS // block, block).mean(axis=(1, 3))
    inner = np.s_[1:-1, 1:-1]
    bias_plain = np.sqrt(np.mean((plain - truth)[inner] ** 2))
    bias_now = np.sqrt(np.mean((avg.u - truth)[inner] ** 2))
    assert bias_plain > 4e-3  # the plain means miss the centre rays' points by micrometres
    assert bias_now < 0.3 * bias_plain, (bias_now, bias_plain)  # 0.98 of the wave kept instead of 0.91
    stated = noise.factor_u * 1e-4 * np.sqrt(CENTRE_VARIANCE_FACTOR) / block
    np.testing.assert_allclose(avg.u_std[avg.valid], stated, rtol=1e-9)


def test_bad_blocks_are_refused():
    coords, _, _ = _coords(1.0, 9, 2)
    with pytest.raises(FringeDecodingError, match="at least 1 pixel"):
        block_average(coords, 0)
    avg, _ = block_average(coords, 2)
    with pytest.raises(FringeDecodingError, match="already averaged"):
        block_average(avg, 2)


def test_block_rays_pass_through_block_centres_and_size_follows_the_knots():
    import scopetwin

    setup = scopetwin.load_setup("thesis-1.10-fringes")
    cam, sub = setup.camera_model, Substrate2D.from_setup(setup)
    valid = np.zeros((cam.ny // 3, cam.nx // 3), dtype=bool)
    valid[100, 200] = valid[5, 7] = True
    rays = PixelRays.of(cam, valid, 3)
    o, d = cam.rays(np.array([[3 * 7 + 1.5, 3 * 5 + 1.5], [3 * 200 + 1.5, 3 * 100 + 1.5]]))
    np.testing.assert_allclose(rays.dirs, d, atol=1e-12)
    foot = pixel_footprint_mm(cam, sub)
    assert 0.03 < foot < 0.08  # 4.65 µm pixels at a magnification of ~0.09
    assert block_size(cam, sub, 0.4) == int(0.2 // foot) == 3
    assert block_size(cam, sub, 0.05) == 1
    with pytest.raises(FringeDecodingError, match="in 3-pixel blocks"):
        PixelRays.of(cam, np.zeros((cam.ny, cam.nx), dtype=bool), 3)


def _scattered(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """n slope positions over the ROI (mm) and their covariances (c11, c12, c22; ~1e-10 rad^2, correlation 0.3)."""
    xy = np.column_stack([rng.uniform(-10, 10, n), rng.uniform(-20, 20, n)])
    c11, c22 = rng.uniform(1, 2, n) * 1e-10, rng.uniform(1, 2, n) * 1e-10
    return xy, np.column_stack([c11, 0.3 * np.sqrt(c11 * c22), c22])


def test_banded_normal_matrix_equals_the_sparse_one():
    import scopetwin

    sub = Substrate2D.from_setup(scopetwin.load_setup("thesis-1.10-fringes"))
    integ = SlopeIntegrator(sub, 0.8, 1e-3)
    rng = np.random.default_rng(3)
    n = 5000
    xy, cov = _scattered(rng, n)
    obs = SlopeObservations(np.arange(n), xy, rng.normal(0, 1e-3, n), rng.normal(0, 1e-3, n), cov, np.zeros((n, 3)))
    rows = integ._whitened(obs)
    band = integ._normal_band(rows)
    indptr = np.arange(0, 16 * n + 1, 16)
    a = sp.vstack(
        [sp.csr_matrix((r.ravel(), rows.idx.ravel(), indptr), shape=(n, integ.n_coef)) for r in (rows.r1, rows.r2)]
    )
    normal = (a.T @ a + integ.prior.T @ integ.prior).toarray()
    kd = integ.kd
    dense = np.zeros_like(normal)
    for k in range(kd + 1):
        i = np.arange(integ.n_coef - (kd - k))
        dense[i, i + kd - k] = band[k, kd - k + i]
    np.testing.assert_allclose(np.triu(dense), np.triu(normal), rtol=1e-12, atol=1e-12 * np.abs(normal).max())


def test_warm_solve_gives_the_factorised_solution_and_posterior():
    """An integration preconditioned by an earlier one's factorisation (observations moved by a few µm, slopes by
    their noise) gives the surface and posterior draws of its own factorisation; a warm start from far-off
    observations (a quarter of them) factorises afresh and gives them too."""
    import scopetwin

    sub = Substrate2D.from_setup(scopetwin.load_setup("thesis-1.10-fringes"))
    integ = SlopeIntegrator(sub, 0.8, 1e-3)
    rng = np.random.default_rng(5)
    n = 6000
    xy, cov = _scattered(rng, n)
    hx, hy = 2e-3 * xy[:, 0] / 10 + rng.normal(0, 1e-5, n), -1e-3 * xy[:, 1] / 20 + rng.normal(0, 1e-5, n)
    obs = SlopeObservations(np.arange(n), xy, hx, hy, cov, np.zeros((n, 3)))
    earlier = integ.solve(obs, 0.01)
    moved = SlopeObservations(
        obs.index, xy + rng.normal(0, 2e-3, xy.shape), hx + rng.normal(0, 1e-5, n), hy, cov * 1.01, obs.hit
    )
    cold = integ.solve(moved, 0.01)
    far = integ.solve(SlopeObservations(obs.index[::4], xy[::4], hx[::4], hy[::4], cov[::4], obs.hit[::4]), 0.01)
    gx, gy = sub.roi_grid(0.5)
    reference = integ.with_samples(cold, 32, 1)
    std = np.std(np.asarray(integ.spline.design(gx, gy) @ reference.samples.T), axis=1)
    for start, preconditioned in ((earlier, True), (far, False)):
        warm = integ.solve(moved, 0.01, warm=start)
        assert (not warm.exact and warm.cg_iterations > 0) == preconditioned
        diff = warm.surface.height(gx, gy) - cold.surface.height(gx, gy)
        assert np.max(np.abs(diff)) < 1e-3 * std.min()  # a thousandth of the heights' own uncertainty
        assert warm.chi2_per_dof == pytest.approx(cold.chi2_per_dof, rel=1e-8)
        drawn = integ.with_samples(warm, 32, 1)
        assert drawn.exact
        np.testing.assert_allclose(drawn.samples, reference.samples, atol=1e-8 * np.abs(reference.samples).max())
