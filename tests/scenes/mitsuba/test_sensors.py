"""The Mitsuba sensor plugin generates the rays of scenes.camera to float32 precision (thesis §1.6.2, §2.5)."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.scenes.camera import ThinLens, concentric_disk
from scopetwin.scenes.setup import load_setup

pytestmark = pytest.mark.mitsuba

N_RAYS = 4000
#: float32 rounding of unit directions is ~6e-8; 3e-7 rad is 0.002 px at b = 28 mm, 4.65 µm pixels.
DIR_TOL = 3e-7


def _sensor(variant, camera, spp=4, window=None):
    from scopetwin.scenes.mitsuba.sensors import sensor_dict
    from scopetwin.scenes.mitsuba.variant import mitsuba

    mi = mitsuba(variant)
    return mi, mi.load_dict(sensor_dict(camera, spp, 0, window, variant))


def _sample(mi, sensor, film_xy, aperture=None):
    ap = np.full_like(film_xy, 0.5) if aperture is None else aperture
    ray, weight = sensor.sample_ray(0.0, 0.5, mi.Point2f(film_xy[:, 0], film_xy[:, 1]), mi.Point2f(ap[:, 0], ap[:, 1]))
    return np.array(ray.o, dtype=np.float64).T, np.array(ray.d, dtype=np.float64).T, np.array(weight)


def _cameras():
    base = load_setup("thesis-1.10-deflectometry").camera_model
    return {
        "pinhole": load_setup("thesis-2.8.1-perpendicular").camera_model,
        "angular": base,
        "offset": base.with_(r_cs=(0.0465, -0.031)),
        "distortion": load_setup("thesis-2.8.5-distortion").camera_model,
        "strong-distortion": base.with_(r_cs=(-0.02, 0.05), c0=1.002, c2=-0.004),
    }


@pytest.mark.parametrize("name", list(_cameras()))
def test_pinhole_rays_equal_camera_rays(name, rng, mono_variant):
    cam = _cameras()[name]
    mi, sensor = _sensor(mono_variant, cam)
    px = rng.uniform([0, 0], [cam.nx, cam.ny], size=(N_RAYS, 2))
    o, d, w = _sample(mi, sensor, px / [cam.nx, cam.ny])
    o_ref, d_ref = cam.rays(px)
    assert np.abs(o - o_ref).max() <= 1e-6 * (1 + np.abs(cam.center).max())
    assert np.abs(d - d_ref).max() <= DIR_TOL
    np.testing.assert_allclose(w, 1.0)
    # the same in pixels: where a point far along the Mitsuba ray projects
    back = cam.project(o + 200.0 * d)
    assert np.abs(back - px).max() < 2e-3


def test_crop_window_maps_to_full_image_pixels(rng, mono_variant):
    cam = _cameras()["distortion"]
    window = (100, 164, 900, 1000)  # rows 100..163, cols 900..999
    mi, sensor = _sensor(mono_variant, cam, window=window)
    r0, r1, c0, c1 = window
    px = rng.uniform([c0, r0], [c1, r1], size=(N_RAYS, 2))
    film_xy = (px - [c0, r0]) / [c1 - c0, r1 - r0]
    _, d, _ = _sample(mi, sensor, film_xy)
    assert np.abs(d - cam.rays(px)[1]).max() <= DIR_TOL


def test_thin_lens_rays_equal_camera_lens_rays(rng, mono_variant):
    cam = _cameras()["offset"].with_(lens=ThinLens(25.0, 2.8, 230.0), c2=0.00123)
    mi, sensor = _sensor(mono_variant, cam)
    px = rng.uniform([0, 0], [cam.nx, cam.ny], size=(N_RAYS, 2))
    ap = rng.random((N_RAYS, 2))
    o, d, _ = _sample(mi, sensor, px / [cam.nx, cam.ny], ap)
    o_ref, d_ref = cam.lens_rays(px, concentric_disk(ap))
    assert np.abs(o - o_ref).max() <= 2e-5  # float32 of |r_c| ~ 233 mm
    assert np.abs(d - d_ref).max() <= DIR_TOL
    # all rays of a pixel meet on the plane in focus, at the chief ray's point
    spread = np.linalg.norm(o - cam.center, axis=1)
    assert spread.max() <= cam.lens.aperture_radius * (1 + 1e-6)
    assert spread.max() > 0.9 * cam.lens.aperture_radius


def test_to_world_convention_matches_mitsuba_perspective(rng, mono_variant):
    """Without offset and distortion the plugin and Mitsuba's own perspective sensor agree."""
    from scopetwin.scenes.mitsuba.sensors import camera_to_world, film_dict

    cam = _cameras()["angular"]
    mi, sensor = _sensor(mono_variant, cam)
    fov = np.degrees(2 * np.arctan(cam.nx * cam.pitch / 2 / cam.b))
    persp = mi.load_dict(
        {
            "type": "perspective",
            "fov": fov,
            "fov_axis": "x",
            "to_world": mi.ScalarTransform4f(camera_to_world(cam)),
            "film": film_dict(cam),
        }
    )
    film_xy = rng.random((N_RAYS, 2))
    _, d, _ = _sample(mi, sensor, film_xy)
    _, d_p, _ = _sample(mi, persp, film_xy)
    assert np.abs(d - d_p).max() <= 1e-6
