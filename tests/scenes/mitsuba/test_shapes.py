"""Heightfield meshes of the substrate: exact vertices and normals, ROI split (thesis §1.6.4, §1.4)."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.scenes.surface import HeightMap

pytestmark = pytest.mark.mitsuba

SIZE = (25.2, 57.0)
ROI = 48.0


def _bow() -> HeightMap:
    """A smooth 40 µm bow with a tilt in x, over the §1.10 substrate."""
    return HeightMap.from_function(
        lambda x, y: -0.032 * ((x / 12.6) ** 2 * 0.25 + (y / 28.5) ** 2) + 0.0004 * x,
        -12.6,
        12.6,
        -28.5,
        28.5,
        nx=64,
        ny=128,
    )


def test_grid_arrays_are_the_surface_with_analytic_normals():
    from scopetwin.scenes.mitsuba.shapes import grid_arrays

    h = _bow()
    pos, nrm, faces = grid_arrays(h, (-12.6, 12.6), (-24.0, 24.0), 33, 61)
    assert pos.shape == (33 * 61, 3) and nrm.shape == pos.shape and faces.shape == (2 * 32 * 60, 3)
    p = pos.astype(np.float64)
    xx, yy = (g.ravel() for g in np.meshgrid(np.linspace(-12.6, 12.6, 33), np.linspace(-24.0, 24.0, 61)))
    np.testing.assert_allclose(p[:, :2], np.stack([xx, yy], axis=-1), atol=2e-6)
    np.testing.assert_allclose(p[:, 2], h.height(xx, yy), atol=1e-8)
    np.testing.assert_allclose(nrm, h.normals(xx, yy), atol=1e-7)
    assert p[:, 1].min() == -24.0 and p[:, 1].max() == 24.0
    # counter-clockwise seen from +z: every geometric normal points up
    a, b, c = (p[faces[:, k]] for k in range(3))
    assert np.all(np.cross(b - a, c - a)[:, 2] > 0)


def test_mesh_hits_and_shading_normals_follow_the_spline(rng, mi_mono, mono_variant):
    from scopetwin.scenes.mitsuba.shapes import substrate_shapes

    mi = mi_mono
    h = _bow()
    shapes = substrate_shapes(h, SIZE, ROI, variant=mono_variant)
    scene = mi.load_dict({"type": "scene", **shapes})
    xy = rng.uniform([-12.5, -28.4], [12.5, 28.4], size=(5000, 2))
    origin = np.concatenate([xy, np.full((len(xy), 1), 10.0)], axis=1)
    ray = mi.Ray3f(mi.Point3f(*origin.T), mi.Vector3f(0.0, 0.0, -1.0))
    si = scene.ray_intersect(ray)
    assert bool(np.all(np.array(si.is_valid())))
    p = np.array(si.p, dtype=np.float64).T
    n = np.array(si.sh_frame.n, dtype=np.float64).T
    # 256 x 512 vertices: piecewise-linear error of the bow is ~h''*dx^2/8 < 0.1 µm
    assert np.abs(p[:, 2] - h.height(xy[:, 0], xy[:, 1])).max() < 1e-4
    # interpolated analytic vertex normals: a few µrad at most
    assert np.abs(n - h.normals(xy[:, 0], xy[:, 1])).max() < 5e-6
    # only the ROI mirrors; the frame regions are black
    in_roi = np.abs(xy[:, 1]) < 0.5 * ROI
    names = {s.id(): s for s in scene.shapes()}
    assert set(names) == {"substrate_roi", "frame_low", "frame_high"}
    delta = {k: mi.has_flag(s.bsdf().flags(), mi.BSDFFlags.DeltaReflection) for k, s in names.items()}
    assert delta == {"substrate_roi": True, "frame_low": False, "frame_high": False}
    roi_hit = np.array(si.shape == mi.ShapePtr(names["substrate_roi"]))
    np.testing.assert_array_equal(roi_hit, in_roi)


def test_no_frame_strips_when_the_roi_is_the_whole_substrate():
    from scopetwin.scenes.mitsuba.shapes import substrate_shapes

    shapes = substrate_shapes(_bow(), SIZE, SIZE[1], vertices=(16, 32))
    assert list(shapes) == ["substrate_roi"]


def test_bad_heights_raise_setup_error():
    from scopetwin.scenes.errors import SetupError
    from scopetwin.scenes.mitsuba.shapes import substrate_shapes

    with pytest.raises(SetupError, match="HeightMap"):
        substrate_shapes(np.zeros((4, 4)), SIZE, ROI)  # type: ignore[arg-type]
