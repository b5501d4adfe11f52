"""``scopetwin rig RIG serve``: python-microscope's device server on 127.0.0.1, driven by python-microscope's own
client (signing with the server's key) from another process, stopped by SIGTERM (one line, exit 0); other hosts
refused. The attacks (no key, a wrong key) are in tests/robustness/test_security.py."""

from __future__ import annotations

import os
import re
import signal

import pytest

pytest.importorskip("microscope", reason="python-microscope is not installed")

from scopetwin.cli import main  # noqa: E402
from tests.instrument.cli_processes import scopetwin, stop  # noqa: E402

RIG = """
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
[devices.uv]
kind = "light"
driver = "sim"
max_current_ma = 500.0
[devices.cam]
kind = "camera"
driver = "sim"
sensor_shape = [32, 40]
renderer = { kind = "texture", lights = ["uv"] }
"""


def test_serve_answers_a_python_microscope_client_until_sigterm(tmp_path):
    from functools import partial

    from scopetwin.instrument.pymicroscope import connect

    rig = tmp_path / "rig.toml"
    rig.write_text(RIG)
    proc = scopetwin("rig", str(rig), "serve", "--port", "0")
    try:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        assert line.startswith("serving 3 device(s)") and "on 127.0.0.1" in line, line
        uris = dict(re.findall(r"(\w+)=(PYRO:\S+?@127\.0\.0\.1:\d+)", line))
        assert set(uris) == {"cam", "uv", "xy"}
        key_line = proc.stdout.readline()
        key_file = re.search(r"key in (\S+) ", key_line).group(1)  # a new key per server, only its owner reads it
        assert oct(os.stat(key_file).st_mode & 0o777) == "0o600", key_line
        Client = partial(connect, key=key_file)  # python-microscope's Client with the key  # noqa: N806
        light = Client(uris["uv"])
        light.power = 0.5
        light.enable()
        assert light.get_is_on()
        light.disable()
        assert not light.get_is_on()
        xy = Client(uris["xy"])
        xy.move_to({"x": 12500.0})
        # a Client copies property values when it connects: a new one reads the position after the move
        assert Client(uris["xy"]).position["x"] == pytest.approx(12500.0)  # um, python-microscope's unit
        assert xy.axes["x"].position == pytest.approx(12500.0)  # the axes travel as live proxies
        camera = Client(uris["cam"])
        assert camera.get_sensor_shape() == (40, 32)  # (width, height)
    finally:
        code, out, err = stop(proc, signal.SIGTERM)
    assert code == 0, err
    assert out.strip().splitlines() == ["serve: stopped on SIGTERM"]
    assert "Traceback" not in err and "Exception" not in err  # no complaint from python-microscope at exit
    assert not os.path.exists(key_file)  # the generated key goes with its server


def test_serve_refuses_other_hosts(tmp_path, capsys):
    rig = tmp_path / "rig.toml"
    rig.write_text(RIG)
    assert main(["rig", str(rig), "serve", "--host", "0.0.0.0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "127.0.0.1 only" in err
