"""Normals from rays (thesis §1.7.1) and gradients (§1.7.2-1.7.3): recovered from constructed reflections."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.recon.gradients import (
    GradientError,
    gradients_from_normals,
    marker_gradients,
    normals_from_gradients,
    normals_from_rays,
)
from scopetwin.scenes.geometry import Frame, normalize, reflect


def _scene(rng: np.random.Generator, n: int = 200):
    hx, hy = rng.normal(0, 0.05, n), rng.normal(0, 0.05, n)
    normal = normals_from_gradients(hx, hy)
    hit = np.column_stack([rng.uniform(-10, 10, n), rng.uniform(-20, 20, n), rng.normal(0, 0.02, n)])
    cam = np.array([0.0, -200.0, 120.0])
    s_c = normalize(hit - cam)
    s_p = reflect(s_c, normal)
    pattern = hit + rng.uniform(50, 120, n)[:, None] * s_p
    return hx, hy, normal, hit, s_c, pattern


def test_normals_from_rays_recover_the_reflecting_normal(rng: np.random.Generator) -> None:
    hx, hy, normal, hit, s_c, pattern = _scene(rng)
    got = normals_from_rays(hit, s_c * 3.0, pattern)  # camera direction need not be unit
    assert np.max(np.abs(got - normal)) < 1e-12


def test_gradients_round_trip_and_eq_1_2(rng: np.random.Generator) -> None:
    hx, hy, normal, hit, s_c, pattern = _scene(rng)
    gx, gy = gradients_from_normals(normals_from_rays(hit, s_c, pattern))
    assert np.max(np.abs(gx - hx)) < 1e-12 and np.max(np.abs(gy - hy)) < 1e-12


def test_gradients_in_a_rotated_base_frame(rng: np.random.Generator) -> None:
    a = 0.3
    frame = Frame(
        np.array([1.0, 2.0, 3.0]),
        np.array([np.cos(a), np.sin(a), 0.0]),
        np.array([-np.sin(a), np.cos(a), 0.0]),
        np.array([0.0, 0.0, 1.0]),
    )
    hx, hy = rng.normal(0, 0.01, 50), rng.normal(0, 0.01, 50)
    n_global = normals_from_gradients(hx, hy, frame)
    gx, gy = gradients_from_normals(n_global, frame)
    assert np.allclose(gx, hx, atol=1e-13) and np.allclose(gy, hy, atol=1e-13)
    hits = frame.to_global(np.column_stack([rng.uniform(-5, 5, 50), rng.uniform(-5, 5, 50), np.zeros(50)]))
    s_c = normalize(hits - np.array([0.0, -200.0, 120.0]))
    pattern = hits + 80.0 * reflect(s_c, n_global)
    xy, gx2, gy2 = marker_gradients(hits, s_c, pattern, frame)
    assert np.allclose(xy, frame.to_local(hits)[:, :2]) and np.allclose(gx2, hx, atol=1e-12)


def test_degenerate_geometry_is_an_error() -> None:
    with pytest.raises(GradientError, match="coincides"):
        normals_from_rays(np.zeros((1, 3)), np.array([[0.0, 0.0, -1.0]]), np.zeros((1, 3)))
    with pytest.raises(GradientError, match="grazing"):
        normals_from_rays(np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0]]), np.array([[5.0, 0.0, 0.0]]))
    with pytest.raises(GradientError, match="N_z"):
        gradients_from_normals(np.array([[1.0, 0.0, 0.0]]))
