"""The one signal policy of the command line: SIGTERM and SIGHUP end a command the way Ctrl-C does.

A batch system cancelling a job (SIGTERM), ``timeout`` (SIGTERM) and a dropped terminal session (SIGHUP) must leave
the same state behind as Ctrl-C (SIGINT): lights off and shutters closed, staged outputs discarded, every finished
dataset sample listed in the manifest. Python turns SIGINT into :class:`KeyboardInterrupt`; while
:func:`terminate_on_signals` is active (:func:`scopetwin.cli.main` runs every command inside it), SIGTERM and SIGHUP
raise :class:`Terminated`, a :class:`KeyboardInterrupt` that carries the signal number. So every
``except KeyboardInterrupt`` or ``finally`` clean-up of the package (and of the instrument layer, which catches
``KeyboardInterrupt`` to switch lights off) runs for all three signals, and :func:`exit_status` gives the shell's
convention, 128 + n.

:func:`deferred_signals` (the one implementation, :mod:`scopetwin.instrument.interrupts`, re-exported here) protects a
short clean-up (writing the manifest lines of finished samples) from a second signal: signals that arrive inside the
block are held and delivered to these handlers when it ends, or dropped when the block runs because of an earlier
interruption. :func:`ignore_interrupts_in_worker` is run by every Dask worker process the package starts
(a Dask *preload*): the client, not each worker, handles Ctrl-C, so a terminal's SIGINT to the whole process group
prints no worker tracebacks.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Iterator, Sequence
from types import FrameType
from typing import Any

from scopetwin.instrument.interrupts import HELD_SIGNALS, available_signals, deferred_signals

#: The signals that :func:`terminate_on_signals` turns into :class:`Terminated` (SIGINT stays KeyboardInterrupt);
#: SIGHUP only where the platform has it (not on Windows).
TERMINATING: tuple[signal.Signals, ...] = available_signals("SIGTERM", "SIGHUP")
#: Every signal the policy covers (those :func:`deferred_signals` holds).
INTERRUPTING: tuple[signal.Signals, ...] = HELD_SIGNALS


def signal_name(signum: int) -> str:
    """``SIGTERM`` for 15, ...; ``signal N`` for a number without a name."""
    try:
        return signal.Signals(signum).name
    except ValueError:
        return f"signal {signum}"


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP arrived: the command stops as after Ctrl-C; ``signum`` says which signal it was."""

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        super().__init__(signal_name(self.signum))

    def __reduce__(self) -> tuple[Any, tuple[int]]:  # picklable with its signal number
        return (type(self), (self.signum,))


def interrupt_signal(exc: BaseException) -> int:
    """The signal behind an interruption: ``exc.signum`` for :class:`Terminated`, SIGINT for a KeyboardInterrupt."""
    return exc.signum if isinstance(exc, Terminated) else int(signal.SIGINT)


def exit_status(exc: BaseException) -> int:
    """The exit status of a command stopped by ``exc``: 128 + the signal number (130 for Ctrl-C, 143 for SIGTERM)."""
    return 128 + interrupt_signal(exc)


def describe(exc: BaseException) -> str:
    """The one line printed for an interruption, e.g. ``interrupted by SIGTERM``."""
    return f"interrupted by {signal_name(interrupt_signal(exc))}"


def _raise_terminated(signum: int, frame: FrameType | None) -> None:
    raise Terminated(signum)


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


@contextlib.contextmanager
def terminate_on_signals(signals: Sequence[int] = TERMINATING) -> Iterator[None]:
    """Within the block, ``signals`` (default SIGTERM, SIGHUP) raise :class:`Terminated` in the main thread.

    A signal that was ignored when the block started stays ignored (``nohup`` ignores SIGHUP; a shell's background
    job ignores SIGINT), and the previous handlers come back at the end. Outside the main thread (where Python
    cannot install handlers) the block runs unchanged.
    """
    if not _in_main_thread():
        yield
        return
    previous: dict[int, Any] = {}
    try:
        for s in signals:
            current = signal.getsignal(s)
            if current is not signal.SIG_IGN and current is not None:  # None: not installed from Python, kept
                previous[s] = signal.signal(s, _raise_terminated)
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


#: Seconds an interrupted command's process may take to end after its one line (the interpreter joining threads and
#: running exit hooks, e.g. a library closing a cluster again) before :func:`exit_within` ends it at once.
EXIT_GRACE_S = 10.0


def exit_within(status: int, seconds: float = EXIT_GRACE_S) -> threading.Timer:
    """End this process with ``status`` if it is still running ``seconds`` from now (a daemon timer).

    For the command line's entry point after an interruption: the command's own clean-up (lights off, samples listed,
    staged outputs removed) has run and its line is printed; what remains is the interpreter's shutdown, which
    waits for every non-daemon thread and exit hook a library left behind. A batch system that sent SIGTERM waits a
    grace period and then kills; so the process ends within ``seconds`` with ``status``, stdout and stderr flushed.
    Never called by the library (it would end a host process such as a test runner).
    """

    def _end() -> None:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os._exit(status)

    timer = threading.Timer(seconds, _end)
    timer.daemon = True
    timer.start()
    return timer


def ignore_interrupts_in_worker() -> None:
    """In a worker process: ignore SIGINT and SIGHUP (the client stops its workers; SIGTERM still ends one)."""
    if _in_main_thread():
        for s in available_signals("SIGINT", "SIGHUP"):
            signal.signal(s, signal.SIG_IGN)


def dask_setup(worker: Any = None) -> None:
    """Dask preload hook (``distributed.worker.preload = ["scopetwin.sim.signals"]``):
    :func:`ignore_interrupts_in_worker`."""
    ignore_interrupts_in_worker()


__all__ = [
    "EXIT_GRACE_S",
    "INTERRUPTING",
    "TERMINATING",
    "Terminated",
    "dask_setup",
    "deferred_signals",
    "describe",
    "exit_status",
    "exit_within",
    "ignore_interrupts_in_worker",
    "interrupt_signal",
    "signal_name",
    "terminate_on_signals",
]
