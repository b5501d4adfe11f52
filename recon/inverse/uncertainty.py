"""The inverse fit's shape uncertainty from the Fisher information of its pixels: the Cramér-Rao bound of the pixel
data (plus the fit's prior) on the ROI shape, the held start height's part of it (thesis §1.4), and the Bayesian
(Van Trees) bound under a prior of the surface family."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from scipy.linalg import null_space

from scopetwin.recon.errors import ReconstructionError
from scopetwin.recon.inverse.gauss_newton import _GaussNewton
from scopetwin.recon.inverse.objective import mean_row, photometric, prior_weight
from scopetwin.recon.inverse.render import _Level
from scopetwin.recon.spline import SplineSurface
from scopetwin.scenes.geometry import Array


@dataclass
class _Information:
    """The Fisher information of a fit's pixels (:meth:`InverseReconstructor._information`): ``fisher`` J^T W J of
    the coefficients (k x k, J scaled by the photometric gain where the image is in its own units), ``cross`` J^T W V
    (k x 2) and ``photometric`` V^T W V (2 x 2) with V = d(alpha v + beta)/d(alpha, beta) = [v, 1] per pixel."""

    fisher: sp.csc_matrix
    cross: Array
    photometric: Array


def without_plane(x: Array, y: Array, values: Array) -> Array:
    """``values`` (points, ...) less their least-squares plane a + b x + c y over the points (x, y)."""
    plane = np.column_stack([np.ones(len(x)), x, y])
    return values - plane @ np.linalg.lstsq(plane, values, rcond=None)[0]


def _shape_rms_um(s_mat: Array, cov: Array) -> float:
    """sqrt(tr(S C S^T) / m) in µm: the RMS over m points of the variance of S w (mm) for w of covariance C."""
    return float(np.sqrt(max(float(np.sum(s_mat * (s_mat @ cov))), 0.0) / s_mat.shape[0])) * 1e3


def _orthonormal(span: Array) -> Array:
    """An orthonormal basis of the span's columns (QR): the same surfaces in well-conditioned coordinates.

    A shifted Gaussian basis's own coefficients are nearly collinear (condition ~5e10 at 15 mm on the §1.10
    substrate); the squared systems formed in them, P^T A P, lost every digit of an inverse (the shape's standard
    deviation moved by 10 % when the Jacobian moved by 1e-12 relative) and six of a solve. Only for the undamped
    systems of the uncertainty: the fit's damped steps depend on the coordinates they are taken in."""
    return np.asarray(np.linalg.qr(span)[0])


def _span_shape_std_um(precision: Any, span: Array, design: Any, m: Array) -> float:
    """:meth:`_ShapeUncertainty.shape_std_um` in a span's few coordinates: the trace exactly, with dense algebra.

    ``precision``: J^T W J + lambda D^T D of the coefficients; ``design`` the ROI heights' rows, ``m`` their mean.
    """
    p = _orthonormal(span)
    a = p.T @ (precision @ p)
    q = null_space((p.T @ m)[None, :])  # coordinates that keep the mean ROI height, as in the fit
    a_q = q.T @ a @ q
    scale = 1.0 / np.sqrt(np.abs(np.diag(a_q)) + 1e-300)  # equilibrated: DN images have a huge J^T W J
    cov = q @ (scale[:, None] * np.linalg.inv(scale[:, None] * a_q * scale[None, :]) * scale[None, :]) @ q.T
    dc = np.asarray(design @ p)
    return _shape_rms_um(dc - dc.mean(axis=0), cov)  # mean removed: the shape


def _probed_shape_std_um(precision: Any, design: Any, m: Array, n: int, probes: int) -> float:
    """:meth:`_ShapeUncertainty.shape_std_um` of the free spline (``n`` coefficients): sqrt(mean diag(A C A^T)) over
    the ROI heights A (mean removed) traced by ``probes`` Hutchinson probes, C from the KKT system of the held mean."""
    kkt = sp.bmat([[precision, m[:, None]], [m[None, :], None]], format="csc")
    lu = spla.splu(kkt)
    rng = np.random.default_rng(0)
    acc = 0.0
    for _ in range(probes):
        z = rng.choice([-1.0, 1.0], size=design.shape[0])
        z -= z.mean()  # mean removed: the shape
        v = np.asarray(design.T @ z).ravel()
        x = lu.solve(np.concatenate([v, [0.0]]))[:n]
        acc += float(v @ x)
    return float(np.sqrt(max(acc, 0.0) / probes / design.shape[0])) * 1e3


