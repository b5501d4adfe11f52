"""``scopetwin`` commands in their own processes, as a user starts them: an emulator, a device server, a rig."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def scopetwin(*args: str, **kwargs) -> subprocess.Popen:
    """``python -m scopetwin.cli ARGS`` from the repository root, stdout and stderr piped as text."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(
        [sys.executable, "-m", "scopetwin.cli", *args],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        **kwargs,
    )


def stop(proc: subprocess.Popen, sig: int = signal.SIGTERM, timeout_s: float = 20.0) -> tuple[int, str, str]:
    """Send ``sig``, wait for the exit; return (exit status, rest of stdout, stderr)."""
    if proc.poll() is None:
        proc.send_signal(sig)
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        raise AssertionError(f"process did not end within {timeout_s} s after signal {sig}: {err[-2000:]}") from None
    return proc.returncode, out, err


@contextlib.contextmanager
def emulator(kind: str, *options: str, log: Path | None = None) -> Iterator[tuple[str, subprocess.Popen]]:
    """``scopetwin emulate KIND OPTIONS [--log LOG]`` in its own process; yields (port path, process).

    The process gets SIGTERM on exit of the block if it still runs.
    """
    args = ["emulate", kind, *options] + (["--log", str(log)] if log is not None else [])
    proc = scopetwin(*args)
    try:
        assert proc.stdout is not None
        port = proc.stdout.readline().strip()
        if not port.startswith("/dev/"):
            _, _, err = stop(proc)
            raise AssertionError(f"first stdout line is not a port: {port!r}; stderr: {err[-2000:]}")
        yield port, proc
    finally:
        if proc.poll() is None:
            stop(proc)
