"""Widefield fluorescence tile of a bent substrate, seen through a thin-lens objective (thesis §4.1.2, §6).

The microscope unit images a fluorescent sample lying on a bent glass
substrate through a 10x / NA 0.45 objective onto 6.45 µm camera pixels
(thesis §4.1.2, §4.1.4), so one pixel sees 0.645 µm of the object and the depth
of field is a few micrometres: a substrate that bows by tens of micrometres
is sharp only where the focus follows it, which is what the thesis's focus map
(§1, §6) is for. This module renders one camera frame of that situation:

* the sample is an emitting heightfield patch (Mitsuba ``area`` emitter with a
  bitmap radiance) whose heights come from a known height function
  ``height_mm(x, y)`` and whose radiance is a fixed fluorescent texture of the
  sample coordinates (a band-limited random field of ~1 µm features);
* the camera is Mitsuba's ``thinlens`` sensor in object space: field of view
  ``pixels * pixel_pitch / magnification``, aperture radius ``d * tan(asin(NA))``
  at distance ``d`` (the working distance) above the plane in focus, so a
  defocus ``dz`` blurs a point into a disc of radius ``dz * tan(asin(NA))``;
* the stage position ``(x, y)`` is the sample point on the optical axis, and the
  focus drive position ``focus_um`` puts the plane in focus at
  ``z = (focus_um - focus_ref_um) * 1e-3`` mm.

Geometric optics only (no diffraction): a 10x/0.45 objective's Airy radius
(~0.7 µm at 520 nm) is about one object-side pixel, so the blur of any
defocus beyond ~1.5 µm is dominated by the geometric disc modelled here.
The objective's numbers and formulas are those of :class:`scopetwin.scenes.objective.Objective`
(the model the focus map uses too); the frame's pixel grid is a :class:`scopetwin.scenes.camera.PixelGrid`
in the object plane.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from scopetwin.scenes.camera import PixelGrid
from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.mitsuba.variant import mitsuba, render_complete, resolve
from scopetwin.scenes.objective import Objective

HeightFunction = Callable[[NDArray[np.float64], NDArray[np.float64]], NDArray[np.float64]]


@dataclass(frozen=True)
class BentSubstrate:
    """A bent substrate's height h(x, y) in mm: tilt + bow + saddle around ``center``.

    ``h = tilt_x*x' + tilt_y*y' + bow_mm*(x'^2 + y'^2)/radius^2 + saddle_mm*(x'^2 - y'^2)/radius^2``
    with ``(x', y') = (x, y) - center`` (all mm).
    """

    bow_mm: float = 0.03
    saddle_mm: float = 0.0
    tilt_x: float = 0.0
    tilt_y: float = 0.0
    radius_mm: float = 1.5
    center_mm: tuple[float, float] = (0.0, 0.0)

    def __call__(self, x: NDArray[np.float64], y: NDArray[np.float64]) -> NDArray[np.float64]:
        """Heights (mm) at sample coordinates (mm), vectorised."""
        xp = np.asarray(x, dtype=np.float64) - self.center_mm[0]
        yp = np.asarray(y, dtype=np.float64) - self.center_mm[1]
        r2 = self.radius_mm**2
        return (
            self.tilt_x * xp
            + self.tilt_y * yp
            + self.bow_mm * (xp**2 + yp**2) / r2
            + self.saddle_mm * (xp**2 - yp**2) / r2
        )


@dataclass(frozen=True)
class WidefieldOptics:
    """Objective, camera and sample texture of the widefield tile (thesis §4.1.2, §4.1.4 numbers).

    Attributes
    ----------
    magnification : float
        Lateral magnification (10).
    na : float
        Object-side numerical aperture (0.45).
    working_distance_mm : float
        Distance of the thin lens above the plane in focus (2 mm).
    pixel_pitch_mm : float
        Camera pixel pitch (0.00645 mm).
    pixels : tuple of int
        Frame size ``(cols, rows)``; keep it small (e.g. 256 x 256) for speed.
    focus_ref_um : float
        Focus-drive position that puts the plane in focus at z = 0.
    feature_um : float
        Correlation length of the fluorescent texture, µm.
    texture_period_mm : float
        The texture repeats with this period (it is a periodic random field).
    texture_seed : int
        Seed of the texture.
    max_defocus_mm : float
        Largest defocus the patch margin is sized for (blur disc radius ``max_defocus*tan(asin NA)``).
    mesh_step_mm : float
        Vertex spacing of the heightfield patch.
    spp : int
        Samples per pixel.
    """

    magnification: float = Objective.magnification
    na: float = Objective.na
    working_distance_mm: float = 2.0
    pixel_pitch_mm: float = Objective.pixel_pitch_um * 1e-3
    pixels: tuple[int, int] = (256, 256)
    focus_ref_um: float = 200.0
    feature_um: float = 1.0
    texture_period_mm: float = 1.024
    texture_seed: int = 7
    max_defocus_mm: float = 0.08
    mesh_step_mm: float = 0.01
    spp: int = 16
    extra: dict[str, Any] = field(default_factory=dict, compare=False)

    def __post_init__(self) -> None:
        if not (0 < self.na < 1) or self.magnification <= 0 or self.working_distance_mm <= 0:
            raise SetupError("widefield optics need 0 < na < 1, magnification > 0, working distance > 0")
        if min(self.pixels) < 8 or self.pixel_pitch_mm <= 0 or self.spp < 1:
            raise SetupError("widefield frame needs at least 8x8 pixels, pixel pitch > 0 and spp >= 1")

    @property
    def objective(self) -> Objective:
        """The objective model (:class:`scopetwin.scenes.objective.Objective`) of these optics."""
        return Objective(
            magnification=self.magnification,
            na=self.na,
            pixel_pitch_um=self.pixel_pitch_mm * 1e3,
            sensor_px=(int(self.pixels[0]), int(self.pixels[1])),
        )

    @property
    def object_pixel_mm(self) -> float:
        """Pixel size in the object plane, mm (the pitch e / M in mm, as given)."""
        return self.pixel_pitch_mm / self.magnification

    @property
    def object_grid(self) -> PixelGrid:
        """The frame's pixel grid in the object plane (pitch :attr:`object_pixel_mm`, centred on the axis)."""
        return PixelGrid(int(self.pixels[0]), int(self.pixels[1]), self.object_pixel_mm)

    @property
    def field_mm(self) -> tuple[float, float]:
        """Field of view ``(x, y)`` in the object plane, mm."""
        grid = self.object_grid
        return grid.width_mm, grid.height_mm

    @property
    def aperture_radius_mm(self) -> float:
        """Thin-lens aperture radius giving the numerical aperture at the working distance."""
        return self.objective.aperture_radius_mm(self.working_distance_mm)

    def blur_radius_mm(self, defocus_mm: float) -> float:
        """Radius of the geometric blur disc of a point ``defocus_mm`` away from the plane in focus."""
        return self.objective.blur_radius_mm(defocus_mm)

    def focal_plane_z_mm(self, focus_um: float) -> float:
        """Height of the plane in focus for a focus-drive position (µm)."""
        return (float(focus_um) - self.focus_ref_um) * 1e-3


