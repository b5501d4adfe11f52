"""scopetwin.instrument.emulators.serve: an emulator on a pty with a JSON log (in its own process:
test_cli_emulate.py)."""

from __future__ import annotations

import json
import threading
import time

import pytest
import serial

from scopetwin.instrument.drivers.fpga_board import FpgaBoard, FpgaLight
from scopetwin.instrument.emulators.serve import parse_options, serve
from scopetwin.instrument.errors import RigError


def test_parse_options():
    assert parse_options(["travel_mm=0,150", "max-velocity-mm-s=50", "model=C-863.11"]) == {
        "travel_mm": (0.0, 150.0),
        "max_velocity_mm_s": 50.0,
        "model": "C-863.11",
    }
    with pytest.raises(RigError):
        parse_options(["travel_mm"])


def test_board_log_records_requests_and_lights_on(tmp_path):
    log = tmp_path / "board.jsonl"
    stop = threading.Event()
    ports: list[str] = []
    result: dict = {}
    thread = threading.Thread(
        target=lambda: result.update(serve("fpga-board", log_path=log, announce=ports.append, stop=stop))
    )
    thread.start()
    try:
        deadline = time.monotonic() + 5.0
        while not ports and time.monotonic() < deadline:
            time.sleep(0.01)
        port = serial.Serial(ports[0], 115200, timeout=0.02)
        light = FpgaLight("led", FpgaBoard(port), channel=2, max_current_ma=1000.0)
        light.initialize()
        light.switch_on(100.0)
        light.switch_off()
        port.close()
    finally:
        stop.set()
        thread.join(5.0)
    records = [json.loads(line) for line in log.read_text().splitlines()]
    assert result["requests"] == len(records) >= 4
    assert records[0]["request"].startswith("02 7f 00")  # identification read, as hex bytes
    on = [r for r in records if r["request"] == "01 1a 01 01"]  # light 2 action register: 1 = on
    assert on and on[0]["state"]["lights_on"] == [2] and on[0]["reply"] == "81 1a 00"
    assert records[-1]["state"]["lights_on"] == []
