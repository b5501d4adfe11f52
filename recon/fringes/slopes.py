"""Dense slopes: every decoded pixel's surface gradient through the project's ray model (thesis §1.6, §1.7).

For each valid pixel: its camera ray through the pixel centre (:meth:`scopetwin.scenes.camera.Camera.rays`, the
pixel convention of :class:`scopetwin.scenes.camera.PixelGrid`), where it meets the current surface estimate (the
secant iteration of §1.6.4, eq. 1.6, :func:`scopetwin.scenes.secant.secant_intersection`), the display point it sees
(display coordinates -> world through the pattern frame, §1.6.3), and from the two rays the normal and the gradients
(§1.7.1-§1.7.3, :func:`scopetwin.recon.gradients.marker_gradients`: the same geometry as for a marker).

The display points' uncertainty is carried into the gradients by the Jacobian d(h_x, h_y)/d(u, v) (central
differences of the same ray model): each observation has a 2 x 2 covariance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scopetwin.recon.errors import SubstrateNotVisibleError
from scopetwin.recon.fringes.phase import DisplayCoordinates, FringeDecodingError
from scopetwin.recon.gradients import marker_gradients
from scopetwin.recon.substrate import Substrate2D
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array, Frame
from scopetwin.scenes.secant import HeightModel, secant_intersection

#: Step of the central differences of the gradients in the display coordinates, mm.
JACOBIAN_STEP_MM = 1e-3


@dataclass(frozen=True)
class PixelRays:
    """The camera rays of the decoded pixels (flat pixel index, origin, unit direction), global coordinates."""

    index: NDArray[np.intp]
    origins: Array
    dirs: Array

    @classmethod
    def of(cls, camera: Camera, valid: NDArray[np.bool_], block: int = 1) -> PixelRays:
        """Rays through the centres (col + 0.5, row + 0.5) of the pixels where ``valid`` (rows, cols) is True; with
        ``block`` b > 1 ``valid`` is over b x b pixel tiles and the rays pass through the tiles' centres
        ((col + 0.5) b, (row + 0.5) b) in pixels.

        Raises
        ------
        FringeDecodingError
            ``valid`` is not the camera's image shape (in tiles).
        """
        shape = (camera.ny // block, camera.nx // block)
        if valid.shape != shape:
            raise FringeDecodingError(
                f"decoded maps of shape {valid.shape} for a {camera.ny} x {camera.nx} (rows x cols) camera"
                + (f" in {block}-pixel blocks" if block > 1 else "")
            )
        idx = np.flatnonzero(valid)
        rows, cols = np.divmod(idx, shape[1])
        px = (block * np.stack([cols + 0.5, rows + 0.5], axis=-1)).astype(np.float64)
        o, d = camera.rays(px)
        return cls(idx, o, d)


@dataclass(frozen=True)
class SlopeObservations:
    """Gradients of the surface at the points where the pixels' rays meet it, with their covariance.

    Attributes
    ----------
    index : ndarray of int
        Flat pixel index of each observation.
    xy : ndarray, (n, 2)
        Base-plane point, mm.
    hx, hy : ndarray, (n,)
        Gradients dh/dx, dh/dy.
    cov : ndarray, (n, 3)
        (var h_x, cov(h_x, h_y), var h_y), rad^2, from the display points' uncertainty.
    hit : ndarray, (n, 3)
        Global surface points, mm.
    """

    index: NDArray[np.intp]
    xy: Array
    hx: Array
    hy: Array
    cov: Array
    hit: Array

    def __len__(self) -> int:
        return len(self.hx)


def display_points(frame: Frame, u: Array, v: Array) -> Array:
    """Global points of display coordinates (u, v), mm: origin + u T_x + v T_y (thesis §1.6.3)."""
    return frame.to_global(np.stack([u, v, np.zeros_like(u)], axis=-1))


def intersect_rays(
    surface: HeightModel, origins: Array, dirs: Array, sub: Substrate2D, tol: float = 1e-10
) -> tuple[Array, NDArray[np.bool_]]:
    """Where rays meet the surface estimate (secant iteration of §1.6.4 from the plane at its centre height).

    Returns the global hit points and whether each converged in front of the camera on the ROI.
    """
    o = sub.frame.to_local(origins)
    d = sub.frame.vectors_to_local(dirs)
    z0 = float(np.asarray(surface.height(np.zeros(1), np.zeros(1))).ravel()[0])
    with np.errstate(divide="ignore", invalid="ignore"):
        lam0 = (z0 - o[:, 2]) / d[:, 2]
    lam, ok = secant_intersection(surface, o, d, lam0, tol=tol)
    ok &= lam > 0
    local = o + np.where(ok, lam, 0.0)[:, None] * d
    ok &= (np.abs(local[:, 0]) <= 0.5 * sub.size_x) & (np.abs(local[:, 1]) < 0.5 * sub.roi_length)
    return sub.frame.to_global(local), ok


def dense_slopes(
    camera: Camera,
    pattern_frame: Frame,
    coords: DisplayCoordinates,
    surface: HeightModel,
    sub: Substrate2D,
    rays: PixelRays | None = None,
) -> SlopeObservations:
    """The gradient seen by every valid pixel through the current surface estimate (module docstring).

    Parameters
    ----------
    camera : Camera
        The (calibrated) camera.
    pattern_frame : Frame
        The display's frame: origin at its centre, T_x / T_y along the display coordinates u / v.
    coords : DisplayCoordinates
        Decoded display points per pixel (rows, cols).
    surface : HeightModel
        Current surface estimate h(x, y) on the substrate's base plane.
    sub : Substrate2D
        The substrate's footprint and ROI.
    rays : PixelRays, optional
        The valid pixels' rays, when already formed (they do not change between iterations).

    Raises
    ------
    SubstrateNotVisibleError
        No valid pixel's ray meets the region of interest.
    """
    rays = rays if rays is not None else PixelRays.of(camera, coords.valid, coords.block)
    hit, ok = intersect_rays(surface, rays.origins, rays.dirs, sub)
    if not ok.any():
        raise SubstrateNotVisibleError("no decoded pixel's ray meets the substrate's region of interest")
    idx = rays.index[ok]
    u, v = coords.u.ravel()[idx], coords.v.ravel()[idx]
    su, sv = coords.u_std.ravel()[idx], coords.v_std.ravel()[idx]
    hit, d = hit[ok], rays.dirs[ok]
    e = JACOBIAN_STEP_MM
    # the point and its four displaced copies at once: (5, n, 3)
    du = np.array([0.0, e, -e, 0.0, 0.0])[:, None]
    dv = np.array([0.0, 0.0, 0.0, e, -e])[:, None]
    targets = display_points(pattern_frame, (u + du).ravel(), (v + dv).ravel())
    xy, hx, hy = marker_gradients(np.tile(hit, (5, 1)), np.tile(d, (5, 1)), targets, sub.frame)
    n = len(idx)
    hx, hy = hx.reshape(5, n), hy.reshape(5, n)
    jxu, jyu = (hx[1] - hx[2]) / (2 * e), (hy[1] - hy[2]) / (2 * e)
    jxv, jyv = (hx[3] - hx[4]) / (2 * e), (hy[3] - hy[4]) / (2 * e)
    su2, sv2 = su * su, sv * sv
    cov = np.stack(
        [jxu * jxu * su2 + jxv * jxv * sv2, jxu * jyu * su2 + jxv * jyv * sv2, jyu * jyu * su2 + jyv * jyv * sv2],
        axis=-1,
    )
    return SlopeObservations(idx, xy[:n], hx[0], hy[0], cov, hit)
