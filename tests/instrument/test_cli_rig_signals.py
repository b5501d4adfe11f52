"""SIGTERM and SIGHUP during ``rig acquire`` on the emulated-hardware rig whose FPGA board is a
``scopetwin emulate fpga-board`` in its own process: the board's log shows every light off afterwards, the frames
on disk are exactly those of the manifest, one line names the signal, exit 128 + n, no traceback (and Ctrl-C alike)."""

from __future__ import annotations

import json
import signal
import time

import pytest

from tests.instrument.cli_processes import ROOT, emulator, scopetwin, stop

EMULATED = ROOT / "rigs" / "emulated-hardware.toml"


def _rig_on_board(tmp_path, port):
    """The emulated-hardware rig with its board on ``port`` (stages and focus stay on in-process emulators)."""
    text = EMULATED.read_text()
    assert '"emu://fpga-board"' in text
    path = tmp_path / "rig.toml"
    path.write_text(text.replace('"emu://fpga-board"', f'"{port}"'))
    return path


def _frames_listed(manifest_path):
    try:
        return json.loads(manifest_path.read_text())["frames"]
    except (OSError, ValueError, KeyError):
        return []


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_signal_during_acquire_switches_the_board_off_and_keeps_the_manifest(tmp_path, sig):
    log = tmp_path / "board.jsonl"
    with emulator("fpga-board", log=log) as (port, board):
        rig = _rig_on_board(tmp_path, port)
        out = tmp_path / "frames"
        args = ["rig", str(rig), "acquire", str(out), "--frames", "100000", "--light", "halogen"]
        proc = scopetwin(*args, "--exposure-s", "0.01")
        deadline = time.monotonic() + 60.0
        while len(_frames_listed(out / "manifest.json")) < 3 and time.monotonic() < deadline:
            assert proc.poll() is None, proc.communicate()[1]
            time.sleep(0.05)
        records = [json.loads(line) for line in log.read_text().splitlines()]
        assert records[-1]["state"]["lights_on"] == [2]  # halogen (channel 2) is on mid-acquisition
        code, stdout, stderr = stop(proc, sig)
        lines = [line for line in stderr.splitlines() if line.strip()]
        assert code == 128 + sig, stderr[-3000:]
        assert "Traceback" not in stderr and lines and signal.Signals(sig).name in lines[-1]
        time.sleep(0.1)  # the board's last reply is logged before its process answers the next
        records = [json.loads(line) for line in log.read_text().splitlines()]
        assert records[-1]["state"]["lights_on"] == []  # every light off, on the board itself
        code, _, err = stop(board)
        assert code == 0, err
    manifest = json.loads((out / "manifest.json").read_text())
    on_disk = sorted(p.name for p in out.glob("*.exr"))
    assert len(on_disk) >= 3 and on_disk == sorted(f["path"] for f in manifest["frames"])
    assert not manifest["complete"] and signal.Signals(sig).name in manifest["error"]
    assert not list(out.glob(".*.part*"))  # no half-written file left behind
