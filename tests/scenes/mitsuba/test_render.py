"""render_setup / render_window: geometry to 0.002 px, radiometry and determinism (thesis §1.10, §2.8)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from scopetwin.scenes.camera import ThinLens
from scopetwin.scenes.setup import load_setup

pytestmark = pytest.mark.mitsuba


def spot_centroids(image: np.ndarray, window: tuple[int, int, int, int]) -> np.ndarray:
    """Grey-weighted centroids (x_px, y_px) of the spots lying wholly inside a rendered window."""
    labels, n = ndimage.label(image > 0)
    objects = ndimage.find_objects(labels)
    keep = [
        k + 1
        for k, (rs, cs) in enumerate(objects)
        if rs.start > 0 and cs.start > 0 and rs.stop < image.shape[0] and cs.stop < image.shape[1]
    ]
    c = np.array(ndimage.center_of_mass(image.astype(np.float64), labels, keep))
    return c[:, ::-1] + 0.5 + [window[2], window[0]]


def match(found: np.ndarray, expected: np.ndarray) -> np.ndarray:
    """Distance of each found centroid to the nearest expected point, px."""
    d = np.linalg.norm(found[:, None, :] - expected[None, :, :], axis=-1)
    return d.min(axis=1)


def test_perpendicular_target_centroids_are_the_projected_centres():
    """A perpendicular target images round markers as symmetric spots: centroid = projected centre."""
    from scopetwin.scenes.mitsuba.render import render_window

    setup = load_setup("thesis-2.8.1-perpendicular")
    window = (250, 620, 370, 900)  # 3 x 5 markers around the image centre, 103 px apart
    image = render_window(setup, spp=64, seed=2, window=window)
    found = spot_centroids(image, window)
    err = match(found, setup.camera_model.project(setup.marker_pattern.centers()))
    rms = float(np.sqrt(np.mean(err**2)))
    print(f"perpendicular target: {len(err)} spots, RMS {rms:.5f} px, max {err.max():.5f} px")
    assert len(err) >= 12
    assert rms <= 0.002


def test_flat_mirror_reflects_the_pattern_where_the_mirror_image_projects():
    """Pattern seen in the flat mirror z = 0: spots at the projections of the mirrored marker centres."""
    from scopetwin.scenes.mitsuba.render import render_window

    setup = load_setup("thesis-2.8.3-mirror")
    window = (380, 650, 520, 840)
    image = render_window(setup, spp=64, seed=5, window=window)
    found = spot_centroids(image, window)
    mirrored = setup.marker_pattern.centers() * [1.0, 1.0, -1.0]
    err = match(found, setup.camera_model.project(mirrored))
    rms = float(np.sqrt(np.mean(err**2)))
    print(f"flat mirror: {len(err)} spots, RMS {rms:.5f} px, max {err.max():.5f} px")
    assert len(err) >= 12
    assert rms <= 0.002


@pytest.mark.parametrize("name", ["thesis-2.8.1-perpendicular", "thesis-2.8.3-mirror"])
def test_pixel_values_equal_the_analytic_renderer(name):
    """Linear radiometry: a white texel, seen directly or in the mirror, is the pattern radiance."""
    from scopetwin.scenes.analytic import render as analytic_render
    from scopetwin.scenes.mitsuba.render import render_window

    setup = load_setup(name, overrides={"pattern": {"radiance": 2.0}})
    window = (480, 540, 640, 720)
    mine = render_window(setup, spp=64, seed=1, window=window)
    ref = analytic_render(setup, spp=64, seed=1, window=window)
    assert mine.dtype == np.float32 and mine.shape == ref.shape == (60, 80)
    assert ref.max() > 1.5  # the window holds a marker centre
    diff = np.abs(mine.astype(np.float64) - ref)
    print(f"{name}: mean |diff| {diff.mean():.2e}, max {diff.max():.2e}")
    assert diff.mean() < 2e-3
    assert diff.max() < 0.03


def test_holding_frame_regions_are_black_as_in_the_analytic_model():
    """Near the ROI edge y = -24 mm only hits inside the ROI reflect; the frame region renders black."""
    from scopetwin.scenes.analytic import render as analytic_render
    from scopetwin.scenes.mitsuba.render import render_window
    from scopetwin.scenes.surface import HeightMap, Substrate

    setup = load_setup("thesis-1.10-deflectometry")
    heights = HeightMap.from_function(
        lambda x, y: -0.03 * (1 - (y / 28.5) ** 2) + 0.0003 * x, -12.6, 12.6, -28.5, 28.5, nx=32, ny=64
    )
    cam = setup.camera_model
    sub = Substrate(heights, *setup.substrate.size, setup.substrate.roi_length)
    # the image row where camera rays meet y = -24 mm on the base plane
    rows = np.arange(cam.ny) + 0.5
    o, d = cam.rays(np.stack([np.full_like(rows, cam.nx / 2), rows], axis=-1))
    y_hit = o[:, 1] - o[:, 2] / d[:, 2] * d[:, 1]
    edge = int(np.argmin(np.abs(y_hit + 24.0)))
    window = (edge - 16, edge + 16, 560, 800)
    mine = render_window(setup, heights, spp=64, seed=3, window=window)
    ref = analytic_render(setup, heights, spp=64, seed=4, window=window)
    # pixels whose four corners all hit the surface inside / outside the ROI (exact analytic geometry)
    cc, rr = np.meshgrid(np.arange(window[2], window[3] + 1), np.arange(window[0], window[1] + 1))
    o, d = cam.rays(np.stack([cc, rr], axis=-1).reshape(-1, 2).astype(float))
    corner_in = sub.points_and_normals(o, d)[2].reshape(cc.shape)
    inside = corner_in[:-1, :-1] & corner_in[1:, :-1] & corner_in[:-1, 1:] & corner_in[1:, 1:]
    outside = ~(corner_in[:-1, :-1] | corner_in[1:, :-1] | corner_in[:-1, 1:] | corner_in[1:, 1:])
    assert outside.sum() > 1000 and (ref[inside] > 0.05).sum() > 200
    assert np.all(mine[outside] == 0) and np.all(ref[outside] == 0)
    diff = np.abs(mine - ref)
    assert diff[inside].max() < 0.03
    assert diff[inside].mean() < 2e-3
    assert diff.max() < 0.1  # pixels cut by the edge: 64 different samples each


def test_thin_lens_in_focus_keeps_the_spots_in_place(mono_variant):
    from scopetwin.scenes.mitsuba.render import render_window

    setup = load_setup("thesis-2.8.1-perpendicular", overrides={"camera": {"f_number": 4.0, "focus_distance": 233.24}})
    assert setup.camera_model.lens == ThinLens(25.0, 4.0, 233.24)
    window = (300, 560, 420, 840)
    image = render_window(setup, spp=64, seed=2, window=window, variant=mono_variant)
    found = spot_centroids(image, window)
    err = match(found, setup.camera_model.project(setup.marker_pattern.centers()))
    assert len(err) >= 6
    assert float(np.sqrt(np.mean(err**2))) <= 0.003


def test_render_setup_full_frame_contract():
    """(ny, nx) float32, row 0 on top, defaults from setup.render, same seed -> same bytes."""
    from scopetwin.scenes.mitsuba.render import render_setup

    setup = load_setup(
        "thesis-2.8.1-perpendicular",
        overrides={"camera": {"pixels": [136, 102], "pixel_pitch": 0.0465}, "render": {"spp": 4, "seed": 7}},
    )
    a = render_setup(setup)
    b = render_setup(setup, spp=4, seed=7)
    c = render_setup(setup, seed=8)
    assert a.dtype == np.float32 and a.shape == (102, 136)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    # the reference marker (the -x/-y corner of the target) is at the bottom left of the image
    ref_px = setup.camera_model.project(setup.marker_pattern.centers(np.array([[0, 0]])))[0]
    assert ref_px[0] < 68 and ref_px[1] > 51
    assert a[int(ref_px[1]), int(ref_px[0])] > 0.5


def test_rendering_in_another_thread_gives_the_same_image():
    """Plugins are registered per thread on demand: a worker thread renders the same bytes."""
    from concurrent.futures import ThreadPoolExecutor

    from scopetwin.scenes.mitsuba.render import render_setup

    setup = load_setup("thesis-2.8.3-mirror", overrides={"camera": {"pixels": [136, 102], "pixel_pitch": 0.0465}})
    here = render_setup(setup, spp=4, seed=3)
    with ThreadPoolExecutor(max_workers=1) as pool:
        there = pool.submit(render_setup, setup, None, 4, 3).result()
    assert here.max() > 0.3
    np.testing.assert_array_equal(here, there)
