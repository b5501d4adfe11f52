"""Tracing only the pixels that can see a marker: every pixel skipped is 0 in a render of every pixel, and the
trace's short cuts (its own hit points and normals, the pattern plane met directly) give Mitsuba's answer."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.scenes.setup import load_setup
from scopetwin.sim.families import family_spec
from scopetwin.sim.surfaces import surface_for

pytestmark = pytest.mark.mitsuba

#: Surfaces and scenes of every kind the renderer meets: the §1.10 surface, a cut sheet with rolled-off edges (the
#: steepest family), a steep high sheet, a 3 mm / 60 µm surface whose spots are no longer compact, a smaller sensor,
#: the flat mirror, a target seen directly.
CASES = [
    ("thesis-1.10-deflectometry", {}),
    ("thesis-1.10-deflectometry", {"substrate": {"surface": family_spec("cut", 2)}}),
    ("thesis-1.10-deflectometry", {"substrate": {"surface": family_spec("steep", 1)}}),
    (
        "thesis-1.10-deflectometry",
        {"substrate": {"surface": {"kind": "random", "seed": 4, "correlation_length": 3.0, "range_um": 60.0}}},
    ),
    ("thesis-1.10-deflectometry", {"camera": {"pixels": [680, 512], "pixel_pitch": 0.0093}}),
    ("thesis-2.8.3-mirror", {}),
    ("thesis-2.9.1-target-6x4", {}),
]


def _loaded(name: str, overrides: dict, variant: str):
    from scopetwin.scenes.mitsuba.render import live_window, load_scene

    setup = load_setup(name, overrides)
    heights = surface_for(setup)
    window = live_window(setup, heights)
    scene = load_scene(setup, heights, window, variant)
    return setup, heights, window, scene


@pytest.mark.parametrize(("name", "overrides"), CASES)
def test_every_skipped_pixel_is_black_in_a_render_of_every_pixel(name, overrides, mono_variant):
    from scopetwin.scenes.mitsuba.lit import lit_pixels
    from scopetwin.scenes.mitsuba.render import render_window
    from scopetwin.scenes.mitsuba.scene import TEXEL

    setup, heights, window, scene = _loaded(name, overrides, mono_variant)
    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    ms = scene.integrator().geometry(scene)
    traced = np.zeros(width * height, dtype=bool)
    traced[lit_pixels(ms, scene, setup.marker_pattern, TEXEL, width, height)] = True
    traced = traced.reshape(height, width)
    every = render_window(setup, heights, spp=64, seed=7, window=window, variant=mono_variant)
    lit = every > 0
    print(f"{name} {overrides}: {traced.mean():.3f} of the window traced, {lit.mean():.3f} lit")
    assert lit.sum() > 1000
    assert not (lit & ~traced).any()
    assert traced.mean() < 0.65  # most of the black is skipped


def test_marked_render_is_the_render_of_every_pixel_where_light_is(mono_variant):
    """Same rays, sampler and box filter on the traced pixels: the image sums agree to Monte-Carlo noise; the same
    seed gives the same bytes."""
    from scopetwin.scenes.mitsuba.render import render_marked, render_window

    setup, heights, window, _ = _loaded("thesis-1.10-deflectometry", {}, mono_variant)
    marked = render_marked(setup, heights, spp=16, seed=3, window=window, variant=mono_variant)
    every = render_window(setup, heights, spp=16, seed=3, window=window, variant=mono_variant)
    assert marked.shape == every.shape and marked.dtype == np.float32
    assert abs(float(marked.sum()) - float(every.sum())) < 1e-3 * float(every.sum())
    again = render_marked(setup, heights, spp=16, seed=3, window=window, variant=mono_variant)
    np.testing.assert_array_equal(marked, again)


@pytest.mark.parametrize(("name", "overrides"), [CASES[0], CASES[1], CASES[5]])
def test_reflected_rays_met_directly_land_where_mitsuba_sends_them(name, overrides, mono_variant):
    """The trace meets the pattern's plane directly where a reflected ray rises faster than the surface's slopes;
    with every reflected ray traced by Mitsuba instead, the same rays land at the same points."""
    import dataclasses

    import drjit as dr

    from scopetwin.scenes.mitsuba.lit import _centre_rays
    from scopetwin.scenes.mitsuba.trace import landing
    from scopetwin.scenes.mitsuba.variant import mitsuba

    mi = mitsuba(mono_variant)
    _, _, _, scene = _loaded(name, overrides, mono_variant)
    ms = scene.integrator().geometry(scene)
    assert 0.0 <= ms.slope < 0.05
    traced = dataclasses.replace(ms, rise=dr.opaque(mi.Float, 3.0e38))
    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    ray, _, _ = _centre_rays(mi, scene.sensors()[0], width, height)
    fast = [np.asarray(v) for v in landing(ms, scene, ray)]
    slow = [np.asarray(v) for v in landing(traced, scene, ray)]
    assert fast[2].sum() > 1000
    np.testing.assert_array_equal(fast[2], slow[2])
    np.testing.assert_array_equal(fast[0], slow[0])
    np.testing.assert_array_equal(fast[1], slow[1])


def test_the_mirror_integrator_renders_the_trace(mono_variant):
    """The plugin Mitsuba's own render calls and the marked render share the trace: a white texel seen in the mirror
    is the pattern radiance in both."""
    from scopetwin.scenes.mitsuba.render import render_marked, render_window

    setup = load_setup("thesis-2.8.3-mirror", {"pattern": {"radiance": 2.0}})
    window = (380, 650, 520, 840)
    a = render_window(setup, spp=16, seed=1, window=window, variant=mono_variant)
    b = render_marked(setup, spp=16, seed=1, window=window, variant=mono_variant)
    assert a.max() > 1.9 and b.max() > 1.9
    assert abs(float(a.sum()) - float(b.sum())) < 2e-3 * float(a.sum())


def test_a_scene_the_trace_does_not_know_is_refused(mono_variant):
    from scopetwin.scenes.errors import SetupError
    from scopetwin.scenes.mitsuba.trace import mirror_scene
    from scopetwin.scenes.mitsuba.variant import mitsuba

    mi = mitsuba(mono_variant)
    two = mi.load_dict(
        {
            "type": "scene",
            "a": {"type": "rectangle", "emitter": {"type": "area"}},
            "b": {"type": "rectangle", "emitter": {"type": "area"}},
        }
    )
    with pytest.raises(SetupError, match="exactly one emitter"):
        mirror_scene(mi, two, 1e-3)
    sphere = mi.load_dict(
        {"type": "scene", "a": {"type": "rectangle", "emitter": {"type": "area"}}, "s": {"type": "sphere"}}
    )
    with pytest.raises(SetupError, match="meshes and rectangles"):
        mirror_scene(mi, sphere, 1e-3)


def test_another_camera_pose_window_and_surface_reuse_the_compiled_kernels(mono_variant):
    """The camera's pose, the render window, the film and the shapes' pointers enter the kernels as opaque values:
    a dataset's next sample (camera jitter, a new surface, another window) launches the kernels already compiled."""
    import drjit as dr

    from scopetwin.scenes.mitsuba.render import live_window, render_marked

    hashes = []
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for k, shift in enumerate((0.0, 0.29)):
            setup = load_setup(
                "thesis-1.10-deflectometry",
                {"camera": {"origin": [shift, -200.0, 120.0]}, "substrate": {"surface": {"seed": 3 + k}}},
            )
            heights = surface_for(setup)
            hashes.append(live_window(setup, heights))
            dr.kernel_history_clear()
            render_marked(setup, heights, spp=4, seed=1, window=hashes[-1], variant=mono_variant)
            big = [h for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT and h["size"] > 50_000]
            hashes.append({h["hash"] for h in big})
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert hashes[0] != hashes[2]  # another window
    assert len(hashes[1]) >= 3 and hashes[1] == hashes[3]
