"""Frames and ray optics (thesis §1.6.1, §1.6.5) against hand-computed truth."""

import numpy as np
import pytest

from scopetwin.scenes.errors import GeometryError
from scopetwin.scenes.geometry import Frame, intersect_plane, normalize, reflect, refract, row_norms


def test_thesis_four_digit_axes_become_exactly_orthonormal():
    f = Frame([0, -200, 120], [1, 0, 0], [0, 0.5145, 0.8575], [0, -0.8575, 0.5145])
    m = f.rotation
    np.testing.assert_allclose(m @ m.T, np.eye(3), atol=1e-15)
    np.testing.assert_allclose(np.cross(f.tx, f.ty), f.nz, atol=1e-15)
    np.testing.assert_allclose(f.nz, [0, -0.8575, 0.5145], atol=2e-5)


@pytest.mark.parametrize(
    ("tx", "ty", "nz", "message"),
    [
        ([1.1, 0, 0], [0, 1, 0], [0, 0, 1], "not a unit vector"),
        ([1, 0, 0], [0.1, 0.995, 0], [0, 0, 1], "not orthogonal"),
        ([1, 0, 0], [0, 1, 0], [0, 0, -1], "left-handed"),
        ([1, 0, 0], [0, 1, 0], [0, 0], "3-vector"),
    ],
)
def test_invalid_frames_name_the_problem(tx, ty, nz, message):
    with pytest.raises(GeometryError, match=message):
        Frame([0, 0, 0], tx, ty, nz)


def test_local_global_round_trip(rng):
    axes = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    f = Frame(rng.normal(size=3) * 100, axes[:, 0], axes[:, 1], axes[:, 2])
    p = rng.normal(size=(50, 3)) * 50
    np.testing.assert_allclose(f.to_global(f.to_local(p)), p, atol=1e-12)
    local = f.to_local(f.origin + 2.0 * f.tx - 3.0 * f.nz)
    np.testing.assert_allclose(local, [2.0, 0.0, -3.0], atol=1e-12)


def test_mirrored_frame_is_right_handed_and_mirrors_points():
    f = Frame([0, 80, 48], [1, 0, 0], [0, -0.5145, 0.8575], [0, -0.8575, -0.5145])
    m = f.mirrored_z()
    np.testing.assert_allclose(np.cross(m.tx, m.ty), m.nz, atol=1e-15)
    np.testing.assert_allclose(m.origin, [0, 80, -48])
    np.testing.assert_allclose(m.nz, f.nz * [1, 1, -1], atol=1e-15)


def test_plane_intersection_and_reflection():
    plane = Frame.identity()
    o = np.array([[0.0, -200.0, 120.0]])
    d = normalize(np.array([[0.0, 200.0, -120.0]]))
    lam = intersect_plane(o, d, plane)
    np.testing.assert_allclose(o + lam[:, None] * d, [[0, 0, 0]], atol=1e-12)
    r = reflect(d, np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(r, d * [1, 1, -1], atol=1e-15)
    assert np.isinf(intersect_plane(o, np.array([[1.0, 0, 0]]), plane))[0]


def test_refraction_obeys_snell_and_total_internal_reflection(rng):
    n = np.array([0.0, 0.0, 1.0])
    theta = rng.uniform(0, 1.2, 20)
    d = np.stack([np.sin(theta), np.zeros_like(theta), -np.cos(theta)], axis=-1)
    t, tir = refract(d, n, 1.0, 1.5)
    assert not tir.any()
    sin_t = np.hypot(t[:, 0], t[:, 1])
    np.testing.assert_allclose(1.0 * np.sin(theta), 1.5 * sin_t, atol=1e-14)
    _, tir2 = refract(np.array([[np.sin(1.0), 0, -np.cos(1.0)]]), n, 1.5, 1.0)
    assert tir2.all()


@pytest.mark.parametrize("shape", [(1000, 2), (1000, 3), (40, 50, 3), (200, 7), (200, 9), (5, 1)])
def test_row_norms_are_numpys_to_the_bit(shape):
    """row_norms replaces np.linalg.norm(axis=-1) on the hot paths (camera distortion, unit rays): same bits, so that
    no result anywhere moves at rounding level."""
    rng = np.random.default_rng(sum(shape))
    v = rng.standard_normal(shape) * rng.uniform(1e-6, 1e6, size=shape[:-1] + (1,))
    assert np.array_equal(row_norms(v), np.linalg.norm(v, axis=-1))
    assert np.array_equal(row_norms(v, keepdims=True), np.linalg.norm(v, axis=-1, keepdims=True))
    assert np.array_equal(normalize(v), v / np.linalg.norm(v, axis=-1, keepdims=True))
