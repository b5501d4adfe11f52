"""The basis scale chosen from the data (beyond the thesis's fixed §1.8 scales): among the scales that fit, the one
that best extrapolates towards the holding frame (§1.4)."""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from scopetwin.recon.config import ReconstructionConfig
from scopetwin.recon.parallel import thread_map
from scopetwin.recon.shifted_basis import ShiftedBasis
from scopetwin.recon.substrate import Substrate2D
from scopetwin.scenes.geometry import Array


def select_sigma(
    sub: Substrate2D,
    x: Array,
    y: Array,
    hx: Array,
    hy: Array,
    config: ReconstructionConfig,
    max_threads: int | None = None,
) -> tuple[float, dict[float, float], dict[float, float]]:
    """Basis scale from the data: among the scales that fit the data, the one that best extrapolates.

    A scale fits when its residual on all the gradients is at most ``config.fit_ratio`` times the smallest
    residual of the candidates (a basis too coarse for the surface — a 12 mm Gaussian on a 3 mm correlated
    glass — leaves hundreds of µrad and would otherwise win by extrapolating smoothly). Among those, for each end
    of the data along y the markers within ``config.holdout_band`` mm of the data's edge are held out, the basis
    is fitted to the rest, and the RMS gradient error on the held-out band is measured: the same extrapolation the
    frame criterion relies on (thesis §1.4). The scale with the smallest RMS over both ends wins. Returns
    (sigma, {sigma: held-out score in µrad}, {sigma: residual of the fit to all gradients in µrad}).

    The candidates are fitted on up to ``max_threads`` threads (default: every CPU the process may use,
    :func:`scopetwin.recon.parallel.thread_map`); their products and factorisations release the interpreter lock.
    """
    scores: dict[float, float] = {}
    fits: dict[float, float] = {}
    ends = [y >= y.max() - config.holdout_band, y <= y.min() + config.holdout_band]
    candidates = [float(s) for s in config.sigma_candidates or ()]

    def one(sigma: float) -> tuple[float, list[float]]:
        return _fit_and_holdouts(config.make_basis(sub, sigma), x, y, hx, hy, ends, config.regularization)

    for sigma, (fit, errs) in zip(candidates, thread_map(one, candidates, max_threads), strict=True):
        fits[float(sigma)] = fit * 1e6
        if errs:
            scores[float(sigma)] = float(np.sqrt(np.mean(errs)) * 1e6)
    if not scores:
        return float(config.sigma[0]), scores, fits
    floor = min(fits.values())
    fitting = [s for s in scores if fits[s] <= config.fit_ratio * floor] or list(scores)
    return min(fitting, key=scores.__getitem__), scores, fits


def _fit_and_holdouts(
    basis: ShiftedBasis, x: Array, y: Array, hx: Array, hy: Array, ends: list[NDArray[np.bool_]], regularization: float
) -> tuple[float, list[float]]:
    """RMS gradient residual of the fit to all markers, and per held-out end the mean squared gradient error of the
    fit to the rest on it (both components summed), rad and rad^2.

    The same ridge fits as :func:`scopetwin.recon.shifted_basis.fit_gradients` (lambda from the fitted rows' own
    column norms), by the normal equations: the Gram matrix of all rows is formed once and each held-out band's rows
    are subtracted from it, so one scale costs one product and three Cholesky factorisations instead of three
    least-squares solves (the scores rank scales; the normal equations' round-off, ~1e-7 relative with the ridge,
    does not change a ranking).
    """
    px, py = basis.derivatives(x, y)
    a = np.concatenate([px, py], axis=0)
    b = np.concatenate([hx, hy])
    nb = basis.n_basis
    gram, rhs = a.T @ a, a.T @ b
    col = np.einsum("ij,ij->j", a[:, :nb], a[:, :nb])
    errs = []
    for test in ends:
        if test.all() or (~test).sum() * 2 < basis.n_terms // 4:
            continue
        rows = np.concatenate([test, test])
        at, bt = a[rows], b[rows]
        lam = regularization * float(np.mean(col - np.einsum("ij,ij->j", at[:, :nb], at[:, :nb])))
        coef = _ridge(gram - at.T @ at, rhs - at.T @ bt, nb, lam)
        errs.append(float(np.mean((at @ coef - bt) ** 2) * 2.0))
    coef = _ridge(gram, rhs, nb, regularization * float(np.mean(col)))  # the last use of gram: no copy
    fit = float(np.sqrt(np.mean((a @ coef - b) ** 2) * 2.0))
    return fit, errs


def _ridge(m: NDArray[np.float64], rhs: Array, nb: int, lam: float) -> Array:
    """Solve (m + lam on the first ``nb`` diagonal entries) c = rhs (Cholesky; least squares if singular); ``m`` (a
    Gram matrix) is overwritten."""
    m[np.arange(nb), np.arange(nb)] += lam
    try:
        # numpy's factorisation releases the interpreter lock (SciPy's wrappers hold it): threads fit side by side
        return np.asarray(sla.cho_solve((np.linalg.cholesky(m), True), rhs, check_finite=False))
    except np.linalg.LinAlgError:
        return np.asarray(sla.lstsq(m, rhs, lapack_driver="gelsy", check_finite=False)[0])
