"""The substrate's footprint and where rays meet a fitted surface on it (thesis §1.4, §1.6.4, §1.10)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from scopetwin.recon.errors import ReconstructionError, SubstrateNotVisibleError
from scopetwin.recon.shifted_basis import SBFSurface
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array, Frame
from scopetwin.scenes.secant import secant_intersection
from scopetwin.scenes.setup import Setup


@dataclass(frozen=True)
class Substrate2D:
    """The substrate's footprint on its base plane (thesis §1.4, §1.10): extent, ROI length, frame position."""

    size_x: float
    size_y: float
    roi_length: float
    frame: Frame = field(default_factory=Frame.identity)
    frame_z: float = 0.0

    @classmethod
    def from_setup(cls, setup: Setup, frame_z: float = 0.0) -> Substrate2D:
        if setup.scene != "deflectometry" or setup.substrate is None:
            raise ReconstructionError(f"setup {setup.name} is a {setup.scene!r} scene, not a deflectometry setup")
        sx, sy = setup.substrate.size
        return cls(float(sx), float(sy), float(setup.substrate.roi_length), Frame.identity(), frame_z)

    @property
    def x_range(self) -> tuple[float, float]:
        return (-0.5 * self.size_x, 0.5 * self.size_x)

    @property
    def y_range(self) -> tuple[float, float]:
        return (-0.5 * self.size_y, 0.5 * self.size_y)

    def roi_grid(self, step: float) -> tuple[Array, Array]:
        """Points of a regular grid over the ROI (flattened x, y)."""
        nx = max(2, int(round(self.size_x / step)) + 1)
        ny = max(2, int(round(self.roi_length / step)) + 1)
        xx, yy = np.meshgrid(np.linspace(*self.x_range, nx), np.linspace(-0.5, 0.5, ny) * self.roi_length)
        return xx.ravel(), yy.ravel()

    def frame_grid(self, region: int, step: float) -> tuple[Array, Array]:
        """Points of a regular grid over frame region 1 (y < 0) or 2 (y > 0), edges included."""
        depth = 0.5 * (self.size_y - self.roi_length)
        nx = max(2, int(round(self.size_x / step)) + 1)
        ny = max(2, int(round(depth / step)) + 1)
        ys = 0.5 * self.roi_length + np.linspace(0.0, depth, ny)
        xx, yy = np.meshgrid(np.linspace(*self.x_range, nx), ys if region == 2 else -ys)
        return xx.ravel(), yy.ravel()


def intersect_surface(
    surface: SBFSurface,
    origins: Array,
    dirs: Array,
    frame: Frame | None = None,
    tol: float = 1e-10,
    max_iter: int = 30,
    start: Literal["offset", "surface"] = "offset",
    max_height_change: float = 2.0,
) -> tuple[Array, NDArray[np.bool_]]:
    """Ray parameters where rays meet a fitted surface z = f(x, y) (secant iteration of thesis §1.6.4, eq. 1.6).

    :func:`scopetwin.scenes.secant.secant_intersection`, started at the rays' intersections with a plane and with
    the plane z = f there, which is close to the root for a nearly flat substrate. ``start="offset"``: the plane
    z = the surface's offset term. ``start="surface"``: the plane through the surface's height at the substrate's
    centre, and a root more than ``max_height_change`` (mm) above or below it is not taken — an ill-posed fit whose
    basis functions cancel a large offset and tilt over the substrate continues far beyond it and can meet the ray
    there, where the offset plane's start finds it (cut sheets with rolled-off edges).

    Parameters
    ----------
    surface : SBFSurface
        The current surface estimate (§1.8), in the coordinates of ``frame``.
    origins, dirs : ndarray, (n, 3)
        Camera rays, global coordinates.
    frame : Frame, optional
        The substrate's base plane (None: the rays are given in it).
    tol, max_iter : float, int
        Convergence threshold on ``|f|``, mm, and largest number of secant steps.
    start : {"offset", "surface"}
        The start plane.
    max_height_change : float
        ``start="surface"`` only: largest height of a root above or below the start plane, mm.

    Returns
    -------
    lam : ndarray, (n,)
        Ray parameters (meaningful where ``ok``).
    ok : ndarray of bool, (n,)
        Converged, in front of the ray origin (lam > 0) and (``start="surface"``) within ``max_height_change`` of
        the start plane.
    """
    o = frame.to_local(origins) if frame is not None else np.asarray(origins, dtype=np.float64)
    d = frame.vectors_to_local(dirs) if frame is not None else np.asarray(dirs, dtype=np.float64)
    if start == "surface":
        z0 = float(np.asarray(surface.height(np.zeros(1), np.zeros(1))).ravel()[0])
    else:
        z0 = float(surface.offset)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam0 = (z0 - o[:, 2]) / d[:, 2]
    lam, converged = secant_intersection(surface, o, d, lam0, tol=tol, max_iter=max_iter)
    ok = converged & (lam > 0)
    if start == "surface":
        # a root far along the ray from the plane at the surface's height is a fit's continuation far off the
        # substrate, never the substrate the ray sees
        ok &= np.abs((lam - lam0) * d[:, 2]) <= max_height_change
    return lam, ok


def check_substrate_visible(camera: Camera, sub: Substrate2D) -> None:
    """Raise :class:`SubstrateNotVisibleError` if no point of the ROI projects into the image."""
    xs, ys = sub.roi_grid(max(sub.size_x, sub.roi_length) / 12.0)
    pts = sub.frame.to_global(np.stack([xs, ys, np.full_like(xs, sub.frame_z)], axis=-1))
    px = camera.project(pts)
    inside = np.all(np.isfinite(px), axis=1) & camera.in_image(np.nan_to_num(px, nan=-1.0))
    if not inside.any():
        raise SubstrateNotVisibleError(
            "the setup's camera cannot see the substrate: no point of the region of interest projects into the "
            f"{camera.nx} x {camera.ny} image (check the camera pose in the setup)"
        )
