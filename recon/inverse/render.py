"""The fit's forward model: the measurement rendered through the thesis's ray model of §1.6 in Dr.Jit
(:mod:`scopetwin.scenes.mitsuba.deflectometry_ad`), one resolution level at a time, with its Jacobian.

A level is a window of the image binned b x b (each block rendered as one super-pixel: the image blurred and
decimated, which widens the basin) and the ray model of those super-pixels. The Jacobian with respect to the spline
coefficients is sparse (16 coefficients per ray) and exact: per ray, the render returns the derivative with respect to
a local height/slope perturbation (forward-mode AD), combined here with the B-spline basis.

The one module of the package that renders: the renderer is imported inside its functions only
(``tests/architecture/test_layers.py``), so that importing the package loads no renderer.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from scopetwin.recon.spline import SplineSurface
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array
from scopetwin.scenes.pattern import MarkerPattern
from scopetwin.scenes.setup import Setup

if TYPE_CHECKING:  # the renderer is imported lazily at run time
    from scopetwin.scenes.mitsuba.deflectometry_ad import RayModel, SplineGrid


def bin_image(image: Array, b: int, rows: tuple[int, int], cols: tuple[int, int]) -> Array:
    """Mean of b x b pixel blocks of ``image[rows, cols]`` (the window is cut to a multiple of b)."""
    r0, r1 = rows
    c0, c1 = cols
    nr, nc = (r1 - r0) // b, (c1 - c0) // b
    crop = np.asarray(image, dtype=np.float64)[r0 : r0 + nr * b, c0 : c0 + nc * b]
    return crop.reshape(nr, b, nc, b).mean(axis=(1, 3))


def _binned_camera(camera: Camera, b: int, r0: int, c0: int) -> Camera:
    """A camera whose pixel (r, c) is the b x b block of ``camera``'s pixels starting at (r0 + b r, c0 + b c)."""
    if b == 1 and r0 == 0 and c0 == 0:
        return camera
    nx_b = camera.nx // b + 2
    ny_b = camera.ny // b + 2
    # pixel grid: u = (x - nx/2) p + x_cs; block c covers x in [c0 + b c, c0 + b (c + 1))
    pitch = camera.pitch * b
    x_cs = camera.r_cs[0] + (c0 - 0.5 * camera.nx) * camera.pitch + 0.5 * nx_b * pitch
    y_cs = camera.r_cs[1] + (0.5 * camera.ny - r0) * camera.pitch - 0.5 * ny_b * pitch
    return camera.with_(nx=nx_b, ny=ny_b, pitch=pitch, r_cs=(x_cs, y_cs))


def spline_grid(surf: SplineSurface) -> SplineGrid:
    """The renderer's description of a spline surface's knot grid (:class:`scopetwin.scenes.mitsuba.deflectometry_ad.
    SplineGrid`)."""
    from scopetwin.scenes.mitsuba.deflectometry_ad import SplineGrid

    ny, nx = surf.shape
    return SplineGrid(surf.x0, surf.y0, surf.dx, surf.dy, nx, ny)


def _pixel_moments(res: Any, ok: NDArray[np.bool_], spp: int, block: int = 32768) -> tuple[Array, ...]:
    """Per usable pixel: the mean hit point and the moments of the rays' sensitivities about it.

    Returns (xm, ym, ma, mb, mc, m_ax, m_ay, m_bx, m_by, m_cx, m_cy): the means of the hit x, y and of the
    sensitivities a, b, c (to a local height, x-slope and y-slope perturbation), and the means of a, b, c times the
    hit's offset from the pixel's mean hit in x and y. The basis is expanded to second order about the mean hit
    (the rays of a pixel land within ~0.05 knot spacings of each other). Worked in blocks of ``block`` pixels, so
    that the temporaries stay a few tens of MB whatever the image size.
    """
    good = np.flatnonzero(ok)
    out = np.empty((11, len(good)))
    x_all = res.x.reshape(-1, spp)
    y_all = res.y.reshape(-1, spp)
    s_all = [res.sens[k].reshape(-1, spp) for k in range(3)]
    for start in range(0, len(good), block):
        rows = good[start : start + block]
        x, y = x_all[rows], y_all[rows]
        xm, ym = x.mean(axis=1), y.mean(axis=1)
        ddx, ddy = x - xm[:, None], y - ym[:, None]
        sa, sb, sc = (s[rows] for s in s_all)
        part = out[:, start : start + len(rows)]
        part[0], part[1] = xm, ym
        part[2], part[3], part[4] = sa.mean(axis=1), sb.mean(axis=1), sc.mean(axis=1)
        part[5], part[6] = (sa * ddx).mean(axis=1), (sa * ddy).mean(axis=1)
        part[7], part[8] = (sb * ddx).mean(axis=1), (sb * ddy).mean(axis=1)
        part[9], part[10] = (sc * ddx).mean(axis=1), (sc * ddy).mean(axis=1)
    return tuple(out)