def _height_response(a: sp.csr_matrix, m_row: Array, information: _Information, span: Array | None) -> Array:
    """dc/dH from the fit's KKT system (undamped; equilibrated by its diagonal, which leaves dc unchanged):
    [[A, C, m], [C^T, B, 0], [m^T, 0, 0]] [dc; d(alpha, beta); nu] = [0; 0; 1].

    ``a`` = F + lambda D^T D and ``m_row`` the mean ROI row of the spline's coefficients, C and B the photometric
    blocks of ``information``; where the fit keeps to ``span``, solved in it as the fit's equations.
    """
    cross = information.cross
    if span is not None:  # in the span, as the fit's normal equations (in orthonormal coordinates: the same dc)
        span = _orthonormal(span)
        a, m_row = sp.csr_matrix(span.T @ (a @ span)), span.T @ m_row
        cross = span.T @ cross
    k = len(m_row)
    diag = np.concatenate([a.diagonal(), np.diag(information.photometric)])
    scale = 1.0 / np.sqrt(np.maximum(np.abs(diag), 1e-300))
    s_c, s_p = scale[:k], scale[k:]
    c_s = sp.csr_matrix(s_c[:, None] * cross * s_p[None, :])
    m_s = (s_c * m_row)[:, None]
    kkt = sp.bmat(
        [
            [sp.diags(s_c) @ a @ sp.diags(s_c), c_s, m_s],
            [c_s.T, sp.csr_matrix(s_p[:, None] * information.photometric * s_p[None, :]), None],
            [m_s.T, None, None],
        ],
        format="csc",
    )
    rhs = np.zeros(k + 3)
    rhs[-1] = 1.0
    dc = s_c * spla.spsolve(kkt, rhs)[:k]
    return dc if span is None else span @ dc


