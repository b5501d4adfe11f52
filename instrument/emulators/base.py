"""Wire-protocol emulators on pseudo-terminals, with a byte log and fault injection.

An emulator opens a pseudo-terminal pair with :func:`os.openpty`; a thread reads
the master side, splits the byte stream into requests (:meth:`PtyEmulator.split`),
answers each (:meth:`PtyEmulator.handle`) and writes the answer back. A driver
opens the slave side (:attr:`PtyEmulator.port`, e.g. ``/dev/pts/5``) as an
ordinary serial port, so the real driver code runs end to end through a real
tty. Every received byte is appended to :attr:`PtyEmulator.log`, which lets a
test prove that nothing was sent when a limit check failed.

Faults (:class:`Fault`) change how answers go out: ``SILENT`` stops answering,
``GARBAGE`` answers bytes that do not follow the protocol, ``DROP`` sends half a
reply and hangs the line up, ``FLOOD`` answers with a stream of bytes that never
ends in a terminator. Assign :attr:`PtyEmulator.fault`, or give the options
``fault=NAME`` and ``fault_after=N`` (the first N requests are answered normally) —
as ``emu://`` URL options or ``scopetwin emulate`` arguments, so a device can stop
answering in the middle of a command.

Every numeric option is checked when the emulator is built (:func:`finite_span`,
:func:`number_in`): finite, and in the range the emulated hardware could have.

:meth:`PtyEmulator.state` describes the emulated device (for logs and for the
simulated devices of the same rig); :attr:`PtyEmulator.on_request`, when set,
is called after every request with ``(request, reply, state)`` — the hook behind
``scopetwin emulate --log`` (:func:`scopetwin.instrument.emulators.serve.serve`).

Pseudo-terminals are POSIX (Linux, macOS): elsewhere (Windows) the emulators import, but starting one
(``scopetwin emulate``, a rig with an ``emu://`` port) raises :class:`EmulatorUnavailable` with one line
(:func:`require_pty`).
"""

from __future__ import annotations

import enum
import math
import os
import select
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from scopetwin.instrument.errors import InstrumentError

#: The one line said where an emulator is started on a platform without pseudo-terminals.
NO_PTY = "emulators need a POSIX pseudo-terminal (Linux, macOS); not available on this platform"


class EmulatorUnavailable(InstrumentError):
    """This platform has no POSIX pseudo-terminal (Windows), so no wire-protocol emulator can run here."""


def pty_available() -> bool:
    """Whether this platform has POSIX pseudo-terminals (:func:`os.openpty`, :mod:`tty`, :mod:`termios`)."""
    if not hasattr(os, "openpty") or not hasattr(os, "ttyname"):
        return False
    try:
        import termios  # noqa: F401 - only whether it imports
        import tty  # noqa: F401
    except ImportError:
        return False
    return True


def require_pty() -> None:
    """Raise :class:`EmulatorUnavailable` (one line) where the platform has no POSIX pseudo-terminal.

    Raises
    ------
    EmulatorUnavailable
        Not on a POSIX platform (Windows).
    """
    if not pty_available():
        raise EmulatorUnavailable(NO_PTY)


class Fault(enum.Enum):
    """Injected misbehaviour of an emulator."""

    NONE = "none"
    SILENT = "silent"
    GARBAGE = "garbage"
    DROP = "drop"
    FLOOD = "flood"


#: Bytes one flooded answer writes at most (far beyond any driver's longest reply).
FLOOD_BYTES = 256 * 1024


