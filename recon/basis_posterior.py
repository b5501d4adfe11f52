"""The shifted-basis fit read as the Bayesian linear model it is: a finite-basis posterior.

The surface of thesis §1.8 is a sum of shifted Gaussians, f(r) = sum_k c_k psi(r - r_k) + t_x x + t_y y. Give the
coefficients a prior, c_k ~ N(0, tau^2) and the tilt terms N(0, :data:`~scopetwin.recon.posterior.TILT_STD` ^2), and
the gradients white noise of variance b_x and b_y per component, and a ridge fit of the gradients is the posterior
mean of a Bayesian linear model. With A_x, A_y the basis's gradient design matrices (n x m) and S the diagonal of the
prior standard deviations, everything is read from one m x m factorisation:

* the precision, scaled: M = I + S (A_x^T A_x / b_x + A_y^T A_y / b_y) S = R R^T (R lower triangular);
* the coefficients' posterior N(S R^-T v, S R^-T R^-1 S), v = R^-1 S (A_x^T g_x / b_x + A_y^T g_y / b_y);
* a linear functional e^T c of the coefficients (a height contrast to the ROI mean, thesis §1.4) has posterior mean
  w^T v and standard deviation |w|, w = R^-1 S e: its square root comes from the factor itself, so draws of the frame
  regions' heights need no further factorisation and no eigendecomposition;
* the log evidence, -(g^T B^-1 g - |v|^2) / 2 - (n log b_x + n log b_y) / 2 - sum log diag R - n log 2 pi, and its
  gradient in (log tau, log b_x, log b_y) in closed form (:func:`_evidence_and_gradient`).

Under this prior a Gaussian basis of scale sigma on a grid of spacing h is a Gaussian process of covariance about
tau^2 pi sigma^2 / h^2 exp(-|d|^2 / (4 sigma^2)) — the squared exponential of length sqrt(2) sigma that
:mod:`scopetwin.recon.posterior` uses for the smooth part of smooth surfaces — with the short-wavelength content
(broadband part, noise) in the white noise. The scale is chosen among :data:`SCALES` by the evidence too
(:func:`fit_basis_prior`). Where the evidence still rises at the finest of them, the surface is rougher than such a
prior describes (glass-like, cut or locally featured sheets, whose power-law spectra the Gaussian process's
rational-quadratic, local-features and broadband parts carry): :func:`fit_basis_prior` returns None and the
reconstruction reads the gradients with that process instead (:func:`scopetwin.recon.uncertainty.evidence_prior`).

Nothing here imports Mitsuba or sim.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from scopetwin.recon.lapack import cholesky_lower, lower_inverse
from scopetwin.recon.posterior import (
    FRAME_STEP,
    FTOL,
    TILT_STD,
    BasisPrior,
    FramePosterior,
    PosteriorError,
    frame_maxima,
    frame_points,
    node_grid,
    same_positions,
)
from scopetwin.recon.shifted_basis import SBFSurface, ShiftedBasis
from scopetwin.scenes.geometry import Array

#: Basis scales (mm) the evidence chooses among, coarsest first. The Gaussian process's smooth part spans 3-60 mm;
#: below 8 mm the basis over the §1.10 substrate has more terms (427 at 6 mm, 695 at 4 mm) than the 2n x 2n kernel of
#: the process's evidence subsample (500), and the surfaces whose evidence rises there are the rough ones.
SCALES = (24.0, 18.0, 15.0, 12.0, 10.0, 8.0)
#: The scale a cold search starts from: the finest, so that a rough surface, whose evidence falls at the next coarser
#: scale, is known after two scales (a search from 12 mm took three scales and 124 plain iterations on a glass-like
#: sheet).
FIRST_SCALE = 8.0
#: Bounds of the white gradient noise's standard deviation, rad (the Gaussian process's noise floor and ceiling).
NOISE_BOUNDS = (2e-8, 1e-3)


def covering(x_range: tuple[float, float], y_range: tuple[float, float], sigma: float) -> ShiftedBasis:
    """The finite-basis posterior's basis of scale ``sigma`` (mm) over a substrate's extent: Gaussians on a grid of
    spacing sigma / 2 with a margin of 1.5 sigma beyond the substrate, and the tilt terms
    (:meth:`ShiftedBasis.covering`'s defaults: dense enough to be a stationary prior over the whole substrate, frame
    regions included)."""
    return ShiftedBasis.covering(x_range, y_range, sigma)


def _flushed(a: Array) -> Array:
    """``a`` with entries below 1e-200 of its largest set to zero, in place: Gaussians between points many scales
    apart leave subnormal numbers, which the processor multiplies 10-100x slower."""
    a[np.abs(a) < 1e-200 * float(np.max(np.abs(a), initial=0.0))] = 0.0
    return a


@dataclass(frozen=True)
class _Design:
    """One scale's data: the basis, its gradient design at the observations, the Gram matrices and right-hand sides
    per component and the gradients' squared norms (formed once per scale and data)."""

    basis: ShiftedBasis
    ax: Array
    ay: Array
    gxx: Array
    gyy: Array
    hx: Array
    hy: Array
    sx: float
    sy: float

    @classmethod
    def of(cls, basis: ShiftedBasis, xy: Array, gx: Array, gy: Array) -> _Design:
        ax, ay = (_flushed(a) for a in basis.derivatives(xy[:, 0], xy[:, 1]))
        return cls(basis, ax, ay, ax.T @ ax, ay.T @ ay, ax.T @ gx, ay.T @ gy, float(gx @ gx), float(gy @ gy))

    @property
    def n(self) -> int:
        return len(self.ax)

    def scales(self, tau: float) -> Array:
        """The prior standard deviations of the coefficients: tau, the tilt terms' :data:`TILT_STD`."""
        s = np.full(self.basis.n_terms, tau)
        s[self.basis.n_basis :] = TILT_STD
        return s

    def factor(self, tau: float, bx: float, by: float) -> tuple[Array, Array]:
        """(R, s): the lower Cholesky factor of the scaled precision M (Fortran order) and the prior deviations."""
        s = self.scales(tau)
        m = self.gxx * (1.0 / bx)
        m += self.gyy * (1.0 / by)
        m *= s[:, None]
        m *= s[None, :]
        m[np.diag_indices(len(s))] += 1.0
        return cholesky_lower(m), s

    def whiten(self, r: Array, s: Array, bx: float, by: float) -> Array:
        """v = R^-1 S A^T B^-1 g for this design's gradients."""
        return sla.solve_triangular(r, s * (self.hx / bx + self.hy / by), lower=True, check_finite=False)


