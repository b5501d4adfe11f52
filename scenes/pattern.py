"""Marker patterns (thesis §1.6.3 for the deflectometry pattern, §2.2 for the calibration target).

A pattern is a plane (a :class:`~scopetwin.scenes.geometry.Frame`) carrying a Cartesian
grid of round markers whose grey value fades linearly from 1 at the centre to
0 at the rim, g = 1 - r/r_m (thesis §1.6.3, "Marker Shape"). One marker, the
reference, is larger.

Index conventions (docs/contract.md, "Marker indices")
------------------------------------------------------
(i, j) counts pitches along the pattern's own T_x, T_y.

* ``layout="deflectometry"``: the reference marker is (0, 0). For an odd
  marker count the marker with index 0 sits at the pattern centre; for an even
  count the left edge of marker 0 is at the centre, i.e. its centre is at +pitch/2
  (thesis §1.6.3, "Marker Index").
* ``layout="calibration"``: the origin is the pattern centre and the reference
  marker is the last one in -x and -y (thesis §2.2); it has index (0, 0), so indices
  run 0..n-1.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scopetwin.scenes.errors import GeometryError
from scopetwin.scenes.geometry import Array, Frame

Layout = Literal["deflectometry", "calibration"]


@dataclass(frozen=True)
class MarkerPattern:
    """A planar grid of fading round markers.

    Parameters
    ----------
    frame : Frame
        Pattern plane: centre r_c and axes T_x, T_y, N_z (N_z is the emitting side).
    n_x, n_y : int
        Marker counts NM_x, NM_y.
    pitch_x, pitch_y : float
        Marker periods, mm.
    radius : float
        Marker radius r_m, mm.
    ref_radius : float
        Radius of the reference marker, mm (larger than ``radius``).
    layout : {"deflectometry", "calibration"}
        Where the reference marker is and how indices run (module docstring).
    size_x, size_y : float
        Extent of the emitting plate, mm (centred on r_c). 0 (the default; None is taken as 0): the marker grid
        plus one pitch, (n + 1) * pitch, filled in on construction.
    """

    frame: Frame
    n_x: int
    n_y: int
    pitch_x: float
    pitch_y: float
    radius: float
    ref_radius: float
    layout: Layout = "deflectometry"
    size_x: float = 0.0
    size_y: float = 0.0

    def __post_init__(self) -> None:
        for name in ("n_x", "n_y"):
            v = getattr(self, name)
            if int(v) != v or v < 1:
                raise GeometryError(f"pattern marker count {name} must be a positive integer, got {v}")
        for name in ("pitch_x", "pitch_y", "radius", "ref_radius"):
            v = getattr(self, name)
            if not v > 0:
                raise GeometryError(f"pattern {name} must be > 0 mm, got {v}")
        if self.layout not in ("deflectometry", "calibration"):
            raise GeometryError(f"pattern layout must be 'deflectometry' or 'calibration', got {self.layout!r}")
        if self.ref_radius < self.radius:
            raise GeometryError("pattern ref_radius must not be smaller than the marker radius")
        pitch = min(self.pitch_x, self.pitch_y)
        if self.radius + self.ref_radius > pitch:
            raise GeometryError(
                f"markers overlap: radius {self.radius} + ref_radius {self.ref_radius} mm exceed the pitch {pitch} mm"
            )
        if not self.size_x:  # 0 or None: derived from the grid
            object.__setattr__(self, "size_x", (self.n_x + 1) * self.pitch_x)
        if not self.size_y:
            object.__setattr__(self, "size_y", (self.n_y + 1) * self.pitch_y)
        lo_x, hi_x = self._axis_range(self.n_x, self.pitch_x)
        lo_y, hi_y = self._axis_range(self.n_y, self.pitch_y)
        if max(abs(lo_x), abs(hi_x)) + self.ref_radius > 0.5 * self.size_x + 1e-9 or (
            max(abs(lo_y), abs(hi_y)) + self.ref_radius > 0.5 * self.size_y + 1e-9
        ):
            raise GeometryError(f"pattern plate {self.size_x} x {self.size_y} mm is smaller than its marker grid")

    # -- index <-> position ------------------------------------------------------------
    def _first_index(self, n: int) -> int:
        if self.layout == "calibration":
            return 0
        return -(n - 1) // 2 if n % 2 else -n // 2

    def _offset(self, n: int, pitch: float) -> float:
        """Local coordinate of the marker with index 0 along one axis."""
        if self.layout == "calibration":
            return -0.5 * (n - 1) * pitch
        return 0.0 if n % 2 else 0.5 * pitch

    def _axis_range(self, n: int, pitch: float) -> tuple[float, float]:
        k0 = self._first_index(n)
        off = self._offset(n, pitch)
        return off + k0 * pitch, off + (k0 + n - 1) * pitch

    @property
    def reference_index(self) -> tuple[int, int]:
        """Index of the reference marker: always (0, 0) (docs/contract.md, "Marker indices")."""
        return (0, 0)

    def indices(self) -> NDArray[np.int64]:
        """All marker indices (i, j), shape (n_x*n_y, 2), i fastest."""
        i = np.arange(self.n_x) + self._first_index(self.n_x)
        j = np.arange(self.n_y) + self._first_index(self.n_y)
        jj, ii = np.meshgrid(j, i, indexing="ij")
        return np.stack([ii.ravel(), jj.ravel()], axis=-1)

    def centers_local(self, ij: ArrayLike | None = None) -> Array:
        """Local (x, y) of marker centres, mm, for indices ``ij`` (default: all)."""
        ij = self.indices() if ij is None else np.asarray(ij)
        x = self._offset(self.n_x, self.pitch_x) + ij[..., 0] * self.pitch_x
        y = self._offset(self.n_y, self.pitch_y) + ij[..., 1] * self.pitch_y
        return np.stack([x, y], axis=-1).astype(np.float64)

    def centers(self, ij: ArrayLike | None = None) -> Array:
        """Global positions of marker centres, mm, shape (..., 3)."""
        xy = self.centers_local(ij)
        return self.frame.to_global(np.concatenate([xy, np.zeros(xy.shape[:-1] + (1,))], axis=-1))

    def radii(self, ij: ArrayLike | None = None) -> Array:
        """Radius of each marker (the reference marker is larger), mm."""
        ij = self.indices() if ij is None else np.asarray(ij)
        is_ref = (ij[..., 0] == 0) & (ij[..., 1] == 0)
        return np.where(is_ref, self.ref_radius, self.radius)

    def nearest_index(self, local_xy: ArrayLike) -> NDArray[np.int64]:
        """Index (i, j) of the marker cell containing local points (thesis §1.6.3, "Marker Index")."""
        p = np.asarray(local_xy, dtype=np.float64)
        out = []
        for axis, n, pitch in ((0, self.n_x, self.pitch_x), (1, self.n_y, self.pitch_y)):
            k0 = self._first_index(n)
            k = np.rint((p[..., axis] - self._offset(n, pitch)) / pitch)
            out.append(np.clip(k, k0, k0 + n - 1).astype(np.int64))
        return np.stack(out, axis=-1)

    # -- radiance --------------------------------------------------------------------
    def grey_local(self, local_xy: ArrayLike) -> Array:
        """Grey value at local points: g = max(0, 1 - r/r_m) of the nearest marker, 0 off the plate."""
        p = np.asarray(local_xy, dtype=np.float64)
        ij = self.nearest_index(p)
        rel = p[..., :2] - self.centers_local(ij)
        r = np.hypot(rel[..., 0], rel[..., 1])
        g = np.clip(1.0 - r / self.radii(ij), 0.0, 1.0)
        on_plate = (np.abs(p[..., 0]) <= 0.5 * self.size_x) & (np.abs(p[..., 1]) <= 0.5 * self.size_y)
        return np.where(on_plate, g, 0.0)

    def texture(self, texel: float = 0.0125) -> Array:
        """Raster of :meth:`grey_local` over the plate, float32, texel centres sampled.

        Row 0 / column 0 is the (-x, -y) corner of the plate, so that row index grows
        along T_y and column index along T_x (Mitsuba's uv convention for a rectangle).
        """
        nx = max(2, int(np.ceil(self.size_x / texel)))
        ny = max(2, int(np.ceil(self.size_y / texel)))
        x = (np.arange(nx) + 0.5) / nx * self.size_x - 0.5 * self.size_x
        y = (np.arange(ny) + 0.5) / ny * self.size_y - 0.5 * self.size_y
        xx, yy = np.meshgrid(x, y)
        return self.grey_local(np.stack([xx, yy], axis=-1)).astype(np.float32)

    def rim_points(self, n_points: int = 16, ij: ArrayLike | None = None) -> Array:
        """Global points on each marker's rim, shape (n_markers, n_points, 3)."""
        ij = self.indices() if ij is None else np.asarray(ij)
        c = self.centers_local(ij)
        t = np.linspace(0.0, 2 * np.pi, n_points, endpoint=False)
        r = self.radii(ij)[:, None]
        local = np.stack(
            [c[:, None, 0] + r * np.cos(t), c[:, None, 1] + r * np.sin(t), np.zeros((len(c), n_points))], axis=-1
        )
        return self.frame.to_global(local)
