"""The camera model (thesis §1.6.2, §2.5.1-2.5.2): round trips and known geometry."""

import numpy as np
import pytest

from scopetwin.scenes.camera import Camera, ThinLens, concentric_disk, pose_parameters
from scopetwin.scenes.errors import GeometryError
from scopetwin.scenes.setup import load_setup, preset_names


def _cameras():
    cams = [load_setup(n).camera_model for n in preset_names() if n.startswith("thesis-1") or n.startswith("thesis-2")]
    base = cams[0]
    cams.append(base.with_(r_cs=(0.0465, -0.031), c0=1.002, c2=0.00123))
    cams.append(base.with_(c2=-0.004))
    return cams


@pytest.mark.parametrize("cam", _cameras())
def test_project_pixel_ray_round_trip_1e9_mm(cam, rng):
    px = rng.uniform([0, 0], [cam.nx, cam.ny], size=(500, 2))
    o, d = cam.rays(px)
    depth = rng.uniform(50, 400, size=500)
    world = o + depth[:, None] * d
    np.testing.assert_allclose(cam.project(world), px, atol=1e-9)
    back_o, back_d = cam.rays(cam.project(world))
    v = world - back_o
    dist = np.linalg.norm(v - np.sum(v * back_d, axis=1, keepdims=True) * back_d, axis=1)
    assert dist.max() < 1e-9


def test_distortion_inverse_to_1e12(rng):
    cam = _cameras()[0].with_(c0=0.998, c2=0.00123)
    uv = rng.uniform(-4, 4, size=(1000, 2))
    np.testing.assert_allclose(cam.undistort(cam.distort(uv)), uv, atol=1e-12, rtol=0)
    np.testing.assert_allclose(cam.distort(cam.undistort(uv)), uv, atol=1e-12, rtol=0)


def test_pixel_convention_matches_design():
    cam = load_setup("thesis-1.10-deflectometry").camera_model.with_(r_cs=(0.01, 0.02))
    # pixel (row 0, col 0) centre: u = (0.5 - nx/2)*pitch + x_cs, v = (ny/2 - 0.5)*pitch + y_cs
    uv = cam.pixel_to_sensor(np.array([0.5, 0.5]))
    np.testing.assert_allclose(uv, [(0.5 - 680) * 0.00465 + 0.01, (512 - 0.5) * 0.00465 + 0.02], atol=1e-15)
    # column grows along T_x, row grows against T_y (upright image)
    p = cam.project(np.array([[1.0, 0, 0], [0, 0, 0], [0, 1.0, 0.5]]))
    assert p[0, 0] > p[1, 0] and p[2, 1] < p[1, 1]


def test_pose_parameters_round_trip_and_thin_lens_equation():
    cam = Camera.from_pose([194.567, -0.140, 112.961], [4.498, -2.225], 3.144, 25.0, 1360, 1024, 0.00465)
    rc, r0, phi = pose_parameters(cam)
    np.testing.assert_allclose(rc, [194.567, -0.140, 112.961])
    np.testing.assert_allclose(r0[:2], [4.498, -2.225], atol=1e-12)
    assert abs(np.angle(np.exp(1j * (phi - 3.144)))) < 1e-12
    g = np.linalg.norm(rc - r0)
    assert cam.b == pytest.approx(g * 25.0 / (g - 25.0), rel=1e-14)
    # the optical axis hits r_0: the axis foot projects to the grid centre (r_cs = 0)
    np.testing.assert_allclose(cam.project(r0[None]), [[680.0, 512.0]], atol=1e-9)


def test_thin_lens_rays_meet_in_the_focus_plane(rng):
    base = load_setup("thesis-1.10-deflectometry").camera_model
    cam = base.with_(lens=ThinLens(25.0, 4.0))
    g = cam.focus_distance()
    assert g == pytest.approx(28 * 25 / 3)
    px = np.repeat(rng.uniform([0, 0], [1360, 1024], size=(1, 2)), 64, axis=0)
    o, d = cam.lens_rays(px, concentric_disk(rng.random((64, 2))))
    assert np.ptp(o, axis=0).max() > 1.0  # rays start across the 6.25 mm aperture
    t = (g + (cam.center - o) @ (-cam.frame.nz)) / (d @ -cam.frame.nz)
    hits = o + t[:, None] * d
    assert np.ptp(hits, axis=0).max() < 1e-9


def test_bad_camera_parameters_raise():
    base = load_setup("thesis-1.10-deflectometry").camera_model
    for field, value in (("b", -1.0), ("pitch", 0.0), ("nx", 0), ("c0", 0.0)):
        with pytest.raises(GeometryError, match=field if field != "nx" else "pixel counts"):
            base.with_(**{field: value})
