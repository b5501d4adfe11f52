"""The camera model of the thesis — the ONE module that maps pixels, sensor points, rays and world points.

Thesis §1.6.2 (pinhole camera with the centre behind the sensor, upright image)
and §2.5.1-2.5.2 (principal-point offset r_cs, radial distortion
r_dist = (c0 + c2*|r|)*r, the parameters (r_c, r_0, phi) of the non-linear
optimisation). Every other module calls these functions.

Coordinates
-----------
* World: mm, global frame.
* Sensor (u, v): mm in the sensor plane, measured from the foot of the optical
  axis ``r_c - b*N_z`` along T_x and T_y. The sensor point (u, v) is
  ``r_c - b*N_z + u*T_x + v*T_y``; the camera looks along -N_z.
* Distortion acts about the optical axis: the ideal (pinhole) sensor point r
  is seen at r_dist = (c0 + c2*|r|)*r (c2 in 1/mm).
* Pixels: continuous coordinates (x_px, y_px) = (column, row); pixel (row, col)
  covers [col, col+1) x [row, row+1), so its centre is (col+0.5, row+0.5).
  ``u_dist = (x_px - nx/2)*pitch + x_cs`` and ``v_dist = (ny/2 - y_px)*pitch + y_cs``
  (docs/contract.md, "Camera": column grows along T_x, row grows against T_y).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scopetwin.scenes.errors import GeometryError
from scopetwin.scenes.geometry import Array, Frame, normalize, row_norms


@dataclass(frozen=True)
class ThinLens:
    """Thin-lens option for depth of field.

    Parameters
    ----------
    focal_length : float
        f in mm.
    f_number : float
        N; the aperture diameter is f/N.
    focus_distance : float or None
        Distance (mm, along -N_z from r_c) of the plane in focus. None: the plane
        conjugate to the image distance, g = b*f/(b - f) (thin-lens equation, §2.5.2).
    """

    focal_length: float
    f_number: float
    focus_distance: float | None = None

    def __post_init__(self) -> None:
        if not self.focal_length > 0:
            raise GeometryError(f"thin lens focal length must be > 0 mm, got {self.focal_length}")
        if not self.f_number > 0:
            raise GeometryError(f"thin lens f-number must be > 0, got {self.f_number}")
        if self.focus_distance is not None and not self.focus_distance > 0:
            raise GeometryError(f"thin lens focus distance must be > 0 mm, got {self.focus_distance}")

    @property
    def aperture_radius(self) -> float:
        """Radius of the entrance pupil, mm."""
        return 0.5 * self.focal_length / self.f_number


def _is_zero(value: Any) -> bool:
    """True for a Python/numpy number that is exactly 0 (never for an array)."""
    return isinstance(value, int | float | np.floating) and float(value) == 0.0


def _plus(value: Any, term: Any) -> Any:
    """``value + term``, leaving out a term that is exactly 0 (adding +0.0 never changes a value here)."""
    return value if _is_zero(term) else value + term


@dataclass(frozen=True)
class PixelGrid:
    """The sensor's pixel grid: continuous pixel coordinates <-> sensor coordinates (docs/contract.md, "Camera").

    The one definition of the pixel convention, used by every renderer (Part I, the CMU channels, the GRIN image
    plane), the datasets and the analyses. Pixel (row, col) covers [col, col+1) x [row, row+1); the column grows
    along T_x (u), the row against T_y (v)::

        u = (x_px - nx/2) * pitch + x_cs        v = (ny/2 - y_px) * pitch + y_cs

    The scalar forms :meth:`uv` / :meth:`xy` use arithmetic only, so they run on numpy arrays and on Dr.Jit arrays
    alike (the Mitsuba sensors call them with ``dr.llvm.Float``).

    Parameters
    ----------
    nx, ny : int
        Pixel counts (columns, rows).
    pitch : float
        Pixel size (square pixels), mm.
    r_cs : tuple of float
        (x_cs, y_cs): the grid centre relative to the optical-axis foot, mm (thesis §2.5.1).
    """

    nx: int
    ny: int
    pitch: float
    r_cs: tuple[float, float] = (0.0, 0.0)

    def __post_init__(self) -> None:
        if int(self.nx) != self.nx or int(self.ny) != self.ny or self.nx < 1 or self.ny < 1:
            raise GeometryError(f"camera pixel counts must be positive integers, got {self.nx} x {self.ny}")
        if not self.pitch > 0:
            raise GeometryError(f"camera pixel pitch must be > 0 mm, got {self.pitch}")
        object.__setattr__(self, "r_cs", (float(self.r_cs[0]), float(self.r_cs[1])))

    @property
    def width_mm(self) -> float:
        """Sensor width nx*pitch, mm."""
        return self.nx * self.pitch

    @property
    def height_mm(self) -> float:
        """Sensor height ny*pitch, mm."""
        return self.ny * self.pitch

    @staticmethod
    def map_uv(
        x_px: Any,
        y_px: Any,
        nx: float,
        ny: float,
        pitch: Any,
        r_cs: tuple[Any, Any] = (0.0, 0.0),
        shift_px: tuple[float, float] = (0.0, 0.0),
    ) -> tuple[Any, Any]:
        """The convention itself, with the grid given field by field (numpy, Dr.Jit or Python numbers).

        ``u = ((x_px - nx/2) - shift_x) * pitch + x_cs``, ``v = ((ny/2 - y_px) + shift_y) * pitch + y_cs``.
        A renderer whose pitch and r_cs live in opaque Dr.Jit variables (the Part I sensor, so that a new camera
        reuses the compiled kernel) calls this form; :meth:`uv` is it with the grid's own fields. ``shift_px``
        moves the image content by (+shift_x, +shift_y) px (a camera's in-plane offset given in pixels, as the
        CMU poses are); terms that are exactly zero (Python numbers) are left out, so no operation is emitted
        into a Dr.Jit kernel for them.
        """
        u = x_px - 0.5 * nx
        v = 0.5 * ny - y_px
        if not _is_zero(shift_px[0]):
            u = u - shift_px[0]
        if not _is_zero(shift_px[1]):
            v = v + shift_px[1]
        return _plus(u * pitch, r_cs[0]), _plus(v * pitch, r_cs[1])

    def uv(self, x_px: Any, y_px: Any, shift_px: tuple[float, float] = (0.0, 0.0)) -> tuple[Any, Any]:
        """Sensor (u, v), mm, of continuous pixel coordinates given as separate arrays (numpy or Dr.Jit).

        ``shift_px``: see :meth:`map_uv` (the image content moved by that many pixels).
        """
        return self.map_uv(x_px, y_px, self.nx, self.ny, self.pitch, self.r_cs, shift_px)

    def uv_film(self, fx: Any, fy: Any) -> tuple[Any, Any]:
        """Sensor (u, v), mm, of film coordinates (fx, fy) = (x_px/nx, y_px/ny) in [0, 1)^2 (Mitsuba's film samples).

        The same convention as :meth:`uv` (``uv(fx*nx, fy*ny)`` up to rounding), written on the sensor's size:
        ``u = (fx - 1/2) * nx*pitch + x_cs``, ``v = (1/2 - fy) * ny*pitch + y_cs``.
        """
        return _plus((fx - 0.5) * self.width_mm, self.r_cs[0]), _plus((0.5 - fy) * self.height_mm, self.r_cs[1])

    def xy(self, u: Any, v: Any, shift_px: tuple[float, float] = (0.0, 0.0)) -> tuple[Any, Any]:
        """Continuous pixel coordinates (x_px, y_px) of sensor points (u, v), mm (numpy or Dr.Jit): uv undone."""
        a = (u - self.r_cs[0]) / self.pitch
        b = (v - self.r_cs[1]) / self.pitch
        if not _is_zero(shift_px[0]):
            a = a + shift_px[0]
        if not _is_zero(shift_px[1]):
            b = b - shift_px[1]
        return a + 0.5 * self.nx, 0.5 * self.ny - b

    def pixel_to_sensor(self, px: ArrayLike) -> Array:
        """Continuous pixel coordinates (..., 2) as (x_px, y_px) -> sensor (u, v), mm."""
        p = np.asarray(px, dtype=np.float64)
        return np.stack(self.uv(p[..., 0], p[..., 1]), axis=-1)

    def sensor_to_pixel(self, uv: ArrayLike) -> Array:
        """Sensor (u, v), mm, (..., 2) -> continuous pixel coordinates (x_px, y_px)."""
        q = np.asarray(uv, dtype=np.float64)
        return np.stack(self.xy(q[..., 0], q[..., 1]), axis=-1)

    def pixel_centers(self, rows: slice | None = None, cols: slice | None = None) -> Array:
        """Continuous coordinates of pixel centres, shape (n_rows, n_cols, 2) as (x_px, y_px)."""
        r = np.arange(self.ny)[rows if rows is not None else slice(None)] + 0.5
        c = np.arange(self.nx)[cols if cols is not None else slice(None)] + 0.5
        cc, rr = np.meshgrid(c, r)
        return np.stack([cc, rr], axis=-1)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready grid: ``nx``, ``ny``, ``pitch`` (mm), ``r_cs`` (mm) -- the one writer of a camera's grid."""
        return {"nx": self.nx, "ny": self.ny, "pitch": self.pitch, "r_cs": list(self.r_cs)}

    def contains(self, px: ArrayLike, margin: float = 0.0) -> NDArray[np.bool_]:
        """True where continuous pixel coordinates lie inside the image (shrunk by ``margin`` px)."""
        p = np.asarray(px, dtype=np.float64)
        return (
            (p[..., 0] >= margin)
            & (p[..., 0] <= self.nx - margin)
            & (p[..., 1] >= margin)
            & (p[..., 1] <= self.ny - margin)
        )


@dataclass(frozen=True)
class Camera:
    """Pinhole camera of thesis §1.6.2 / §2.5.2 with optional distortion and thin lens.

    Parameters
    ----------
    frame : Frame
        Camera centre r_c (frame origin) and sensor axes T_x, T_y, N_z.
    b : float
        Image distance, mm.
    nx, ny : int
        Pixel counts NP_x, NP_y.
    pitch : float
        Pixel size (square pixels), mm.
    r_cs : tuple of float
        (x_cs, y_cs): the pixel-grid centre's position relative to the optical-axis foot, mm.
    c0, c2 : float
        Radial distortion r_dist = (c0 + c2*|r|)*r; c2 in 1/mm.
    lens : ThinLens or None
        Depth-of-field model; None is an ideal pinhole.
    """

    frame: Frame
    b: float
    nx: int
    ny: int
    pitch: float
    r_cs: tuple[float, float] = (0.0, 0.0)
    c0: float = 1.0
    c2: float = 0.0
    lens: ThinLens | None = None

    def __post_init__(self) -> None:
        if not self.b > 0:
            raise GeometryError(f"camera image distance b must be > 0 mm, got {self.b}")
        PixelGrid(self.nx, self.ny, self.pitch, self.r_cs)  # validates the grid fields
        if not self.c0 > 0:
            raise GeometryError(f"distortion coefficient c0 must be > 0, got {self.c0}")
        object.__setattr__(self, "r_cs", (float(self.r_cs[0]), float(self.r_cs[1])))

    # -- construction ------------------------------------------------------------------
    @classmethod
    def from_pose(
        cls,
        r_c: ArrayLike,
        r_0: ArrayLike,
        phi: float,
        focal_length: float,
        nx: int,
        ny: int,
        pitch: float,
        **kwargs,
    ) -> Camera:
        """Camera from the optimisation parameters of thesis §2.5.2.

        ``N_z = (r_c - r_0)/|r_c - r_0|``, T_0x = e_y x N_z, T_0y = N_z x T_0x,
        T_x = cos(phi) T_0x + sin(phi) T_0y, T_y = cos(phi) T_0y - sin(phi) T_0x,
        ``g = |r_c - r_0|``, b = g f/(g - f). ``r_0`` may be 2-D (a point of the plane z = 0).
        """
        rc = np.asarray(r_c, dtype=np.float64)
        r0 = np.zeros(3)
        r0[: len(np.atleast_1d(r_0))] = np.asarray(r_0, dtype=np.float64)
        nz, tx, ty, g = pose_axes(rc, r0, phi)
        if not g > focal_length:
            raise GeometryError(f"object distance g = {g:.4g} mm must exceed the focal length {focal_length} mm")
        b = g * focal_length / (g - focal_length)
        return cls(Frame(rc, tx, ty, nz), b, nx, ny, pitch, **kwargs)

    def with_(self, **changes) -> Camera:
        """A copy with some fields changed."""
        return replace(self, **changes)

    # -- intrinsic mappings ------------------------------------------------------------
    @property
    def center(self) -> Array:
        """Camera centre r_c, mm."""
        return self.frame.origin

    def distort(self, uv: ArrayLike) -> Array:
        """Ideal sensor coordinates -> distorted, r_dist = (c0 + c2*|r|) r (thesis §2.5.1)."""
        r = np.asarray(uv, dtype=np.float64)
        rho = row_norms(r, keepdims=True)
        return (self.c0 + self.c2 * rho) * r

    def undistort(self, uv_dist: ArrayLike) -> Array:
        """Closed-form inverse of :meth:`distort`.

        ``|r_d| = c0 rho + c2 rho^2`` is solved for rho with the cancellation-free
        root ``rho = 2|r_d| / (c0 + sqrt(c0^2 + 4 c2 |r_d|))``; then r = r_d/(c0 + c2 rho).
        """
        rd = np.asarray(uv_dist, dtype=np.float64)
        s = row_norms(rd, keepdims=True)
        disc = self.c0**2 + 4.0 * self.c2 * s
        if np.any(disc < 0):
            raise GeometryError("distortion is not invertible here: c0^2 + 4*c2*|r| < 0 (c2 too negative)")
        rho = 2.0 * s / (self.c0 + np.sqrt(disc))
        return rd / (self.c0 + self.c2 * rho)

    @property
    def grid(self) -> PixelGrid:
        """The camera's pixel grid (the pixel <-> sensor convention)."""
        return PixelGrid(self.nx, self.ny, self.pitch, self.r_cs)

    def pixel_to_sensor(self, px: ArrayLike) -> Array:
        """Continuous pixel coordinates (x_px, y_px) -> distorted sensor (u, v), mm."""
        return self.grid.pixel_to_sensor(px)

    def sensor_to_pixel(self, uv: ArrayLike) -> Array:
        """Distorted sensor (u, v), mm -> continuous pixel coordinates (x_px, y_px)."""
        return self.grid.sensor_to_pixel(uv)

    def pixel_centers(self, rows: slice | None = None, cols: slice | None = None) -> Array:
        """Continuous coordinates of pixel centres, shape (n_rows, n_cols, 2) as (x_px, y_px)."""
        return self.grid.pixel_centers(rows, cols)

    # -- world mappings ----------------------------------------------------------------
    def sensor_points(self, uv_ideal: ArrayLike) -> Array:
        """Global position r_s = r_c - b N_z + u T_x + v T_y of ideal sensor points (thesis §1.6.2)."""
        q = np.asarray(uv_ideal, dtype=np.float64)
        f = self.frame
        return f.origin - self.b * f.nz + q[..., :1] * f.tx + q[..., 1:2] * f.ty

    def project_ideal(self, points: ArrayLike) -> Array:
        """World points -> ideal sensor (u, v): m = b / (-D.N_z), u = m D.T_x, v = m D.T_y (thesis §2.5.3)."""
        d = self.frame.vectors_to_local(np.asarray(points, dtype=np.float64) - self.center)
        depth = -d[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            m = np.where(depth > 0, self.b / np.where(depth > 0, depth, 1.0), np.nan)
        return np.stack([m * d[..., 0], m * d[..., 1]], axis=-1)

    def project(self, points: ArrayLike) -> Array:
        """World points -> continuous pixel coordinates (x_px, y_px); NaN behind the camera."""
        return self.sensor_to_pixel(self.distort(self.project_ideal(points)))

    def rays_from_sensor(self, uv_ideal: ArrayLike) -> tuple[Array, Array]:
        """Pinhole chief rays through ideal sensor points: origin r_c, unit direction ``(r_s - r_c)/|r_s - r_c|``."""
        d = self._directions(uv_ideal)
        return np.broadcast_to(self.center, d.shape).copy(), d

    def _directions(self, uv_ideal: ArrayLike) -> Array:
        """The unit directions of :meth:`rays_from_sensor`."""
        q = np.asarray(uv_ideal, dtype=np.float64)
        f = self.frame
        return normalize(-self.b * f.nz + q[..., :1] * f.tx + q[..., 1:2] * f.ty)

    def rays(self, px: ArrayLike) -> tuple[Array, Array]:
        """Pinhole rays (origin, unit direction) through continuous pixel coordinates."""
        return self.rays_from_sensor(self.undistort(self.pixel_to_sensor(px)))

    def ray_directions(self, px: ArrayLike) -> Array:
        """The unit directions of :meth:`rays` alone (their origin is the centre r_c)."""
        return self._directions(self.undistort(self.pixel_to_sensor(px)))

    def focus_distance(self) -> float | None:
        """Distance of the plane in focus (thin lens), mm; None for a pinhole."""
        if self.lens is None:
            return None
        if self.lens.focus_distance is not None:
            return self.lens.focus_distance
        f = self.lens.focal_length
        if not self.b > f:
            raise GeometryError(f"image distance b = {self.b} mm must exceed the focal length {f} mm")
        return self.b * f / (self.b - f)

    def lens_rays(self, px: ArrayLike, lens_uv: ArrayLike) -> tuple[Array, Array]:
        """Thin-lens rays: from a point of the aperture toward the in-focus point of the chief ray.

        Parameters
        ----------
        px : array_like, (..., 2)
            Continuous pixel coordinates.
        lens_uv : array_like, (..., 2)
            Points on the unit disk (e.g. from :func:`concentric_disk`), scaled by the aperture radius.
        """
        o, d = self.rays(px)
        if self.lens is None:
            return o, d
        g = self.focus_distance()
        assert g is not None  # a thin lens has a plane in focus
        f = self.frame
        depth = -(d @ f.nz)
        focus = o + (g / depth)[..., None] * d
        lu = np.asarray(lens_uv, dtype=np.float64) * self.lens.aperture_radius
        start = self.center + lu[..., :1] * f.tx + lu[..., 1:2] * f.ty
        return start, normalize(focus - start)

    def in_image(self, px: ArrayLike, margin: float = 0.0) -> NDArray[np.bool_]:
        """True where continuous pixel coordinates lie inside the image (shrunk by ``margin`` px)."""
        return self.grid.contains(px, margin)

    def as_dict(
        self,
        *,
        pose: tuple[ArrayLike, float, float] | None = None,
        focus: bool = False,
        grid: bool = True,
    ) -> dict[str, Any]:
        """JSON-ready camera parameters with the contract's keys (docs/contract.md, `calibrate`): the one camera writer.

        Always the frame and image distance (``r_c``, ``t_x``, ``t_y``, ``n_z``, ``b``), then, with ``pose`` =
        (r_0, phi, g), the optimisation parameters of §2.5.2 (``g``, ``r_0`` as its x, y, ``phi``), the
        principal-point offset and distortion (``r_cs``, ``c0``, ``c2``), with ``focus`` the thin lens's
        ``focus_distance`` (None for a pinhole), and with ``grid`` the rest of the pixel grid
        (:meth:`PixelGrid.as_dict`: ``nx``, ``ny``, ``pitch``).
        """
        f = self.frame
        cells = self.grid.as_dict()
        out: dict[str, Any] = {
            "r_c": f.origin.tolist(),
            "t_x": f.tx.tolist(),
            "t_y": f.ty.tolist(),
            "n_z": f.nz.tolist(),
            "b": self.b,
        }
        if pose is not None:
            r0, phi, g = pose
            out |= {"g": float(g), "r_0": [float(v) for v in np.asarray(r0)[:2]], "phi": float(phi)}
        out |= {"r_cs": cells["r_cs"], "c0": self.c0, "c2": self.c2}
        if focus:
            out["focus_distance"] = self.focus_distance()
        if grid:
            out |= {"nx": cells["nx"], "ny": cells["ny"], "pitch": cells["pitch"]}
        return out


def pose_axes(r_c: ArrayLike, r_0: ArrayLike, phi: float) -> tuple[Array, Array, Array, float]:
    """N_z, T_x, T_y and g from (r_c, r_0, phi), thesis §2.5.2.

    Raises :class:`GeometryError` when N_z is parallel to e_y (T_0x undefined).
    """
    rc = np.asarray(r_c, dtype=np.float64)
    r0 = np.asarray(r_0, dtype=np.float64)
    diff = rc - r0
    g = float(np.linalg.norm(diff))
    if g == 0:
        raise GeometryError("camera centre r_c coincides with the axis point r_0")
    nz = diff / g
    t0x = np.cross([0.0, 1.0, 0.0], nz)
    n0 = np.linalg.norm(t0x)
    if n0 < 1e-12:
        raise GeometryError("optical axis is parallel to e_y: T_0x = e_y x N_z is undefined (thesis §2.5.2)")
    t0x /= n0
    t0y = np.cross(nz, t0x)
    tx = np.cos(phi) * t0x + np.sin(phi) * t0y
    ty = np.cos(phi) * t0y - np.sin(phi) * t0x
    return nz, tx, ty, g


def pose_parameters(camera: Camera, plane: Frame | None = None) -> tuple[Array, Array, float]:
    """Inverse of :meth:`Camera.from_pose`: (r_c, r_0, phi) of a camera (thesis §2.5.1).

    r_0 is where the optical axis meets the plane (default: z = 0), phi the sensor tilt
    measured from T_0x = e_y x N_z toward T_0y.
    """
    from scopetwin.scenes.geometry import intersect_plane

    plane = plane or Frame.identity()
    f = camera.frame
    lam = intersect_plane(f.origin, -f.nz, plane)
    r0 = f.origin - lam * f.nz
    t0x = normalize(np.cross([0.0, 1.0, 0.0], f.nz))
    t0y = np.cross(f.nz, t0x)
    phi = float(np.arctan2(f.tx @ t0y, f.tx @ t0x))
    return f.origin.copy(), r0, phi


def concentric_disk(samples: ArrayLike) -> Array:
    """Shirley's concentric map of [0,1)^2 samples to the unit disk (area preserving)."""
    s = 2.0 * np.asarray(samples, dtype=np.float64) - 1.0
    a, b = s[..., 0], s[..., 1]
    use_a = np.abs(a) > np.abs(b)
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where(use_a, a, b)
        theta = np.where(
            use_a, (np.pi / 4) * (b / np.where(a == 0, 1, a)), np.pi / 2 - (np.pi / 4) * (a / np.where(b == 0, 1, b))
        )
    zero = (a == 0) & (b == 0)
    r = np.where(zero, 0.0, r)
    return np.stack([r * np.cos(theta), r * np.sin(theta)], axis=-1)
