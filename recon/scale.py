"""The basis scale chosen from the data (beyond the thesis's fixed §1.8 scales): among the scales that fit, the one
that best extrapolates towards the holding frame (§1.4)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from scopetwin.recon.config import ReconstructionConfig
from scopetwin.recon.lapack import cholesky_solve
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

    The candidates' normal equations, then their fits, are computed on up to ``max_threads`` threads (default: every
    CPU the process may use, :func:`scopetwin.recon.parallel.thread_map`); their products and factorisations release
    the interpreter lock.
    """
    ends = [y >= y.max() - config.holdout_band, y <= y.min() + config.holdout_band]
    candidates = [float(s) for s in config.sigma_candidates or ()]
    # two passes over the threads: every candidate's normal equations, then every ridge fit of them (the finest
    # scale's three factorisations are most of the work; its fits run beside the other candidates')
    normals = thread_map(lambda s: _Normal.of(config.make_basis(sub, s), x, y, hx, hy), candidates, max_threads)
    jobs = [(k, test) for k, nrm in enumerate(normals) for test in [*nrm.held_out(ends), None]]
    jobs.sort(key=lambda job: -normals[job[0]].size)  # the largest first: the threads end together
    errors = thread_map(lambda job: normals[job[0]].error(job[1], config.regularization), jobs, max_threads)
    fits: dict[float, float] = {}
    held: dict[float, list[float]] = {}
    for (k, test), err in zip(jobs, errors, strict=True):
        if test is None:
            fits[candidates[k]] = float(np.sqrt(err)) * 1e6
        else:
            held.setdefault(candidates[k], []).append(err)
    scores = {s: float(np.sqrt(np.mean(e)) * 1e6) for s, e in held.items()}
    if not scores:
        return float(config.sigma[0]), scores, fits
    floor = min(fits.values())
    fitting = [s for s in scores if fits[s] <= config.fit_ratio * floor] or list(scores)
    return min(fitting, key=scores.__getitem__), scores, fits


@dataclass(frozen=True)
class _Normal:
    """One scale's ridge fits by the normal equations: the same fits as
    :func:`scopetwin.recon.shifted_basis.fit_gradients` (lambda from the fitted rows' own column norms). The Gram
    matrix of all rows is formed once and each held-out band's rows are subtracted from it, so a scale costs one
    product and three Cholesky factorisations instead of three least-squares solves (the scores rank scales; the
    normal equations' round-off, ~1e-7 relative with the ridge, does not change a ranking)."""

    a: Array  # the design matrix [Psi_x; Psi_y], (2n, terms)
    b: Array  # the gradients [hx; hy]
    gram: Array
    rhs: Array
    col: Array  # the basis functions' column norms (without the plane terms)
    nb: int  # basis functions (the plane terms after them are not damped)

    @classmethod
    def of(cls, basis: ShiftedBasis, x: Array, y: Array, hx: Array, hy: Array) -> _Normal:
        px, py = basis.derivatives(x, y)
        a = np.concatenate([px, py], axis=0)
        b = np.concatenate([hx, hy])
        nb = basis.n_basis
        return cls(a, b, a.T @ a, a.T @ b, np.einsum("ij,ij->j", a[:, :nb], a[:, :nb]), nb)

    @property
    def size(self) -> int:
        return len(self.gram)

    def held_out(self, ends: list[NDArray[np.bool_]]) -> list[NDArray[np.bool_]]:
        """The ends that can be held out: some markers in them, enough left to fit (a quarter of the terms)."""
        return [t for t in ends if not (t.all() or (~t).sum() * 2 < len(self.gram) // 4)]

    def error(self, test: NDArray[np.bool_] | None, regularization: float) -> float:
        """Mean squared gradient error (both components summed, rad^2) on the held-out markers ``test`` of the fit
        to the rest; ``test`` None: of the fit to all markers on all of them."""
        if test is None:
            coef = _ridge(self.gram.copy(), self.rhs, self.nb, regularization * float(np.mean(self.col)))
            return float(np.mean((self.a @ coef - self.b) ** 2) * 2.0)
        rows = np.concatenate([test, test])
        at, bt = self.a[rows], self.b[rows]
        lam = regularization * float(np.mean(self.col - np.einsum("ij,ij->j", at[:, : self.nb], at[:, : self.nb])))
        coef = _ridge(self.gram - at.T @ at, self.rhs - at.T @ bt, self.nb, lam)
        return float(np.mean((at @ coef - bt) ** 2) * 2.0)


def _ridge(m: NDArray[np.float64], rhs: Array, nb: int, lam: float) -> Array:
    """Solve (m + lam on the first ``nb`` diagonal entries) c = rhs (Cholesky; least squares if singular); ``m`` (a
    Gram matrix) is overwritten."""
    m[np.arange(nb), np.arange(nb)] += lam
    try:
        # without the interpreter lock: threads fit side by side, and beside an evidence search in a thread
        return cholesky_solve(m.copy(), rhs)
    except np.linalg.LinAlgError:
        return np.asarray(sla.lstsq(m, rhs, lapack_driver="gelsy", check_finite=False)[0])
