"""The fit's forward model: the measurement rendered through the thesis's ray model of §1.6 in Dr.Jit
(:mod:`scopetwin.scenes.mitsuba.deflectometry_ad`), one resolution level at a time, with its Jacobian.

A level is a window of the image binned b x b (each block rendered as one super-pixel: the image blurred and
decimated, which widens the basin) and the ray model of those super-pixels. The Jacobian with respect to the spline
coefficients is sparse (16 coefficients per ray) and exact: per ray, the render returns the derivative with respect to
a local height/slope perturbation (in closed form, in the trace's kernel), combined here with the B-spline basis.

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
        ddx, ddy = x_all[rows], y_all[rows]  # copies, centred in place
        part = out[:, start : start + len(rows)]
        part[0], part[1] = ddx.mean(axis=1), ddy.mean(axis=1)
        ddx -= part[0][:, None]
        ddy -= part[1][:, None]
        for k, s in enumerate(s_all):  # mean of a, b, c and of each times the hit's offsets (row-wise dots)
            sk = s[rows]
            part[2 + k] = sk.mean(axis=1)
            part[5 + 2 * k] = np.einsum("ij,ij->i", sk, ddx) / spp
            part[6 + 2 * k] = np.einsum("ij,ij->i", sk, ddy) / spp
    return tuple(out)


def _coefficient_jacobian(res: Any, ok: NDArray[np.bool_], spp: int, surf: SplineSurface) -> sp.csr_matrix:
    """The sparse Jacobian (usable pixels x coefficients) of the pixel values: each pixel's ray sensitivities
    combined with the B-spline basis expanded to second order about its mean hit point (:func:`_pixel_moments`)."""
    npix = int(ok.sum())
    xm, ym, ma, mb, mc, max_, may, mbx, mby, mcx, mcy = _pixel_moments(res, ok, spp)
    idx, (wu, du, su), (wv, dv, sv) = surf.axis_weights(xm, ym)
    col = lambda v: v[:, None]  # noqa: E731
    # ma w + (max + mb) w_x + (may + mc) w_y + mbx w_xx + (mby + mcx) w_xy + mcy w_yy, the basis a tensor product:
    # gathered by its y factor, three outer products
    ax = col(ma) * wu + col(max_ + mb) * du + col(mbx) * su
    bx = col(may + mc) * wu + col(mby + mcx) * du
    data = wv[:, :, None] * ax[:, None, :]
    data += dv[:, :, None] * bx[:, None, :]
    data += sv[:, :, None] * (col(mcy) * wu)[:, None, :]
    # 16 entries a row, their columns increasing (axis_weights' order): the compressed rows directly
    indptr = np.arange(0, 16 * npix + 1, 16)
    return sp.csr_matrix((data.ravel(), idx.ravel(), indptr), shape=(npix, surf.coef.size))


class _Level:
    """One resolution level: the ray model of the (binned) window's pixels and the binned image with weights.

    ``near`` = (surface, margin): trace only the pixels near a marker's image through that surface
    (:func:`_near_pixels`)."""

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
        near: tuple[SplineSurface, int] | None = None,
    ) -> None:
        from scopetwin.scenes.mitsuba.deflectometry_ad import RayModel

        r0, r1, c0, c1 = window
        self.b = b
        self.data = bin_image(image, b, (r0, r1), (c0, c1)).ravel()
        # variance of a block mean: mean variance / b^2
        self.var = bin_image(var, b, (r0, r1), (c0, c1)).ravel() / (b * b)
        nr, nc = (r1 - r0) // b, (c1 - c0) // b
        self.shape = (nr, nc)
        rr, cc = np.meshgrid(np.arange(nr), np.arange(nc), indexing="ij")
        #: the pixels traced (indices into the level's pixels), None: all; of the others, whether their rays meet the
        #: substrate (then they are dark) or miss it (:func:`_near_pixels`)
        self.near: NDArray[np.intp] | None = None
        self._far_ok: NDArray[np.bool_] | None = None
        # a super-pixel of b x b pixels: model its rays on a b-times coarser pixel grid
        assert setup.substrate is not None
        cam_b = _binned_camera(camera, b, r0, c0)
        size, roi, radiance = setup.substrate.size, setup.substrate.roi_length, setup.pattern.radiance
        #: the one-ray probe the traced pixels were chosen with, and their margin (:meth:`widen`)
        self._probe: tuple[RayModel, int] | None = None
        if near is not None:  # one ray per pixel first, to find the pixels near the markers' images
            probe = RayModel(cam_b, pattern, radiance, size, roi, rr.ravel(), cc.ravel(), 1, variant, False)
            self.near, self._far_ok = _near_pixels(probe, self.shape, *near)
            self._probe = (probe, near[1])
        self.model = RayModel(
            cam_b, pattern, radiance, size, roi, rr.ravel(), cc.ravel(), sub, variant, jitter, self.near
        )

    def linearise(
        self, surf: SplineSurface, need_jac: bool = True, pose: bool = False
    ) -> tuple[Array, NDArray[np.bool_], sp.csr_matrix | None, Array | None]:
        """Model pixel values, usable-pixel mask, sparse Jacobian (usable pixels x coefficients) and, with ``pose``,
        the Jacobian of the 12 camera and pattern motions (usable pixels x 12). Of the level's every pixel: those
        not traced (:func:`_near_pixels`) are dark (value 0, rows of the Jacobians zero) and usable where their
        centre ray met the substrate."""
        model = self.model
        res = model.trace(spline_grid(surf), surf.coef, sensitivities=need_jac, pose=pose)
        vals, ok = model.pixel_values(res)
        jac = jpose = None
        if need_jac:
            assert res.sens is not None
            jac = _coefficient_jacobian(res, ok, model.spp, surf)
            if res.pose is not None:
                jpose = np.stack([p.reshape(-1, model.spp).mean(axis=1)[ok] for p in res.pose], axis=1)
        if self.near is None:
            return vals, ok, jac, jpose
        assert self._far_ok is not None
        vals_all, ok_all = np.zeros(len(self._far_ok)), self._far_ok.copy()
        vals_all[self.near], ok_all[self.near] = vals, ok
        if jac is not None:  # the traced pixels' rows among every usable pixel's
            rows = (np.cumsum(ok_all) - 1)[self.near[ok]]
            jac = _with_rows(jac, rows, int(ok_all.sum()))
            if jpose is not None:
                jpose_all = np.zeros((int(ok_all.sum()), 12))
                jpose_all[rows] = jpose
                jpose = jpose_all
        return vals_all, ok_all, jac, jpose

    def widen(self, surf: SplineSurface) -> int:
        """Check the traced pixels against ``surf`` (the fit's last surface); where it needs more, add them. Returns
        how many were added (0: the selection held; every pixel traced: always 0).

        The equations are those of every pixel traced while each pixel within one of one whose centre ray sees a
        marker, or of the substrate image's edge, through ``surf`` is traced (:func:`_near_pixels` with margin 1:
        a marker's image is several pixels wide). Where one is not, the pixels within the level's margin through
        ``surf`` are added: the margin stays the slack for the next fit."""
        if self.near is None or self._probe is None:
            return 0
        probe, margin = self._probe
        needed, _ = _near_pixels(probe, self.shape, surf, 1)
        if not len(np.setdiff1d(needed, self.near, assume_unique=True)):
            return 0
        near, far_ok = _near_pixels(probe, self.shape, surf, margin)
        added = np.setdiff1d(near, self.near, assume_unique=True)
        self.near = np.union1d(self.near, added)
        self._far_ok = far_ok
        self.model = self._model(self.model, self.near)
        return len(added)

    def aim(self, camera: Camera, pattern: MarkerPattern) -> None:
        """The level's rays traced anew from a moved camera (on the level's pixel grid) and pattern."""
        m = self.model
        m.camera, m.pattern = camera, pattern
        self.model = self._model(m, self.near)

    @staticmethod
    def _model(m: RayModel, keep: NDArray[np.intp] | None) -> RayModel:
        """``m``'s ray model (its camera, pattern and pixels) anew, tracing the pixels ``keep``."""
        from scopetwin.scenes.mitsuba.deflectometry_ad import RayModel

        cam, pat = m.camera, m.pattern
        fresh = RayModel(cam, pat, m.radiance, m.size, m.roi_length, m.rows, m.cols, m.sub, None, m.jitter, keep)
        fresh.m = m.m
        return fresh