@dataclass(frozen=True)
class _Moments:
    """What the evidence and its stationarity conditions need at one (tau, b_x, b_y): the negative log evidence, the
    number of basis functions N and of observations per component n, and of the coefficients' posterior (mean c,
    covariance Sigma): tr Sigma_NN, |c_N|^2, tr(Sigma A_x^T A_x), tr(Sigma A_y^T A_y) and the residuals' squared norms
    |r_x|^2, |r_y|^2."""

    nll: float
    nb: int
    n: int
    tr_nn: float
    c2: float
    tr_x: float
    tr_y: float
    rx2: float
    ry2: float


def _moments(tau: float, bx: float, by: float, d: _Design) -> _Moments | None:
    """The :class:`_Moments` of the design ``d`` at (tau, b_x, b_y); None where M's factor fails."""
    try:
        r, s = d.factor(tau, bx, by)
    except np.linalg.LinAlgError:
        return None
    v = d.whiten(r, s, bx, by)
    n, nb = d.n, d.basis.n_basis
    logdet = 2.0 * float(np.sum(np.log(np.diag(r)))) + n * (np.log(bx) + np.log(by))
    nll = 0.5 * (d.sx / bx + d.sy / by - float(v @ v)) + 0.5 * logdet + n * np.log(2.0 * np.pi)
    coef = s * sla.solve_triangular(r, v, lower=True, trans=1, check_finite=False)
    inv = lower_inverse(r)  # M^-1 in the lower triangle, in place of the factor (used no more)
    inv = np.tril(inv)
    inv += np.tril(inv, -1).T
    sigma = inv * s[:, None] * s[None, :]
    return _Moments(
        float(nll), nb, n, float(np.trace(sigma[:nb, :nb])), float(coef[:nb] @ coef[:nb]),
        float(np.vdot(sigma, d.gxx)), float(np.vdot(sigma, d.gyy)),
        d.sx - 2.0 * float(coef @ d.hx) + float(coef @ d.gxx @ coef),
        d.sy - 2.0 * float(coef @ d.hy) + float(coef @ d.gyy @ coef),
    )  # fmt: skip


