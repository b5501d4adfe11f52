"""Substrate model (thesis §1.6.4): exact bicubic heights/gradients and the secant intersection."""

import numpy as np
import pytest

from scopetwin.scenes.errors import GeometryError
from scopetwin.scenes.geometry import normalize
from scopetwin.scenes.surface import HeightMap, Substrate


def _cubic(x, y):
    return 1e-4 * (x**3 - 2 * x * y**2 + 0.5 * y**3) + 2e-3 * x * y - 0.01


def _cubic_grad(x, y):
    return 1e-4 * (3 * x**2 - 2 * y**2) + 2e-3 * y, 1e-4 * (-4 * x * y + 1.5 * y**2) + 2e-3 * x


def test_bicubic_spline_reproduces_cubic_surfaces_exactly(rng):
    hm = HeightMap.from_function(_cubic, -12.6, 12.6, -28.5, 28.5, nx=16, ny=24)
    x = rng.uniform(-12.6, 12.6, 200)
    y = rng.uniform(-28.5, 28.5, 200)
    np.testing.assert_allclose(hm.height(x, y), _cubic(x, y), atol=1e-13)
    gx, gy = hm.gradient(x, y)
    ex, ey = _cubic_grad(x, y)
    np.testing.assert_allclose(gx, ex, atol=1e-13)
    np.testing.assert_allclose(gy, ey, atol=1e-13)
    n = hm.normals(x, y)
    np.testing.assert_allclose(n, normalize(np.stack([-ex, -ey, np.ones_like(x)], -1)), atol=1e-13)


def test_secant_intersection_lands_on_the_surface(rng):
    hm = HeightMap.from_function(lambda x, y: -2e-5 * (x**2 + y**2), -12.6, 12.6, -28.5, 28.5, 64, 128)
    sub = Substrate(hm)
    o = np.tile([0.0, -200.0, 120.0], (300, 1))
    target = np.stack([rng.uniform(-12, 12, 300), rng.uniform(-23, 23, 300), np.zeros(300)], -1)
    d = normalize(target - o)
    lam, ok = sub.intersect(o, d)
    assert ok.all()
    p = o + lam[:, None] * d
    np.testing.assert_allclose(p[:, 2], hm.height(p[:, 0], p[:, 1]), atol=1e-10)


def test_frame_regions_and_roi():
    sub = Substrate(HeightMap(np.zeros((8, 8)), -12.6, 12.6, -28.5, 28.5), roi_length=48.0)
    y = np.array([-28.0, -24.0, -23.9, 0.0, 23.9, 24.0, 28.0, 29.0])
    r1, r2 = sub.frame_regions(np.zeros_like(y), y)
    np.testing.assert_array_equal(r1, [1, 1, 0, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(r2, [0, 0, 0, 0, 0, 1, 1, 0])
    np.testing.assert_array_equal(sub.in_roi(np.zeros_like(y), y), [0, 0, 1, 1, 1, 0, 0, 0])


@pytest.mark.parametrize(
    ("z", "ext", "message"),
    [
        (np.zeros((3, 8)), (-1, 1, -1, 1), "at least 4x4"),
        (np.full((8, 8), np.nan), (-1, 1, -1, 1), "NaN"),
        (np.zeros((8, 8)), (1, -1, -1, 1), "increasing"),
    ],
)
def test_bad_height_maps_raise(z, ext, message):
    with pytest.raises(GeometryError, match=message):
        HeightMap(z, *ext)
