"""scopetwin.sim.signals: SIGTERM and SIGHUP end a command like Ctrl-C — one line, exit 128 + n, nothing half-written.

The subprocess tests run a command that waits inside a study (registered by a small driver script) and signal it
there; the dataset generator under signals is in ``test_dataset_kill.py``.
"""

from __future__ import annotations

import os
import pickle
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from scopetwin.cli import main
from scopetwin.sim import signals
from scopetwin.sim.studies import runner
from scopetwin.sim.studies.context import StudyContext, StudyResult
from scopetwin.sim.studies.tables import Row, Table

ROOT = Path(__file__).resolve().parents[2]


def test_terminated_is_a_keyboard_interrupt_with_its_signal():
    exc = signals.Terminated(signal.SIGTERM)
    assert isinstance(exc, KeyboardInterrupt) and exc.signum == 15
    assert signals.exit_status(exc) == 143 and signals.exit_status(KeyboardInterrupt()) == 130
    assert signals.describe(signals.Terminated(signal.SIGHUP)) == "interrupted by SIGHUP"
    assert signals.describe(KeyboardInterrupt()) == "interrupted by SIGINT"
    assert pickle.loads(pickle.dumps(exc)).signum == 15


def test_handlers_are_installed_and_restored_and_ignored_signals_stay_ignored():
    before = signal.getsignal(signal.SIGTERM)
    old_hup = signal.signal(signal.SIGHUP, signal.SIG_IGN)  # as under nohup
    try:
        with pytest.raises(signals.Terminated) as info, signals.terminate_on_signals():
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)  # interrupted at once
        assert info.value.signum == signal.SIGTERM
        assert signal.getsignal(signal.SIGTERM) is before
    finally:
        signal.signal(signal.SIGHUP, old_hup)


def test_deferred_signals_hold_a_signal_until_the_block_ends():
    done = []
    with pytest.raises(signals.Terminated), signals.terminate_on_signals():
        with signals.deferred_signals():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.05)
            done.append("clean-up finished")
    assert done == ["clean-up finished"]
    # inside an interruption's clean-up a second signal is dropped: the first one is the one reported
    with pytest.raises(KeyboardInterrupt) as info, signals.terminate_on_signals():
        try:
            raise KeyboardInterrupt
        finally:
            with signals.deferred_signals():
                os.kill(os.getpid(), signal.SIGTERM)
                time.sleep(0.05)
    assert not isinstance(info.value, signals.Terminated)


def test_main_turns_sigterm_into_one_line_and_143_and_discards_the_study(tmp_path, monkeypatch, capsys):
    def slow(ctx: StudyContext) -> StudyResult:
        (ctx.out / "partial.txt").write_text("half")
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)
        return StudyResult("never", "", [Table("T", [Row("a", 1.0, 1.0, "")])])

    monkeypatch.setitem(runner.STUDIES, "slow", slow)
    code = main(["study", "slow", "--out", str(tmp_path / "rep"), "--workers", "0", "--quiet"])
    err = capsys.readouterr().err
    assert code == 143
    assert err == "scopetwin: interrupted by SIGTERM\n"
    assert list(tmp_path.iterdir()) == []


DRIVER = textwrap.dedent(
    """
    import sys, time
    from pathlib import Path
    from scopetwin.cli import main
    from scopetwin.sim.studies import runner
    from scopetwin.sim.studies.context import StudyResult

    def waits(ctx):
        (ctx.out / "partial.txt").write_text("half")
        Path(sys.argv[2]).write_text("ready")
        time.sleep(60)
        return StudyResult("never", "", [])

    runner.STUDIES["waits"] = waits
    out = sys.argv[1]
    sys.exit(main(["study", "waits", "--out", out, "--workers", "0", "--quiet", "--json", out + ".json"]))
    """
)


def _start_waiting_study(tmp_path: Path, *prefix: str) -> subprocess.Popen:
    """The driver in its own session (``prefix``: a command it runs under, e.g. ``nohup``), once its study waits."""
    out, ready = tmp_path / "report", tmp_path / "ready"
    proc = subprocess.Popen(
        [*prefix, sys.executable, "-c", DRIVER, str(out), str(ready)],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        t0 = time.monotonic()
        while not ready.exists():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() - t0 < 60, "the study did not start"
            time.sleep(0.05)
    except BaseException:
        proc.kill()
        proc.wait()
        raise
    return proc


def _signal_and_wait(proc: subprocess.Popen, sig: int) -> str:
    """Send ``sig`` to the driver's whole group, as a terminal, `timeout` or a batch system does; its stderr."""
    try:
        os.killpg(proc.pid, sig)
        _, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return err


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT], ids=lambda s: signal.Signals(s).name)
def test_a_signalled_study_process_prints_one_line_and_leaves_nothing(tmp_path, sig):
    proc = _start_waiting_study(tmp_path)
    err = _signal_and_wait(proc, sig)
    assert proc.returncode == 128 + sig, err
    assert err == f"scopetwin: interrupted by {signal.Signals(sig).name}\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ready"]  # no report, no staging folder, no JSON


