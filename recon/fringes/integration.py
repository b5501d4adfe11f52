"""Integration of dense slope observations into heights, with the posterior uncertainty (beyond thesis §1.8).

The surface is a uniform cubic B-spline over the substrate's base plane (:class:`scopetwin.recon.spline.SplineSurface`,
the weights of :mod:`scopetwin.scenes.bspline`) with knots a fraction of a millimetre apart. Its coefficients c solve
the sparse least-squares problem

    min_c  sum_i r_i^T C_i^{-1} r_i  +  |D c|^2 / kappa^2,     r_i = (h_x, h_y)(x_i, y_i; c) - g_i,

with C_i the 2 x 2 covariance of observation i's gradients (from the display points' noise, :mod:`.slopes`) and D
the second differences (xx, yy, sqrt(2) xy) of the coefficient grid per mm^2: a curvature (thin-plate) prior under
which the curvature of every knot cell is N(0, kappa^2). The slopes leave the constant free; the surface is put at
the requested mean height over the region of interest afterwards (thesis eq. 1.5). The normal matrix is banded
(bandwidth 3 knot rows + 3): each observation's 16 B-spline weights are accumulated into its band directly (no
sparse design matrix), and it is factorised by LAPACK's banded Cholesky (scipy.linalg.cholesky_banded).

Posterior by perturbation: re-solving with the observations perturbed by their noise and the prior by draws of its
own distribution gives exact samples of the Gaussian posterior (c_s - c = M^{-1}(A^T W^{1/2} e + D^T z / kappa));
each sample costs one back-substitution with the same factors. Heights relative to the ROI mean are read off them.

Repeated solves: between the iterations of the reconstruction the observations move little (the rays meet a surface
a fraction of a micrometre away), so the normal matrix changes little. A solve given an earlier one (``warm``) skips
the band accumulation and the factorisation: conjugate gradients on its own normal equations (matrix-vector products
straight from the whitened rows), preconditioned by the earlier banded Cholesky factor and started at the earlier
coefficients, converge in a few iterations to the same solution (to :data:`WARM_RTOL`); a fresh factorisation where
they do not within :data:`WARM_MAXITER`. The posterior draws then factorise once, when asked for.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg as sl
import scipy.sparse as sp
import scipy.sparse.linalg as spl
from numpy.typing import NDArray

from scopetwin.recon.errors import ReconstructionError
from scopetwin.recon.fringes.slopes import SlopeObservations
from scopetwin.recon.reconstruct import single_thread_blas
from scopetwin.recon.spline import SplineSurface
from scopetwin.recon.substrate import Substrate2D
from scopetwin.scenes.geometry import Array

#: Relative ridge on the coefficients that fixes the constant the slopes leave free (removed by the ROI gauge).
GAUGE_RIDGE = 1e-9
#: Relative residual |M c - A^T W g| / |A^T W g| at which the preconditioned conjugate gradients of a warm solve stop.
WARM_RTOL = 1e-8
#: Most conjugate-gradient iterations of a warm solve before it factorises afresh.
WARM_MAXITER = 6


@dataclass(frozen=True)
class Integrated:
    """A solved surface and its posterior samples.

    Attributes
    ----------
    surface : SplineSurface
        The posterior-mean surface, its mean over the ROI at the requested height.
    samples : ndarray, (k, n_coef)
        Posterior deviations of the coefficients (add to ``surface.coef.ravel()`` for a sample), the ROI mean of
        each removed.
    chi2_per_dof : float
        Whitened residual sum of squares of the observations per observation row (about 1 when the noise model
        holds and the surface follows the data).
    factor, rows : ndarray, optional
        A banded Cholesky factor of the normal matrix and the whitened observation rows of the solve (for
        :meth:`SlopeIntegrator.with_samples`, and the preconditioner of a warm solve).
    exact : bool
        Whether ``factor`` is of these rows' normal matrix (False: an earlier solve's, that preconditioned this one).
    cg_iterations : int
        Conjugate-gradient iterations of a warm solve (0: solved by a factorisation of its own).
    """

    surface: SplineSurface
    samples: Array
    chi2_per_dof: float
    factor: Array | None = field(default=None, repr=False)
    rows: _Rows | None = field(default=None, repr=False)
    exact: bool = True
    cg_iterations: int = 0


class SlopeIntegrator:
    """Sparse least-squares integration of slopes on a cubic B-spline with a curvature prior (module docstring).

    Parameters
    ----------
    sub : Substrate2D
        The substrate (the spline covers it, half a cell to spare).
    spacing : float
        Knot spacing, mm.
    curvature_std : float
        kappa, the prior standard deviation of a knot cell's curvature components, 1/mm.
    roi_step : float
        Step of the grid over the ROI whose mean is the surface's height, mm.

    Raises
    ------
    ReconstructionError
        A spacing or curvature that is not positive.
    """

    def __init__(self, sub: Substrate2D, spacing: float, curvature_std: float, roi_step: float = 0.5) -> None:
        if not spacing > 0 or not curvature_std > 0:
            raise ReconstructionError(
                f"the knot spacing ({spacing} mm) and the curvature prior ({curvature_std} /mm) must be positive"
            )
        self.sub = sub
        self.spline = SplineSurface.covering(sub, spacing)
        self.curvature_std = float(curvature_std)
        d = self.spline.smoothness() / np.sqrt(self.spline.dx * self.spline.dy)
        self.prior = (d / self.curvature_std).tocsr()
        #: Bandwidth of the normal matrix: an observation's 16 coefficients span 3 knot rows + 3.
        self.kd = 3 * self.spline.shape[1] + 3
        self._prior_normal = sp.csr_matrix(self.prior.T @ self.prior)
        self._prior_band = _band(self._prior_normal, self.kd)
        # the (a, b) places of an observation's 16 x 16 outer product in the upper triangle (its indices increase)
        self._pairs = np.triu_indices(16)
        gx, gy = sub.roi_grid(roi_step)
        self.roi_row = np.asarray(self.spline.design(gx, gy).mean(axis=0)).ravel()

    @property
    def n_coef(self) -> int:
        return int(self.spline.coef.size)

    def roi_mean(self, coef: Array) -> Array:
        """Mean height over the ROI of coefficient vectors (last axis), mm."""
        return np.asarray(np.asarray(coef) @ self.roi_row)

    def _whitened(self, obs: SlopeObservations) -> _Rows:
        """The whitened observation equations L^{-1} (A c - g), C = L L^T per observation, as each observation's 16
        coefficient indices and its two rows' weights there."""
        c11, c12, c22 = obs.cov[:, 0], obs.cov[:, 1], obs.cov[:, 2]
        if np.any(~(c11 > 0)) or np.any(~(c11 * c22 - c12 * c12 > 0)):
            raise ReconstructionError("slope observations with a covariance that is not positive definite")
        l11 = np.sqrt(c11)
        l21 = c12 / l11
        l22 = np.sqrt(c22 - l21 * l21)
        a, b, c = 1.0 / l11, -l21 / (l11 * l22), 1.0 / l22
        idx, _, wx, wy = self.spline.basis_rows(obs.xy[:, 0], obs.xy[:, 1])
        return _Rows(idx, a[:, None] * wx, b[:, None] * wx + c[:, None] * wy, a * obs.hx, b * obs.hx + c * obs.hy)

    def _normal_band(self, rows: _Rows) -> Array:
        """Upper banded storage (LAPACK, bandwidth :attr:`kd`) of A^T A + D^T D / kappa^2, the observations' part
        accumulated straight into the band (no sparse design matrix): the observations grouped by knot cell (all of a
        cell's share its 16 coefficients), each cell's 16 x 16 Gram matrix of its whitened rows by one batched
        matrix product (the groups zero-padded to the largest), and the cells' upper triangles added at their places
        in the band."""
        n_coef, kd = self.n_coef, self.kd
        a, b = self._pairs
        cell = rows.idx[:, 0]
        order = np.argsort(cell, kind="stable")
        sorted_cell = cell[order]
        starts = np.flatnonzero(np.r_[True, sorted_cell[1:] != sorted_cell[:-1]])
        counts = np.diff(np.r_[starts, len(cell)])
        group = np.repeat(np.arange(len(starts)), counts)
        slot = np.arange(len(cell)) - starts[group]
        width = int(counts.max())
        stacked = np.zeros((len(starts), 2 * width, 16))
        stacked[group, slot] = rows.r1[order]
        stacked[group, width + slot] = rows.r2[order]
        gram = np.matmul(stacked.transpose(0, 2, 1), stacked)
        first = rows.idx[order[starts]]
        flat = (kd + first[:, a] - first[:, b]) * n_coef + first[:, b]
        band = np.bincount(flat.ravel(), gram[:, a, b].ravel(), (kd + 1) * n_coef).reshape(kd + 1, n_coef)
        return band + self._prior_band

    def solve(
        self,
        obs: SlopeObservations,
        height: float,
        samples: int = 0,
        rng: np.random.Generator | int | None = 0,
        warm: Integrated | None = None,
    ) -> Integrated:
        """The posterior-mean surface of the observations at ROI-mean height ``height`` (mm), and ``samples`` draws
        (:meth:`with_samples`).

        With ``warm``, an earlier solve of nearby observations (the same integrator), its factorisation
        preconditions conjugate gradients on these observations' normal equations (module docstring).

        Raises
        ------
        ReconstructionError
            Fewer observations than 3 (no surface), or a covariance that is not positive definite.
        """
        if len(obs) < 3:
            raise ReconstructionError(f"only {len(obs)} slope observations: too few to integrate a surface")
        rows = self._whitened(obs)
        n_coef = self.n_coef
        weighted = (rows.r1 * rows.g1[:, None] + rows.r2 * rows.g2[:, None]).ravel()
        aty: Array = np.bincount(rows.idx.ravel(), weighted, n_coef).astype(np.float64)
        coef: Array | None = None
        factor, exact, iterations = None, True, 0
        with single_thread_blas():  # threaded BLAS on a banded factorisation: nothing gained on 2 cores, up to 10x lost
            if warm is not None and warm.factor is not None and warm.factor.shape == (self.kd + 1, n_coef):
                coef, iterations = self._warm_solve(rows, aty, warm.factor, warm.surface.coef.ravel())
                factor, exact = warm.factor, False
            if coef is None:
                factor, exact, iterations = _banded_cholesky(self._normal_band(rows)), True, 0
                coef = np.asarray(sl.cho_solve_banded((factor, False), aty), dtype=np.float64)
        at = coef[rows.idx]
        resid = np.concatenate([np.sum(rows.r1 * at, axis=1) - rows.g1, np.sum(rows.r2 * at, axis=1) - rows.g2])
        chi2 = float(resid @ resid) / len(resid)
        coef = coef + (height - float(self.roi_mean(coef)))
        solved = Integrated(self.spline.with_coef(coef), np.zeros((0, n_coef)), chi2, factor, rows, exact, iterations)
        return self.with_samples(solved, samples, rng) if samples > 0 else solved

    def _warm_solve(self, rows: _Rows, aty: Array, factor: Array, start: Array) -> tuple[Array | None, int]:
        """Conjugate gradients on the normal equations of ``rows`` (gauge ridge included, as
        :func:`_banded_cholesky` adds it), preconditioned by an earlier banded Cholesky ``factor`` and started at
        ``start``: the solution and the iterations, or None where they did not reach :data:`WARM_RTOL` within
        :data:`WARM_MAXITER`."""
        n_coef = self.n_coef
        design = rows.design(n_coef)
        # the diagonal's mean, as the factorisation's ridge is set: the rows' squared weights and the prior's
        ridge = GAUGE_RIDGE * (float(design.data @ design.data) + float(self._prior_band[self.kd].sum())) / n_coef
        prior = self._prior_normal

        def normal(x: Array) -> Array:
            return np.asarray(design.T @ (design @ x) + prior @ x + ridge * x)

        def precondition(r: Array) -> Array:
            return np.asarray(sl.cho_solve_banded((factor, False), r, check_finite=False))

        count = [0]

        def counted(_: Array) -> None:
            count[0] += 1

        op = spl.LinearOperator((n_coef, n_coef), matvec=normal, dtype=np.float64)
        pre = spl.LinearOperator((n_coef, n_coef), matvec=precondition, dtype=np.float64)
        coef, info = spl.cg(op, aty, x0=start, rtol=WARM_RTOL, maxiter=WARM_MAXITER, M=pre, callback=counted)
        return (np.asarray(coef, dtype=np.float64) if info == 0 else None), count[0]

    def with_samples(
        self, solved: Integrated, samples: int, rng: np.random.Generator | int | None = 0, height: float | None = None
    ) -> Integrated:
        """``solved`` with ``samples`` posterior draws from its own factorisation (module docstring: one
        back-substitution each), and moved to ROI-mean height ``height`` (mm) when given.

        The draws are scaled by sqrt(max(1, chi^2 per dof)): residuals larger than the observations' covariance
        says (noise the model left out, or surface detail the spline and prior do not follow) widen the posterior
        by their excess (the Birge ratio), never narrow it.

        A warm solve (``solved.exact`` False) factorises its own normal matrix first.

        Raises
        ------
        ReconstructionError
            ``solved`` does not carry its observation rows (not from :meth:`solve`).
        """
        rows = solved.rows
        if rows is None:
            raise ReconstructionError("posterior draws need the solve's observation rows (SlopeIntegrator.solve)")
        factor = solved.factor
        if factor is None or not solved.exact:
            with single_thread_blas():
                factor = _banded_cholesky(self._normal_band(rows))
            solved = replace(solved, factor=factor, exact=True)
        coef = solved.surface.coef.ravel()
        if height is not None:
            coef = coef + (height - float(self.roi_mean(coef)))
        gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        n_coef = self.n_coef
        n = len(rows.g1)
        e = np.concatenate([gen.standard_normal((n, samples)), gen.standard_normal((n, samples))])
        z = gen.standard_normal((self.prior.shape[0], samples))
        pert = np.asarray(rows.design(n_coef).T @ e) + np.asarray(self.prior.T @ z)
        with single_thread_blas():
            draws = np.asarray(sl.cho_solve_banded((factor, False), pert), dtype=np.float64).T
        draws -= self.roi_mean(draws)[:, None]
        draws *= np.sqrt(max(solved.chi2_per_dof, 1.0))
        return replace(solved, surface=self.spline.with_coef(coef), samples=draws)