def _coefficient_jacobian(res: Any, ok: NDArray[np.bool_], spp: int, surf: SplineSurface) -> sp.csr_matrix:
    """The sparse Jacobian (usable pixels x coefficients) of the pixel values: each pixel's ray sensitivities
    combined with the B-spline basis expanded to second order about its mean hit point (:func:`_pixel_moments`)."""
    npix = int(ok.sum())
    xm, ym, ma, mb, mc, max_, may, mbx, mby, mcx, mcy = _pixel_moments(res, ok, spp)
    idx, w, wx, wy, (wxx, wxy, wyy) = surf.basis_rows_second(xm, ym)
    col = lambda v: v[:, None]  # noqa: E731
    data = (
        col(ma) * w + col(max_ + mb) * wx + col(may + mc) * wy + col(mbx) * wxx + col(mby + mcx) * wxy + col(mcy) * wyy
    )
    rows = np.repeat(np.arange(npix), 16)
    return sp.csr_matrix((data.ravel(), (rows, idx.ravel())), shape=(npix, surf.coef.size))


class _Level:
    """One resolution level: the ray model of the (binned) window's pixels and the binned image with weights."""

    def __init__(
        self,
        camera: Camera,
        pattern: MarkerPattern,
        setup: Setup,
        image: Array,
        var: Array,
        window: tuple[int, int, int, int],
        b: int,
        sub: int,
        variant: str | None,
        jitter: bool = False,
    ) -> None:
        from scopetwin.scenes.mitsuba.deflectometry_ad import RayModel

        r0, r1, c0, c1 = window
        self.b = b
        self.data = bin_image(image, b, (r0, r1), (c0, c1)).ravel()
        # variance of a block mean: mean variance / b^2
        self.var = bin_image(var, b, (r0, r1), (c0, c1)).ravel() / (b * b)
        nr, nc = (r1 - r0) // b, (c1 - c0) // b
        rr, cc = np.meshgrid(np.arange(nr), np.arange(nc), indexing="ij")
        # a super-pixel of b x b pixels: model its rays on a b-times coarser pixel grid
        assert setup.substrate is not None
        self.model: RayModel = RayModel(
            _binned_camera(camera, b, r0, c0),
            pattern,
            setup.pattern.radiance,
            setup.substrate.size,
            setup.substrate.roi_length,
            rr.ravel(),
            cc.ravel(),
            sub,
            variant,
            jitter,
        )

    def linearise(
        self, surf: SplineSurface, need_jac: bool = True, pose: bool = False
    ) -> tuple[Array, NDArray[np.bool_], sp.csr_matrix | None, Array | None]:
        """Model pixel values, usable-pixel mask, sparse Jacobian (usable pixels x coefficients) and, with ``pose``,
        the Jacobian of the 12 camera and pattern motions (usable pixels x 12)."""
        model = self.model
        res = model.trace(spline_grid(surf), surf.coef, sensitivities=need_jac, pose=pose)
        vals, ok = model.pixel_values(res)
        if not need_jac:
            return vals, ok, None, None
        assert res.sens is not None
        jac = _coefficient_jacobian(res, ok, model.spp, surf)
        jpose = None
        if res.pose is not None:
            jpose = res.pose.reshape(12, -1, model.spp).mean(axis=2)[:, ok].T
        return vals, ok, jac, jpose

    def aim(self, camera: Camera, pattern: MarkerPattern) -> None:
        """The level's rays traced anew from a moved camera (on the level's pixel grid) and pattern."""
        from scopetwin.scenes.mitsuba.deflectometry_ad import RayModel

        m = self.model
        m.camera, m.pattern = camera, pattern
        fresh = RayModel(m.camera, m.pattern, m.radiance, m.size, m.roi_length, m.rows, m.cols, m.sub, None, m.jitter)
        fresh.m = m.m
        self.model = fresh
