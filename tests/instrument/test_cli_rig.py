"""``scopetwin rig`` as a newcomer meets it: limits in ``info``, the emu:// note, bad numbers refused with the option
named, a PNG preview beside the frames, one warning line when the frames carry no signal, and ``move`` then
``position`` in two commands against ``scopetwin emulate`` (state kept, unlike an emu:// port)."""

from __future__ import annotations

import json

import cv2
import pytest

from scopetwin.cli import main
from scopetwin.cli.rig import EMU_NOTE
from tests.instrument.cli_processes import ROOT, emulator, stop

RIG = """
[rig]
name = "two-lights"
[devices.x]
kind = "stage"
driver = "sim"
travel_mm = [0.0, 150.0]
max_velocity_mm_s = 50.0
[devices.focus]
kind = "focus"
driver = "sim"
range_um = [0.0, 400.0]
[devices.uv]
kind = "light"
driver = "sim"
max_current_ma = 500.0
[devices.deep_red]
kind = "light"
driver = "sim"
max_current_ma = 1000.0
[devices.cam]
kind = "camera"
driver = "sim"
sensor_shape = [32, 40]
exposure_range_s = [1.0e-4, 2.0]
renderer = { kind = "texture", lights = ["uv"] }
"""


@pytest.fixture
def rig_path(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text(RIG)
    return path


def test_info_shows_the_limits_and_explains_emu_ports(capsys):
    assert main(["rig", str(ROOT / "rigs" / "emulated-hardware.toml"), "info"]) == 0
    out = capsys.readouterr().out
    lines = {line.split()[0]: line for line in out.splitlines()}
    assert "travel 0..150 mm" in lines["x"] and "max 50 mm/s" in lines["x"]
    assert "range 0..400 um" in lines["focus"] and "nv40-1" in lines["focus"]
    assert "max 500 mA" in lines["uv"] and "[emu://fpga-board]" in lines["uv"]
    assert "exposure 2e-05..10 s" in lines["camera"] and "128x128 px" in lines["camera"]
    assert EMU_NOTE in out and "scopetwin emulate" in EMU_NOTE


def test_info_of_a_simulated_rig_has_no_emu_note(rig_path, capsys):
    assert main(["rig", str(rig_path), "info"]) == 0
    out = capsys.readouterr().out
    assert "exposure 0.0001..2 s" in out and EMU_NOTE not in out


@pytest.mark.parametrize(
    "args, option",
    [
        (["--frames", "-1"], "--frames"),
        (["--frames", "0"], "--frames"),
        (["--frames", "2.5"], "--frames"),
        (["--exposure-s", "0"], "--exposure-s"),
        (["--exposure-s", "nan"], "--exposure-s"),
    ],
)
def test_bad_acquire_numbers_are_refused_naming_the_option(rig_path, tmp_path, capsys, args, option):
    with pytest.raises(SystemExit) as stopped:
        main(["rig", str(rig_path), "acquire", str(tmp_path / "frames"), *args])
    assert stopped.value.code == 2
    assert f"argument {option}:" in capsys.readouterr().err
    assert not (tmp_path / "frames").exists()


def test_exposure_outside_the_camera_range_is_one_line(rig_path, tmp_path, capsys):
    assert main(["rig", str(rig_path), "acquire", str(tmp_path / "f"), "--exposure-s", "5"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--exposure-s" in err and "outside [0.0001, 2.0]" in err


def test_acquire_writes_a_preview_and_warns_once_when_dark(rig_path, tmp_path, capsys):
    lit = tmp_path / "lit"
    argv = ["rig", str(rig_path), "acquire", str(lit), "--light", "uv", "--frames", "2", "--json", str(tmp_path / "a")]
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert "warning" not in captured.err
    result = json.loads((tmp_path / "a").read_text())
    preview = cv2.imread(result["preview"], cv2.IMREAD_UNCHANGED)
    assert preview.shape == (32, 40) and preview.dtype.name == "uint8" and preview.mean() > 100  # ~70 % of range
    assert not result["dark"] and min(result["signal_dn"]) > 1000

    dark = tmp_path / "dark"  # the camera sees only uv: with deep_red on its frames are black
    assert main(["rig", str(rig_path), "acquire", str(dark), "--light", "deep_red", "--exposure-s", "0.01"]) == 0
    err = capsys.readouterr().err
    warnings = [line for line in err.splitlines() if "warning" in line]
    assert len(warnings) == 1 and "no signal" in warnings[0]
    assert (dark / "preview.png").is_file()
    assert cv2.imread(str(dark / "preview.png"), cv2.IMREAD_UNCHANGED).max() < 10  # shown dark, not stretched


def test_move_then_position_in_two_commands_against_scopetwin_emulate(tmp_path, capsys):
    with emulator("pi-gcs", "travel_mm=0,150") as (port, proc):
        rig = tmp_path / "stage.toml"
        rig.write_text(f'[devices.x]\nkind = "stage"\ndriver = "pi-gcs"\nport = "{port}"\ntravel_mm = [0.0, 150.0]\n')
        assert main(["rig", str(rig), "move", "x", "12.5"]) == 0
        assert main(["rig", str(rig), "position", "x", "--json", str(tmp_path / "p.json")]) == 0
        assert json.loads((tmp_path / "p.json").read_text()) == {"device": "x", "position_mm": 12.5}
        code, out, err = stop(proc)
    assert code == 0 and '"position_mm": 12.5' in out, err
