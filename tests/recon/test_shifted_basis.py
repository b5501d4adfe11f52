"""Shifted basis functions (thesis §1.8): fits of constructed gradient data recover the known heights."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.recon.shifted_basis import BasisError, SBFSurface, ShiftedBasis, fit_gradients


def _samples(rng: np.random.Generator, n: int = 600):
    return rng.uniform(-12, 12, n), rng.uniform(-24, 24, n)


@pytest.mark.parametrize("kind", ["imq", "gauss"])
def test_fit_recovers_a_surface_in_the_span(rng: np.random.Generator, kind: str) -> None:
    basis = ShiftedBasis.grid((5, 9), (-12.6, 12.6), (-28.5, 28.5), (6.0, 7.0), kind)
    truth = SBFSurface(basis, rng.normal(0, 0.01, basis.n_terms))
    x, y = _samples(rng)
    gx, gy = truth.gradient(x, y)
    coef, resid = fit_gradients(basis, x, y, gx, gy)
    fit = SBFSurface(basis, coef)
    xe, ye = _samples(rng, 400)
    err = fit.height(xe, ye) - truth.height(xe, ye)
    assert resid < 1e-12
    assert np.std(err) < 1e-9  # heights without integration, up to the constant of integration


def test_derivatives_match_finite_differences(rng: np.random.Generator) -> None:
    for kind in ("imq", "gauss"):
        basis = ShiftedBasis.grid((4, 6), (-10, 10), (-20, 20), (4.0, 3.0), kind, tilt=True)
        s = SBFSurface(basis, rng.normal(0, 1, basis.n_terms))
        x, y = _samples(rng, 50)
        gx, gy = s.gradient(x, y)
        e = 1e-6
        fx = (s.height(x + e, y) - s.height(x - e, y)) / (2 * e)
        fy = (s.height(x, y + e) - s.height(x, y - e)) / (2 * e)
        assert np.max(np.abs(gx - fx)) < 1e-7 and np.max(np.abs(gy - fy)) < 1e-7


def test_tilt_terms_carry_a_plane_and_solvers_agree(rng: np.random.Generator) -> None:
    basis = ShiftedBasis.covering((-12.6, 12.6), (-28.5, 28.5), 12.0)
    x, y = _samples(rng)
    a, b = 2.5e-4, -1.25e-4
    smooth = lambda x, y: 3e-3 * np.cos(x / 9.0) * np.sin(y / 13.0)  # noqa: E731
    gx = a - 3e-3 / 9.0 * np.sin(x / 9.0) * np.sin(y / 13.0)
    gy = b + 3e-3 / 13.0 * np.cos(x / 9.0) * np.cos(y / 13.0)
    out = {}
    for method in ("lstsq", "normal"):
        coef, _ = fit_gradients(basis, x, y, gx, gy, regularization=1e-10, method=method)
        s = SBFSurface(basis, coef)
        xe, ye = _samples(rng, 300)
        err = s.height(xe, ye) - (a * xe + b * ye + smooth(xe, ye))
        out[method] = err - err.mean()
        assert np.std(err) < 2e-8  # < 0.02 nm on a 3 µm + tilt surface
    assert np.max(np.abs(out["lstsq"] - out["normal"])) < 1e-8


def test_regularisation_damps_the_coefficients(rng: np.random.Generator) -> None:
    basis = ShiftedBasis.grid((9, 17), (-12.6, 12.6), (-28.5, 28.5), (3.0, 3.0), "imq")
    x, y = _samples(rng, 300)
    gx, gy = rng.normal(0, 1e-3, 300), rng.normal(0, 1e-3, 300)
    c0, _ = fit_gradients(basis, x, y, gx, gy)
    c1, _ = fit_gradients(basis, x, y, gx, gy, regularization=1e-3)
    assert np.linalg.norm(c1) < 0.5 * np.linalg.norm(c0)


def test_bad_requests() -> None:
    basis = ShiftedBasis.grid((9, 17), (-1, 1), (-1, 1), (1.0, 1.0))
    with pytest.raises(BasisError, match="cannot determine"):
        fit_gradients(basis, np.zeros(10), np.zeros(10), np.zeros(10), np.zeros(10))
    with pytest.raises(BasisError, match="NaN"):
        fit_gradients(basis, [np.nan], [0.0], [0.0], [0.0], regularization=1.0)
    with pytest.raises(BasisError, match="sigma"):
        ShiftedBasis.grid((2, 2), (-1, 1), (-1, 1), (0.0, 1.0))


@pytest.mark.parametrize("sigma", [2.0, 15.0])
def test_the_semi_normal_least_squares_is_qr_on_the_stacked_design(rng: np.random.Generator, sigma: float) -> None:
    """The default least squares (corrected semi-normal equations) gives the stacked design's QR solution: fitted
    gradients within 1e-11 of the largest, on a basis wider than the data (2 mm: 2,145 terms for 1,200 equations,
    the ridge decides) and a coarse one (165 terms); where the normal equations have no factor (no ridge, more terms
    than equations), QR decides."""
    from scopetwin.recon.shifted_basis import _solve_lstsq, _solve_stacked

    basis = ShiftedBasis.covering((-12.6, 12.6), (-28.5, 28.5), sigma)
    x, y = _samples(rng)
    px, py = basis.derivatives(x, y)
    a = np.concatenate([px, py])
    g = a @ rng.standard_normal(a.shape[1]) * 1e-6 + 1e-7 * rng.standard_normal(len(a))
    nb = basis.n_basis
    lam = 1e-9 * float(np.mean(np.einsum("ij,ij->j", a[:, :nb], a[:, :nb])))
    fast, qr = _solve_lstsq(a, g, nb, lam), _solve_stacked(a, g, nb, lam)
    assert np.max(np.abs(a @ fast - a @ qr)) <= 1e-11 * np.max(np.abs(g))
    wide = np.concatenate([a, a[:, :5]], axis=1)[: a.shape[1] // 2]  # repeated columns: a singular Gram matrix
    np.testing.assert_array_equal(
        _solve_lstsq(wide, g[: len(wide)], 0, 0.0), _solve_stacked(wide, g[: len(wide)], 0, 0.0)
    )
