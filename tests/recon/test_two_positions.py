"""Two pattern positions (recon.two_positions, scenes.pattern_stage; thesis §1.3): the pattern moved
along its normal by a known distance resolves the height-normal ambiguity that one image leaves to the frame
criterion."""

from __future__ import annotations

import json

import numpy as np
import pytest

from scopetwin.recon.reconstruct import MarkerObservations
from scopetwin.recon.strategy import reconstruct_markers_pair
from scopetwin.recon.substrate import Substrate2D
from scopetwin.recon.two_positions import combine
from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.pattern_stage import shift_pattern, stage_shift
from scopetwin.scenes.setup import load_setup
from scopetwin.sim.pipeline import roi_errors
from scopetwin.sim.surfaces import surface_for
from scopetwin.sim.truth import marker_truth

PRESET = "thesis-1.10-deflectometry"
#: A glass-like surface without micro-waviness (power law f^-3.3 flat below 1/50 mm, 2.4 mm roll-off, 30 µm) on
#: which the frame criterion's extrapolation misses the absolute height by ~2 µm (exact marker images: +2.07 µm,
#: reported u 0.18 µm; rendered at 16 spp with sensor noise: +2.04 µm, u 0.22 µm).
SURFACE = {
    "kind": "psd",
    "spectrum": "power",
    "correlation_length": 50.0,
    "psd_exponent": 3.3,
    "psd_rolloff_mm": 2.4,
    "range_um": 30.0,
    "seed": 3,
}
SHIFT_MM = 40.0


def test_the_second_position_is_the_pattern_moved_along_its_normal():
    setup = load_setup(PRESET, {"pattern_stage": {"shift_mm": 25.0}})
    moved = shift_pattern(setup, stage_shift(setup))
    n = np.asarray(setup.pattern.n_z)
    assert np.allclose(np.asarray(moved.pattern.origin) - np.asarray(setup.pattern.origin), 25.0 * n)
    for axis in ("t_x", "t_y", "n_z"):
        assert getattr(moved.pattern, axis) == getattr(setup.pattern, axis)
    assert moved.camera == setup.camera and moved.substrate == setup.substrate
    assert moved.pattern_stage is None  # one position, not a pair
    assert np.allclose(moved.marker_pattern.frame.origin, setup.marker_pattern.frame.origin + 25.0 * n)
    assert stage_shift(setup, -10.0) == -10.0  # an explicit shift wins over the table


@pytest.mark.parametrize(
    "overrides",
    [
        {"pattern_stage": {"shift_mm": 0.0}},
        {"pattern_stage": {"shift_mm": 1e4}},
        {"pattern_stage": {"shift": 3.0}},
    ],
)
def test_a_bad_pattern_stage_is_refused(overrides):
    with pytest.raises(SetupError, match="pattern_stage"):
        load_setup(PRESET, overrides)


def test_only_a_deflectometry_setup_takes_a_pattern_stage_and_the_shift_must_be_known():
    with pytest.raises(SetupError, match="pattern_stage"):
        load_setup("thesis-2.8.1-perpendicular", {"pattern_stage": {"shift_mm": 10.0}})
    with pytest.raises(SetupError, match="no \\[pattern_stage\\]"):
        stage_shift(load_setup(PRESET))
    with pytest.raises(SetupError, match="non-zero"):
        stage_shift(load_setup(PRESET), 0.0)


def test_a_setup_toml_with_a_pattern_stage_loads(tmp_path):
    path = tmp_path / "stage.toml"
    path.write_text(f'base = "{PRESET}"\n\n[pattern_stage]\nshift_mm = 30.0\n')
    setup = load_setup(path)
    assert setup.pattern_stage is not None and setup.pattern_stage.shift_mm == 30.0
    assert json.loads(setup.to_json())["pattern_stage"] == {"shift_mm": 30.0}


def test_combine_weights_by_inverse_variance_and_takes_the_measurement_where_the_frame_criterion_fails():
    mean, std, z = combine(0.0, 1.0, 1.0, 1.0)
    assert mean == pytest.approx(0.5) and std == pytest.approx(1 / np.sqrt(2)) and z == pytest.approx(1 / np.sqrt(2))
    mean, std, z = combine(0.0, 1.0, 2.0, 1.0)  # 1 < |z| <= 3: the Birge ratio scales the uncertainty
    assert mean == pytest.approx(1.0) and std == pytest.approx(1 / np.sqrt(2) * np.sqrt(2))
    mean, std, z = combine(0.0, 0.1, 5.0, 0.2)  # |z| > 3: the two positions alone
    assert (mean, std) == (5.0, 0.2) and z == pytest.approx(5.0 / np.hypot(0.1, 0.2))
    assert combine(0.0, None, 5.0, 0.2) == (5.0, 0.2, None)
    assert combine(0.0, 1.0, 5.0, 0.2, use_frame=False) == (5.0, 0.2, None)


@pytest.mark.slow  # 18 s; combine()'s arithmetic above stays in the default suite (make test <= 5 min)
def test_two_positions_recover_the_absolute_height_where_the_frame_criterion_misses_it():
    """Exact marker images (the project's own ray model, sim.truth) at the pattern's two positions plus 0.01 px of
    centroid noise: the frame criterion misses the absolute height by ~2 µm; the two positions find it within 0.1 µm,
    inside twice their reported standard uncertainty, and so does the result they give."""
    setup = load_setup(PRESET, {"substrate": {"surface": SURFACE}})
    heights = surface_for(setup)
    rng = np.random.default_rng(27)
    obs = []
    for s in (setup, shift_pattern(setup, SHIFT_MM)):
        t = marker_truth(s, heights, rim_points=8)
        v = t.visible
        obs.append(MarkerObservations(t.ij[v], t.center_px[v] + 0.01 * rng.standard_normal((int(v.sum()), 2))))
    result = reconstruct_markers_pair(setup, obs[0], obs[1], SHIFT_MM)
    sub = Substrate2D.from_setup(setup)
    single = roi_errors(result.single.surface.height, heights, sub)
    both = roi_errors(result.surface.height, heights, sub)
    est = result.estimate
    pair_error = single["roi_absolute_um"] + est.pair_um - est.frame_um
    assert abs(single["roi_absolute_um"]) > 1.0  # the frame criterion's extrapolation misses it
    assert abs(pair_error) <= 0.1 and abs(pair_error) <= 2 * est.pair_std_um, (pair_error, est)
    assert abs(both["roi_absolute_um"]) <= 0.1 and abs(both["roi_absolute_um"]) <= 2 * est.std_um, (both, est)
    assert both["roi_shape_um"] < single["roi_shape_um"]  # the start height's error no longer tilts the shape
    assert est.markers[0] > 400 and est.markers[1] > 300
    assert result.summary()["two_positions"]["shift_mm"] == SHIFT_MM
    assert any("second pattern position" in step for step in result.strategy)
