"""Culling: the pixels outside the live window are black in a full render, so skipping them changes nothing."""

from __future__ import annotations

import pytest

from scopetwin.scenes.setup import load_setup
from scopetwin.sim.surfaces import surface_for

pytestmark = pytest.mark.mitsuba


@pytest.mark.parametrize(
    ("name", "overrides"),
    [
        ("thesis-1.10-deflectometry", {}),
        ("thesis-2.8.5-distortion", {"camera": {"c2": -0.004}}),  # barrel distortion bends the target's edges
        ("thesis-2.9.1-target-6x4", {}),
    ],
)
def test_full_render_is_black_outside_the_live_window(name, overrides):
    from scopetwin.scenes.mitsuba.render import live_window, render_setup, render_window

    setup = load_setup(name, overrides)
    heights = surface_for(setup)
    window = live_window(setup, heights)
    assert window is not None
    r0, r1, c0, c1 = window
    full = render_window(setup, heights, spp=4, seed=2, window=None)
    outside = full.copy()
    outside[r0:r1, c0:c1] = 0.0
    assert outside.max() == 0.0
    assert full[r0:r1, c0:c1].max() > 0.5
    culled = render_setup(setup, heights, spp=4, seed=2)
    assert culled.shape == full.shape
    culled_outside = culled.copy()
    culled_outside[r0:r1, c0:c1] = 0.0
    assert culled_outside.max() == 0.0
    # same scene, same sample count: the means agree to Monte-Carlo noise
    assert abs(float(culled.sum()) - float(full.sum())) < 1e-3 * float(full.sum())


def test_no_culling_where_light_can_spread():
    from scopetwin.scenes.mitsuba.render import live_window

    thin = load_setup("thesis-2.8.1-angular", {"camera": {"f_number": 4.0}})
    assert live_window(thin) is None
    assert live_window(load_setup("thesis-2.8.1-perpendicular")) is None  # the target fills the frame