def _evidence_and_gradient(theta: Array, d: _Design) -> tuple[float, Array]:
    """Negative log evidence and its gradient in theta = log(tau, b_x, b_y) (b: the noise variances).

    With c and Sigma the coefficients' posterior mean and covariance, r_x, r_y the residuals and N the number of
    basis functions: d/dlog tau = N - (tr Sigma_NN + |c_N|^2) / tau^2 and d/dlog b_x = (n - tr(Sigma A_x^T A_x) / b_x
    - |r_x|^2 / b_x) / 2 (the derivatives of the Gaussian evidence, tr(K^-1 dK) - alpha^T dK alpha, written in the
    coefficients' space). Their zeros are the fixed points :func:`_max_evidence` iterates.
    """
    tau, bx, by = (float(x) for x in np.exp(theta))
    m = _moments(tau, bx, by, d)
    if m is None:
        return 1e30, np.zeros(3)
    grad = [
        m.nb - (m.tr_nn + m.c2) / tau**2,
        0.5 * (m.n - m.tr_x / bx - m.rx2 / bx),
        0.5 * (m.n - m.tr_y / by - m.ry2 / by),
    ]
    return m.nll, np.array(grad)


#: Most fixed-point iterations of one scale's evidence maximisation (:func:`_max_evidence`).
MAX_ITERATIONS = 60  # measured: 4-5 on the §1.10 preset's surface, 9-13 (over-relaxed) on glass-like sheets


def _max_evidence(d: _Design, g_rms: float, x0: Array | None) -> tuple[float, Array]:
    """The least negative log evidence of one scale, from ``x0`` = log(tau, b_x, b_y) or a cold start; with its theta.

    MacKay's fixed-point iteration of the evidence's stationarity conditions (:func:`_evidence_and_gradient`):
    gamma = N - tr Sigma_NN / tau^2 well-determined parameters, tau^2 <- |c_N|^2 / gamma, and per component
    b <- |r|^2 / (n - tr(Sigma A^T A) / b); until the evidence changes by less than :data:`FTOL` of itself. Each
    step is one factorisation and stays inside the region where M's factor exists: a gradient method's first steps
    (L-BFGS-B takes the gradient itself, hundreds of nats per unit of log noise) leapt to the bounds, where it fails.
    """
    sig = d.basis.sigma[0]
    tau, bx, by = (
        (float(x) for x in np.exp(x0))
        if x0 is not None
        else (0.3 * g_rms * sig, (3e-2 * g_rms) ** 2, (3e-2 * g_rms) ** 2)
    )
    theta = np.log([tau, bx, by])
    best: tuple[float, Array, Array] = (np.inf, theta, np.zeros(3))  # nll, theta, the plain step from it
    step, last = 1.0, np.zeros(3)
    for _ in range(MAX_ITERATIONS):
        tau, bx, by = (float(x) for x in np.exp(theta))
        m = _moments(tau, bx, by, d)
        if m is None or m.nll > best[0]:  # an over-relaxed step overshot: the plain step from the best point
            if step == 1.0:
                break
            theta, step, last = _clipped(best[1] + best[2]), 1.0, best[2]
            continue
        move = _fixed_point_step(m, theta)
        done = step == 1.0 and best[0] - m.nll <= FTOL * abs(m.nll)  # a plain step's gain: converged
        best = (m.nll, theta, move)
        if done:
            break
        # over-relaxed while the fixed-point steps keep their direction (they shrink slowly on rough surfaces)
        aligned = float(move @ last) > 0.9 * float(np.linalg.norm(move) * np.linalg.norm(last))
        step = min(2.0 * step, 8.0) if aligned else 1.0
        last = move
        theta = _clipped(theta + step * move)
    return best[0], best[1]


