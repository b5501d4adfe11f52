"""The reprojection model of the non-linear optimisation (thesis §2.5.1 parameters, §2.5.2 camera, §2.5.3 goal).

:class:`ReprojectionModel` maps the parameter vector p = (r_c, r_0, phi) [, b] [, r_cs, c0, c2] to the camera of
§2.5.2 and evaluates the reprojection residuals of the goal function (§2.5.3) with an analytic Jacobian: the
per-marker chain rule is written out, and the 7-parameter frame map (:func:`_frame_batch`) is differentiated by
complex step, which is exact to round-off.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from scopetwin.calib.oneshot.camera_parameters import (
    Prior,
)
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array, Frame

_CSTEP = 1e-30


def _frame_batch(q: NDArray, focal_length: float, lens: str, b_fixed: float) -> NDArray:
    """Frame map of thesis §2.5.2 for rows q = (x_c, y_c, z_c, x_0, y_0, phi, b); complex-step safe.

    Returns rows (N_z, T_x, T_y, b, g) of length 11.
    """
    rc = q[:, 0:3]
    d = rc - np.stack([q[:, 3], q[:, 4], np.zeros_like(q[:, 3])], axis=1)
    g = np.sqrt(np.sum(d * d, axis=1))
    nz = d / g[:, None]
    h = np.sqrt(nz[:, 2] ** 2 + nz[:, 0] ** 2)
    t0x = np.stack([nz[:, 2], np.zeros_like(h), -nz[:, 0]], axis=1) / h[:, None]
    t0y = np.cross(nz, t0x)
    c, s = np.cos(q[:, 5])[:, None], np.sin(q[:, 5])[:, None]
    tx = c * t0x + s * t0y
    ty = c * t0y - s * t0x
    if lens == "thin-lens":
        b = g * focal_length / (g - focal_length)
    elif lens == "free":
        b = q[:, 6]
    else:
        b = np.full_like(g, b_fixed)
    return np.concatenate([nz, tx, ty, b[:, None], g[:, None]], axis=1)


@dataclass
class ReprojectionModel:
    """The reprojection model: parameter layout and residual / Jacobian (thesis §2.5.1-§2.5.3).

    Parameters
    ----------
    xy, px : ndarray, (n, 2)
        Marker centres in target coordinates, mm, and their measured images, continuous px.
    prior : Prior
        Pixel pitch, format, focal length and the distortion kept fixed.
    lens : {"thin-lens", "free", "fixed"}
        How b follows (thin-lens equation of §2.5.2, a parameter, or ``b_fixed``).
    distortion : bool
        Also estimate r_cs, c2 and (unless b is free) c0 (§2.5.1).
    b_fixed : float
        The image distance of ``lens="fixed"``, mm.

    prior_weight : dict, optional
        Pseudo-observations of estimated parameters at their a-priori values (``prior.r_cs``, ``prior.c0``):
        ``{name: w}`` appends the residual ``w * (p[name] - a-priori value)`` (px) after the 2n marker
        residuals. One view of a plane fixes a homography (8 numbers) and cannot separate r_cs from the pose, nor
        c0 from the distance along the axis, when there is no distortion to show where the optical axis is;
        the pseudo-observations keep those directions at the a-priori values instead of
        letting the optimiser wander along them.

    Attributes
    ----------
    names : list of str
        Names of the parameters p, in order: x_c, y_c, z_c, x_0, y_0, phi [, b] [, x_cs, y_cs, c0, c2].
    """

    xy: Array
    px: Array
    prior: Prior
    lens: str
    distortion: bool
    b_fixed: float
    names: list[str] = field(default_factory=list)
    fixed_dist: dict = field(default_factory=dict)
    prior_weight: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.names = ["x_c", "y_c", "z_c", "x_0", "y_0", "phi"]
        if self.lens == "free":
            self.names.append("b")
        if self.distortion:
            self.names += ["x_cs", "y_cs"]
            if self.lens != "free":
                self.names.append("c0")  # c0 and a free b are exactly degenerate (c0*b is what the image fixes)
            self.names.append("c2")
        self.fixed_dist = {
            "x_cs": self.prior.r_cs[0],
            "y_cs": self.prior.r_cs[1],
            "c0": self.prior.c0,
            "c2": self.prior.c2,
        }
        self.X = np.column_stack([self.xy, np.zeros(len(self.xy))])
        self.prior_weight = {k: float(w) for k, w in self.prior_weight.items() if k in self.names and w > 0}

    def _prior_rows(self, p: Array) -> tuple[Array, Array]:
        """Residuals and Jacobian rows of the pseudo-observations (:attr:`prior_weight`)."""
        names = list(self.prior_weight)
        res = np.array([self.prior_weight[k] * (p[self.names.index(k)] - self.fixed_dist[k]) for k in names])
        jac = np.zeros((len(names), len(self.names)))
        for row, k in enumerate(names):
            jac[row, self.names.index(k)] = self.prior_weight[k]
        return res, jac

    def get(self, p: Array, name: str) -> float:
        """Parameter ``name`` of ``p``, or its fixed value when it is not estimated."""
        return float(p[self.names.index(name)]) if name in self.names else float(self.fixed_dist[name])

    def base(self, p: Array) -> Array:
        """The 7 base parameters (x_c, y_c, z_c, x_0, y_0, phi, b) of the frame map from ``p``."""
        q = np.empty(7)
        q[:6] = p[:6]
        q[6] = p[6] if self.lens == "free" else self.b_fixed
        return q

    def frame_and_jac(self, p: Array) -> tuple[Array, Array]:
        """Frame outputs (11,) and their derivatives w.r.t. the 7 base parameters (11, 7), by complex step."""
        q = self.base(p)
        qc = np.tile(q.astype(np.complex128), (8, 1))
        qc[1:, :] += 1j * _CSTEP * np.eye(7)
        out = _frame_batch(qc, self.prior.focal_length, self.lens, self.b_fixed)
        return out[0].real, (out[1:].imag / _CSTEP).T

    def evaluate(self, p: Array, jac: bool) -> tuple[Array, Array | None]:
        """Residuals model - measurement (2n,: all x, then all y; then the pseudo-observations), px, and their
        Jacobian if ``jac`` (goal, §2.5.3)."""
        fr, dfr = self.frame_and_jac(p)
        nz, tx, ty, b = fr[0:3], fr[3:6], fr[6:9], fr[9]
        rc = p[0:3]
        dvec = self.X - rc
        a = dvec @ tx
        c = dvec @ ty
        dep = -(dvec @ nz)
        # a trial step that puts markers behind the camera gets huge (finite) residuals, so LM rejects it
        dep = np.where(dep > 0, dep, 1e-9 * (1.0 + np.abs(dep)))
        u = b * a / dep
        v = b * c / dep
        rho = np.sqrt(u * u + v * v)
        c0, c2 = self.get(p, "c0"), self.get(p, "c2")
        k = c0 + c2 * rho
        xcs, ycs = self.get(p, "x_cs"), self.get(p, "y_cs")
        pr = self.prior
        x = (k * u - xcs) / pr.pitch + 0.5 * pr.nx
        y = 0.5 * pr.ny - (k * v - ycs) / pr.pitch
        pres, pjac = self._prior_rows(p)
        res = np.concatenate([x - self.px[:, 0], y - self.px[:, 1], pres])
        if not jac:
            return res, None
        # derivatives w.r.t. the 7 base parameters (x_c, y_c, z_c, x_0, y_0, phi, b)
        drc = np.zeros((3, 7))
        drc[:, :3] = np.eye(3)
        da = dvec @ dfr[3:6] - tx @ drc
        dc = dvec @ dfr[6:9] - ty @ drc
        ddep = -(dvec @ dfr[0:3] - nz @ drc)
        db = dfr[9]
        inv = 1.0 / dep
        du = (b * inv)[:, None] * da + (a * inv)[:, None] * db[None, :] - (u * inv)[:, None] * ddep
        dv = (b * inv)[:, None] * dc + (c * inv)[:, None] * db[None, :] - (v * inv)[:, None] * ddep
        safe = np.where(rho > 0, rho, 1.0)
        drho = np.where((rho > 0)[:, None], (u[:, None] * du + v[:, None] * dv) / safe[:, None], 0.0)
        dx_base = (k[:, None] * du + (c2 * u)[:, None] * drho) / pr.pitch
        dy_base = -(k[:, None] * dv + (c2 * v)[:, None] * drho) / pr.pitch
        cols = [0, 1, 2, 3, 4, 5] + ([6] if self.lens == "free" else [])
        jx = [dx_base[:, cols]]
        jy = [dy_base[:, cols]]
        n = len(u)
        for name in self.names[len(cols) :]:
            if name == "x_cs":
                jx.append(np.full((n, 1), -1.0 / pr.pitch))
                jy.append(np.zeros((n, 1)))
            elif name == "y_cs":
                jx.append(np.zeros((n, 1)))
                jy.append(np.full((n, 1), 1.0 / pr.pitch))
            elif name == "c0":
                jx.append((u / pr.pitch)[:, None])
                jy.append((-v / pr.pitch)[:, None])
            elif name == "c2":
                jx.append((rho * u / pr.pitch)[:, None])
                jy.append((-rho * v / pr.pitch)[:, None])
        return res, np.vstack([np.hstack(jx), np.hstack(jy), pjac])

    def residual_and_jacobian(self, p: Array) -> tuple[Array, Array]:
        """Residuals (2n,) and their Jacobian (2n, n_params) at ``p``."""
        res, jmat = self.evaluate(p, True)
        assert jmat is not None  # evaluate(jac=True) always returns the Jacobian
        return res, jmat

    def camera(self, p: Array) -> Camera:
        """The camera of parameters ``p`` (frame of §2.5.2, b, r_cs, c0, c2)."""
        fr, _ = self.frame_and_jac(p)
        frame = Frame(p[0:3], fr[3:6], fr[6:9], fr[0:3])
        return self.prior.sensor_camera(
            float(fr[9]),
            frame,
            r_cs=(self.get(p, "x_cs"), self.get(p, "y_cs")),
            c0=self.get(p, "c0"),
            c2=self.get(p, "c2"),
        )

    def start(self, camera: Camera, r0: Array, phi: float) -> Array:
        """Parameter vector p of a start camera (e.g. the linear approximation's), its axis point and tilt angle."""
        p = list(camera.center) + [r0[0], r0[1], phi]
        if self.lens == "free":
            p.append(camera.b)
        for name in self.names[len(p) :]:
            p.append(self.fixed_dist[name])
        return np.asarray(p, dtype=np.float64)
