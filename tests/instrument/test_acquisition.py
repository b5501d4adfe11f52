"""Acquisition routines on simulated and emulated rigs: tile scan with a focus map, simultaneous
capture on the global trigger, automatic exposure, and failures that keep frames and switch lights off."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.interpolate import RegularGridInterpolator

from scopetwin.instrument import open_rig
from scopetwin.instrument.acquisition import (
    calibration_capture,
    deflectometry_capture,
    grid,
    simultaneous_capture,
    tile_scan,
)
from scopetwin.instrument.devices import TriggerType
from scopetwin.instrument.emulators import Fault
from scopetwin.instrument.errors import DisconnectedError, InstrumentTimeout
from scopetwin.scenes.emva1288 import EmvaSensor
from scopetwin.scenes.io import read_image
from scopetwin.scenes.mitsuba.widefield import BentSubstrate

RIGS = Path(__file__).resolve().parents[2] / "rigs"


def _focus_map_from_heights(substrate: BentSubstrate, focus_ref_um: float = 200.0):
    """A focus map as the reconstruction delivers it: heights on a coarse grid, interpolated (µm)."""
    x = np.linspace(72.0, 78.0, 25)
    y = np.linspace(147.0, 153.0, 25)
    xx, yy = np.meshgrid(x, y, indexing="ij")
    table = RegularGridInterpolator((x, y), substrate(xx, yy) * 1e3, method="cubic")
    return lambda x_mm, y_mm: focus_ref_um + float(table([[x_mm, y_mm]])[0])


@pytest.mark.mitsuba
def test_tile_scan_focus_map_vs_fixed_focus(tmp_path):
    """Acceptance: focus from the focus map keeps every tile sharp; one fixed focus blurs most tiles."""
    substrate = BentSubstrate(bow_mm=0.03, tilt_x=0.004, tilt_y=0.002, radius_mm=1.5, center_mm=(75.0, 150.0))
    focus_map = _focus_map_from_heights(substrate)
    positions = grid((73.8, 76.2), (148.8, 151.2), 3, 3)
    with open_rig(RIGS / "sim-cmu.toml") as rig:
        kw = {"camera": "cam_blue", "light": "uv", "exposure_s": 0.02}
        mapped = tile_scan(rig, tmp_path / "map", positions, focus_map=focus_map, **kw)
        fixed = tile_scan(rig, tmp_path / "fixed", positions, fixed_focus_um=focus_map(75.0, 150.0), **kw)
        assert not rig.world.any_light_on()
    print("\ntile   x_mm    y_mm   focus_map_um  sharpness(map)  sharpness(fixed)")
    for m, f in zip(mapped, fixed, strict=True):
        print(f"{m.index}  {m.x_mm:6.2f}  {m.y_mm:7.2f}  {m.focus_um:10.2f}  {m.sharpness:12.4f}  {f.sharpness:14.4f}")
        assert m.focus_um == pytest.approx(200.0 + 1e3 * float(substrate(m.x_mm, m.y_mm)), abs=0.2)
        frame, _ = read_image(m.path)
        assert frame.shape == (256, 256)
    s_map = np.array([m.sharpness for m in mapped])
    s_fixed = np.array([f.sharpness for f in fixed])
    assert s_map.min() > 0.6 * s_map.max()  # every focus-map tile is in focus
    blurred = s_fixed < 0.2 * s_map
    assert blurred.sum() >= 2 * len(positions) // 3  # most fixed-focus tiles are blurred
    centre = [i for i, m in enumerate(mapped) if m.index == (1, 1)][0]
    assert s_fixed[centre] == pytest.approx(s_map[centre], rel=0.1)  # where the fixed focus is right, it is sharp


SIMULTANEOUS_RIG = """
[devices.trigger]
kind = "trigger"
driver = "sim"
""" + "".join(
    f"""
[devices.led{i}]
kind = "light"
driver = "sim"
max_current_ma = 1000.0
[devices.cam{i}]
kind = "camera"
driver = "sim"
sensor_shape = [48, 64]
trigger_line = {i}
seed = {i}
renderer = {{ kind = "texture", lights = ["led{i}"], peak = 1.0, seed = {i} }}
"""
    for i in range(4)
)


def _four_channel_rig(tmp_path):
    path = tmp_path / "four.toml"
    path.write_text(SIMULTANEOUS_RIG)
    return path


def test_simultaneous_capture_on_global_trigger(tmp_path):
    """Four channels on one global trigger: each frame has exactly its light's dose; lights off afterwards."""
    exposure = 0.01
    with open_rig(_four_channel_rig(tmp_path)) as rig:
        for i in range(4):
            rig.light(f"led{i}").configure(current_ma=250.0 * (i + 1))
        paths = simultaneous_capture(rig, tmp_path / "out", {f"cam{i}": f"led{i}" for i in range(4)}, exposure)
        assert not rig.world.any_light_on()
        assert [e[0] for e in rig.world.events].count("global-trigger") == 1
        expected = [
            EmvaSensor().mean_dn(rig[f"cam{i}"].render_irradiance({f"led{i}": 0.25 * (i + 1)}), 1.0e6, exposure).mean()
            for i in range(4)
        ]
    for i in range(4):
        frame, _ = read_image(paths[f"cam{i}"])
        assert frame.mean() == pytest.approx(expected[i], rel=0.03)


