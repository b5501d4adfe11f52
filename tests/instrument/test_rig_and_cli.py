"""Rig files, open_rig's safe exit, the `rig` CLI, and Micro-Manager interop."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from scopetwin.cli.rig import register
from scopetwin.instrument import open_rig
from scopetwin.instrument.errors import RigError
from scopetwin.instrument.rig import load_rig
from scopetwin.scenes.io import read_image

RIGS = Path(__file__).resolve().parents[2] / "rigs"

TEXTURE_RIG = """
[rig]
name = "texture"
[devices.x]
kind = "stage"
driver = "sim"
travel_mm = [0.0, 150.0]
max_velocity_mm_s = 50.0
position_mm = 10.0
[devices.y]
kind = "stage"
driver = "sim"
travel_mm = [0.0, 300.0]
max_velocity_mm_s = 100.0
position_mm = 10.0
[devices.focus]
kind = "focus"
driver = "sim"
position_um = 100.0
[devices.led]
kind = "light"
driver = "sim"
max_current_ma = 700.0
[devices.camera]
kind = "camera"
driver = "sim"
sensor_shape = [64, 80]
renderer = { kind = "texture" }
"""


@pytest.fixture
def texture_rig(tmp_path):
    path = tmp_path / "texture.toml"
    path.write_text(TEXTURE_RIG)
    return path


@pytest.mark.parametrize("name", ["sim-deflectometry", "sim-cmu", "emulated-hardware"])
def test_presets_load(name):
    rig = load_rig(RIGS / f"{name}.toml")
    try:
        assert rig.devices and {d.kind for d in rig.devices.values()} <= {
            "camera",
            "stage",
            "focus",
            "light",
            "shutter",
            "trigger",
        }
    finally:
        rig.close()


@pytest.mark.parametrize(
    "edit, match",
    [
        (
            ('driver = "sim"\ntravel_mm = [0.0, 150.0]', 'driver = "warp"\ntravel_mm = [0.0, 150.0]'),
            "unknown driver",
        ),
        (("position_um = 100.0", "position_um = 100.0\ncolour = 3"), "unknown field"),
        (("max_current_ma = 700.0", "max_current_ma = 700.0\nshutter = 3"), "shutter must be str"),
        (("travel_mm = [0.0, 150.0]", "travel_mm = [0.0]"), "two numbers"),
    ],
)
def test_bad_rig_files_name_the_problem(tmp_path, edit, match):
    path = tmp_path / "bad.toml"
    path.write_text(TEXTURE_RIG.replace(*edit, 1))
    with pytest.raises(RigError, match=match):
        load_rig(path)


def test_open_rig_switches_lights_off_on_exception():
    """Drivers on emulators: an exception inside the block still leaves every light off on the board."""
    with pytest.raises(RuntimeError, match="boom"), open_rig(RIGS / "emulated-hardware.toml") as rig:
        board = rig.light("uv").board.link.transport.emulator
        for name in ("uv", "blue_led", "deep_red"):
            rig.light(name).switch_on(200.0)
        rig["shutter"].open()
        assert board.any_light_on() and board.ttl[0] == 1
        raise RuntimeError("boom")
    assert not board.any_light_on()
    assert board.ttl[0] == 0 and board.ttl[1] == 1  # shutter closed
    assert not rig.stage("x").controller.link.transport.is_open  # transports closed with the rig


def _cli(argv):
    parser = argparse.ArgumentParser(prog="scopetwin")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return args, args.func(args)


def test_cli_move_position_info_acquire(texture_rig, tmp_path, capsys):
    args, result = _cli(["rig", str(texture_rig), "move", "x", "12.5", "--json", str(tmp_path / "m.json")])
    assert result == {"device": "x", "position_mm": 12.5} and args.json.endswith("m.json")
    _, result = _cli(["rig", str(texture_rig), "move", "focus", "150"])
    assert result == {"device": "focus", "position_um": 150.0}
    _, result = _cli(["rig", str(RIGS / "emulated-hardware.toml"), "position", "focus"])
    assert result == {"device": "focus", "position_um": 0.0}
    _, info = _cli(["rig", str(RIGS / "emulated-hardware.toml"), "info"])
    drivers = {d["name"]: d["driver"] for d in info["devices"]}
    assert drivers["x"] == "pi-gcs" and drivers["focus"] == "jena-piezo" and drivers["uv"] == "fpga-board"
    with pytest.raises(RigError):
        _cli(["rig", str(texture_rig), "move", "led", "1"])
    _, result = _cli(["rig", str(texture_rig), "acquire", str(tmp_path / "frames"), "--frames", "2"])
    assert len(result["frames"]) == 2
    frame, _ = read_image(result["frames"][1])
    # automatic exposure: the 99.5th percentile sits at ~70 % of the 12-bit range
    assert np.percentile(frame, 99.5) == pytest.approx(0.7 * 4095, rel=0.05)
    manifest = json.loads((tmp_path / "frames" / "manifest.json").read_text())
    assert manifest["complete"] and len(manifest["frames"]) == 2
    json.dumps(info)  # JSON-ready
    assert "pi-gcs" in capsys.readouterr().out


def test_micro_manager_mda_runs_on_simulated_rig(texture_rig):
    useq = pytest.importorskip("useq", reason="useq-schema (optional extra 'mm') is not installed")
    pytest.importorskip("pymmcore_plus", reason="pymmcore-plus (optional extra 'mm') is not installed")
    from scopetwin.instrument.micromanager import load_into_core

    with open_rig(texture_rig) as rig:
        rig.light().configure(current_ma=350.0)
        core = load_into_core(rig)
        seq = useq.MDASequence(
            stage_positions=[(10000.0, 10000.0, 100.0), (10250.0, 10050.0, 120.0)], z_plan={"range": 4.0, "step": 2.0}
        )
        seen = []
        core.mda.events.frameReady.connect(
            lambda img, event, meta: seen.append(
                (img.copy(), event.x_pos, event.z_pos, rig.stage("x").position_mm, rig.focus().position_um)
            )
        )
        core.mda.run(seq)
        assert not rig.light().is_on
    assert len(seen) == 6
    for img, x_um, z_um, x_mm, focus_um in seen:
        assert x_mm == pytest.approx(x_um * 1e-3) and focus_um == pytest.approx(z_um)
        assert img.shape == (64, 80) and img.mean() > 200  # lit: well above the 32 DN black level
    assert not np.array_equal(seen[0][0], seen[3][0])  # the stage moved the sample