@lru_cache(maxsize=4)
def _texture_lattice(seed: int, n: int, sigma_px: float) -> NDArray[np.float32]:
    """A periodic, band-limited random field on an n x n lattice, scaled to [0, 1] contrast."""
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((n, n))
    smooth = ndimage.gaussian_filter(noise, sigma_px, mode="wrap")
    smooth = (smooth - smooth.mean()) / smooth.std()
    # fluorophore-like: bright structures on a dim background
    return (0.15 + 0.85 / (1.0 + np.exp(-2.5 * (smooth - 0.5)))).astype(np.float32)


def sample_texture(
    x_mm: NDArray[np.float64], y_mm: NDArray[np.float64], optics: WidefieldOptics
) -> NDArray[np.float32]:
    """Fluorescent radiance of the sample at sample coordinates (mm); a fixed periodic function."""
    lattice_step = optics.feature_um * 1e-3 / 2.0
    n = int(round(optics.texture_period_mm / lattice_step))
    lattice = _texture_lattice(int(optics.texture_seed), n, 2.0)
    rows = np.asarray(y_mm) / lattice_step
    cols = np.asarray(x_mm) / lattice_step
    return (
        ndimage.map_coordinates(lattice, [rows.ravel(), cols.ravel()], order=1, mode="grid-wrap")
        .reshape(np.shape(x_mm))
        .astype(np.float32)
    )


