"""scopetwin.instrument.interrupts: a signal inside a held block waits for its end; a frame and its manifest entry are
written together even when SIGTERM arrives between them."""

from __future__ import annotations

import json
import os
import signal
import threading

import numpy as np
import pytest

import scopetwin.instrument.acquisition as acquisition
from scopetwin.instrument.acquisition import FrameWriter
from scopetwin.instrument.interrupts import deferred_signals, stop_on_signals


class Stopped(KeyboardInterrupt):
    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


@pytest.fixture
def raising_sigterm():
    """SIGTERM raises :class:`Stopped` (as the CLI's policy does) for the test's length."""

    def handler(signum, _frame):
        raise Stopped(signum)

    previous = signal.signal(signal.SIGTERM, handler)
    yield
    signal.signal(signal.SIGTERM, previous)


def test_signal_in_a_held_block_is_delivered_when_it_ends(raising_sigterm):
    steps = []
    with pytest.raises(Stopped) as stopped, deferred_signals() as received:
        os.kill(os.getpid(), signal.SIGTERM)
        steps.append("after the signal")  # the block runs on
    assert steps == ["after the signal"] and received == [signal.SIGTERM] and stopped.value.signum == signal.SIGTERM


def test_signal_is_dropped_when_the_block_is_stopping_already(raising_sigterm):
    with pytest.raises(RuntimeError, match="first"), deferred_signals():
        os.kill(os.getpid(), signal.SIGTERM)
        raise RuntimeError("first")  # the held SIGTERM does not replace it


def test_on_signal_lets_a_long_step_stop_early(raising_sigterm):
    stop = threading.Event()
    with pytest.raises(Stopped), deferred_signals(on_signal=lambda _s: stop.set()):
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.wait(1.0)


def test_stop_on_signals_consumes_the_signal(raising_sigterm):
    stop = threading.Event()
    with stop_on_signals(stop) as received:
        os.kill(os.getpid(), signal.SIGTERM)
        assert stop.wait(1.0)
    assert received == [signal.SIGTERM]  # and nothing raised


def test_sigterm_between_frame_and_manifest_keeps_them_together(tmp_path, monkeypatch, raising_sigterm):
    real_write = acquisition.write_image

    def write_then_signal(path, *args, **kwargs):
        real_write(path, *args, **kwargs)
        os.kill(os.getpid(), signal.SIGTERM)  # the frame is on disk, its manifest entry not yet

    writer = FrameWriter(tmp_path, {"routine": "test"}, display_range=(0.0, 4095.0))
    writer.write("frame_000", np.full((8, 8), 100.0))
    monkeypatch.setattr(acquisition, "write_image", write_then_signal)
    with pytest.raises(Stopped):
        writer.write("frame_001", np.full((8, 8), 200.0))
    writer.finish(Stopped(signal.SIGTERM))
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert [f["path"] for f in manifest["frames"]] == sorted(p.name for p in tmp_path.glob("*.exr"))
    assert len(manifest["frames"]) == 2 and manifest["error"] == "Stopped: SIGTERM" and not manifest["complete"]
    assert (tmp_path / "preview.png").is_file()