@dataclass(frozen=True)
class _Rows:
    """Whitened observation rows: per observation the 16 coefficient indices (increasing), the weights of its two
    whitened equations there, and their right-hand sides."""

    idx: NDArray[np.int64]
    r1: Array
    r2: Array
    g1: Array
    g2: Array

    def design(self, n_coef: int) -> sp.csr_matrix:
        """The whitened equations' design matrix (2 n x ``n_coef``: every observation's first equations, then its
        second ones), sparse."""
        n = len(self.g1)
        data = np.concatenate([self.r1.ravel(), self.r2.ravel()])
        idx = np.ravel(self.idx)
        indptr = np.arange(0, 32 * n + 1, 16)
        return sp.csr_matrix((data, np.concatenate([idx, idx]), indptr), shape=(2 * n, n_coef))


def _band(normal: sp.csr_matrix, kd: int) -> Array:
    """Upper banded storage (bandwidth ``kd``) of a sparse symmetric matrix.

    Raises
    ------
    ReconstructionError
        An entry outside the band.
    """
    upper = sp.triu(normal).tocoo()
    if upper.nnz and int((upper.col - upper.row).max()) > kd:
        raise ReconstructionError(f"a normal matrix wider than its band of {kd}")
    band = np.zeros((kd + 1, normal.shape[0]))
    band[kd + upper.row - upper.col, upper.col] = upper.data
    return band


def _banded_cholesky(band: Array) -> Array:
    """Upper banded Cholesky factor (LAPACK pbtrf) of a symmetric positive-definite matrix in upper banded storage,
    with the gauge ridge :data:`GAUGE_RIDGE` on the diagonal.

    Raises
    ------
    ReconstructionError
        The matrix is not positive definite (no data and no prior on some coefficient).
    """
    kd = band.shape[0] - 1
    band = band.copy()
    band[kd] += GAUGE_RIDGE * float(band[kd].mean())
    try:
        return np.asarray(sl.cholesky_banded(band, lower=False), dtype=np.float64)
    except np.linalg.LinAlgError:
        raise ReconstructionError("the slope integration's normal matrix is not positive definite") from None
