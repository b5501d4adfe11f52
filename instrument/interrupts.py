"""Hold SIGINT, SIGTERM and SIGHUP across a step that must finish once started: the one :func:`deferred_signals`.

Hardware clean-up and file bookkeeping must not be cut in half by a signal: a frame on disk whose manifest entry
was never written, a light left on because the clean-up itself was interrupted, an OME file whose sink was never
closed, a finished dataset sample missing from the manifest, a command's result half moved into place.
:class:`deferred_signals` replaces the handlers of the three signals for the length of a ``with`` block by a
recorder; when the block ends the old handlers come back and the first signal that arrived is delivered to its
handler then (the command line's handler, ``scopetwin.sim.signals.terminate_on_signals``, turns SIGTERM and SIGHUP
into an exception; Python's default SIGINT handler raises :class:`KeyboardInterrupt`; a default SIGTERM/SIGHUP ends
the process by that signal) — unless the block raised or runs while an earlier interruption propagates: the command
is stopping already, and the held signal is dropped. A signal that is ignored when the block starts stays ignored
(``nohup`` ignores SIGHUP). ``on_signal`` lets a long step stop early and cleanly (a Micro-Manager MDA cancels at the
next event boundary; a starting Dask cluster silences its logs), and :meth:`deferred_signals.interruption` lets a
caller that must tidy up first take the held signal's exception inside the block.

A server that ends on a signal as its normal way of ending (``scopetwin rig RIG serve``, ``scopetwin emulate``) uses
:func:`stop_on_signals` instead: the signal sets an event and is not delivered again.

Signal handlers belong to the main thread: elsewhere the blocks run unchanged. Windows has no SIGHUP: the signal
sets here hold only the signals the platform has (:func:`available_signals`).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator, Sequence
from types import TracebackType
from typing import Any


def available_signals(*names: str) -> tuple[signal.Signals, ...]:
    """The signals called ``names`` that this platform has, in order (``SIGHUP`` is POSIX-only)."""
    found = (getattr(signal, name, None) for name in names)
    return tuple(signal.Signals(s) for s in found if s is not None)


#: The signals :class:`deferred_signals` holds: SIGINT, SIGTERM and (where the platform has it) SIGHUP.
HELD_SIGNALS: tuple[signal.Signals, ...] = available_signals("SIGINT", "SIGTERM", "SIGHUP")


def _in_main_thread() -> bool:
    return threading.current_thread() is threading.main_thread()


def _deliver(signum: int, handler: Any) -> None:
    """Hand ``signum`` to ``handler`` as the kernel would have done."""
    if callable(handler):
        handler(signum, None)
    elif handler == signal.SIG_IGN:
        return
    elif signum == signal.SIGINT:
        raise KeyboardInterrupt
    else:  # SIG_DFL: end the process by the signal
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)


class deferred_signals:  # noqa: N801 - used like a function: ``with deferred_signals():``
    """Record SIGINT/SIGTERM/SIGHUP during the block; deliver the first one to its handler when it ends.

    The held signal is dropped when the block raised, or when it runs inside the ``except``/``finally`` of an
    earlier exception (the command is stopping already). Signals that are ignored (or whose handler was not
    installed from Python) when the block starts are left alone. Outside the main thread this does nothing.

    Parameters
    ----------
    on_signal : callable, optional
        Called with the signal number as each signal arrives (in the main thread, between two bytecodes of the
        block: keep it short and lock-free, e.g. set an event).
    signals : sequence of int, optional
        The signals to hold (default :data:`HELD_SIGNALS`).

    Attributes
    ----------
    received : list of int
        The signals received so far, in order; also what ``with deferred_signals() as received`` binds.
    """

    def __init__(self, on_signal: Callable[[int], None] | None = None, signals: Sequence[int] = HELD_SIGNALS) -> None:
        self.received: list[int] = []
        self.on_signal = on_signal
        self._signals = tuple(signals)
        self._previous: dict[int, Any] = {}
        self._handled = False
        self._interruption: BaseException | None = None

    def _record(self, signum: int, _frame: Any) -> None:
        self.received.append(signum)
        if self.on_signal is not None:
            self.on_signal(signum)

    def _handler_of(self, signum: int) -> Any:
        return self._previous.get(signum, signal.getsignal(signum))

    def interruption(self) -> BaseException | None:
        """Deliver the first held signal now and return the exception its handler raised (None if none arrived).

        For a caller inside the block that must tidy up before it stops: it raises the returned exception itself
        (the command line's handlers raise ``Terminated``, Python's SIGINT handler KeyboardInterrupt). The signal
        counts as delivered, so the end of the block does not deliver it again; calling this again returns the
        same exception. A signal whose handler is the default action ends the process here, as it would have on
        arrival; one whose handler returns (an outer block's recorder) gives None.
        """
        if self.received and not self._handled:
            self._handled = True
            signum = self.received[0]
            try:
                _deliver(signum, self._handler_of(signum))
            except BaseException as exc:  # noqa: BLE001 - handed to the caller, who raises it
                self._interruption = exc
        return self._interruption

    def __enter__(self) -> list[int]:
        if _in_main_thread():
            for s in self._signals:
                current = signal.getsignal(s)
                if current is signal.SIG_IGN or current is None:  # ignored stays ignored; None cannot be restored
                    continue
                self._previous[s] = signal.signal(s, self._record)
        return self.received

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        previous, self._previous = self._previous, {}
        for s, handler in previous.items():
            signal.signal(s, handler)
        # a block that raised, or that runs while an earlier interruption propagates, is stopping already:
        # the held signal is dropped rather than replacing that exception
        if self.received and not self._handled and exc_type is None and sys.exc_info()[1] is None:
            self._handled = True
            signum = self.received[0]
            _deliver(signum, previous.get(signum, signal.SIG_DFL))


@contextlib.contextmanager
def stop_on_signals(
    stop: threading.Event, signals: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM)
) -> Iterator[list[int]]:
    """Set ``stop`` on any of ``signals`` during the block (the signal is consumed, not delivered again).

    Yields
    ------
    list of int
        The signals received (the caller names the first in its closing line).
    """
    received: list[int] = []
    if not _in_main_thread():
        yield received
        return

    def record(signum: int, _frame: Any) -> None:
        received.append(signum)
        stop.set()

    previous = {sig: signal.signal(sig, record) for sig in signals}
    try:
        yield received
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


__all__ = ["HELD_SIGNALS", "available_signals", "deferred_signals", "stop_on_signals"]
