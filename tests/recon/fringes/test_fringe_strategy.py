"""The fringe method in the one strategy (recon.strategy.reconstruct, reconstruct_fringe_images) on synthetic stacks.

The frames of the thesis-1.10-fringes preset (4x binned camera, 24 frames in the sequence's order) are built from
the numpy truth of each pixel's display point with EMVA 1288 noise (fringe_cases.capture). Acceptance: the strategy
picks the fringe method by itself, the shape error <= 0.1 µm RMS (frame criterion) and <= 0.03 µm (two display
positions), the absolute error within 3 of the reported uncertainty; a stack of the wrong length, size or with a NaN,
a marker setup, or a marker method on the fringe setup is refused before any work with one clear error.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fringe_cases import SMALL_CAMERA, capture, second_position, truth  # noqa: E402

import scopetwin  # noqa: E402
from scopetwin.recon.errors import MethodMismatchError  # noqa: E402
from scopetwin.recon.fringes.phase import FringeDecodingError  # noqa: E402
from scopetwin.recon.strategy import Reconstruction, reconstruct, reconstruct_fringe_images  # noqa: E402
from scopetwin.scenes.errors import SetupError  # noqa: E402

SHIFT_MM = 10.0


def fringe_setup(**over):
    return scopetwin.load_setup("thesis-1.10-fringes", {**SMALL_CAMERA, **over})


def stack_of(setup, maps, seed) -> np.ndarray:
    """The frames in the order of the setup's sequence (x then y, coarsest period first, the steps)."""
    seq = setup.fringe_sequence
    frames = capture(setup, maps, seed, seq.steps, seq.periods_mm)
    return np.concatenate([*frames.x, *frames.y]).astype(np.float32)


@pytest.fixture(scope="module")
def case():
    setup = fringe_setup()
    heights, maps = truth(setup)
    return setup, heights, maps


def _errors(r: Reconstruction, heights) -> tuple[float, float]:
    """(absolute error, shape error RMS) over the ROI, µm."""
    gx, gy = r.result.substrate.roi_grid(0.5)
    est, tru = r.height_at(gx, gy), heights.height(gx, gy)
    shape = (est - est.mean()) - (tru - tru.mean())
    return float(est.mean() - tru.mean()) * 1e3, float(np.sqrt(np.mean(shape**2))) * 1e3


def test_the_strategy_picks_fringes_for_a_fringe_stack(case):
    setup, heights, maps = case
    r = reconstruct(stack_of(setup, maps, 1), setup)
    abs_um, shape_um = _errors(r, heights)
    assert r.method == "fringes" and r.markers is None and r.result.converged
    assert shape_um < 0.1, shape_um
    assert abs(abs_um) < 3.0 * r.uncertainty.absolute_um, (abs_um, r.uncertainty)
    assert shape_um < 3.0 * r.uncertainty.shape_um, (shape_um, r.uncertainty)
    assert r.strategy[0].startswith("decode: ") and "low modulation" in r.strategy[0]
    assert "frame criterion" in r.strategy[1] and "converged" in r.strategy[1]
    s = r.summary()
    assert s["method"] == "fringes" and s["absolute_from"] == "frame-criterion" and s["observations"] > 20_000
    assert s["uncertainty"] == {"absolute_um": r.uncertainty.absolute_um, "shape_um": r.uncertainty.shape_um}
    assert r.heightmap(64, 144).z.shape == (144, 64) and r.measured_mask(64, 144).mean() > 0.9


def test_two_display_positions(case):
    setup, heights, maps = case
    moved = second_position(setup, heights, SHIFT_MM)
    r = reconstruct_fringe_images(stack_of(setup, maps, 2), setup, second=(stack_of(setup, moved, 3), SHIFT_MM))
    abs_um, shape_um = _errors(r, heights)
    assert r.result.method == "two-positions" and r.result.converged
    assert shape_um < 0.03, shape_um
    assert abs(abs_um) < 3.0 * r.uncertainty.absolute_um and r.uncertainty.absolute_um < 0.3, (abs_um, r.uncertainty)
    assert r.strategy[1].startswith("decode, display moved +10 mm") and "two display positions" in r.strategy[2]


def test_the_second_position_shift_comes_from_the_pattern_stage(case):
    setup, _, _ = case
    staged = fringe_setup(pattern_stage={"shift_mm": SHIFT_MM})
    good = np.zeros((24, 256, 340), np.float32)
    with pytest.raises(FringeDecodingError, match="second display position: 23 frames"):
        reconstruct_fringe_images(good, staged, second=(good[:-1], None))
    with pytest.raises(SetupError, match=r"no \[pattern_stage\] table"):
        reconstruct_fringe_images(good, setup, second=(good, None))


@pytest.mark.parametrize(
    ("change", "error", "match"),
    [
        (lambda s: s[:-1], FringeDecodingError, "23 frames, but the sequence .* has 24"),
        (lambda s: s[:, :-1], FringeDecodingError, "images of 340 x 255 px, but the camera .* has 340 x 256"),
        (lambda s: np.where(np.arange(24)[:, None, None] == 5, np.nan, s), FringeDecodingError, r"frame\(s\) \[5\]"),
        (lambda s: s[0], MethodMismatchError, r"give the \(K, rows, cols\) stack of its 24 frames"),
    ],
)
def test_a_bad_stack_is_refused_before_any_work(case, change, error, match):
    setup = case[0]
    with pytest.raises(error, match=match):
        reconstruct(change(np.ones((24, 256, 340), np.float32)), setup)


def test_methods_and_setups_that_do_not_fit_are_refused(case):
    setup = case[0]
    stack = np.ones((24, 256, 340), np.float32)
    markers = scopetwin.load_setup("thesis-1.10-deflectometry", SMALL_CAMERA)
    with pytest.raises(MethodMismatchError, match="shows fringes, not markers: the centroid method"):
        reconstruct(stack, setup, "centroid")
    with pytest.raises(MethodMismatchError, match=r"is a fringe measurement, but setup .* has no \[fringes\]"):
        reconstruct(stack, markers)
    with pytest.raises(MethodMismatchError, match=r"has no \[fringes\] table: it is a marker setup"):
        reconstruct(stack, markers, "fringes")
    with pytest.raises(MethodMismatchError, match=r"has no \[fringes\] table"):
        reconstruct_fringe_images(stack, markers)