def _fixed_point_step(m: _Moments, theta: Array) -> Array:
    """MacKay's update of log(tau, b_x, b_y) at ``theta`` from its moments, as a step from ``theta``."""
    tau2, bx, by = (float(x) for x in np.exp(theta * np.array([2.0, 1.0, 1.0])))
    gamma = max(m.nb - m.tr_nn / tau2, 1e-6)
    fixed = np.log([
        max(m.c2, 1e-300) / gamma,
        m.rx2 / max(m.n - m.tr_x / bx, 1e-6),
        m.ry2 / max(m.n - m.tr_y / by, 1e-6),
    ])  # fmt: skip
    fixed[0] *= 0.5  # log tau from log tau^2
    return fixed - theta


def _clipped(theta: Array) -> Array:
    """``theta`` with the noise variances within :data:`NOISE_BOUNDS`."""
    lo, hi = (2.0 * float(np.log(b)) for b in NOISE_BOUNDS)
    return np.concatenate([theta[:1], np.clip(theta[1:], lo, hi)])


def fit_basis_prior(
    xy: Array, gx: Array, gy: Array, x_range: tuple[float, float], y_range: tuple[float, float],
    start: BasisPrior | None = None,
) -> tuple[BasisPrior, float] | None:  # fmt: skip
    """The finite-basis prior of maximum evidence for gradients (gx, gy) at ``xy`` over a substrate of extent
    (``x_range``, ``y_range``), and its log evidence; None where the evidence over the scales of :data:`SCALES` still
    rises at the finest (a surface rougher than this prior describes; module docstring).

    From :data:`FIRST_SCALE` (or ``start``'s scale, a warm start from an earlier frame's prior) towards finer scales
    while the evidence rises, else towards coarser ones while it rises: at each scale tau and the noise of maximum
    evidence (:func:`_max_evidence`), started from the neighbouring scale's. Measured on all the traced gradients of
    16 spp renders of the §1.10 setup with sensor noise: its own surface peaks at 12 mm (-12417 nats against -12400 at
    10 mm and -12387 at 15 mm; 42-51 ms on one thread), glass-like sheets fall from 8 to 10 mm (None in 53-61 ms).
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    gx, gy = np.ravel(gx).astype(np.float64), np.ravel(gy).astype(np.float64)
    g_rms = float(np.sqrt(np.mean(np.concatenate([gx, gy]) ** 2))) + 1e-12
    found: dict[int, tuple[float, Array]] = {}

    def nll(i: int, x0: Array | None) -> float:
        if i not in found:
            found[i] = _max_evidence(_Design.of(covering(x_range, y_range, SCALES[i]), xy, gx, gy), g_rms, x0)
        return found[i][0]

    def moved(i: int, j: int) -> Array:  # scale i's optimum as the start at scale j (tau in proportion)
        x = found[i][1].copy()
        x[0] += np.log(SCALES[j] / SCALES[i])
        return x

    warm = start is not None and start.sigma in SCALES
    first = SCALES.index(start.sigma if warm and start is not None else FIRST_SCALE)
    i = first
    nll(i, np.log([start.tau, start.noise**2, start.noise_y**2]) if warm and start is not None else None)
    while i + 1 < len(SCALES) and nll(i + 1, moved(i, i + 1)) < found[i][0]:
        i += 1
    while i == first and i > 0 and nll(i - 1, moved(i, i - 1)) < found[i][0]:
        i, first = i - 1, i - 1
    if i == len(SCALES) - 1:
        return None
    best, theta = found[i]
    tau, bx, by = (float(x) for x in np.exp(theta))
    return BasisPrior(SCALES[i], tau, float(np.sqrt(bx)), float(np.sqrt(by))), -best


def squared_distance(prior: BasisPrior, xy: Array, gx: Array, gy: Array, x_range: tuple[float, float],
                     y_range: tuple[float, float]) -> float:  # fmt: skip
    """g^T K^-1 g of gradients (gx, gy) at ``xy`` under ``prior`` over a substrate of extent (``x_range``,
    ``y_range``): the squared Mahalanobis distance of a change of the gradients within the prior's spread of them.

    Raises
    ------
    PosteriorError
        The prior's precision has no factor.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    gx, gy = np.ravel(gx).astype(np.float64), np.ravel(gy).astype(np.float64)
    d = _Design.of(covering(x_range, y_range, prior.sigma), xy, gx, gy)
    bx, by = prior.noise**2, prior.noise_y**2
    try:
        r, s = d.factor(prior.tau, bx, by)
    except np.linalg.LinAlgError:
        raise PosteriorError("the finite-basis prior's precision is singular") from None
    v = d.whiten(r, s, bx, by)
    return float(d.sx / bx + d.sy / by - v @ v)


