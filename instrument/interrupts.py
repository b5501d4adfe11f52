"""Hold SIGINT, SIGTERM and SIGHUP across a step that must finish once started.

Hardware clean-up and file bookkeeping must not be cut in half by a signal: a
frame on disk whose manifest entry was never written, a light left on because
the clean-up itself was interrupted, an OME file whose sink was never closed.
:func:`deferred_signals` replaces the handlers of the three signals for the
length of a ``with`` block by a recorder; when the block ends the old handlers
come back and the first signal that arrived is delivered to its handler then
(the CLI's handler turns it into an exception; Python's default SIGINT handler
raises :class:`KeyboardInterrupt`; a default SIGTERM/SIGHUP ends the process by
that signal) — unless the block raised or runs while an earlier interruption
propagates: the command is stopping already, and the held signal is dropped
(the policy of the CLI's own clean-ups, ``sim.signals``). ``on_signal`` lets a
long step stop early and cleanly (a Micro-Manager MDA cancels at the next event
boundary).

A server that ends on a signal as its normal way of ending (``scopetwin rig RIG serve``,
``scopetwin emulate``) uses :func:`stop_on_signals` instead: the signal sets an event and is
not delivered again.

Signal handlers belong to the main thread: elsewhere the block runs unchanged.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
from collections.abc import Callable, Iterator
from typing import Any

HELD_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def _deliver(signum: int, handler: Any) -> None:
    """Hand ``signum`` to ``handler`` as the kernel would have done."""
    if callable(handler):
        handler(signum, None)
    elif handler == signal.SIG_IGN:
        return
    elif signum == signal.SIGINT:
        raise KeyboardInterrupt
    else:  # SIG_DFL (or a handler not installed from Python): end the process by the signal
        os.kill(os.getpid(), signum)


@contextlib.contextmanager
def deferred_signals(on_signal: Callable[[int], None] | None = None) -> Iterator[list[int]]:
    """Record SIGINT/SIGTERM/SIGHUP during the block; deliver the first one when it ends.

    Parameters
    ----------
    on_signal : callable, optional
        Called with the signal number as each signal arrives (in the main thread, between two
        bytecodes of the block: keep it short and lock-free, e.g. set an event).

    Yields
    ------
    list of int
        The signals received so far (in order).
    """
    received: list[int] = []
    if threading.current_thread() is not threading.main_thread():
        yield received
        return

    def record(signum: int, _frame: Any) -> None:
        received.append(signum)
        if on_signal is not None:
            on_signal(signum)

    previous = {sig: signal.signal(sig, record) for sig in HELD_SIGNALS}
    try:
        yield received
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        # a block that raised, or that runs while an earlier interruption propagates, is stopping already:
        # the held signal is dropped rather than replacing that exception
        if received and sys.exc_info()[1] is None:
            _deliver(received[0], previous[signal.Signals(received[0])])


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
    if threading.current_thread() is not threading.main_thread():
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


__all__ = ["HELD_SIGNALS", "deferred_signals", "stop_on_signals"]