def _near_pixels(
    probe: RayModel, shape: tuple[int, int], surf: SplineSurface, margin: int
) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
    """The pixels to trace (indices) and whether each pixel's centre ray meets the substrate, from ``probe``'s one
    ray at each pixel's centre through ``surf``: those within ``margin`` pixels of one that sees a marker, of the
    edge of the substrate's image or of the level's. The others see the dark ground between the markers (value 0,
    rows of the Jacobians zero) or miss the substrate (not usable), as long as the markers' images move by less than
    the margin (a fit that starts from the centroid method's surface and holds its start height: hundredths of a
    pixel)."""
    from scipy import ndimage

    if margin < 1:
        raise ValueError(f"the margin of the pixels traced must be >= 1 pixel, got {margin}")
    res = probe.trace(spline_grid(surf), surf.coef, sensitivities=False)

    def within(mask: NDArray[np.bool_]) -> NDArray[np.bool_]:
        return np.asarray(ndimage.binary_dilation(mask.reshape(shape), np.ones((3, 3), bool), iterations=margin))

    valid = np.asarray(res.valid, dtype=bool)
    # (a marker beyond the window's edge is not seen by its rays: the pixels within the margin of the edge traced)
    edge = np.ones(shape, dtype=bool)
    edge[margin:-margin, margin:-margin] = False
    near = within(res.value > 0.0) | (within(valid) & within(~valid)) | edge
    return np.flatnonzero(near), valid


def _with_rows(jac: sp.csr_matrix, rows: NDArray[np.intp], n: int) -> sp.csr_matrix:
    """``jac``'s rows placed at ``rows`` of an n-row matrix (the others zero)."""
    coo = jac.tocoo()
    return sp.csr_matrix((coo.data, (rows[coo.row], coo.col)), shape=(n, jac.shape[1]))
