"""The thesis camera as a Mitsuba sensor plugin (thesis §1.6.2, §2.5.1-2.5.2).

The plugin ``scopetwin_camera`` generates exactly the rays of
:class:`scopetwin.scenes.camera.Camera`: a pixel position is mapped to distorted sensor
coordinates (principal-point offset r_cs), undistorted in closed form
(the inverse of r_dist = (c0 + c2*|r|)*r used by :meth:`Camera.undistort`) and
turned into the pinhole ray through ``r_c``; with a thin lens the ray starts on
the aperture and aims at the chief ray's point on the plane in focus
(:meth:`Camera.lens_rays`). All camera parameters, its pose and the film's size and crop window included, are
kept in opaque Dr.Jit variables, so a new camera pose or render window reuses the compiled kernels.

Camera-space convention (the one of Mitsuba's ``perspective`` sensor, docs/rendering.md):
``to_world`` has the columns (-T_x, T_y, -N_z, r_c); the camera looks along local +z.
It is built directly from the float64 frame, never with ``look_at``.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.camera import Camera, PixelGrid
from scopetwin.scenes.mitsuba.variant import mitsuba, register_plugin, resolve

PLUGIN = "scopetwin_camera"


def camera_to_world(camera: Camera) -> NDArray[np.float64]:
    """4x4 camera-to-world matrix with the columns (-T_x, T_y, -N_z, r_c) (float64).

    With this matrix Mitsuba's own ``perspective`` sensor (``fov_axis='x'``) produces the
    thesis's upright image: column grows along T_x, row grows against T_y.
    """
    f = camera.frame
    m = np.eye(4)
    m[:3, 0] = -f.tx
    m[:3, 1] = f.ty
    m[:3, 2] = -f.nz
    m[:3, 3] = f.origin
    return m


def film_dict(camera: Camera, window: tuple[int, int, int, int] | None = None) -> dict[str, Any]:
    """``hdrfilm`` of the camera's pixel grid: box filter (pixel integration), one float32 channel.

    ``window`` = (row0, row1, col0, col1) (half-open) renders only a crop of the image.
    """
    film: dict[str, Any] = {
        "type": "hdrfilm",
        "width": int(camera.nx),
        "height": int(camera.ny),
        "rfilter": {"type": "box"},
        "pixel_format": "luminance",
        "component_format": "float32",
        "sample_border": False,
    }
    if window is not None:
        r0, r1, c0, c1 = (int(w) for w in window)
        film.update(crop_offset_x=c0, crop_offset_y=r0, crop_width=c1 - c0, crop_height=r1 - r0)
    return film


def sensor_dict(
    camera: Camera,
    spp: int,
    seed: int = 0,
    window: tuple[int, int, int, int] | None = None,
    variant: str | None = None,
) -> dict[str, Any]:
    """Scene-dictionary entry of the thesis camera (plugin ``scopetwin_camera``).

    Parameters
    ----------
    camera : Camera
        The camera model (pose, b, pixel grid, r_cs, c0, c2, optional thin lens).
    spp : int
        Samples per pixel of the ``multijitter`` sampler.
    seed : int
        Sampler seed.
    window : (row0, row1, col0, col1), optional
        Crop window (half-open pixel ranges); default the whole image.
    variant : str, optional
        Mitsuba variant (default ``choose("mono")``).
    """
    variant = resolve(variant, "mono")
    mi = mitsuba(variant)
    register(variant)
    lens = camera.lens
    focus = camera.focus_distance()  # None for a pinhole
    return {
        "type": PLUGIN,
        "to_world": mi.ScalarTransform4f(camera_to_world(camera)),
        "image_distance": float(camera.b),
        "pixel_pitch": float(camera.pitch),
        "x_cs": float(camera.r_cs[0]),
        "y_cs": float(camera.r_cs[1]),
        "c0": float(camera.c0),
        "c2": float(camera.c2),
        "aperture_radius": float(lens.aperture_radius) if lens is not None else 0.0,
        "focus_distance": float(focus) if focus is not None else 1.0,
        "film": film_dict(camera, window),
        "sampler": {"type": "multijitter", "sample_count": int(spp), "seed": int(seed)},
    }


def film_grid(mi: Any, film: Any) -> tuple[Any, ...]:
    """A film's size, crop size and crop offset (x, y each) as opaque Floats: a camera with another render window or
    pixel count reuses the compiled kernels."""
    import drjit as dr

    values = (*film.size(), *film.crop_size(), *film.crop_offset())
    return tuple(dr.opaque(mi.Float, float(v)) for v in values)


def opaque_transform(transform: Any) -> Any:
    """An opaque copy of a Mitsuba transform (a sensor's holds literal constants: each camera pose would compile the
    kernels anew)."""
    import drjit as dr

    copy = type(transform)(transform)
    dr.make_opaque(copy)
    return copy


def _make_class(mi: Any) -> type:
    """Define the sensor class for the current variant (Mitsuba classes are per variant)."""
    import drjit as dr

    class ThesisCamera(mi.Sensor):
        """Pinhole / thin-lens camera with principal-point offset and radial distortion (thesis §2.5)."""

        def __init__(self, props: mi.Properties) -> None:
            super().__init__(props)

            def opaque(key: str, default: float) -> Any:
                return dr.opaque(mi.Float, float(props.get(key, default)))

            self.b = opaque("image_distance", 28.0)
            self.pitch = opaque("pixel_pitch", 0.00465)
            self.x_cs = opaque("x_cs", 0.0)
            self.y_cs = opaque("y_cs", 0.0)
            self.c0 = opaque("c0", 1.0)
            self.c2 = opaque("c2", 0.0)
            self.lens_radius = float(props.get("aperture_radius", 0.0))
            self.aperture = dr.opaque(mi.Float, self.lens_radius)
            self.focus = opaque("focus_distance", 1.0)
            self.thin_lens = self.lens_radius > 0.0
            self.m_needs_sample_3 = self.thin_lens

        # -- the mapping of scenes.camera --------------------------------------------------
        def local_ray(self, film_sample: mi.Point2f, aperture_sample: mi.Point2f) -> tuple[Any, Any]:
            """Ray origin and unit direction in camera space for film samples relative to the crop window."""
            nx, ny, crop_x, crop_y, offset_x, offset_y = film_grid(mi, self.film())
            x_px = dr.fma(film_sample.x, crop_x, offset_x)
            y_px = dr.fma(film_sample.y, crop_y, offset_y)
            # the pixel grid's convention (scenes.camera.PixelGrid), on the opaque pitch and r_cs
            u_d, v_d = PixelGrid.map_uv(x_px, y_px, nx, ny, self.pitch, (self.x_cs, self.y_cs))
            s = dr.sqrt(dr.fma(u_d, u_d, v_d * v_d))
            rho = 2.0 * s / (self.c0 + dr.sqrt(dr.fma(4.0 * self.c2, s, self.c0 * self.c0)))
            k = dr.rcp(dr.fma(self.c2, rho, self.c0))
            # camera space: x = -T_x, y = T_y, z = -N_z (the viewing direction)
            chief = mi.Vector3f(-u_d * k, v_d * k, self.b)
            if not self.thin_lens:
                return mi.Point3f(0.0), dr.normalize(chief)
            lens = mi.warp.square_to_uniform_disk_concentric(aperture_sample) * self.aperture
            start = mi.Point3f(-lens.x, lens.y, 0.0)
            focus = chief * (self.focus / self.b)
            return start, dr.normalize(mi.Vector3f(focus - start))

        def _ray(self, time, sample1, sample2, sample3, active):
            o_local, d_local = self.local_ray(sample2, sample3)
            to_world = opaque_transform(self.world_transform())
            o = to_world @ o_local
            d = dr.normalize(to_world @ d_local)
            if mi.is_spectral:
                wavelengths, weight = mi.sample_rgb_spectrum(mi.sample_shifted(sample1))
                return o, d, wavelengths, weight
            return o, d, [], mi.Spectrum(1.0)

        def sample_ray(self, time, sample1, sample2, sample3, active=True):
            o, d, wavelengths, weight = self._ray(time, sample1, sample2, sample3, active)
            return mi.Ray3f(o, d, time, wavelengths), weight

        def sample_ray_differential(self, time, sample1, sample2, sample3, active=True):
            o, d, wavelengths, weight = self._ray(time, sample1, sample2, sample3, active)
            ray = mi.RayDifferential3f(mi.Ray3f(o, d, time, wavelengths))
            ray.has_differentials = False
            return ray, weight

        def bbox(self):
            p = self.world_transform() @ mi.ScalarPoint3f(0.0)
            return mi.ScalarBoundingBox3f(p, p)

        def to_string(self) -> str:
            return f"ThesisCamera[thin_lens={self.thin_lens}, film={self.film()}]"

    return ThesisCamera


def register(variant: str | None = None) -> None:
    """Register ``scopetwin_camera`` for ``variant`` (default ``choose("mono")``) in this thread (idempotent).

    Mitsuba's Python plugin registry is per thread and per variant (docs/rendering.md).
    """
    register_plugin("sensor", PLUGIN, _make_class, resolve(variant, "mono"))
