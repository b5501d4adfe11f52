"""The pattern stage of a rig (instrument.acquisition.two_position_capture, thesis §1.3): one frame at the stage's
position and one a known shift further, the same exposure, the positions read back into the manifest, the stage
back where it started and the light off. The texture renderer (numpy) stands in for the pattern's image here; the
Mitsuba rig is tested end to end in tests/recon/test_two_positions_rendered.py."""

from __future__ import annotations

import json

import numpy as np
import pytest

from scopetwin.instrument import open_rig
from scopetwin.instrument.acquisition import two_position_capture
from scopetwin.instrument.errors import OutOfRangeError
from scopetwin.scenes.io import read_image

RIG = """
[devices.pattern]
kind = "light"
driver = "sim"
max_current_ma = 1000.0

[devices.camera]
kind = "camera"
driver = "sim"
sensor_shape = [48, 64]
renderer = { kind = "texture", lights = ["pattern"], stage_x = "pattern_z", pixel_mm = 0.5, seed = 3 }

[devices.pattern_z]
kind = "stage"
driver = "sim"
travel_mm = [0.0, 50.0]
max_velocity_mm_s = 500.0
"""


def test_two_frames_at_two_known_positions(tmp_path):
    rig_path = tmp_path / "rig.toml"
    rig_path.write_text(RIG)
    with open_rig(rig_path) as rig:
        rig.stage("pattern_z").move_absolute(5.0)
        paths, positions = two_position_capture(rig, tmp_path / "out", "pattern_z", 30.0)
        assert rig.stage("pattern_z").position_mm == pytest.approx(5.0)  # back where it started
        assert not rig.world.any_light_on()
    assert positions == pytest.approx([5.0, 35.0])
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert manifest["complete"] and manifest["meta"]["pattern_stage"] == "pattern_z"
    frames = manifest["frames"]
    assert [f["name"] for f in frames] == ["deflectometry_1", "deflectometry_2"]
    assert [f["pattern_stage_mm"] for f in frames] == pytest.approx([5.0, 35.0])
    assert frames[0]["exposure_s"] == frames[1]["exposure_s"]
    first, _ = read_image(paths[0])
    second, _ = read_image(paths[1])
    assert first.shape == second.shape == (48, 64) and not np.allclose(first, second)  # the stage moved what is seen


def test_a_second_position_beyond_the_travel_is_refused_before_anything_is_switched_on(tmp_path):
    rig_path = tmp_path / "rig.toml"
    rig_path.write_text(RIG)
    with open_rig(rig_path) as rig:
        with pytest.raises(OutOfRangeError):
            two_position_capture(rig, tmp_path / "out", "pattern_z", 60.0)
        assert not rig.world.any_light_on()
        assert rig.stage("pattern_z").position_mm == pytest.approx(0.0)
    assert not (tmp_path / "out").exists()
