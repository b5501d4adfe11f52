"""Serial transports for the hardware drivers: deadlines, framing and error mapping.

Drivers never open a global port: they receive a transport object, a pyserial
``Serial`` or anything :func:`serial.serial_for_url` returns (``/dev/ttyUSB0``,
``loop://``, ``socket://127.0.0.1:port``, or ``emu://pi-gcs`` for an in-process
emulator, see :mod:`scopetwin.instrument.emulators.protocol_emu`). :class:`Link` wraps it
with the two operations every protocol here needs, each bounded by one timeout:
write bytes, and read until a terminator or a byte count. Pyserial and OS
errors become :class:`~scopetwin.instrument.errors.DisconnectedError`; a deadline that
passes becomes :class:`~scopetwin.instrument.errors.InstrumentTimeout`.
"""

from __future__ import annotations

import threading
import time
from typing import Any

import serial

from scopetwin.instrument.errors import DisconnectedError, InstrumentTimeout, ProtocolError

EMULATOR_PACKAGE = "scopetwin.instrument.emulators"


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
        try:
            transport.timeout = self._poll_s
        except (serial.SerialException, OSError, ValueError, AttributeError) as exc:
            raise self._fail("configuring", exc) from exc

    def _fail(self, what: str, exc: Exception) -> DisconnectedError:
        return DisconnectedError(f"{self.name}: line lost while {what}: {exc}")

    def write(self, data: bytes) -> None:
        """Send ``data`` (after dropping stale input)."""
        try:
            if not getattr(self.transport, "is_open", True):
                raise DisconnectedError(f"{self.name}: transport is closed")
            self.transport.reset_input_buffer()
            self._pending.clear()
            self.transport.write(data)
            self.transport.flush()
        except (serial.SerialException, OSError, ValueError, TypeError) as exc:
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
        except (serial.SerialException, OSError, ValueError, TypeError) as exc:
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
                got = f" (got {bytes(buf)!r})" if buf else ""
                raise InstrumentTimeout(f"{self.name}: {n} bytes did not arrive within {self.timeout_s} s{got}")
        self._pending += buf[n:]
        return bytes(buf[:n])

    def close(self) -> None:
        """Close the transport (errors ignored: closing is always allowed)."""
        try:
            self.transport.close()
        except Exception:  # noqa: BLE001 - closing must not raise
            pass