@pytest.mark.parametrize("light_delay_fraction", [0.0, 0.25, 0.5, 1.0])
def test_global_trigger_delay_sets_the_dose(tmp_path, light_delay_fraction):
    """A light that starts ``f`` of an exposure late (thesis §4.3.2 trigger delay) gives ``1 - f`` of the signal."""
    exposure = 0.01
    with open_rig(_four_channel_rig(tmp_path)) as rig:
        cam, led, board = rig["cam0"], rig.light("led0"), rig.trigger()
        led.configure(
            current_ma=1000.0,
            use_duration=True,
            duration_s=exposure,
            listen_global_trigger=True,
            global_trigger_delay_s=light_delay_fraction * exposure,
        )
        cam.set_exposure_s(exposure)
        cam.set_trigger(TriggerType.RISING_EDGE)
        board.configure_camera_line(0, True, 0.0)
        cam.arm()
        board.fire()
        frame = cam.grab()
        full = EmvaSensor().mean_dn(cam.render_irradiance({"led0": 1.0}), 1.0e6, exposure).mean()
    black = EmvaSensor().black_level_dn
    assert frame.mean() - black == pytest.approx((1 - light_delay_fraction) * (full - black), rel=0.03, abs=1.0)


def test_failures_keep_frames_and_switch_lights_off(tmp_path):
    """Real drivers on emulators: the x stage's line drops mid-frame at the third tile."""
    out = tmp_path / "scan"
    with open_rig(RIGS / "emulated-hardware.toml") as rig:
        board = rig.light("uv").board.link.transport.emulator
        stage_emulator = rig.stage("x").controller.link.transport.emulator
        rig.light("uv").configure(current_ma=300.0)

        def after_tile(result):
            if result.index == (1, 0):
                stage_emulator.fault = Fault.DROP

        with pytest.raises((DisconnectedError, InstrumentTimeout)):
            tile_scan(
                rig,
                out,
                grid((1.0, 1.2), (2.0, 2.2), 3, 2),
                focus_map=lambda x, y: 150.0 + 10 * x,
                light="uv",
                on_tile=after_tile,
            )
        assert not board.any_light_on()
    manifest = json.loads((out / "manifest.json").read_text())
    assert not manifest["complete"] and manifest["error"]
    assert [f["name"] for f in manifest["frames"]] == ["tile_000_000", "tile_000_001"]
    for f in manifest["frames"]:
        frame, _ = read_image(out / f["path"])
        # the simulated camera sees the emulated board's light: the tiles were exposed with uv on
        assert frame.shape == (128, 128) and frame.mean() > EmvaSensor().black_level_dn + 100.0
    assert stage_emulator.errors == [] and board.errors == []


def test_dropped_frames_keep_earlier_frames(tmp_path):
    """The simulated camera drops frames after two: timeout, two frames on disk, lights off."""
    with open_rig(_four_channel_rig(tmp_path)) as rig:
        rig["cam0"].inject_fault("drop", after=2)
        rig["cam0"].timeout_s = 0.05
        with pytest.raises(InstrumentTimeout):
            calibration_capture(rig, tmp_path / "cal", n_frames=4, camera="cam0", light="led0", exposure_s=0.01)
        assert not rig.world.any_light_on()
    manifest = json.loads((tmp_path / "cal" / "manifest.json").read_text())
    assert len(manifest["frames"]) == 2 and "InstrumentTimeout" in manifest["error"]


@pytest.mark.mitsuba
def test_deflectometry_capture_exposes_to_70_percent(tmp_path):
    with open_rig(RIGS / "sim-deflectometry.toml") as rig:
        path = deflectometry_capture(rig, tmp_path / "defl")
        assert not rig.world.any_light_on()
    frame, _ = read_image(path)
    assert frame.shape == (1024, 1360)
    assert np.percentile(frame, 99.5) == pytest.approx(0.7 * 4095, rel=0.05)