class _NodePart:
    """The node grid's whitened contrasts w = R^-1 S e, (m, N), and their posterior standard deviation |w|."""

    def __init__(self, whitened: Array, shape: tuple[int, int]) -> None:
        self.whitened = whitened
        self._shape = shape

    @cached_property
    def std(self) -> Array:
        """(ny, nx), mm."""
        return np.sqrt(np.einsum("ij,ij->j", self.whitened, self.whitened)).reshape(self._shape)


@dataclass(frozen=True)
class BasisFrameModel:
    """The finite-basis counterpart of :class:`scopetwin.recon.posterior.FrameModel`: for one set of observation
    positions and one :class:`BasisPrior`, the factor, the frame points' whitened contrasts and draws' deviations and
    the node grid's part; :meth:`read` gives the posterior for any gradients at those positions (a triangular solve
    and a product), as the process's model does.

    Attributes
    ----------
    xy : ndarray, (n, 2)
        Observation positions, mm.
    hyper : BasisPrior
        The prior.
    design : _Design
        The basis and its gradient design at ``xy``.
    chol, s : ndarray
        R, the lower factor of the scaled precision, and the prior standard deviations S.
    whitened : ndarray, (m, k)
        R^-1 S e of the frame points' contrasts to the ROI mean.
    deviations : ndarray, (samples, k)
        Draws of the frame points' joint posterior less its mean.
    roi_row : ndarray, (m,)
        The ROI mean as a functional of the coefficients.
    """

    xy: Array
    hyper: BasisPrior
    design: _Design
    chol: Array
    s: Array
    whitened: Array
    deviations: Array
    node_x: Array
    node_y: Array
    roi: NDArray[np.bool_]
    frame1: Array
    frame2: Array
    nodes: _NodePart
    roi_row: Array

    @property
    def node_std(self) -> Array:
        """The contrasts' posterior standard deviation on the node grid, (ny, nx), mm."""
        return self.nodes.std

    def covers(self, xy: Array) -> bool:
        """Whether gradients observed at ``xy`` may be read with this model (:func:`same_positions`)."""
        return same_positions(self.xy, xy)

    def whiten(self, gx: Array, gy: Array) -> tuple[Array, float]:
        """v = R^-1 S A^T B^-1 g, and g^T K^-1 g = g^T B^-1 g - |v|^2, for gradients observed at :attr:`xy`."""
        bx, by = self.hyper.noise**2, self.hyper.noise_y**2
        gx, gy = np.ravel(gx).astype(np.float64), np.ravel(gy).astype(np.float64)
        rhs = self.s * (self.design.ax.T @ gx / bx + self.design.ay.T @ gy / by)
        v = sla.solve_triangular(self.chol, rhs, lower=True, check_finite=False)
        return v, float(gx @ gx / bx + gy @ gy / by - v @ v)

    def mean_coef(self, v: Array) -> Array:
        """The coefficients' posterior mean S R^-T v."""
        return self.s * sla.solve_triangular(self.chol, v, lower=True, trans=1, check_finite=False)

    def read(self, gx: Array, gy: Array) -> FramePosterior:
        """The posterior of D and of the contrasts for gradients (gx, gy) observed at :attr:`xy`."""
        v, q = self.whiten(gx, gy)
        d = frame_maxima(self.whitened.T @ v, self.deviations, len(self.frame1))
        return FramePosterior(
            *d, self.node_x, self.node_y, self.roi, self.hyper, self.frame1, self.frame2, self.nodes, v,
            (q, 2 * len(self.xy)),
        )  # fmt: skip


