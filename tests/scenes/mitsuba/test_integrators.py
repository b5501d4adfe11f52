"""The mirror integrator: reflected rays start along the ray, one-sided emitters, black elsewhere (§1.6.5)."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.scenes.setup import load_setup

pytestmark = pytest.mark.mitsuba

WINDOW = (380, 650, 520, 840)


def _render(variant: str, setup, eps: float, window=WINDOW, spp: int = 4) -> np.ndarray:
    from scopetwin.scenes.mitsuba.render import scene_render
    from scopetwin.scenes.mitsuba.scene import scene_dict
    from scopetwin.scenes.mitsuba.variant import mitsuba

    mi = mitsuba(variant)
    return scene_render(mi.load_dict(scene_dict(setup, window=window, eps=eps, variant=variant)), spp, 1, variant)


def test_reflected_ray_offset_along_the_ray_moves_nothing(mono_variant):
    """Starting the reflected ray 0.1 µm or 10 µm further along it gives the same image.

    (An offset along the normal, as in Mitsuba's spawn_ray, would move the reflected ray sideways.)
    """
    setup = load_setup("thesis-2.8.3-mirror")
    near = _render(mono_variant, setup, 1e-4)
    far = _render(mono_variant, setup, 1e-2)
    assert near.max() > 0.9
    assert np.abs(near - far).max() < 1e-4


def test_back_of_the_target_and_empty_space_are_black():
    from scopetwin.scenes.mitsuba.render import render_setup

    small = {"camera": {"pixels": [136, 102], "pixel_pitch": 0.0465}}
    front = load_setup("thesis-2.8.1-perpendicular", overrides=small)
    back = load_setup(
        "thesis-2.8.1-perpendicular", overrides={**small, "pattern": {"t_y": [0.0, -1.0, 0.0], "n_z": [0.0, 0.0, -1.0]}}
    )
    img_front = render_setup(front, spp=4)
    img_back = render_setup(back, spp=4)
    assert img_front.max() > 0.5
    assert np.all(img_back == 0)
    # pixels whose rays miss the target plate entirely stay black
    cam, pattern = front.camera_model, front.marker_pattern
    corners = cam.project(
        pattern.frame.to_global(
            np.array([[sx * pattern.size_x / 2, sy * pattern.size_y / 2, 0] for sx in (-1, 1) for sy in (-1, 1)])
        )
    )
    lo, hi = corners.min(axis=0), corners.max(axis=0)
    cols = np.arange(cam.nx) + 0.5
    rows = np.arange(cam.ny) + 0.5
    off = (
        (cols[None, :] < lo[0] - 1)
        | (cols[None, :] > hi[0] + 1)
        | (rows[:, None] < lo[1] - 1)
        | (rows[:, None] > hi[1] + 1)
    )
    assert off.sum() > 1000
    assert np.all(img_front[off] == 0)