@pytest.mark.skipif(shutil.which("nohup") is None, reason="no nohup here")
def test_a_command_under_nohup_survives_a_hangup_and_still_ends_cleanly_on_sigterm(tmp_path):
    """SIGHUP ignored when the command starts (``nohup scopetwin ...``) stays ignored: the user asked for the command
    to outlive the terminal. SIGTERM and SIGINT still end it with one line and nothing half-written."""
    proc = _start_waiting_study(tmp_path, shutil.which("nohup") or "nohup")
    os.killpg(proc.pid, signal.SIGHUP)
    time.sleep(1.0)
    assert proc.poll() is None, proc.communicate()
    err = _signal_and_wait(proc, signal.SIGTERM)
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert err == "scopetwin: interrupted by SIGTERM\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ready"]


def test_the_signal_tests_pass_in_a_suite_started_with_sighup_ignored(tmp_path):
    """A suite started under ``nohup`` inherits SIGHUP ignored, and so would every command it starts (a hangup then
    ends nothing): the suite's conftest gives its children the default action back, so the SIGHUP case above still
    sees its command end cleanly with 129 there."""
    node = f"{Path(__file__).relative_to(ROOT)}::test_a_signalled_study_process_prints_one_line_and_leaves_nothing"
    code = textwrap.dedent(
        f"""
        import signal, sys
        import pytest
        signal.signal(signal.SIGHUP, signal.SIG_IGN)  # as under nohup
        sys.exit(pytest.main(["-q", "-p", "no:cacheprovider", "--basetemp", sys.argv[1], {node + "[SIGHUP]"!r}]))
        """
    )
    proc = subprocess.run(
        [sys.executable, "-c", code, str(tmp_path / "inner")],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdin=subprocess.DEVNULL,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "1 passed" in proc.stdout


def test_sigterm_during_a_render_leaves_no_output(tmp_path, monkeypatch, capsys):
    import scopetwin.sim.measurement as measurement

    real = measurement.write_measurement

    def write_then_signal(stage, *a, **k):
        names = real(stage, *a, **k)  # the files are staged ...
        os.kill(os.getpid(), signal.SIGTERM)  # ... and the job is cancelled before they are moved into place
        time.sleep(5)
        return names

    monkeypatch.setattr(measurement, "write_measurement", write_then_signal)  # the command imports it when run
    setup = tmp_path / "small.toml"
    setup.write_text('base = "thesis-2.8.1-angular"\n[camera]\npixels = [68, 51]\npixel_pitch = 0.093\n')
    code = main(["render", str(setup), "--out", str(tmp_path / "o"), "--renderer", "analytic", "--spp", "1"])
    assert code == 143 and capsys.readouterr().err == "scopetwin: interrupted by SIGTERM\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["small.toml"]


def test_an_interrupted_program_ends_within_its_grace_even_if_a_thread_never_finishes():
    """``exit_within``: after the one line, a non-daemon thread a library left blocked (the interpreter would join it
    for ever) does not keep the process alive past the grace; the status and what was printed survive."""
    code = textwrap.dedent(
        """
        import sys, threading
        from scopetwin.sim import signals
        threading.Thread(target=threading.Event().wait).start()  # non-daemon, never ends
        print("scopetwin: interrupted by SIGTERM", file=sys.stderr)
        print("listed", flush=False)
        signals.exit_within(143, 0.5)
        """
    )
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, timeout=60, cwd=ROOT)
    assert proc.returncode == 143 and proc.stdout == b"listed\n"
    assert proc.stderr == b"scopetwin: interrupted by SIGTERM\n"
    assert time.monotonic() - t0 < 30


def test_the_program_arms_the_grace_only_after_an_interruption(monkeypatch):
    """``console_main`` arms :func:`signals.exit_within` for 128 + n only; ``main`` (used in-process) never does."""
    import scopetwin.cli as cli

    armed: list[int] = []
    monkeypatch.setattr(signals, "exit_within", lambda status, *a: armed.append(status))
    for status in (0, 2, 143):
        monkeypatch.setattr(cli, "main", lambda status=status: status)
        assert cli.console_main() == status
    assert armed == [143]
