"""pyserial URL handler ``emu://NAME?key=value&...``: a wire-protocol emulator as a serial port.

``serial.serial_for_url("emu://pi-gcs?travel_mm=0,150&max_velocity_mm_s=50")``
starts a :class:`~scopetwin.instrument.emulators.pi_gcs.PiGcsEmulator` on a
pseudo-terminal and opens its slave as a real ``serial.Serial``; closing the
port stops the emulator. The emulator object is reachable as ``port.emulator``
(for logs and fault injection). Query values are finite numbers, or comma-separated
number lists for tuple options; ``axes`` is a comma-separated list of names;
``fault=silent|garbage|drop|flood`` with ``fault_after=N`` makes the device stop
answering properly after N requests.
:func:`scopetwin.instrument.transport.open_transport` registers this handler.
"""

from __future__ import annotations

import math
import urllib.parse
from typing import Any

from scopetwin.instrument.emulators.base import PtyEmulator, require_pty
from scopetwin.instrument.errors import RigError

try:
    from serial.serialposix import Serial as PortBase
except ImportError:  # no termios/fcntl (Windows): the class imports, and opening it says emulators need a pty
    from serial import Serial as PortBase


def option_value(key: str, text: str) -> Any:
    """An emulator option from text: ``axes`` a name list, ``model``/``stage`` text, else numbers."""
    if key == "axes":
        return tuple(t for t in text.split(",") if t)
    if key in ("model", "stage", "fault"):
        return text
    try:
        numbers = [float(t) for t in text.split(",")]
    except ValueError as exc:
        raise RigError(f"emulator option {key}={text!r} is not a number or number list") from exc
    if not all(math.isfinite(v) for v in numbers):
        raise RigError(f"emulator option {key}={text!r}: every number must be finite")
    if key in ("seed", "fault_after") or key.endswith("_index"):
        if len(numbers) != 1 or numbers[0] != int(numbers[0]):
            raise RigError(f"emulator option {key}={text!r} must be one integer")
        return int(numbers[0])
    return tuple(numbers) if len(numbers) > 1 else numbers[0]


def parse_url(url: str) -> tuple[str, dict[str, Any]]:
    """Split ``emu://NAME?opts`` into the emulator name and its keyword arguments."""
    parts = urllib.parse.urlsplit(url)
    if parts.scheme.lower() != "emu":
        raise RigError(f"not an emu:// URL: {url!r}")
    name = (parts.netloc + parts.path).strip("/")
    options = {k: option_value(k, v) for k, v in urllib.parse.parse_qsl(parts.query, keep_blank_values=False)}
    return name, options


class Serial(PortBase):
    """A pyserial port whose other end is an in-process emulator."""

    emulator: PtyEmulator | None = None
    portstr: str

    def open(self) -> None:
        """Start the emulator named by the URL and open its pseudo-terminal.

        Raises
        ------
        EmulatorUnavailable
            The platform has no POSIX pseudo-terminal (Windows).
        """
        from scopetwin.instrument.emulators import EMULATORS

        require_pty()
        url = self.portstr
        name, options = parse_url(url)
        if name not in EMULATORS:
            raise RigError(f"emu:// names an unknown emulator {name!r}; known: {sorted(EMULATORS)}")
        try:
            emulator = EMULATORS[name](**options)
        except (TypeError, ValueError) as exc:
            raise RigError(f"emu://{name}: bad option ({exc})") from exc
        self.emulator = emulator
        self.port = emulator.start()
        try:
            super().open()
        except Exception:
            emulator.stop()
            raise
        self._port = self.portstr = url

    def close(self) -> None:
        """Close the port and stop the emulator."""
        super().close()
        if self.emulator is not None:
            self.emulator.stop()
            self.emulator = None
