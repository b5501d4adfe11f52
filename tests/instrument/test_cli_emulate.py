"""``scopetwin emulate``: each wire-protocol emulator in its own process, driven by clients others wrote (pipython)
and by the project's own drivers; the port on the first stdout line, a JSON log, a clean stop on SIGTERM/SIGINT."""

from __future__ import annotations

import json
import signal

import pytest

from scopetwin.cli import main
from scopetwin.instrument.drivers.fpga_board import FpgaBoard, FpgaLight
from scopetwin.instrument.drivers.jena_piezo import DIALECTS, JenaPiezoFocus
from scopetwin.instrument.transport import open_transport
from tests.instrument.cli_processes import emulator, stop


def _records(log):
    return [json.loads(line) for line in log.read_text().splitlines()]


def test_pi_gcs_emulator_drives_pipython(tmp_path):
    pytest.importorskip("pipython", reason="pipython (dev extra) is not installed")
    from pipython import GCSDevice, pitools
    from pipython.pidevice.interfaces.piserial import PISerial

    log = tmp_path / "pi.jsonl"
    with emulator("pi-gcs", "travel_mm=0,150", "max_velocity_mm_s=50", log=log) as (port, proc):
        gateway = PISerial(port, 115200)
        gateway.settimeout(1000)
        with GCSDevice(gateway=gateway) as device:
            pitools.startup(device, refmodes="FRF")
            device.MOV("1", 7.5)
            pitools.waitontarget(device, axes="1")
            assert device.qPOS("1")["1"] == pytest.approx(7.5)
        gateway.close()
        code, out, err = stop(proc, signal.SIGTERM)
    assert code == 0, err
    lines = out.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"emulate: pi-gcs on {port} stopped after")
    assert "Traceback" not in err
    records = _records(log)
    assert records[0]["request"] == "CSV?" and records[0]["reply"] == "2.0\n"
    moved = [r for r in records if r["request"] == "MOV 1 7.5"]
    assert moved and moved[0]["state"]["referenced"] and moved[0]["state"]["servo"]
    assert records[-1]["state"]["position_mm"] == pytest.approx(7.5)


def test_fpga_board_emulator_logs_lights_on(tmp_path):
    log = tmp_path / "board.jsonl"
    with emulator("fpga-board", log=log) as (port, proc):
        transport = open_transport(port, baudrate=115200, timeout_s=0.02)
        try:
            light = FpgaLight("halogen", FpgaBoard(transport), channel=2, max_current_ma=1000.0)
            light.initialize()
            light.switch_on(250.0)
            light.switch_off()
        finally:
            transport.close()
        code, out, err = stop(proc, signal.SIGINT)  # Ctrl-C ends it as cleanly as SIGTERM
    assert code == 0, err
    assert out.strip().startswith("emulate: fpga-board") and '"lights_on": []' in out
    records = _records(log)
    assert records[0]["request"].startswith("02 7f 00")  # the identification read, as hex bytes
    on = [r for r in records if r["request"] == "01 1a 01 01"]  # light 2's action register: 1 = on
    assert on and on[0]["state"]["lights_on"] == [2]
    assert records[-1]["state"]["lights_on"] == []


def test_jena_nv40_1_emulator_moves_the_focus(tmp_path):
    log = tmp_path / "piezo.jsonl"
    with emulator("jena-piezo", "--model", "nv40-1", log=log) as (port, proc):
        dialect = DIALECTS["nv40-1"]
        transport = open_transport(port, baudrate=dialect.baudrate, timeout_s=0.05, xonxoff=dialect.xonxoff)
        try:
            focus = JenaPiezoFocus("focus", transport, model="nv40-1")
            focus.initialize()
            focus.move_absolute_um(123.5)
            assert focus.position_um == pytest.approx(123.5, abs=0.01)
        finally:
            transport.close()
        code, _, err = stop(proc)
    assert code == 0, err
    records = _records(log)
    requests = [r["request"] for r in records]
    assert requests[0] == "i1" and "cl" in requests  # remote on, closed loop (NV40/1 CLE)
    assert "wr,123.500" in requests and requests.index("cl") < requests.index("wr,123.500")
    last = records[-1]["state"]
    assert last["position_um"] == pytest.approx(123.5) and last["loop"] == "closed" and last["remote"] is True


@pytest.mark.parametrize(
    "args, message",
    [
        (["fpga-board", "--model", "x"], "drop --model"),
        (["jena-piezo", "--model", "nv99"], "unknown jena model"),
        (["pi-gcs", "travel_mm"], "not KEY=VALUE"),
        (["pi-gcs", "colour=3"], "bad option"),
    ],
)
def test_bad_emulator_options_are_one_line_exit_2(args, message, capsys):
    assert main(["emulate", *args]) == 2
    out, err = capsys.readouterr()
    assert out == "" and err.count("\n") == 1 and err.startswith("scopetwin: error:") and message in err