def patch_half_size_mm(optics: WidefieldOptics) -> float:
    """Half size of the sample patch: half the field plus the largest blur disc plus a margin."""
    return 0.5 * max(optics.field_mm) * math.sqrt(2.0) + optics.blur_radius_mm(optics.max_defocus_mm) + 0.01


def _patch_geometry(
    height_mm: HeightFunction, sx: float, sy: float, half: float, step_mm: float
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Vertices (x, y, h), texture coordinates and triangles of the heightfield patch |x|, |y| <= ``half``.

    Vertex (x, y) is the sample point (sx + x, sy + y); the patch is centred on the optical axis.
    """
    n_vert = max(4, int(math.ceil(2 * half / step_mm)) + 1)
    u = np.linspace(-half, half, n_vert)
    uu, vv = np.meshgrid(u, u)
    zz = np.asarray(height_mm(sx + uu, sy + vv), dtype=np.float64) * np.ones_like(uu)
    if not np.all(np.isfinite(zz)):
        raise SetupError("the sample height function returned non-finite heights")
    positions = np.stack([uu, vv, zz], axis=-1).reshape(-1, 3)
    texcoords = np.stack([(uu + half) / (2 * half), (vv + half) / (2 * half)], axis=-1).reshape(-1, 2)
    col, row = np.meshgrid(np.arange(n_vert - 1), np.arange(n_vert - 1))
    v00 = (row * n_vert + col).ravel()
    faces = np.concatenate(
        [np.stack([v00, v00 + 1, v00 + n_vert + 1], -1), np.stack([v00, v00 + n_vert + 1, v00 + n_vert], -1)]
    )
    return positions, texcoords, faces


def _patch_radiance(
    sx: float, sy: float, half: float, optics: WidefieldOptics, radiance_scale: float
) -> NDArray[np.float32]:
    """The patch's radiance texture: the sample's fluorescence at half an object pixel per texel."""
    texel = optics.object_pixel_mm / 2.0
    n_tex = int(math.ceil(2 * half / texel))
    t = (np.arange(n_tex) + 0.5) / n_tex * 2 * half - half
    tx, ty = np.meshgrid(t, t)
    return sample_texture(sx + tx, sy + ty, optics) * np.float32(radiance_scale)


def _sample_mesh(
    mi: Any,
    positions: NDArray[np.float64],
    texcoords: NDArray[np.float64],
    faces: NDArray[np.int64],
    radiance: NDArray[np.float32],
) -> Any:
    """The sample as a Mitsuba mesh: a black surface emitting the ``radiance`` texture (bilinear, raw)."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "uniform", "value": 0.0}})
    radiance_texture = {
        "type": "bitmap",
        "data": mi.TensorXf(radiance[..., None]),
        "raw": True,
        "filter_type": "bilinear",
        "wrap_mode": "clamp",
    }
    props["emitter"] = mi.load_dict({"type": "area", "radiance": radiance_texture})
    mesh = mi.Mesh("sample", len(positions), len(faces), props=props, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(positions.astype(np.float32).ravel())
    params["vertex_texcoords"] = mi.Float(texcoords.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    params.update()
    return mesh


def _thinlens_sensor(mi: Any, optics: WidefieldOptics, focus_um: float, seed: int) -> dict[str, Any]:
    """The ``thinlens`` sensor dictionary: ``working_distance_mm`` above the plane in focus, looking down."""
    z_focus = optics.focal_plane_z_mm(focus_um)
    d = optics.working_distance_mm
    # columns (-T_x, T_y, -N_z, r_c) with T_x = +x, T_y = +y, N_z = +z: looks down, upright image
    to_world = np.array([[-1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, -1.0, z_focus + d], [0, 0, 0, 1.0]])
    fov = math.degrees(2 * math.atan(0.5 * optics.field_mm[0] / d))
    cols, rows = optics.pixels
    film = {
        "type": "hdrfilm",
        "width": int(cols),
        "height": int(rows),
        "rfilter": {"type": "box"},
        "pixel_format": "luminance",
        "component_format": "float32",
    }
    sampler = {"type": "multijitter", "sample_count": int(optics.spp), "seed": int(seed)}
    return {
        "type": "thinlens",
        "fov": fov,
        "fov_axis": "x",
        "aperture_radius": optics.aperture_radius_mm,
        "focus_distance": d,
        "to_world": mi.ScalarTransform4f(to_world),
        "film": film,
        "sampler": sampler,
    }


def tile_scene_dict(
    height_mm: HeightFunction,
    stage_xy_mm: tuple[float, float],
    focus_um: float,
    optics: WidefieldOptics,
    radiance_scale: float = 1.0,
    seed: int = 0,
    variant: str | None = None,
) -> dict[str, Any]:
    """The Mitsuba scene dictionary of one tile (sample patch around the stage position + thin-lens camera).

    Coordinates are the objective's: the optical axis is the z axis, and the sample
    point ``stage_xy_mm`` lies on it. ``variant``: the Mitsuba variant (default ``choose("mono")``).
    """
    mi = mitsuba(resolve(variant, "mono"))
    sx, sy = (float(v) for v in stage_xy_mm)
    half = patch_half_size_mm(optics)
    positions, texcoords, faces = _patch_geometry(height_mm, sx, sy, half, optics.mesh_step_mm)
    radiance = _patch_radiance(sx, sy, half, optics, radiance_scale)
    mesh = _sample_mesh(mi, positions, texcoords, faces, radiance)
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 1},
        "sensor": _thinlens_sensor(mi, optics, focus_um, seed),
        "sample": mesh,
    }


def render_tile(
    height_mm: HeightFunction,
    stage_xy_mm: tuple[float, float],
    focus_um: float,
    optics: WidefieldOptics | None = None,
    radiance_scale: float = 1.0,
    seed: int = 0,
    variant: str | None = None,
) -> NDArray[np.float32]:
    """Render one widefield frame: linear irradiance, float32 (rows, cols), row 0 = top.

    Parameters
    ----------
    height_mm : callable
        Substrate height h(x, y) in mm at sample coordinates in mm (vectorised).
    stage_xy_mm : (float, float)
        Sample point on the optical axis (the stage position), mm.
    focus_um : float
        Focus-drive position, µm (plane in focus at ``(focus_um - focus_ref_um) * 1e-3`` mm).
    optics : WidefieldOptics
        Objective, frame and texture parameters (default: 10x / 0.45, 256 x 256 px).
    radiance_scale : float
        Multiplies the sample's radiance (excitation light level).
    seed : int
        Sampler seed.
    variant : str, optional
        Mitsuba variant (default ``choose("mono")``, resolved now).
    """
    import drjit as dr

    variant = resolve(variant, "mono")
    optics = optics or WidefieldOptics()
    mi = mitsuba(variant)
    scene = mi.load_dict(tile_scene_dict(height_mm, stage_xy_mm, focus_um, optics, radiance_scale, seed, variant))
    image = np.asarray(render_complete(mi, scene, spp=int(optics.spp), seed=int(seed)), dtype=np.float32)
    dr.sync_thread()
    return np.ascontiguousarray(image[..., 0] if image.ndim == 3 else image)
