"""Serial transports for the hardware drivers: deadlines, framing and error mapping.

Drivers never open a global port: they receive a transport object, a pyserial
``Serial`` or anything :func:`serial.serial_for_url` returns (``/dev/ttyUSB0``,
``loop://``, ``socket://127.0.0.1:port``, or ``emu://pi-gcs`` for an in-process
emulator, see :mod:`scopetwin.instrument.emulators.protocol_emu`). :class:`Link` wraps it
with the two operations every protocol here needs, each bounded by one timeout:
write bytes, and read until a terminator or a byte count. Pyserial, OS and
``termios`` errors (a pseudo-terminal whose other end is gone) become
:class:`~scopetwin.instrument.errors.DisconnectedError`; a deadline that passes
becomes :class:`~scopetwin.instrument.errors.InstrumentTimeout`; a flood of bytes
without a terminator a :class:`~scopetwin.instrument.errors.ProtocolError`.

A driver wraps each request and its answer in :meth:`Link.exchange`: a failure
there (the port gone, no answer in time, an answer that breaks the protocol —
anything but an error code the device itself reported) marks the link
:attr:`~Link.lost` with the reason; the next complete exchange clears it. The rig
uses the mark to tell which devices stopped answering
(:meth:`scopetwin.instrument.rig.Rig.close`).
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Iterator
from typing import Any

import serial

from scopetwin.instrument.errors import (
    ControllerError,
    DisconnectedError,
    InstrumentError,
    InstrumentTimeout,
    OutOfRangeError,
    ProtocolError,
)

try:  # POSIX: tcflush/tcdrain on a tty whose other end is gone raise termios.error, not OSError
    import termios

    _TTY_ERRORS: tuple[type[Exception], ...] = (termios.error,)
except ImportError:  # pragma: no cover - Windows
    _TTY_ERRORS = ()

EMULATOR_PACKAGE = "scopetwin.instrument.emulators"
#: Errors of a transport that mean the line is gone (pyserial, the OS, the tty layer, a closed file object).
LINE_ERRORS: tuple[type[Exception], ...] = (serial.SerialException, OSError, ValueError, TypeError, *_TTY_ERRORS)
_CONFIG_ERRORS: tuple[type[Exception], ...] = (*LINE_ERRORS, AttributeError)


def open_transport(port: str, *, baudrate: int = 115200, timeout_s: float = 1.0, **kwargs: Any) -> serial.Serial:
    """Open ``port`` (a device path or any pyserial URL) and return the pyserial object.

    ``emu://NAME`` URLs start an in-process wire-protocol emulator on a pseudo-terminal (POSIX only).

    Raises
    ------
    DisconnectedError
        If the port cannot be opened.
    EmulatorUnavailable
        ``port`` is an ``emu://`` URL and the platform has no POSIX pseudo-terminal (Windows).
    """
    if port.lower().startswith("emu://"):
        from scopetwin.instrument.emulators.base import EmulatorUnavailable, require_pty

        try:
            require_pty()
        except EmulatorUnavailable as exc:
            raise EmulatorUnavailable(f"port {port!r}: {exc}") from None
    if EMULATOR_PACKAGE not in serial.protocol_handler_packages:
        serial.protocol_handler_packages.append(EMULATOR_PACKAGE)
    try:
        return serial.serial_for_url(port, baudrate=int(baudrate), timeout=timeout_s, **kwargs)
    except (serial.SerialException, OSError, ValueError) as exc:
        raise DisconnectedError(f"cannot open port {port!r}: {exc}") from exc


class Link:
    """A transport with deadline-bounded, thread-safe reads and writes.

    Parameters
    ----------
    transport : serial.Serial
        An open pyserial object (or any object with ``read``, ``write``, ``reset_input_buffer``).
    timeout_s : float
        Longest time one exchange may take.
    name : str
        Device name for messages.
    max_reply_bytes : int
        A reply longer than this without a terminator is a protocol error.
    """

    def __init__(
        self, transport: Any, *, timeout_s: float = 1.0, name: str = "device", max_reply_bytes: int = 4096
    ) -> None:
        self.transport = transport
        self.timeout_s = float(timeout_s)
        self.name = name
        self.max_reply_bytes = int(max_reply_bytes)
        self.lock = threading.RLock()
        self._pending = bytearray()
        self._poll_s = 0.02
        #: Why the last exchange failed (the port gone, no answer, garbage); ``None`` while the device answers.
        self.lost: str | None = None
        #: Whether the last exchange was cut short after its request may have gone out (a signal, a timeout): its
        #: answer may still arrive, after the next request's input was dropped. Drivers whose replies name their
        #: request (the FPGA board's packets) skip such a stale answer once.
        self.cut = False
        try:
            transport.timeout = self._poll_s
        except _CONFIG_ERRORS as exc:
            raise self._fail("configuring", exc) from exc

    def _fail(self, what: str, exc: Exception) -> DisconnectedError:
        text = str(exc)
        if isinstance(exc, _TTY_ERRORS) and len(exc.args) == 2:  # termios.error carries (errno, text)
            text = f"[Errno {exc.args[0]}] {exc.args[1]}"
        return DisconnectedError(f"{self.name}: line lost while {what}: {text}")

    @contextlib.contextmanager
    def exchange(self) -> Iterator[None]:
        """Hold the link for one request and its answer; record whether the device answered.

        An :class:`~scopetwin.instrument.errors.InstrumentError` inside marks the link :attr:`lost` with its message,
        except an error code the device reported (:class:`~scopetwin.instrument.errors.ControllerError`) or a value
        refused before sending (:class:`~scopetwin.instrument.errors.OutOfRangeError`): the device answered. Any other
        exception (a timeout, a signal's) also marks it :attr:`cut`. A complete exchange clears both marks.
        """
        with self.lock:
            try:
                yield
            except (ControllerError, OutOfRangeError):
                self.lost, self.cut = None, False
                raise
            except InstrumentError as exc:
                self.lost, self.cut = str(exc), True
                raise
            except BaseException:  # a signal's exception between the request and its answer
                self.cut = True
                raise
            self.lost, self.cut = None, False

    def write(self, data: bytes) -> None:
        """Send ``data`` (after dropping stale input)."""
        try:
            if not getattr(self.transport, "is_open", True):
                raise DisconnectedError(f"{self.name}: transport is closed")
            self.transport.reset_input_buffer()
            self._pending.clear()
            self.transport.write(data)
            self.transport.flush()
        except LINE_ERRORS as exc:
            raise self._fail("writing", exc) from exc

    def _read_some(self, deadline: float) -> bytes:
        if self._pending:
            data = bytes(self._pending)
            self._pending.clear()
            return data
        if time.monotonic() >= deadline:
            return b""
        try:
            waiting = self.transport.in_waiting
            return self.transport.read(max(1, min(int(waiting), self.max_reply_bytes + 1)))
        except LINE_ERRORS as exc:
            raise self._fail("reading", exc) from exc

    def read_until(self, terminator: bytes, timeout_s: float | None = None) -> bytes:
        """Read up to and including ``terminator``; return the bytes without it.

        Bytes after the terminator stay buffered for the next read.

        Raises
        ------
        InstrumentTimeout
            If the terminator has not arrived within the timeout (partial frames included).
        ProtocolError
            If more than ``max_reply_bytes`` arrive without a terminator.
        """
        deadline = time.monotonic() + (self.timeout_s if timeout_s is None else timeout_s)
        buf = bytearray()
        while True:
            chunk = self._read_some(deadline)
            if chunk:
                buf += chunk
                at = buf.find(terminator)
                if at >= 0:
                    self._pending += buf[at + len(terminator) :]
                    return bytes(buf[:at])
                if len(buf) > self.max_reply_bytes:
                    raise ProtocolError(
                        f"{self.name}: reply of more than {self.max_reply_bytes} bytes "
                        f"without terminator {terminator!r}"
                    )
            elif time.monotonic() >= deadline:
                got = f" (got {bytes(buf[:40])!r})" if buf else ""
                raise InstrumentTimeout(f"{self.name}: no complete reply within {self.timeout_s} s{got}")

    def read_exact(self, n: int, deadline: float) -> bytes:
        """Read exactly ``n`` bytes before ``deadline`` (a ``time.monotonic`` value); extra bytes stay buffered."""
        buf = bytearray()
        while len(buf) < n:
            chunk = self._read_some(deadline)
            if chunk:
                buf += chunk
            elif time.monotonic() >= deadline:
                got = f" (got {bytes(buf[:40])!r})" if buf else ""
                raise InstrumentTimeout(f"{self.name}: {n} bytes did not arrive within {self.timeout_s} s{got}")
        self._pending += buf[n:]
        return bytes(buf[:n])

    def close(self) -> None:
        """Close the transport (errors ignored: closing is always allowed)."""
        try:
            self.transport.close()
        except Exception:  # noqa: BLE001 - closing must not raise
            pass