def basis_frame_model(
    prior: BasisPrior,
    xy: Array,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    roi_length: float,
    roi_axes: tuple[Array, Array],
    frame_step: float = FRAME_STEP,
    node_step: float = 1.0,
    samples: int = 600,
    seed: int = 0,
) -> BasisFrameModel:
    """The :class:`BasisFrameModel` of observation positions ``xy`` under ``prior``: the arguments as
    :func:`scopetwin.recon.posterior.frame_model`'s (substrate extent and ROI length, mm; the ROI mean over the
    tensor grid ``roi_axes``; frame-region and node grid spacing, mm; draws and their seed)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    design = _Design.of(covering(x_range, y_range, prior.sigma), xy, np.zeros(len(xy)), np.zeros(len(xy)))
    r, s = design.factor(prior.tau, prior.noise**2, prior.noise_y**2)
    node_x, node_y, nodes = node_grid(x_range, y_range, node_step)
    f1, f2 = frame_points(x_range, y_range, roi_length, frame_step)
    gx_roi, gy_roi = np.meshgrid(*roi_axes)
    basis = design.basis
    roi_row = basis.values(gx_roi.ravel(), gy_roi.ravel()).mean(axis=0)
    pts = np.concatenate([f1, f2, nodes])
    e = basis.values(pts[:, 0], pts[:, 1])
    e -= roi_row[None, :]
    e *= s[None, :]
    w = sla.solve_triangular(r, e.T, lower=True, check_finite=False)  # (m, points): R^-1 S e
    k = len(f1) + len(f2)
    deviations = np.random.default_rng(seed).standard_normal((samples, len(s))) @ w[:, :k]
    shape = (len(node_y), len(node_x))
    roi = (np.abs(nodes[:, 1]) < 0.5 * roi_length).reshape(shape)
    return BasisFrameModel(
        xy, prior, design, r, s, w[:, :k], deviations, node_x, node_y, roi, f1, f2, _NodePart(w[:, k:], shape), roi_row
    )


def basis_residual_correction(model: BasisFrameModel, ex: Array, ey: Array) -> SBFSurface:
    """The posterior mean of the heights a fit misses, from its residual gradients (ex, ey) at ``model``'s positions,
    as a basis surface of zero ROI mean (the finite-basis counterpart of
    :func:`scopetwin.recon.posterior.residual_correction`: the same factor, one more triangular solve)."""
    if len(np.ravel(ex)) != len(model.xy):
        raise PosteriorError(f"{len(model.xy)} residual gradients are needed, got {len(np.ravel(ex))}")
    v, _ = model.whiten(ex, ey)
    coef = model.mean_coef(v)
    return SBFSurface(model.design.basis, coef, -float(model.roi_row @ coef))