def number_in(value: Any, what: str, low: float, high: float) -> float:
    """``value`` as a float if it is a finite number in ``[low, high]``.

    Raises
    ------
    ValueError
        Naming ``what`` and the range (an emulator's bad option).
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a number, got {value!r}") from None
    if not (math.isfinite(v) and low <= v <= high):
        raise ValueError(f"{what} must be a finite number in [{low:g}, {high:g}], got {value!r}")
    return v


def finite_span(value: Any, what: str, low: float, high: float) -> tuple[float, float]:
    """``value`` as ``(a, b)``: two finite numbers in ``[low, high]`` with ``a < b``.

    Raises
    ------
    ValueError
        Naming ``what`` (an emulator's bad option).
    """
    if not isinstance(value, tuple | list) or len(value) != 2:
        raise ValueError(f"{what} must be two numbers LOW,HIGH, got {value!r}")
    a, b = (number_in(v, what, low, high) for v in value)
    if not a < b:
        raise ValueError(f"{what} must rise (LOW < HIGH), got {value!r}")
    return a, b


def _fault_of(name: Any) -> Fault:
    try:
        return Fault(str(name).lower())
    except ValueError:
        raise ValueError(f"fault must be one of {[f.value for f in Fault]}, got {name!r}") from None


class PtyEmulator:
    """Base class: a device that speaks a wire protocol on a pseudo-terminal.

    Parameters
    ----------
    seed : int
        Seed of the generator that produces garbage answers.
    fault : str
        A :class:`Fault` by value (``"silent"``, ``"garbage"``, ``"drop"``, ``"flood"``) that starts after
        ``fault_after`` requests (default ``"none"``).
    fault_after : int
        Requests answered normally before ``fault`` starts.

    Attributes
    ----------
    port : str
        Path of the slave tty (valid after :meth:`start`).
    log : bytearray
        Every byte received, in order.
    fault : Fault
        The current fault; assign to inject one.
    """

    protocol = "base"
    terminator = b"\n"
    on_request: Callable[[bytes, bytes, dict[str, Any]], None] | None = None

    def __init__(self, *, seed: int = 0, fault: str = "none", fault_after: int = 0) -> None:
        self.port = ""
        self.log = bytearray()
        self.fault = Fault.NONE
        self._pending_fault = _fault_of(fault)
        self._fault_after = int(number_in(fault_after, "fault_after", 0, 1e9))
        self._requests = 0
        seed = int(number_in(seed, "seed", 0, 2**32 - 1))
        self.errors: list[str] = []
        self._rng = np.random.default_rng(seed)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._master = -1
        self._slave = -1
        self._lock = threading.RLock()

    # lifecycle ---------------------------------------------------------------------------------
    def start(self) -> str:
        """Open the pseudo-terminal, start answering, and return the slave's path.

        Raises
        ------
        EmulatorUnavailable
            The platform has no POSIX pseudo-terminal (Windows).
        """
        require_pty()
        import tty

        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        tty.setraw(self._master)
        os.set_blocking(self._master, False)  # a client that stops reading never blocks the emulator (stop() ends it)
        self.port = os.ttyname(self._slave)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name=f"{self.protocol}-emulator", daemon=True)
        self._thread.start()
        return self.port

    def stop(self) -> None:
        """Stop the thread and close both ends of the pseudo-terminal."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        for fd in (self._master, self._slave):
            if fd >= 0:
                try:
                    os.close(fd)
                except OSError:
                    pass
        self._master = self._slave = -1

    def __enter__(self) -> PtyEmulator:
        if not self.port:
            self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    @property
    def received(self) -> bytes:
        """A copy of the log of received bytes."""
        with self._lock:
            return bytes(self.log)

    # loop --------------------------------------------------------------------------------------
    def _run(self) -> None:
        buffer = bytearray()
        while not self._stop.is_set():
            master = self._master
            if master < 0:
                return
            try:
                ready, _, _ = select.select([master], [], [], 0.02)
            except (OSError, ValueError):
                return
            if not ready:
                continue
            try:
                data = os.read(master, 4096)
            except BlockingIOError:
                continue
            except OSError:
                return
            if not data:
                continue
            with self._lock:
                self.log += data
                buffer += data
                requests, rest = self.split(bytes(buffer))
                buffer = bytearray(rest)
                for request in requests:
                    self._requests += 1
                    if self._pending_fault is not Fault.NONE and self._requests > self._fault_after:
                        self.fault, self._pending_fault = self._pending_fault, Fault.NONE
                    try:
                        reply = self.handle(request)
                    except Exception as exc:  # noqa: BLE001 - an emulator bug must not kill the line
                        self.errors.append(f"{request[:40]!r}: {exc!r}")
                        continue
                    if self.on_request is not None:
                        try:
                            self.on_request(request, reply, self.state())
                        except Exception as exc:  # noqa: BLE001 - a failing log must not kill the line
                            self.errors.append(f"log: {exc!r}")
                    if reply:
                        self._send(reply)
                        if self._master < 0:
                            return

    def _send(self, reply: bytes) -> None:
        fault = self.fault
        if fault is Fault.SILENT:
            return
        if fault is Fault.FLOOD:
            self._flood()
            return
        if fault is Fault.GARBAGE:
            reply = self.garbage(len(reply))
        if fault is Fault.DROP:
            self._emit(reply[: max(1, len(reply) // 2)])
            time.sleep(0.01)
            os.close(self._master)
            self._master = -1
            return
        self._emit(reply)

    def _flood(self) -> None:
        """Write up to :data:`FLOOD_BYTES` of printable bytes without a terminator, as fast as the line takes them
        (stops when the reader has not taken any for 0.1 s, so the emulator never blocks)."""
        chunk = bytes(self._rng.integers(0x21, 0x7F, size=4096, dtype=np.uint8)).replace(self.terminator or b"\n", b"x")
        sent = 0
        while sent < FLOOD_BYTES and self._master >= 0 and not self._stop.is_set():
            _, writable, _ = select.select([], [self._master], [], 0.1)
            if not writable:
                return
            try:
                sent += os.write(self._master, chunk)
            except BlockingIOError:
                continue
            except OSError:
                return

    def _emit(self, data: bytes) -> None:
        """Write ``data`` to the line; waits while the client's input queue is full, gives up when stopped."""
        view = memoryview(data)
        while view and not self._stop.is_set():
            try:
                written = os.write(self._master, view)
            except BlockingIOError:
                select.select([], [self._master], [], 0.05)
                continue
            view = view[written:]

    # protocol hooks ------------------------------------------------------------------------------
    def split(self, buffer: bytes) -> tuple[list[bytes], bytes]:
        """Split ``buffer`` into complete requests and the incomplete rest (default: terminator lines)."""
        parts = buffer.split(self.terminator)
        return parts[:-1], parts[-1]

    def handle(self, request: bytes) -> bytes:
        """Answer one request (empty bytes: no answer)."""
        raise NotImplementedError

    def state(self) -> dict[str, Any]:
        """The emulated device's state as JSON-ready data (subclasses describe theirs)."""
        return {}

    def garbage(self, n: int) -> bytes:
        """Bytes that break the protocol, ending with the terminator so a line reader sees a reply."""
        noise = self._rng.integers(0x80, 0x100, size=max(n, 3), dtype=np.uint8).tobytes()
        return noise + self.terminator
