"""The substrate: a height map with bicubic interpolation, the secant intersection and the holding frame.

Thesis §1.6.4: the surface is a height distribution h(r_perp) over a base plane,
given "as an array with cubic interpolation" for simulation; rays meet it by
the secant iteration of eq. 1.6 (:mod:`scopetwin.scenes.secant`). The substrate lies on a holding frame at both
ends (thesis §1.4, Fig. 1.3); only the gap between the frame regions — the region
of interest (ROI), 48 mm long in §1.10 — reflects into the camera.

Height maps follow the file contract (docs/contract.md, "Height maps"): node (row k, column l) is at
(x_min + l*dx, y_min + k*dy), nodes span the extents inclusive.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.interpolate import RectBivariateSpline

from scopetwin.scenes.errors import GeometryError
from scopetwin.scenes.geometry import Array, Frame, intersect_plane, normalize
from scopetwin.scenes.secant import secant_intersection

if TYPE_CHECKING:
    from scopetwin.scenes.bicubic import BicubicCells


@dataclass(frozen=True)
class HeightMap:
    """Heights on a regular grid with a bicubic interpolating spline (exact h and gradient).

    Parameters
    ----------
    z : array_like, (ny, nx)
        Heights in mm; row k at y_min + k*dy, column l at x_min + l*dx.
    x_min, x_max, y_min, y_max : float
        Extents of the node grid, mm (inclusive).

    Notes
    -----
    The interpolant is scipy's interpolating bicubic spline (``RectBivariateSpline``,
    kx = ky = 3, s = 0): C2-continuous, so h and its gradient are exact derivatives
    of one function — the "array with cubic interpolation" of thesis §1.6.4. Outside
    the extents the surface continues with the value at the nearest edge point.
    """

    z: Array
    x_min: float
    x_max: float
    y_min: float
    y_max: float
    _spline: RectBivariateSpline = field(init=False, repr=False, compare=False)
    _cells: list[BicubicCells] = field(init=False, repr=False, compare=False, default_factory=list)

    def __post_init__(self) -> None:
        z = np.asarray(self.z, dtype=np.float64)
        if z.ndim != 2 or min(z.shape) < 4:
            raise GeometryError(f"height map must be a 2-D array of at least 4x4 nodes, got shape {z.shape}")
        if not np.all(np.isfinite(z)):
            raise GeometryError("height map contains NaN or infinite values")
        if not (self.x_max > self.x_min and self.y_max > self.y_min):
            raise GeometryError(
                f"height map extents must be increasing, got x [{self.x_min}, {self.x_max}], "
                f"y [{self.y_min}, {self.y_max}]"
            )
        object.__setattr__(self, "z", z)
        spline = RectBivariateSpline(self.y_nodes, self.x_nodes, z, kx=3, ky=3, s=0)
        object.__setattr__(self, "_spline", spline)

    @classmethod
    def from_function(
        cls, func, x_min: float, x_max: float, y_min: float, y_max: float, nx: int = 256, ny: int = 512
    ) -> HeightMap:
        """Sample ``func(x, y) -> h`` (vectorised, mm) on an nx x ny node grid."""
        x = np.linspace(x_min, x_max, nx)
        y = np.linspace(y_min, y_max, ny)
        xx, yy = np.meshgrid(x, y)
        return cls(np.asarray(func(xx, yy), dtype=np.float64) * np.ones_like(xx), x_min, x_max, y_min, y_max)

    @property
    def x_nodes(self) -> Array:
        return np.linspace(self.x_min, self.x_max, self.z.shape[1])

    @property
    def y_nodes(self) -> Array:
        return np.linspace(self.y_min, self.y_max, self.z.shape[0])

    def _clamp(self, x: ArrayLike, y: ArrayLike) -> tuple[Array, Array]:
        return (
            np.clip(np.asarray(x, dtype=np.float64), self.x_min, self.x_max),
            np.clip(np.asarray(y, dtype=np.float64), self.y_min, self.y_max),
        )

    def height(self, x: ArrayLike, y: ArrayLike) -> Array:
        """h(x, y), mm."""
        xc, yc = self._clamp(x, y)
        return self._spline.ev(yc, xc)

    def gradient(self, x: ArrayLike, y: ArrayLike) -> tuple[Array, Array]:
        """(dh/dx, dh/dy), dimensionless; zero outside the extents (constant continuation)."""
        xa = np.asarray(x, dtype=np.float64)
        ya = np.asarray(y, dtype=np.float64)
        xc, yc = self._clamp(xa, ya)
        inside_x = (xa >= self.x_min) & (xa <= self.x_max)
        inside_y = (ya >= self.y_min) & (ya <= self.y_max)
        hx = np.where(inside_x, self._spline.ev(yc, xc, dy=1), 0.0)
        hy = np.where(inside_y, self._spline.ev(yc, xc, dx=1), 0.0)
        return hx, hy

    @property
    def spline(self) -> RectBivariateSpline:
        """The interpolating bicubic spline itself (scipy's ``RectBivariateSpline``; its first axis is y)."""
        return self._spline

    def cells(self) -> BicubicCells:
        """The spline as one bicubic polynomial per knot cell (:mod:`scopetwin.scenes.bicubic`), for evaluating it
        at many points and tracing rays through it; built on the first call (a few ms per 10^4 nodes) and kept."""
        if not self._cells:
            from scopetwin.scenes.bicubic import BicubicCells

            self._cells.append(BicubicCells(self._spline, (self.x_min, self.x_max, self.y_min, self.y_max)))
        return self._cells[0]

    def normals(self, x: ArrayLike, y: ArrayLike) -> Array:
        """Unit normals (-h_x, -h_y, 1)/sqrt(1 + h_x^2 + h_y^2) in the base-plane frame (thesis eq. 1.2)."""
        hx, hy = self.gradient(x, y)
        return normalize(np.stack([-hx, -hy, np.ones_like(hx)], axis=-1))

    def resampled(self, nx: int, ny: int) -> HeightMap:
        """The same surface evaluated on another node grid over the same extents."""
        x = np.linspace(self.x_min, self.x_max, nx)
        y = np.linspace(self.y_min, self.y_max, ny)
        xx, yy = np.meshgrid(x, y)
        return HeightMap(self.height(xx, yy), self.x_min, self.x_max, self.y_min, self.y_max)


@dataclass(frozen=True)
class Substrate:
    """A bent glass substrate lying on a holding frame (thesis §1.4, §1.6.4, §1.10).

    Parameters
    ----------
    heights : HeightMap
        h over the base plane (local coordinates of ``frame``), covering the whole substrate.
    size_x, size_y : float
        Substrate extent, mm, centred on the frame origin (25.2 x 57 mm in §1.10).
    roi_length : float
        Length along y of the gap between the two frame regions, mm (48 mm in §1.10).
        The frame regions are ``roi_length/2 <= |y| <= size_y/2``.
    frame : Frame
        The base plane (the global frame by definition, §1.10).
    """

    heights: HeightMap
    size_x: float = 25.2
    size_y: float = 57.0
    roi_length: float = 48.0
    frame: Frame = field(default_factory=Frame.identity)

    def __post_init__(self) -> None:
        if not (self.size_x > 0 and self.size_y > 0):
            raise GeometryError(f"substrate size must be > 0 mm, got {self.size_x} x {self.size_y}")
        if not 0 < self.roi_length <= self.size_y:
            raise GeometryError(f"substrate roi_length must be in (0, size_y={self.size_y}] mm, got {self.roi_length}")

    def on_substrate(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.bool_]:
        """True for local points on the substrate."""
        return (np.abs(x) <= 0.5 * self.size_x) & (np.abs(y) <= 0.5 * self.size_y)

    def in_roi(self, x: ArrayLike, y: ArrayLike) -> NDArray[np.bool_]:
        """True for local points in the region of interest (between the frame regions)."""
        return (np.abs(x) <= 0.5 * self.size_x) & (np.abs(y) < 0.5 * self.roi_length)

    def frame_regions(self, x: ArrayLike, y: ArrayLike) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
        """Masks of frame region 1 (y < 0) and region 2 (y > 0) (thesis eq. 1.3)."""
        on = self.on_substrate(x, y)
        ya = np.asarray(y)
        return on & (ya <= -0.5 * self.roi_length), on & (ya >= 0.5 * self.roi_length)

    def intersect(
        self, origins: ArrayLike, directions: ArrayLike, tol: float = 1e-10, max_iter: int = 60
    ) -> tuple[Array, NDArray[np.bool_]]:
        """Ray parameters of the intersection with the surface by the secant iteration (thesis §1.6.4, eq. 1.6).

        :func:`secant_intersection` on f(lambda) = h(r_perp(lambda)) - z(lambda) in the base frame;
        lambda_0 = 0 (the ray origin), lambda_1 = the base-plane intersection; iterate until ``|f|`` < ``tol`` mm.

        Returns
        -------
        lam : ndarray
            Ray parameter of the hit (NaN where the iteration did not converge).
        converged : ndarray of bool
            Where ``|f(lambda)| < tol`` was reached. Whether the hit lies on the substrate or in
            the ROI is for the caller to decide (:meth:`in_roi`).
        """
        lam, converged, _ = self._intersect(origins, directions, tol, max_iter)
        return lam, converged

    def _intersect(
        self, origins: ArrayLike, directions: ArrayLike, tol: float = 1e-10, max_iter: int = 60
    ) -> tuple[Array, NDArray[np.bool_], Array | None]:
        """:meth:`intersect`, and the local unit normals at the hits where the height map's cells give them."""
        o = self.frame.to_local(origins)
        d = self.frame.vectors_to_local(directions)
        o, d = np.broadcast_arrays(o, d)
        shape = o.shape[:-1]
        o = o.reshape(-1, 3)
        d = d.reshape(-1, 3)
        lam0, lam1 = np.zeros(len(o)), intersect_plane(o, d, Frame.identity())
        if not isinstance(self.heights, HeightMap):
            lam, converged = secant_intersection(self.heights, o, d, lam0, lam1, tol, max_iter)
            return np.where(converged, lam, np.nan).reshape(shape), converged.reshape(shape), None
        lam, converged, _, hx, hy = self.heights.cells().intersect(o, d, lam0, lam1, tol, max_iter)
        n_local = np.stack([-hx, -hy, np.ones_like(hx)], axis=-1) / np.sqrt(1.0 + hx * hx + hy * hy)[:, None]
        return lam.reshape(shape), converged.reshape(shape), n_local.reshape(*shape, 3)

    def points_and_normals(self, origins: ArrayLike, directions: ArrayLike) -> tuple[Array, Array, NDArray]:
        """Global hit points and unit normals of rays on the surface; mask of hits inside the ROI."""
        lam, ok, n_hit = self._intersect(origins, directions)
        lam = np.where(ok, lam, 0.0)
        o = np.asarray(origins, dtype=np.float64)
        d = np.asarray(directions, dtype=np.float64)
        p = o + lam[..., None] * d
        local = self.frame.to_local(p)
        if n_hit is None:
            n_local = self.heights.normals(local[..., 0], local[..., 1])
        else:  # the normal at the hit itself (a ray that missed: the base plane's, as the spline's there)
            n_local = np.where(ok[..., None], n_hit, np.array([0.0, 0.0, 1.0]))
        n = self.frame.vectors_to_global(n_local)
        mask = ok & self.in_roi(local[..., 0], local[..., 1])
        return p, n, mask
