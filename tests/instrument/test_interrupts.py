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


# --- the one deferred_signals: what the command line's clean-ups need as well -----------------------------


def test_the_command_line_uses_this_one_implementation():
    from scopetwin.sim import signals

    assert signals.deferred_signals is deferred_signals


def test_an_ignored_signal_stays_ignored_and_is_not_reported(raising_sigterm):
    seen = []
    old_hup = signal.signal(signal.SIGHUP, signal.SIG_IGN)  # as under nohup
    try:
        with deferred_signals(on_signal=seen.append) as received:
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGHUP)
        assert received == [] and seen == []  # and nothing raised
    finally:
        signal.signal(signal.SIGHUP, old_hup)


def test_interruption_hands_the_signal_to_a_caller_that_tidies_up_first(raising_sigterm):
    shield = deferred_signals()
    with shield:
        assert shield.interruption() is None  # nothing arrived yet
        os.kill(os.getpid(), signal.SIGTERM)
        stop = shield.interruption()  # what the caller's handler raises, for the caller to raise after tidying up
        assert isinstance(stop, Stopped) and stop.signum == signal.SIGTERM
        assert shield.interruption() is stop
    # taken by the caller: the end of the block did not deliver it a second time (nothing raised here)
    assert shield.received == [signal.SIGTERM]


def test_a_nested_block_passes_the_signal_to_the_outer_one(raising_sigterm):
    steps = []
    with pytest.raises(Stopped), deferred_signals() as outer:
        with deferred_signals() as inner:
            os.kill(os.getpid(), signal.SIGTERM)
        steps.append("inner ended")  # the outer block still holds it
        assert inner == [signal.SIGTERM] and outer == [signal.SIGTERM]
    assert steps == ["inner ended"]


def test_outside_the_main_thread_nothing_is_held(raising_sigterm):
    out: dict[str, object] = {}

    def worker():
        with deferred_signals() as received:
            out["handler"] = signal.getsignal(signal.SIGTERM)
            out["received"] = received

    t = threading.Thread(target=worker)
    t.start()
    t.join()
    assert out["received"] == [] and getattr(out["handler"], "__name__", "") == "handler"


def test_held_signals_are_those_the_platform_has(monkeypatch):
    from scopetwin.instrument.interrupts import HELD_SIGNALS, available_signals

    assert HELD_SIGNALS == (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    monkeypatch.delattr(signal, "SIGHUP")  # as on Windows
    assert available_signals("SIGINT", "SIGTERM", "SIGHUP") == (signal.SIGINT, signal.SIGTERM)


def test_a_default_sigterm_ends_the_process_when_the_block_ends(tmp_path):
    """Without the command line's handlers (a library user's process) the clean-up still finishes first."""
    import subprocess
    import sys
    import textwrap

    script = textwrap.dedent(
        """
        import os, signal, sys
        from pathlib import Path
        from scopetwin.instrument.interrupts import deferred_signals

        with deferred_signals():
            os.kill(os.getpid(), signal.SIGTERM)
            Path(sys.argv[1]).write_text("clean-up finished")
        Path(sys.argv[1]).write_text("ran on after the signal")
        """
    )
    marker = tmp_path / "marker"
    proc = subprocess.run([sys.executable, "-c", script, str(marker)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == -signal.SIGTERM, proc.stderr
    assert marker.read_text() == "clean-up finished"
