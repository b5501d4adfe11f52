"""The thesis's deflectometry ray model in Dr.Jit, differentiable: the forward model of the inverse reconstruction.

Thesis §1.6: camera ray (§1.6.2) -> substrate z = h(x, y) (§1.6.4; here Newton's iteration on
f(lambda) = h(r(lambda)) - z(lambda) instead of the secant, a fixed number of steps, so that the chain is
differentiable) -> mirror reflection (§1.6.5, eq. 1.7) -> pattern plane (§1.6.3) -> the marker grey value
g = max(0, 1 - r/r_m) of the nearest marker, times the pattern radiance. It is :mod:`scopetwin.scenes.analytic` (the
float64 numpy reference) restricted to the deflectometry scene, with the surface given as a uniform cubic
B-spline over the base plane, written in Dr.Jit (``Float64``: the measurement's 20 nm are below float32's
rounding of 200 mm coordinates), differentiable by Dr.Jit's forward-mode AD.

The image of a pixel is the mean of ``sub x sub`` rays at fixed stratified positions (a box filter, as the
sensor and the Mitsuba renders integrate the pixel area). Fixed positions make the model a smooth function of
the surface (no sampling noise), and the marker cone is continuous, so the derivatives are well defined
without soft edges; only pixels whose rays all land in the region of interest are used (the ROI edge, where
the image jumps, is left out).

Derivatives with respect to the surface: a ray's value depends on the surface only through the height and
the gradient at its hit point (implicit differentiation of the intersection). :meth:`RayModel.trace` returns,
per ray, ``(a, b, c)``: the derivative of the value with respect to a local perturbation
``d0 + dx*(x - x_hit) + dy*(y - y_hit)`` of the surface, in closed form in the trace's own kernel (the hit's move
and the curvature there, the reflection, the pattern lookup: :class:`_Reflection`); Dr.Jit's forward-mode AD
through the Newton iteration gives the same to round-off, three passes of the whole trace more. The derivative
with respect to any coefficient of any height model is then ``a*B + b*dB/dx + c*dB/dy`` of its basis function B
at the hit: the sparse Jacobian of the image with respect to B-spline coefficients is assembled from it
(:mod:`scopetwin.recon.inverse`). With ``pose=True`` the derivatives with respect to small rigid motions of the
camera and of the pattern (12 columns, for ``--refine-setup``) come the same way, where AD took twelve passes.

The backend follows :func:`scopetwin.scenes.mitsuba.variant.choose`: ``cuda`` when a CUDA device is usable (the
``cuda_ad_mono`` machine), else ``llvm``; nothing needs a GPU. Importing this module sets no variant.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import drjit as _drjit
import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.bspline import cubic_bspline_second, cubic_bspline_weights
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.pattern import MarkerPattern
from scopetwin.scenes.setup import Setup

dr: Any = _drjit  # untyped (pyproject.toml [tool.mypy])

Array = NDArray[np.float64]

#: Newton steps of the ray-surface intersection (quadratic convergence from the mean plane: 1e-15 mm after 5
#: for slopes of 1e-2; the derivatives converge with the iterate).
NEWTON_STEPS = 6
#: Newton steps from the hits of the model's previous trace (:meth:`RayModel.trace` with ``warm``), through a surface
#: a fit's step away: measured on the §1.10 window (300,000 pixels x 64 rays, a 24 µm bow), even three steps from the
#: mean plane leave the values within 8e-14 and the sensitivities within 7e-13 (relative) of six. From a plane's hits
#: through a whole steep or cut sheet (``steep`` seeds 9100, 9101 and ``cut`` 9100, 9102: 59-226 µm; a plane start's
#: first step, at 4 x 4 binning and every pixel): within 1.1e-13 and 1.2e-12 of a cold start.
NEWTON_WARM_STEPS = 3

#: Added to r^2 before the square root of the marker distance (mm^2), so that the cone's apex has a finite
#: derivative.
_APEX = 1e-18


@dataclass(frozen=True)
class SplineGrid:
    """A uniform cubic B-spline's coefficient grid: coefficient (row m, column k) sits at (x0 + k*dx, y0 + m*dy).

    The spline is evaluated on [x0 + dx, x0 + (nx - 2)*dx) x [y0 + dy, y0 + (ny - 2)*dy); outside, the cell index
    is clamped (the nearest edge cell's polynomial continues).
    """

    x0: float
    y0: float
    dx: float
    dy: float
    nx: int
    ny: int


def backend(variant: str | None = None) -> Any:
    """The Dr.Jit AD array namespace (``dr.cuda.ad`` or ``dr.llvm.ad``) of ``variant`` (default: choose("mono"))."""
    from scopetwin.scenes.mitsuba.variant import resolve

    name = resolve(variant, "mono")
    if name.startswith("cuda"):
        try:
            import drjit.cuda.ad as cuda_ad

            cuda_ad.Float64(0.0).numpy()  # a usable device?
            return cuda_ad
        except Exception:  # no usable GPU: LLVM
            pass
    import drjit.llvm.ad as llvm_ad

    return llvm_ad


@dataclass
class TraceResult:
    """Per-ray results of :meth:`RayModel.trace` (numpy, float64, one entry per ray, pixel-major)."""

    value: Array
    x: Array
    y: Array
    valid: NDArray[np.bool_]
    # per-ray derivatives, one array each (the trace's own memory, not copied: 19.7 M rays x 15 derivatives would be
    # 2.4 GB of fresh memory a trace): d value / d (d0, dx, dy) of the local surface perturbation, and d value /
    # d (camera shift 3, camera rotation 3, pattern shift 3, pattern rotation 3)
    sens: tuple[Array, ...] | None
    pose: tuple[Array, ...] | None


def _skew_apply(w: tuple[Any, Any, Any], v: tuple[Any, Any, Any]) -> tuple[Any, Any, Any]:
    """w x v for 3-tuples."""
    return (w[1] * v[2] - w[2] * v[1], w[2] * v[0] - w[0] * v[2], w[0] * v[1] - w[1] * v[0])


def _dot(a: tuple[Any, Any, Any], b: tuple[Any, Any, Any]) -> Any:
    """a . b for 3-tuples."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


_AXES = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


@dataclass(frozen=True)
class _Reflection:
    """A ray's path at its hit (Dr.Jit arrays, one entry per ray): what the first-order moves of the point it reaches
    on the pattern plane, in the plane's own coordinates (lx, ly), need (:meth:`_tangent`)."""

    d: tuple[Any, Any, Any]  # the camera ray's direction
    lam: Any  # the ray parameter of the hit
    slope: tuple[Any, Any]  # (dh/dx, dh/dy) at the hit
    second: tuple[Any, Any, Any]  # (d2h/dx2, d2h/dxdy, d2h/dy2) at the hit
    normal: tuple[Any, Any, Any]  # (-hx, -hy, 1) / sqrt(hx^2 + hy^2 + 1)
    dn: Any  # d . normal
    r: tuple[Any, Any, Any]  # the reflected direction d - 2 (d . n) n
    den: Any  # r . (the pattern plane's normal)
    mu: Any  # the parameter along r of the pattern plane
    q: tuple[Any, Any, Any]  # the point reached, relative to the pattern's origin
    plane: tuple[tuple[Any, Any, Any], ...]  # the pattern's x and y axes and normal

    def surface_tangents(self) -> list[tuple[Any, Any]]:
        """d (lx, ly) / d theta for theta = (d0, dx, dy) of the perturbation d0 + dx (x - x_hit) + dy (y - y_hit) added
        to the surface: d0 moves the hit along the ray, dx and dy add to the slopes there (and, zero at the hit,
        leave it in place)."""
        return [self._tangent(dfz=1.0), self._tangent(dh=(1.0, 0.0)), self._tangent(dh=(0.0, 1.0))]

    def rigid_tangents(self) -> list[tuple[Any, Any]]:
        """d (lx, ly) / d theta for the 12 small rigid motions of ``RayModel._trace``'s ``pose``, in its order: the
        camera's shift (the rays' origin) and rotation about its centre (their directions), the pattern's shift and
        rotation about its origin (its axes and normal)."""
        tx, ty, nz = self.plane
        out = [self._tangent(do=e) for e in _AXES]
        out += [self._tangent(dd=_skew_apply(e, self.d)) for e in _AXES]
        out += [self._tangent(dpo=e) for e in _AXES]
        out += [self._tangent(dplane=(_skew_apply(e, tx), _skew_apply(e, ty), _skew_apply(e, nz))) for e in _AXES]
        return out

    def _tangent(
        self,
        dfz: Any = 0.0,
        dh: tuple[Any, Any] = (0.0, 0.0),
        do: tuple[Any, Any, Any] | None = None,
        dd: tuple[Any, Any, Any] | None = None,
        dpo: tuple[Any, Any, Any] | None = None,
        dplane: tuple[tuple[Any, Any, Any], ...] | None = None,
    ) -> tuple[Any, Any]:
        """The first-order move (d lx, d ly) of the point reached on the pattern plane, from the implicit
        derivatives of the converged hit: the surface raised by ``dfz`` and its slopes changed by ``dh`` at the hit,
        the rays' origin moved by ``do`` and their direction by ``dd``, the pattern's origin moved by ``dpo`` and its
        axes and normal by ``dplane``.

        The hit solves f(lambda) = h(o + lambda d) - (o + lambda d)_z = 0, f' = hx dx + hy dy - dz: at fixed lambda
        the ray's point moves by a = do + lambda dd, so d lambda = -(hx a_x + hy a_y - a_z + dfz) / f' and the hit
        moves by dp = a + d d lambda; its slopes change by the curvature times dp, plus ``dh``. Then the normal, the
        mirror reflection (thesis eq. 1.7) and the line-plane intersection."""
        hx, hy = self.slope
        hxx, hxy, hyy = self.second
        tx, ty, nz = self.plane
        zero = (0.0, 0.0, 0.0)
        a = tuple(
            (do or zero)[k] + (self.lam * dd[k] if dd is not None else 0.0) for k in range(3)
        )  # the ray's point at fixed lambda
        dlam = -(hx * a[0] + hy * a[1] - a[2] + dfz) / (hx * self.d[0] + hy * self.d[1] - self.d[2])
        dp = (a[0] + self.d[0] * dlam, a[1] + self.d[1] * dlam, a[2] + self.d[2] * dlam)
        dhx = hxx * dp[0] + hxy * dp[1] + dh[0]
        dhy = hxy * dp[0] + hyy * dp[1] + dh[1]
        inv = self.normal[2]
        dinv = -inv * inv * inv * (hx * dhx + hy * dhy)
        dnorm = (-(dhx * inv + hx * dinv), -(dhy * inv + hy * dinv), dinv)
        ddn = _dot(self.d, dnorm) + (_dot(dd, self.normal) if dd is not None else 0.0)
        drefl = tuple(
            (dd[k] if dd is not None else 0.0) - 2.0 * (ddn * self.normal[k] + self.dn * dnorm[k]) for k in range(3)
        )
        dnz = dplane[2] if dplane is not None else zero
        # num = (P_o - p) . N and den = r . N, with q + P_o = p + mu r
        dnum = _dot(tuple((dpo or zero)[k] - dp[k] for k in range(3)), nz) + _dot(
            tuple(self.mu * self.r[k] - self.q[k] for k in range(3)), dnz
        )
        dden = _dot(drefl, nz) + _dot(self.r, dnz)
        dmu = (dnum - self.mu * dden) / self.den
        dq = tuple(dp[k] + dmu * self.r[k] + self.mu * drefl[k] - (dpo or zero)[k] for k in range(3))
        dlx, dly = _dot(dq, tx), _dot(dq, ty)
        if dplane is not None:
            dlx, dly = dlx + _dot(self.q, dplane[0]), dly + _dot(self.q, dplane[1])
        return dlx, dly


class RayModel:
    """The deflectometry measurement of one setup as a differentiable function of the substrate's surface.

    Parameters
    ----------
    camera : Camera
        The (calibrated) camera; rays through the pixels' stratified sample positions, distortion included.
    pattern : MarkerPattern
        The (calibrated) marker pattern.
    radiance : float
        Radiance of a marker centre.
    substrate_size : (float, float)
        Substrate extent (x, y), mm.
    roi_length : float
        Length of the region of interest along y, mm (the reflecting gap between the frame regions).
    rows, cols : array_like of int
        The pixels to model (any list).
    sub : int
        Rays per pixel and axis (``sub*sub`` per pixel, at the centres of a ``sub x sub`` grid of sub-pixels).
    jitter : bool
        Fixed pseudo-random positions inside the sub-pixels instead of their centres (the same every trace).
    variant : str, optional
        Selects the backend (:func:`backend`).
    keep : array_like of int, optional
        Indices of the pixels traced among ``rows``, ``cols`` (default all; taken in increasing order); a pixel's
        rays (and their jitter) are the same whichever pixels are traced.
    """

    def __init__(
        self,
        camera: Camera,
        pattern: MarkerPattern,
        radiance: float,
        substrate_size: tuple[float, float],
        roi_length: float,
        rows: Any,
        cols: Any,
        sub: int = 3,
        variant: str | None = None,
        jitter: bool = False,
        keep: Any = None,
    ) -> None:
        self.camera = camera
        self.pattern = pattern
        self.radiance = float(radiance)
        self.size = (float(substrate_size[0]), float(substrate_size[1]))
        self.roi_length = float(roi_length)
        self.rows = np.asarray(rows, dtype=np.int64).ravel()
        self.cols = np.asarray(cols, dtype=np.int64).ravel()
        self.sub = int(sub)
        self.spp = self.sub * self.sub
        self.jitter = bool(jitter)
        self.m = backend(variant)
        self.keep = None if keep is None else np.unique(np.asarray(keep, dtype=np.intp))
        rows_t, cols_t = self.rows, self.cols
        if self.keep is not None:
            rows_t, cols_t = rows_t[self.keep], cols_t[self.keep]
        ox, oy = self._offsets()
        d = np.empty((3, len(rows_t) * self.spp))
        chunk = 16384  # pixels at a time: the camera's temporaries stay within a few tens of MB
        for start in range(0, len(rows_t), chunk):
            sl = slice(start, start + chunk)
            px = np.stack(
                [(cols_t[sl, None] + ox[sl] / self.sub).ravel(), (rows_t[sl, None] + oy[sl] / self.sub).ravel()], -1
            )
            d[:, start * self.spp : start * self.spp + len(px)] = camera.ray_directions(px).T
        F = self.m.Float64
        self._d = tuple(F(d[k]) for k in range(3))
        self._lam: Any = None  # the ray parameters of the last trace's hits (its warm start)

    def _offsets(self, chunk: int = 65536) -> tuple[Array, Array]:
        """The rays' positions inside the traced pixels, in pixels (n traced, spp) for x and y: sub-pixel centres,
        or with ``jitter`` fixed pseudo-random positions inside them (stratified: the midpoint rule's kink errors
        decorrelated), drawn for every pixel of ``rows`` in turn (x for all, then y), ``chunk`` pixels at a time,
        and kept for the traced ones: a pixel's positions do not depend on which others are traced."""
        k = np.arange(self.sub, dtype=np.float64)
        kx, ky = (a.ravel() for a in np.meshgrid(k, k))
        n = len(self.rows) if self.keep is None else len(self.keep)
        if not self.jitter:
            return np.broadcast_to(kx + 0.5, (n, self.spp)).copy(), np.broadcast_to(ky + 0.5, (n, self.spp)).copy()
        rng = np.random.default_rng(12345)
        out = []
        for base in (kx, ky):
            parts = []
            for start in range(0, len(self.rows), chunk):
                draw = rng.random((min(chunk, len(self.rows) - start), self.spp))
                if self.keep is not None:
                    sel = self.keep[(self.keep >= start) & (self.keep < start + len(draw))] - start
                    draw = draw[sel]
                parts.append(draw + base)
            out.append(np.concatenate(parts) if parts else np.empty((0, self.spp)))
        return out[0], out[1]

    @classmethod
    def from_setup(cls, setup: Setup, rows: Any, cols: Any, sub: int = 3, variant: str | None = None) -> RayModel:
        """The model of a deflectometry setup (camera, pattern, radiance, substrate) for the given pixels."""
        sub_spec = setup.substrate
        assert sub_spec is not None, "a deflectometry setup has a substrate"
        return cls(
            setup.camera_model,
            setup.marker_pattern,
            setup.pattern.radiance,
            sub_spec.size,
            sub_spec.roi_length,
            rows,
            cols,
            sub,
            variant,
        )

    @property
    def n_rays(self) -> int:
        return (len(self.rows) if self.keep is None else len(self.keep)) * self.spp

    # -- the surface ---------------------------------------------------------------------------------------------
    def _surface(
        self, grid: SplineGrid, coef: Any, x: Any, y: Any, curvature: bool = False
    ) -> tuple[Any, Any, Any, tuple[Any, Any, Any] | None]:
        """(h, dh/dx, dh/dy) of the B-spline at (x, y), and with ``curvature`` its second derivatives (xx, xy, yy)."""
        m = self.m
        F, I32 = m.Float64, m.Int32
        u = (x - grid.x0) / grid.dx
        v = (y - grid.y0) / grid.dy
        i = dr.clip(I32(dr.floor(u)), 1, grid.nx - 3)
        j = dr.clip(I32(dr.floor(v)), 1, grid.ny - 3)
        tu = u - F(i)
        tv = v - F(j)
        wu = cubic_bspline_weights(tu)
        wv = cubic_bspline_weights(tv)
        su = cubic_bspline_second(tu) if curvature else None
        sv = cubic_bspline_second(tv) if curvature else None
        h = F(0.0)
        hx = F(0.0)
        hy = F(0.0)
        hxx, hxy, hyy = F(0.0), F(0.0), F(0.0)
        base = (j - 1) * grid.nx + (i - 1)
        for mm in range(4):
            row_h = F(0.0)
            row_d = F(0.0)
            row_s = F(0.0)
            for kk in range(4):
                c = dr.gather(F, coef, m.UInt32(base + (mm * grid.nx + kk)))
                row_h = dr.fma(c, wu[kk], row_h)
                row_d = dr.fma(c, wu[4 + kk], row_d)
                if su is not None:
                    row_s = dr.fma(c, su[kk], row_s)
            h = dr.fma(row_h, wv[mm], h)
            hx = dr.fma(row_d, wv[mm], hx)
            hy = dr.fma(row_h, wv[4 + mm], hy)
            if sv is not None:
                hxx = dr.fma(row_s, wv[mm], hxx)
                hxy = dr.fma(row_d, wv[4 + mm], hxy)
                hyy = dr.fma(row_h, sv[mm], hyy)
        second = (hxx / grid.dx**2, hxy / (grid.dx * grid.dy), hyy / grid.dy**2) if curvature else None
        return h, hx / grid.dx, hy / grid.dy, second

    # -- the trace -----------------------------------------------------------------------------------------------
    def _geometry(
        self, pose: tuple[Any, ...] | None
    ) -> tuple[tuple[Any, Any, Any], tuple[Any, Any, Any], tuple[tuple[Any, Any, Any], ...]]:
        """The camera centre, the rays' directions and the pattern plane (origin, x and y axes, normal) as Dr.Jit
        values, moved by ``pose`` (:meth:`_trace`) where given."""
        F = self.m.Float64
        cam_c = self.camera.center
        ox, oy, oz = F(cam_c[0]), F(cam_c[1]), F(cam_c[2])
        dxr, dyr, dzr = self._d
        pat = self.pattern.frame
        p_o = tuple(F(float(v)) for v in pat.origin)
        p_tx = tuple(F(float(v)) for v in pat.tx)
        p_ty = tuple(F(float(v)) for v in pat.ty)
        p_nz = tuple(F(float(v)) for v in pat.nz)
        if pose is not None:
            cs, cr, ps, pr = pose[0:3], pose[3:6], pose[6:9], pose[9:12]
            ox, oy, oz = ox + cs[0], oy + cs[1], oz + cs[2]
            rd = _skew_apply(cr, (dxr, dyr, dzr))
            dxr, dyr, dzr = dxr + rd[0], dyr + rd[1], dzr + rd[2]
            p_o = (p_o[0] + ps[0], p_o[1] + ps[1], p_o[2] + ps[2])
            p_tx = tuple(a + b for a, b in zip(p_tx, _skew_apply(pr, p_tx), strict=True))
            p_ty = tuple(a + b for a, b in zip(p_ty, _skew_apply(pr, p_ty), strict=True))
            p_nz = tuple(a + b for a, b in zip(p_nz, _skew_apply(pr, p_nz), strict=True))
        return (ox, oy, oz), (dxr, dyr, dzr), (p_o, p_tx, p_ty, p_nz)

    def _trace(
        self,
        grid: SplineGrid,
        coef: Any,
        z_start: float,
        local: tuple[Any, Any, Any, Any, Any] | None = None,
        pose: tuple[Any, ...] | None = None,
        lam0: Any = None,
        tangents: bool = False,
        rigid: bool = False,
    ) -> tuple[Any, Any, Any, Any, Any, list[Any]]:
        """Value, hit x, hit y, validity and ray parameter of the hit of every ray (Dr.Jit arrays), and the value's
        derivatives in closed form (through the cone's slope, :meth:`_grey`): with ``tangents`` those with respect to
        a local perturbation (d0, dx, dy) at the hit (:meth:`_Reflection.surface_tangents`), then with ``rigid``
        those with respect to the 12 motions of ``pose`` (:meth:`_Reflection.rigid_tangents`).

        The Newton iteration starts from the plane z = ``z_start`` (:data:`NEWTON_STEPS`), or from the ray
        parameters ``lam0`` where they are finite (:data:`NEWTON_WARM_STEPS`).

        ``local`` = (d0, dx, dy, x_ref, y_ref) adds the perturbation d0 + dx*(x - x_ref) + dy*(y - y_ref) to the
        surface (Dr.Jit's forward-mode AD through it gives what ``tangents`` gives in closed form); ``pose`` = (cam
        shift (3), cam rotation (3), pattern shift (3), pattern rotation (3)) moves the camera rays and the pattern
        plane rigidly by small amounts (rotation vectors about r_c / the pattern centre; AD through it gives what
        ``rigid`` gives).
        """
        (ox, oy, oz), (dxr, dyr, dzr), (p_o, p_tx, p_ty, p_nz) = self._geometry(pose)

        def surf(x: Any, y: Any, curvature: bool = False) -> tuple[Any, Any, Any, tuple[Any, Any, Any] | None]:
            h, hx, hy, second = self._surface(grid, coef, x, y, curvature)
            if local is not None:
                d0, ddx, ddy, xr, yr = local
                h = h + d0 + ddx * (x - xr) + ddy * (y - yr)
                hx = hx + ddx
                hy = hy + ddy
            return h, hx, hy, second

        lam = (z_start - oz) / dzr
        steps = NEWTON_STEPS
        if lam0 is not None:
            lam, steps = dr.select(dr.isfinite(lam0), lam0, lam), NEWTON_WARM_STEPS
        for _ in range(steps):
            px, py, pz = dr.fma(lam, dxr, ox), dr.fma(lam, dyr, oy), dr.fma(lam, dzr, oz)
            h, hx, hy, _ = surf(px, py)
            f = h - pz
            fp = hx * dxr + hy * dyr - dzr
            lam = lam - f / fp
        px, py, pz = dr.fma(lam, dxr, ox), dr.fma(lam, dyr, oy), dr.fma(lam, dzr, oz)
        _, hx, hy, second = surf(px, py, tangents or rigid)
        inv = dr.rsqrt(hx * hx + hy * hy + 1.0)
        nx, ny, nz = -hx * inv, -hy * inv, inv
        dn = dxr * nx + dyr * ny + dzr * nz
        rx, ry, rz = dxr - 2.0 * dn * nx, dyr - 2.0 * dn * ny, dzr - 2.0 * dn * nz
        den = rx * p_nz[0] + ry * p_nz[1] + rz * p_nz[2]
        num = (p_o[0] - px) * p_nz[0] + (p_o[1] - py) * p_nz[1] + (p_o[2] - pz) * p_nz[2]
        mu = num / den
        qx, qy, qz = dr.fma(mu, rx, px) - p_o[0], dr.fma(mu, ry, py) - p_o[1], dr.fma(mu, rz, pz) - p_o[2]
        lx = qx * p_tx[0] + qy * p_tx[1] + qz * p_tx[2]
        ly = qx * p_ty[0] + qy * p_ty[1] + qz * p_ty[2]
        value, slope = self._grey(lx, ly)
        hw, hl = 0.5 * self.size[0], 0.5 * self.roi_length
        valid = (dr.abs(px) <= hw) & (dr.abs(py) < hl) & (den < 0.0) & (mu > 0.0) & (lam > 0.0)
        derivs = []
        if second is not None:
            ray = _Reflection(
                (dxr, dyr, dzr), lam, (hx, hy), second, (nx, ny, nz), dn, (rx, ry, rz), den, mu, (qx, qy, qz),
                (p_tx, p_ty, p_nz),
            )  # fmt: skip
            moves = (ray.surface_tangents() if tangents else []) + (ray.rigid_tangents() if rigid else [])
            derivs = [dr.select(valid, self.radiance * (slope[0] * dl + slope[1] * dm), 0.0) for dl, dm in moves]
        return dr.select(valid, value * self.radiance, 0.0), px, py, valid, lam, derivs

    def _grey(self, lx: Any, ly: Any) -> tuple[Any, tuple[Any, Any]]:
        """g = max(0, 1 - r/r_m) of the nearest marker (the reference marker larger), 0 off the plate (§1.6.3), and
        its derivatives (dg/dlx, dg/dly): -(rx, ry) / (r r_m) inside a marker's cone, else 0."""
        m = self.m
        F = m.Float64
        pat = self.pattern
        out = []
        for coord, n, pitch in ((lx, pat.n_x, pat.pitch_x), (ly, pat.n_y, pat.pitch_y)):
            k0 = pat._first_index(n)
            off = pat._offset(n, pitch)
            k = dr.clip(dr.round((coord - off) / pitch), float(k0), float(k0 + n - 1))
            out.append((k, coord - (off + k * pitch)))
        (ki, rx), (kj, ry) = out
        r = dr.sqrt(rx * rx + ry * ry + _APEX)
        is_ref = (dr.detach(ki) == 0.0) & (dr.detach(kj) == 0.0)
        radius = dr.select(is_ref, F(pat.ref_radius), F(pat.radius))
        cone = 1.0 - r / radius
        on = (dr.abs(lx) <= 0.5 * pat.size_x) & (dr.abs(ly) <= 0.5 * pat.size_y)
        inside = on & (cone > 0.0)
        rate = -1.0 / (r * radius)
        slope = (dr.select(inside, rx * rate, 0.0), dr.select(inside, ry * rate, 0.0))
        return dr.select(on, dr.maximum(cone, 0.0), 0.0), slope

    def trace(
        self,
        grid: SplineGrid,
        coef: Array,
        sensitivities: bool = True,
        pose: bool = False,
        z_start: float | None = None,
        warm: bool = True,
    ) -> TraceResult:
        """Trace every ray through the B-spline surface ``coef`` (ny, nx) on ``grid``.

        Parameters
        ----------
        grid : SplineGrid
            The coefficient grid.
        coef : ndarray, (grid.ny, grid.nx)
            B-spline coefficients, mm.
        sensitivities : bool
            Also return d value / d (d0, dx, dy) of a local perturbation at each hit: in closed form, in the trace's
            own kernel (:meth:`_Reflection.surface_tangents`), what forward-mode AD through the converged Newton
            iteration gives (``tests/recon/test_inverse.py`` checks the one against the other).
        pose : bool
            Also return the derivatives with respect to the 12 rigid-motion parameters of camera and pattern (in
            closed form in the same kernel, :meth:`_Reflection.rigid_tangents`).
        z_start : float, optional
            Plane the Newton iteration starts from (default: the mean coefficient).
        warm : bool
            Without ``z_start``: start from the hits of this model's previous trace where there is one (a fit's
            next surface lies a step away; :data:`NEWTON_WARM_STEPS`).

        Returns
        -------
        TraceResult
        """
        m = self.m
        F = m.Float64
        c_np = np.ascontiguousarray(np.asarray(coef, dtype=np.float64).reshape(grid.ny, grid.nx))
        c = F(c_np.ravel())
        z0 = float(np.mean(c_np)) if z_start is None else float(z_start)
        lam0 = self._lam if warm and z_start is None else None
        value, px, py, valid, lam, derivs = self._trace(grid, c, z0, lam0=lam0, tangents=sensitivities, rigid=pose)
        dr.eval(value, px, py, valid, lam, *derivs)  # one kernel
        self._lam = dr.detach(lam)
        x_np, y_np = px.numpy(), py.numpy()
        out = TraceResult(value.numpy(), x_np, y_np, valid.numpy().astype(bool), None, None)
        if sensitivities:
            out.sens = tuple(s.numpy() for s in derivs[:3])
        if pose:
            out.pose = tuple(s.numpy() for s in derivs[-12:])
        return out

    def pixel_values(self, result: TraceResult) -> tuple[Array, NDArray[np.bool_]]:
        """Per-pixel means of the rays' values and whether every ray of the pixel is valid."""
        v = result.value.reshape(-1, self.spp).mean(axis=1)
        ok = np.asarray(result.valid.reshape(-1, self.spp).all(axis=1), dtype=bool)
        return v, ok
