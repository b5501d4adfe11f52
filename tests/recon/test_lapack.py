"""recon.lapack: SciPy's own triangular solve and Cholesky inverse called without the interpreter lock, against
SciPy's wrappers of the same routines."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

from scopetwin.recon.lapack import (
    BLOCK,
    cholesky_lower,
    cholesky_solve,
    factor_solve,
    lower_inverse,
    solve_lower,
    solve_lower_blocks,
)


@pytest.fixture
def factor() -> tuple[np.ndarray, np.ndarray]:
    """A kernel-like SPD matrix's cho_factor (Fortran order, the matrix's own values left above the diagonal) and
    numpy's factor of it (C order, zeros above)."""
    rng = np.random.default_rng(3)
    a = rng.standard_normal((300, 300))
    k = a @ a.T + 300 * np.eye(300)
    return sla.cho_factor(k, lower=True, check_finite=False)[0], np.linalg.cholesky(k)


@pytest.mark.parametrize("count", [0, 1, BLOCK, BLOCK + 1, 3 * BLOCK - 7])
def test_the_solve_is_scipys_in_either_order(factor, count):
    f_low, c_low = factor
    rhs = np.random.default_rng(count).standard_normal((count, 300))
    ref = sla.solve_triangular(c_low, rhs.T, lower=True, check_finite=False)
    for low in (f_low, c_low):
        x = solve_lower(low, rhs)
        assert x.shape == (300, count) and x.flags.f_contiguous
        np.testing.assert_allclose(x, ref, rtol=0, atol=1e-14 * max(np.abs(ref).max(initial=0.0), 1.0))


def test_the_result_does_not_depend_on_the_threads(factor):
    rhs = np.random.default_rng(4).standard_normal((2 * BLOCK + 5, 300))
    one = solve_lower(factor[0], rhs, max_threads=1)
    assert np.array_equal(one, solve_lower(factor[0], rhs, max_threads=2))
    made = solve_lower_blocks(factor[0], len(rhs), lambda a, b: rhs[a:b], max_threads=2)
    assert np.array_equal(one, made)


def test_the_inverse_is_scipys_potri(factor):
    f_low = np.asfortranarray(np.tril(factor[0]))
    ref, info = sla.lapack.dpotri(f_low.copy(order="F"), lower=1)
    assert info == 0
    got = lower_inverse(f_low.copy(order="F"))
    assert np.array_equal(np.tril(got), np.tril(ref))
    k = factor[1] @ factor[1].T
    np.testing.assert_allclose(np.tril(got) + np.tril(got, -1).T, np.linalg.inv(k), rtol=1e-10)


def test_bad_input_is_refused(factor):
    with pytest.raises(ValueError, match="square float64"):
        solve_lower(np.zeros((3, 4)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="length 300"):
        solve_lower(factor[0], np.zeros((2, 5)))
    with pytest.raises(ValueError, match="contiguous"):
        solve_lower(np.zeros((600, 600))[::2, ::2], np.zeros((1, 300)))
    with pytest.raises(ValueError, match="Fortran order"):
        lower_inverse(factor[1])
    singular = np.zeros((3, 3), order="F")
    with pytest.raises(np.linalg.LinAlgError, match="potri"):
        lower_inverse(singular)


def test_the_cholesky_solve_is_scipys(factor):
    k = factor[1] @ factor[1].T
    rhs = np.random.default_rng(5).standard_normal((300, 3))
    ref = sla.cho_solve(sla.cho_factor(k, lower=True), rhs)
    for order in ("C", "F"):
        for b in (rhs, rhs[:, 0]):
            m = np.array(k, order=order)
            np.testing.assert_allclose(cholesky_solve(m, b), ref if b.ndim == 2 else ref[:, 0], rtol=1e-11)
            stored = np.tril(m.T if order == "C" else m)  # the factor, in the lower triangle as LAPACK sees it
            np.testing.assert_allclose(stored, np.linalg.cholesky(k), rtol=0, atol=1e-12 * np.abs(stored).max())


def test_a_matrix_that_is_not_positive_definite_is_refused():
    with pytest.raises(np.linalg.LinAlgError, match="not positive definite"):
        cholesky_solve(np.diag([1.0, -1.0, 2.0]), np.ones(3))
    with pytest.raises(ValueError, match="length 3"):
        cholesky_solve(np.eye(3), np.ones(4))


def test_scipys_wrappers_serve_where_the_routines_are_not_exported_as_expected(factor, monkeypatch):
    """A SciPy whose capsules carry another signature (another integer width): the same results through SciPy's own
    wrappers."""
    import scopetwin.recon.lapack as lapack

    rhs = np.random.default_rng(6).standard_normal((BLOCK + 3, 300))
    k = factor[1] @ factor[1].T
    f_low = np.asfortranarray(np.tril(factor[0]))
    direct = (solve_lower(factor[0], rhs), lower_inverse(f_low.copy(order="F")), cholesky_solve(k.copy(), rhs[0]))
    monkeypatch.setattr(lapack, "_routine", lambda module, name: None)
    wrapped = (solve_lower(factor[0], rhs), lower_inverse(f_low.copy(order="F")), cholesky_solve(k.copy(), rhs[0]))
    np.testing.assert_allclose(direct[0], wrapped[0], rtol=0, atol=1e-14 * np.abs(direct[0]).max())
    assert np.array_equal(np.tril(direct[1]), np.tril(wrapped[1]))  # the same LAPACK routine
    np.testing.assert_allclose(direct[2], wrapped[2], rtol=1e-11)
    with pytest.raises(np.linalg.LinAlgError, match="not positive definite"):
        cholesky_solve(np.diag([1.0, -1.0, 2.0]), np.ones(3))


def test_every_routine_is_exported_with_the_expected_signature():
    import scopetwin.recon.lapack as lapack

    for module, name in [("cython_blas", "dtrsm"), *(("cython_lapack", n) for n in ("dpotri", "dpotrf", "dpotrs"))]:
        assert lapack._routine(module, name) is not None, name


@pytest.mark.parametrize("n", [1, 200, 501])
def test_the_factor_in_place_is_the_cholesky_factor(n, monkeypatch):
    import scopetwin.recon.lapack as lapack

    x = np.random.default_rng(n).standard_normal((n, n))
    k = x @ x.T + n * np.eye(n)
    for export in (True, False):
        if not export:
            monkeypatch.setattr(lapack, "_routine", lambda module, name: None)
        low = cholesky_lower(k.copy())
        assert low.flags.f_contiguous and not np.triu(low, 1).any()
        np.testing.assert_allclose(low, np.linalg.cholesky(k), rtol=0, atol=1e-13 * np.abs(low).max())
    with pytest.raises(np.linalg.LinAlgError, match="not positive definite"):
        cholesky_lower(np.diag([1.0, -1.0, 2.0]))


def test_the_factor_solve_is_scipys_cho_solve(factor, monkeypatch):
    import scopetwin.recon.lapack as lapack

    f_low = np.asfortranarray(np.tril(factor[0]))
    rhs = np.random.default_rng(7).standard_normal((300, 2))
    ref = sla.cho_solve((f_low, True), rhs)
    assert np.array_equal(factor_solve(f_low, rhs), ref)  # the same LAPACK routine on the same memory
    assert np.array_equal(factor_solve(f_low, rhs[:, 1]), ref[:, 1])
    monkeypatch.setattr(lapack, "_routine", lambda module, name: None)
    assert np.array_equal(factor_solve(f_low, rhs), ref)
    with pytest.raises(ValueError, match="Fortran order"):
        factor_solve(np.ascontiguousarray(f_low), rhs)
