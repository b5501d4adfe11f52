"""Scene dictionaries: every Part I preset builds; the pattern raster and its orientation are right."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.setup import load_setup, preset_info
from scopetwin.scenes.surface import HeightMap

pytestmark = pytest.mark.mitsuba

SETUP_PRESETS = [p["name"] for p in preset_info() if p["kind"] == "setup"]


def _heights(setup) -> HeightMap | None:
    if setup.scene != "deflectometry":
        return None
    sx, sy = setup.substrate.size
    return HeightMap.from_function(
        lambda x, y: -0.02 * (y / (0.5 * sy)) ** 2, -0.5 * sx, 0.5 * sx, -0.5 * sy, 0.5 * sy, nx=16, ny=32
    )


def test_there_are_setup_presets():
    assert {"thesis-1.10-deflectometry", "thesis-2.8.1-perpendicular", "thesis-2.8.3-mirror"} <= set(SETUP_PRESETS)


@pytest.mark.parametrize("name", SETUP_PRESETS)
def test_scene_builds_for_every_setup_preset(name, mi_mono, mono_variant):
    from scopetwin.scenes.mitsuba.render import build_scene

    mi = mi_mono
    setup = load_setup(name)
    scene = mi.load_dict(build_scene(setup, _heights(setup), mono_variant))
    ids = {s.id() for s in scene.shapes()}
    expected = {
        "deflectometry": {"pattern", "substrate_roi", "frame_low", "frame_high"},
        "mirror": {"pattern", "mirror"},
        "target": {"pattern"},
    }[setup.scene]
    assert ids == expected
    assert len(scene.emitters()) == 1
    film = scene.sensors()[0].film()
    assert tuple(film.size()) == setup.camera.pixels


def test_deflectometry_without_heights_is_a_setup_error():
    from scopetwin.scenes.mitsuba.render import build_scene, render_setup

    setup = load_setup("thesis-1.10-deflectometry")
    with pytest.raises(SetupError, match="height map"):
        build_scene(setup)
    with pytest.raises(SetupError, match="height map"):
        render_setup(setup)


def test_window_outside_the_image_is_a_setup_error():
    from scopetwin.scenes.mitsuba.scene import scene_dict

    with pytest.raises(SetupError, match="window"):
        scene_dict(load_setup("thesis-2.8.1-perpendicular"), window=(0, 2000, 0, 10))


@pytest.mark.parametrize("name", ["thesis-1.10-deflectometry", "thesis-2.8.1-perpendicular", "thesis-2.9.1-target-4x4"])
def test_fast_marker_texture_equals_pattern_texture(name):
    from scopetwin.scenes.mitsuba.scene import marker_texture

    pattern = load_setup(name).marker_pattern
    np.testing.assert_allclose(marker_texture(pattern, 0.05), pattern.texture(0.05), atol=2e-7, rtol=0)


def test_pattern_radiance_scales_the_raster():
    from scopetwin.scenes.mitsuba.scene import pattern_texture

    base = load_setup("thesis-2.9.1-target-4x4")
    bright = load_setup("thesis-2.9.1-target-4x4", overrides={"pattern": {"radiance": 2.5}})
    np.testing.assert_allclose(pattern_texture(bright, 0.05), 2.5 * pattern_texture(base, 0.05), rtol=1e-6)


def test_reference_marker_appears_where_the_camera_projects_it():
    """Calibration layout: the large reference marker (0, 0) sits at the -x/-y corner (thesis §2.2)."""
    from scipy import ndimage

    from scopetwin.scenes.mitsuba.render import render_window

    setup = load_setup("thesis-2.8.1-angular")
    cam, pattern = setup.camera_model, setup.marker_pattern
    ij = np.array([[0, 0], [1, 0], [0, 1]])
    px = cam.project(pattern.centers(ij))
    lo = np.floor(px.min(axis=0) - 60).astype(int)
    hi = np.ceil(px.max(axis=0) + 60).astype(int)
    window = (max(lo[1], 0), min(hi[1], cam.ny), max(lo[0], 0), min(hi[0], cam.nx))
    image = render_window(setup, spp=4, seed=0, window=window)
    labels, _ = ndimage.label(image > 0)
    areas = []
    for col, row in px:
        lab = labels[int(row) - window[0], int(col) - window[2]]
        assert lab > 0, "no spot at a projected marker centre"
        areas.append(int((labels == lab).sum()))
    # the reference marker is the big one (radius 1.4 vs 1.0 mm: area ratio ~2)
    assert areas[0] > 1.6 * max(areas[1:])