class _ShapeUncertainty(_GaussNewton):
    """The fit's shape uncertainty and the bounds of the pixel data (the base of :class:`InverseReconstructor`)."""

    def shape_std_um(
        self,
        surf: SplineSurface,
        var: Any = None,
        sub: int = 3,
        probes: int = 32,
        level: _Level | None = None,
        fisher: sp.csc_matrix | None = None,
    ) -> float:
        """Standard deviation of the ROI shape (RMS over the ROI, mean removed) from the Fisher information, µm.

        The covariance of the coefficients is the inverse of J^T W J + lambda D^T D (the render's Jacobian at
        ``surf`` with W = 1/var, the fit's thin-plate prior), with the mean ROI height held fixed as in the fit;
        with the true pixel variances it is the Cramér-Rao bound of the pixel data (plus prior) on the shape.
        sqrt(mean diag(A C A^T)) over the ROI heights A (mean removed) is traced by ``probes`` Hutchinson probes.
        ``var``: pixel variances of the full image in the render's units (irradiance); default: those of the fit,
        in the image's units (DN for a camera), the Jacobian then scaled by the photometric gain alpha of the
        loss. ``level``: the fit's own full-resolution level to reuse (with the fit's variances), instead of
        building a second ray model. Where the fit keeps to a basis's span (``surface="start-basis"``) the
        covariance is that of the span's coordinates and the trace exact. ``fisher``: J^T W J already formed
        (:meth:`_fisher` on the same ``var``, ``sub`` and ``level``).
        """
        if fisher is None:
            fisher = self._fisher(surf, var, sub, level)
        d = surf.smoothness()
        dtd = d.T @ d
        lam = prior_weight(self.config.smoothness, fisher, dtd)
        xs, ys = self.sub.roi_grid(0.5)
        design = surf.design(xs, ys)
        m = np.asarray(design.mean(axis=0)).ravel()
        if self._span is not None:
            return _span_shape_std_um(fisher + lam * dtd, self._span, design, m)
        return _probed_shape_std_um(fisher + lam * dtd, design, m, surf.coef.size, probes)

    def start_height_term_um(
        self,
        lev: _Level,
        surf: SplineSurface,
        h: float,
        absolute_std_um: float,
        information: _Information | None = None,
    ) -> float:
        """The start height's uncertainty carried into the shape, µm (RMS over the ROI).

        The rays are traced through a surface at the start height H, so an error of H tilts and bends the fitted
        shape (thesis §1.4; the centroid method's
        :meth:`scopetwin.recon.reconstruct.Reconstructor._start_height_sensitivity`). The fit's response dc/dH at
        its solution is that of its Gauss-Newton normal equations to the held mean ROI height, the photometric gain
        and offset (alpha, beta) answering with the coefficients: the KKT system
        [[F + lambda D^T D, C, m], [C^T, B, 0], [m^T, 0, 0]] [dc; d(alpha, beta); nu] = [0; 0; 1], with the Fisher
        information F at the fit, C and B its blocks with the photometric parameters (``information``,
        :meth:`_information` on ``lev``), the thin-plate weight lambda and the ROI mean row m as the fit sets them.
        The term is sqrt(mean((d contrast/dH * u_abs)^2)) over the ROI, contrast = height minus its ROI mean. With
        ``refine_setup`` the pose answers too: one more Gauss-Newton pass at H + 0.2 µm from the fit, by finite
        difference (:meth:`_start_height_term_fd`).
        """
        if self.config.refine_setup:
            return self._start_height_term_fd(lev, surf, h, absolute_std_um)
        if information is None:
            information = self._information(surf, None, lev.model.sub, lev)
        xs, ys = self.sub.roi_grid(0.5)
        sens = np.asarray(surf.design(xs, ys) @ self._height_response(surf, information)).ravel()
        return float(np.sqrt(np.mean(((sens - sens.mean()) * absolute_std_um) ** 2)))

    def _height_response(self, surf: SplineSurface, information: _Information) -> Array:
        """dc/dH: the coefficients' first-order response to the mean ROI height the fit holds (its KKT system at
        ``surf``, :meth:`start_height_term_um`), with the thin-plate weight and mean row the fit sets."""
        d = surf.smoothness()
        dtd = (d.T @ d).tocsr()
        lam = prior_weight(self.config.smoothness, information.fisher, dtd)
        held = mean_row(surf, self.sub)
        a = (information.fisher + lam * dtd).tocsr()
        return _height_response(a, held, information, self._span)

    def _start_height_term_fd(self, lev: _Level, surf: SplineSurface, h: float, absolute_std_um: float) -> float:
        """:meth:`start_height_term_um` by one more Gauss-Newton pass at H + 0.2 µm (the pose re-fitted with it)."""
        dh = 2e-4  # mm
        n = len(self.history)
        try:
            other = self.fit_level(lev, surf, h + dh, max(self.config.outer_iterations, 1), -1)
        finally:
            del self.history[n:]  # not a step of the fit
        xs, ys = self.sub.roi_grid(0.5)
        c1, c2 = surf.height(xs, ys), other.height(xs, ys)
        sens = ((c2 - c2.mean()) - (c1 - c1.mean())) / dh
        return float(np.sqrt(np.mean((sens * absolute_std_um) ** 2)))

    def _fisher(self, surf: SplineSurface, var: Any, sub: int, level: _Level | None) -> sp.csc_matrix:
        """J^T W J of the full-resolution render at ``surf`` (:meth:`shape_std_um` on ``var`` and ``level``)."""
        return self._information(surf, var, sub, level).fisher

    def _information(self, surf: SplineSurface, var: Any, sub: int, level: _Level | None) -> _Information:
        """:meth:`_fisher` with the photometric parameters' blocks beside it (one linearisation)."""
        if level is not None and var is None and level.b == 1 and level.model.sub == sub:
            lev = level
        else:
            saved = self.var
            if var is not None:
                self.var = np.asarray(var, dtype=np.float64)
            try:
                lev = self._level(1, sub)
            finally:
                self.var = saved
        vals, ok, jac, _ = self._linearise(lev, surf)
        assert jac is not None
        w = 1.0 / lev.var[ok]
        if var is None:  # the image's own units (DN for a camera): the render scaled by the photometric gain
            jac = jac * photometric(vals[ok], lev.data[ok], w)[0]
        jtw = jac.T.multiply(w[None, :]).tocsr()
        photo = np.stack([vals[ok], np.ones(int(ok.sum()))], axis=1)  # d(alpha v + beta)/d(alpha, beta)
        return _Information((jtw @ jac).tocsc(), np.asarray(jtw @ photo), photo.T @ (w[:, None] * photo))

    def shape_bayes_bound_um(
        self, surf: SplineSurface, prior: Array, var: Any = None, sub: int = 3, untilted: bool = False
    ) -> float:
        """Bayesian Cramér-Rao (Van Trees) bound on the ROI shape RMS under a Gaussian prior of the surface, µm.

        ``prior``: the square root X (n, r) of the prior covariance X X^T of the spline coefficients (e.g. the
        centred coefficients of r draws of the surface family, over sqrt(r - 1): :func:`family_prior`). With the
        Fisher information F = J^T W J of the pixels at ``surf`` (``var`` as in :meth:`shape_std_um`), the
        coefficients c = c_mean + X w have the information I + X^T F X in w; the bound is sqrt(tr(S C S^T) / m)
        with C its inverse and S the shape (mean removed; ``untilted``: best-fit plane removed) of the columns of
        X at the m ROI points. The mean ROI height is known in it (the prior conditioned on it, as the fit holds
        it): without the frame criterion the pixels leave height and tilt nearly interchangeable (thesis §1.4), and
        a bound given more information still bounds every estimator, the centroid method's included, on the
        Bayesian mean-square error over the family (F taken at this surface instead of averaged over it).
        """
        x = np.asarray(prior, dtype=np.float64)
        if x.ndim != 2 or x.shape[0] != surf.coef.size:
            raise ReconstructionError(f"prior square root is {x.shape}, the spline has {surf.coef.size} coefficients")
        fisher = self._fisher(surf, var, sub, None)
        xs, ys = self.sub.roi_grid(0.5)
        design = surf.design(xs, ys)
        heights = np.asarray(design @ x)
        q = null_space(heights.mean(axis=0)[None, :])  # w = Q u: the draws of the known mean ROI height
        xq = x @ q
        info = np.eye(q.shape[1]) + xq.T @ np.asarray(fisher @ xq)
        s_mat = heights @ q
        s_mat = without_plane(xs, ys, s_mat) if untilted else s_mat - s_mat.mean(axis=0)  # the shape
        return _shape_rms_um(s_mat, np.linalg.inv(info))

    def _fit_uncertainty(
        self, surf: SplineSurface, fine: _Level, sub_rays: int, h: float, absolute_std_um: float | None
    ) -> tuple[float, float | None]:
        """The shape uncertainty of a finished fit and the start height's part of it (None where not held).

        The Fisher information at the fit, scaled by the reduced chi^2 (the residuals' own variance where the pixel
        variances are only known up to a factor, as for a noise-free render); with ``absolute_std_um`` (the standard
        uncertainty of the start height held; None where it was searched) the start height's term
        (:meth:`start_height_term_um`) added in quadrature.
        """
        chi2 = self.history[-1].chi2 if self.history else 1.0
        info = self._information(surf, None, sub_rays, fine)  # one linearisation for both terms
        shape_std = self.shape_std_um(surf, None, sub_rays, level=fine, fisher=info.fisher) * float(
            np.sqrt(max(chi2, 0.0))
        )
        height_term = None
        if absolute_std_um is not None:
            height_term = self.start_height_term_um(fine, surf, h, float(absolute_std_um), information=info)
            shape_std = float(np.hypot(shape_std, height_term))
        return shape_std, height_term
