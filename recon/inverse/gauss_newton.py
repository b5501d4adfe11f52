"""The fit at one resolution level: Gauss-Newton / Levenberg-Marquardt steps on the spline coefficients (and, with
``refine_setup``, the pose of camera and pattern) with the mean ROI height held by a Lagrange multiplier.

Each step linearises the render at the current surface, solves the photometric gain and offset in closed form, forms
the normal equations of the loss (:mod:`scopetwin.recon.inverse.objective`) and solves their KKT system with the
mean-height row; trials of growing damping follow until one lowers chi^2.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from scopetwin.recon.inverse.measurement import _Measurement
from scopetwin.recon.inverse.objective import mean_row, photometric, prior_weight
from scopetwin.recon.inverse.pose import _box_fraction, _pose_blocks, _pose_update, _PoseBlocks
from scopetwin.recon.inverse.render import _binned_camera, _Level
from scopetwin.recon.inverse.result import InverseStep
from scopetwin.recon.spline import SplineSurface
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array
from scopetwin.scenes.pattern import MarkerPattern


@dataclass
class _NormalEquations:
    """One Gauss-Newton step's linearisation: the model and data on the usable pixels ``ok``, the photometric gain
    and offset, residuals, the normal equations A x = g with the mean-height row, lambda, the pose blocks and the
    chi^2 at the current coefficients."""

    vals: Array
    ok: NDArray[np.bool_]
    data: Array
    wgt: Array
    alpha: float
    beta: float
    r: Array
    a: sp.csr_matrix
    g: Array
    m_row: Array
    lam: float
    pose: _PoseBlocks | None
    chi2_old: float


@dataclass
class _Trial:
    """One damped trial step: its surface, coefficient and pose steps, chi^2 and the pixels usable on both sides."""

    surf: SplineSurface
    dc: Array
    dp: Array | None
    chi2: float
    both: NDArray[np.bool_]


def _kkt_step(
    ne: _NormalEquations, mu: float, span: Array | None, pose: Array, pose_box: float
) -> tuple[Array, Array | None]:
    """The damped step (coefficients, pose or None) from the KKT system of the mean-height constraint.

    Damping ``mu`` times the diagonal (Levenberg-Marquardt); the joint step is shortened so that the pose (the
    motions so far: ``pose``) stays within ``pose_box`` standard deviations of the setup. ``span``: the coefficients'
    span where the fit keeps to one (the equations are then in its coordinates).
    """
    a, m_row, pb = ne.a, ne.m_row, ne.pose
    damp = a + mu * sp.diags(a.diagonal() + 1e-300)
    blocks = [[damp, m_row[:, None]], [m_row[None, :], None]]
    rhs = [ne.g, np.zeros(1)]
    npose = 0
    if pb is not None:
        npose = 12
        blocks = [
            [damp, pb.a_pc.T, m_row[:, None]],
            [pb.a_pc, sp.csr_matrix(pb.a_pp * (1 + mu)), None],
            [m_row[None, :], None, None],
        ]
        rhs = [ne.g, pb.g_p, np.zeros(1)]
    kkt = sp.bmat(blocks, format="csc")
    step = spla.spsolve(kkt, np.concatenate(rhs))
    k = len(m_row)
    frac = 1.0
    dp = step[k : k + npose] if npose else None
    if dp is not None:  # the joint step shortened so that the pose stays within pose_box sigma
        assert pb is not None
        frac = _box_fraction(pose, dp, pose_box * pb.sig)
        dp = dp * frac
    dc = frac * (step[:k] if span is None else span @ step[:k])
    return dc, dp


class _GaussNewton(_Measurement):
    """Gauss-Newton steps at one level (:meth:`fit_level`), the base of :class:`InverseReconstructor`."""

    def fit_level(self, lev: _Level, surf: SplineSurface, h: float, iterations: int, index: int) -> SplineSurface:
        """Gauss-Newton steps at one level with mean ROI height fixed to ``h``; returns the new surface.

        Each step: the normal equations at the current surface (:meth:`_normal_equations`), then Levenberg-Marquardt
        trials of growing damping until one lowers chi^2 (:meth:`_damped_step`); the level ends when none does, when
        the RMS coefficient step falls below ``tol_um`` or after ``iterations`` steps.
        """
        cfg = self.config
        d = surf.smoothness()
        dtd = (d.T @ d).tocsr()
        held = mean_row(surf, self.sub)
        lam = None
        mu = 1e-3
        c = surf.coef.ravel().copy()
        # enforce the constraint exactly at the start: shift the surface to mean height h
        c += h - float(held @ c)
        surf = surf.with_coef(c)
        for _ in range(iterations):
            ne = self._normal_equations(lev, surf, c, dtd, held, lam)
            lam = ne.lam
            trial, mu = self._damped_step(lev, surf, c, ne, dtd, mu)
            if trial is None:
                self._record(index, lev, h, ne.chi2_old / max(len(ne.r), 1), 0.0, len(ne.r))
                break
            c = c + trial.dc
            if trial.dp is not None:
                self.pose = self.pose + trial.dp
            surf = trial.surf
            step_um = float(np.sqrt(np.mean(trial.dc**2))) * 1e3
            self._record(index, lev, h, trial.chi2 / max(int(trial.both.sum()), 1), step_um, int(trial.both.sum()))
            if step_um < cfg.tol_um:
                break
        return surf

    def _normal_equations(
        self, lev: _Level, surf: SplineSurface, c: Array, dtd: sp.csr_matrix, held: Array, lam: float | None
    ) -> _NormalEquations:
        """The Gauss-Newton normal equations of one step at ``surf`` (coefficients ``c``), photometry solved.

        ``held``: the row of the mean ROI height held. ``lam``: the thin-plate prior's weight, None at a level's first
        step (then set relative to the mean diagonal of J^T W J). Where the fit keeps to a span, the equations are in
        the span's coordinates; with ``refine_setup`` the pose blocks are added (:func:`_pose_blocks`).
        """
        vals, ok, jac, jpose = self._linearise(lev, surf)
        assert jac is not None
        data, wgt = lev.data[ok], 1.0 / lev.var[ok]
        alpha, beta = photometric(vals[ok], data, wgt)
        r = data - alpha * vals[ok] - beta
        ja = jac * alpha
        jtw = ja.T.multiply(wgt[None, :]).tocsr()
        jtj = (jtw @ ja).tocsr()
        if lam is None:
            lam = prior_weight(self.config.smoothness, jtj, dtd)
        g = jtw @ r - lam * (dtd @ c)
        a = (jtj + lam * dtd).tocsr()
        m_row = held
        span = self._span
        if span is not None:  # the surfaces c + P da: the normal equations in the span's coordinates
            a, g, m_row = sp.csr_matrix(span.T @ (a @ span)), span.T @ g, span.T @ held
        pose = None
        if jpose is not None:  # rows of the usable pixels
            pose = _pose_blocks(jpose * alpha, wgt, ja, r, self.config.pose_sigma, self.pose, span)
        chi2_old = float(np.sum(wgt * r * r) + lam * c @ (dtd @ c))
        return _NormalEquations(vals, ok, data, wgt, alpha, beta, r, a, g, m_row, lam, pose, chi2_old)

    def _trial(
        self, lev: _Level, surf: SplineSurface, c: Array, ne: _NormalEquations, dtd: sp.csr_matrix, mu: float
    ) -> tuple[_Trial, float, tuple[Camera, MarkerPattern] | None]:
        """One damped trial step: its surface (the level's rays moved with the pose), chi^2 and the reference chi^2.

        Both chi^2 on the pixels usable before and after the step. Returns the trial, the reference chi^2 and the
        level's (camera, pattern) before the pose step (None without one), to restore if the trial is rejected.
        """
        dc, dp = _kkt_step(ne, mu, self._span, self.pose, self.config.pose_box)
        lam = ne.lam
        trial = surf.with_coef(c + dc)
        saved: tuple[Camera, MarkerPattern] | None = None
        if dp is not None:
            saved = (lev.model.camera, lev.model.pattern)
            self._apply_pose(lev, dp)
        tv, tok, _, _ = self._linearise(lev, trial, need_jac=False)
        both = ne.ok & tok
        ta, tb = photometric(tv[both], lev.data[both], 1.0 / lev.var[both])
        tr = lev.data[both] - ta * tv[both] - tb
        chi2_new = float(np.sum(tr * tr / lev.var[both]) + lam * (c + dc) @ (dtd @ (c + dc)))
        # compare on the common pixels
        r_common = (ne.data - ne.alpha * ne.vals[ne.ok] - ne.beta)[both[ne.ok]]
        chi2_ref = float(np.sum(r_common**2 * ne.wgt[both[ne.ok]]) + lam * c @ (dtd @ c))
        return _Trial(trial, dc, dp, chi2_new, both), chi2_ref, saved

    def _damped_step(
        self, lev: _Level, surf: SplineSurface, c: Array, ne: _NormalEquations, dtd: sp.csr_matrix, mu: float
    ) -> tuple[_Trial | None, float]:
        """Up to four trials, the damping tenfold after each rejected one; the accepted trial (or None) and mu."""
        for _ in range(4):
            trial, chi2_ref, saved = self._trial(lev, surf, c, ne, dtd, mu)
            if trial.chi2 <= chi2_ref or not np.isfinite(chi2_ref):
                mu = max(mu / 3.0, 1e-7)
                return trial, mu
            if saved is not None:  # the pose step's rays undone
                lev.aim(*saved)
            mu *= 10.0
        return None, mu

    def _apply_pose(self, lev: _Level, dp: Array) -> None:
        """The level's rays traced from camera and pattern moved by the pose so far plus ``dp``."""
        cam, pat = _pose_update(self.camera, self.pattern, self.pose + dp)
        lev.aim(_binned_camera(cam, lev.b, self.window[0], self.window[2]), pat)

    def _record(self, index: int, lev: _Level, h: float, chi2: float, step_um: float, pixels: int) -> None:
        self.history.append(InverseStep(index, lev.b, h * 1e3, chi2, step_um, pixels, time.perf_counter() - self._t0))
