"""rigs/emulated-hardware.toml: the simulated camera sees what the drivers did to the emulators."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from scopetwin.instrument import open_rig

RIG = Path(__file__).resolve().parents[2] / "rigs" / "emulated-hardware.toml"


def test_camera_sees_the_board_lights():
    with open_rig(RIG) as rig:
        camera = rig.camera()
        camera.set_roi(0, 0, 64, 64)
        camera.set_exposure_s(0.01)
        dark = camera.grab()
        black = camera.black_level_dn
        assert dark.mean() == pytest.approx(black, abs=5.0)  # all lights off: black (black level + read noise)
        board = rig.light("uv").board.link.transport.emulator
        rig.light("uv").switch_on(250.0)
        assert board.lights_on() == [0]
        lit = camera.grab()
        assert lit.mean() > black + 200.0  # a light on: bright
        rig.light("blue_led").switch_on(1000.0)
        brighter = camera.grab()
        assert brighter.mean() > lit.mean() + 200.0  # the second light adds
        rig.lights_off()
        assert board.lights_on() == []
        assert camera.grab().mean() == pytest.approx(black, abs=5.0)  # black again


def test_level_follows_the_current_on_the_board():
    with open_rig(RIG) as rig:
        camera = rig.camera()
        camera.set_roi(0, 0, 32, 32)
        light = rig.light("halogen")
        means = []
        for current in (100.0, 400.0):
            light.switch_on(current)
            means.append(camera.grab().mean() - camera.black_level_dn)
        assert means[1] == pytest.approx(4 * means[0], rel=0.1)  # irradiance proportional to current


def test_camera_sees_the_emulated_stage_move():
    with open_rig(RIG) as rig:
        camera = rig.camera()
        camera.set_roi(0, 0, 64, 64)
        rig.light("uv").switch_on(500.0)
        before = camera.grab()
        rig.stage("x").move_absolute(0.2)
        after = camera.grab()
        assert rig.world.snapshot("camera", (1, 1), 0.01, {}).stage_mm["x"] == pytest.approx(0.2)
        assert not np.allclose(before, after, atol=50.0)  # the texture moved with the stage
        rig.focus().move_absolute_um(123.0)
        assert rig.world.snapshot("camera", (1, 1), 0.01, {}).focus_um["focus"] == pytest.approx(123.0)
