"""The one signal policy of the command line: SIGTERM and SIGHUP end a command the way Ctrl-C does.

A batch system cancelling a job (SIGTERM), ``timeout`` (SIGTERM) and a dropped terminal session (SIGHUP) must leave
the same state behind as Ctrl-C (SIGINT): lights off and shutters closed, staged outputs discarded, every finished
dataset sample listed in the manifest. Python turns SIGINT into :class:`KeyboardInterrupt`; while
:func:`terminate_on_signals` is active (``sim.cli.main`` runs every command inside it), SIGTERM and SIGHUP raise
:class:`Terminated`, a :class:`KeyboardInterrupt` that carries the signal number. So every ``except KeyboardInterrupt``
or ``finally`` clean-up of the package (and of the instrument layer, which catches ``KeyboardInterrupt`` to switch
lights off) runs for all three signals, and :func:`exit_status` gives the shell's convention, 128 + n.

:func:`deferred_signals` protects a short clean-up (writing the manifest lines of finished samples) from a second
signal: signals that arrive inside the block are held and raised when it ends, or dropped when the block runs because
of an earlier interruption. :func:`ignore_interrupts_in_worker` is run by every Dask worker process the package starts
(a Dask *preload*): the client, not each worker, handles Ctrl-C, so a terminal's SIGINT to the whole process group
prints no worker tracebacks.
"""

from __future__ import annotations

import contextlib
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from types import FrameType, TracebackType
from typing import Any

#: The signals that :func:`terminate_on_signals` turns into :class:`Terminated` (SIGINT stays KeyboardInterrupt).
TERMINATING: tuple[signal.Signals, ...] = (signal.SIGTERM, signal.SIGHUP)
#: Every signal the policy covers.
INTERRUPTING: tuple[signal.Signals, ...] = (signal.SIGINT, *TERMINATING)


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
            if signal.getsignal(s) is not signal.SIG_IGN:
                previous[s] = signal.signal(s, _raise_terminated)
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


class deferred_signals:  # noqa: N801 - used like a function: ``with deferred_signals():``
    """Hold SIGINT, SIGTERM and SIGHUP during a short clean-up; raise the first one when the block ends.

    When the block itself runs because of an earlier interruption (inside an ``except``/``finally`` of it) or raises,
    a held signal is dropped: the command is already stopping. ``on_signal(signum)`` is called as each one arrives;
    :meth:`interruption` gives the exception to raise for a caller that must tidy up first. Outside the main thread
    this does nothing.
    """

    def __init__(self, on_signal: Callable[[int], None] | None = None) -> None:
        self.pending: list[int] = []
        self.on_signal = on_signal
        self._previous: dict[int, Any] = {}

    def _hold(self, signum: int, frame: FrameType | None) -> None:
        self.pending.append(signum)
        if self.on_signal is not None:
            self.on_signal(signum)

    def interruption(self) -> KeyboardInterrupt | None:
        """The exception of the first held signal (:class:`Terminated`, or KeyboardInterrupt for SIGINT), or None."""
        if not self.pending:
            return None
        first = self.pending[0]
        return KeyboardInterrupt() if first == signal.SIGINT else Terminated(first)

    def __enter__(self) -> deferred_signals:
        if _in_main_thread():
            for s in INTERRUPTING:
                current = signal.getsignal(s)
                if current not in (signal.SIG_IGN, signal.SIG_DFL, None):
                    self._previous[s] = signal.signal(s, self._hold)
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        for s, handler in self._previous.items():
            signal.signal(s, handler)
        self._previous.clear()
        interruption = self.interruption()
        if interruption is not None and exc_type is None and sys.exc_info()[1] is None:
            raise interruption


def ignore_interrupts_in_worker() -> None:
    """In a worker process: ignore SIGINT and SIGHUP (the client stops its workers; SIGTERM still ends one)."""
    if _in_main_thread():
        for s in (signal.SIGINT, signal.SIGHUP):
            signal.signal(s, signal.SIG_IGN)


def dask_setup(worker: Any = None) -> None:
    """Dask preload hook (``distributed.worker.preload = ["scopetwin.sim.signals"]``):
    :func:`ignore_interrupts_in_worker`."""
    ignore_interrupts_in_worker()
