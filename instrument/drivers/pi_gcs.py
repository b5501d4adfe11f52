"""PI GCS driver for the lateral stages (thesis §4.2.2: M-404.6PD / M-414.3PD on C-863 controllers).

The General Command Set is line based ASCII: a command is a mnemonic and
arguments separated by spaces, terminated by LF; a query ends in ``?`` and is
answered by one or more lines, where every line but the last ends with a space
before the LF. Set commands are silent, so the driver asks ``ERR?`` after each
one and turns a non-zero code into an exception. ``#5`` (the single byte 0x05)
returns the motion status as a hexadecimal bit mask of moving axes.

Commands used: ``*IDN?``, ``SVO``, ``FRF``/``FRF?``, ``MOV``, ``MVR``, ``POS?``,
``VEL``/``VEL?``, ``ONT?``, ``TMN?``/``TMX?``, ``SPA?`` (parameter 0xA, the maximum
closed-loop velocity, read when the rig states no ``max_velocity_mm_s``), ``HLT``,
``ERR?`` and ``#5``. Error codes are named from PI's published list
(:mod:`scopetwin.instrument.drivers.gcs_errors`).

The decoders (:func:`decode_lines`, :func:`parse_axis_values`,
:func:`parse_error_code`, :func:`parse_motion_status`) raise only
:class:`~scopetwin.instrument.errors.ProtocolError` on malformed input.
"""

from __future__ import annotations

import re
import time
from typing import Any

from scopetwin.instrument.devices import Range, Stage
from scopetwin.instrument.drivers.gcs_errors import describe_error
from scopetwin.instrument.errors import ControllerError, InstrumentTimeout, OutOfRangeError, ProtocolError, RigError
from scopetwin.instrument.transport import Link

#: GCS errors that mean "a value beyond a limit": position, velocity, parameter out of range.
RANGE_ERRORS = {7, 8, 17}
#: Parameter id of the maximum closed-loop velocity (C-863 manual: the largest value ``VEL`` accepts).
MAX_VELOCITY_PARAMETER = 0xA
_SPA = re.compile(r"^\s*([A-Za-z0-9_]+)\s+(0[xX][0-9A-Fa-f]+|\d+)\s*=\s*(\S+)\s*$")
MOTION_STATUS = b"\x05"
_PAIR = re.compile(r"^\s*([A-Za-z0-9_]+)\s*=\s*(\S+)\s*$")


def decode_lines(raw_lines: list[bytes]) -> list[str]:
    """ASCII-decode reply lines (terminator removed), stripping the continuation space.

    Raises
    ------
    ProtocolError
        On bytes outside printable ASCII.
    """
    out = []
    for raw in raw_lines:
        if any(b < 0x20 or b > 0x7E for b in raw):
            raise ProtocolError(f"PI GCS: non-ASCII reply {raw[:40]!r}")
        out.append(raw.decode("ascii").rstrip(" "))
    return out


def is_continued(raw_line: bytes) -> bool:
    """Whether a reply line (without LF) announces another line (trailing space)."""
    return raw_line.endswith(b" ")


def parse_axis_values(lines: list[str]) -> dict[str, float]:
    """Parse ``axis=value`` lines into a dict of floats.

    Raises
    ------
    ProtocolError
        On a line that is not ``axis=number``.
    """
    values: dict[str, float] = {}
    for line in lines:
        m = _PAIR.match(line)
        if m is None:
            raise ProtocolError(f"PI GCS: expected 'axis=value', got {line[:40]!r}")
        try:
            values[m.group(1)] = float(m.group(2))
        except ValueError as exc:
            raise ProtocolError(f"PI GCS: not a number in {line[:40]!r}") from exc
    return values


def parse_error_code(line: str) -> int:
    """Parse the answer of ``ERR?`` (a non-negative integer)."""
    text = line.strip()
    if not text.isdigit() or len(text) > 9:
        raise ProtocolError(f"PI GCS: ERR? answered {line[:40]!r}")
    return int(text)


def parse_motion_status(line: str) -> int:
    """Parse the answer of ``#5``: a hexadecimal bit mask of moving axes (bit 0 = axis 1)."""
    text = line.strip()
    if text.lower().startswith("0x"):
        text = text[2:]
    if not text or len(text) > 8 or any(c not in "0123456789abcdefABCDEF" for c in text):
        raise ProtocolError(f"PI GCS: #5 answered {line[:40]!r}")
    return int(text, 16)


def format_number(value: float) -> str:
    """A GCS number argument (plain decimal, enough digits for 1 nm in mm)."""
    return f"{float(value):.6f}"


class PiGcsController:
    """A GCS controller on a transport: commands with error check, multi-line queries.

    Parameters
    ----------
    transport
        Open pyserial object (or URL-made transport).
    timeout_s : float
        Longest time one exchange may take.
    name : str
        Name for messages.
    """

    def __init__(self, transport: Any, *, timeout_s: float = 1.0, name: str = "PI GCS") -> None:
        self.link = Link(transport, timeout_s=timeout_s, name=name)
        self.name = name

    def query(self, command: str | bytes) -> list[str]:
        """Send a query and return its reply lines (continuation lines joined into a list)."""
        data = command if isinstance(command, bytes) else command.encode("ascii") + b"\n"
        with self.link.exchange():
            self.link.write(data)
            raw: list[bytes] = []
            while True:
                line = self.link.read_until(b"\n")
                raw.append(line)
                if not is_continued(line):
                    break
                if len(raw) > 64:
                    raise ProtocolError(f"{self.name}: reply of more than 64 lines")
            return decode_lines(raw)

    def error_code(self) -> int:
        """Read (and clear) the controller's error code."""
        with self.link.exchange():  # an answer that is not a code marks the line lost
            lines = self.query("ERR?")
            if len(lines) != 1:
                raise ProtocolError(f"{self.name}: ERR? answered {len(lines)} lines")
            return parse_error_code(lines[0])

    def command(self, command: str, check: bool = True) -> None:
        """Send a set command, then ``ERR?``; raise on a non-zero error code."""
        with self.link.exchange():
            self.link.write(command.encode("ascii") + b"\n")
            if check:
                code = self.error_code()
                if code:
                    text = f"{self.name}: {command!r} failed with GCS error {code} ({describe_error(code)})"
                    if code in RANGE_ERRORS:
                        raise OutOfRangeError(text)
                    raise ControllerError(text, code)

    def axis_values(self, query: str, axis: str) -> float:
        """Send ``QUERY axis`` and return the value for ``axis``."""
        with self.link.exchange():
            values = parse_axis_values(self.query(f"{query} {axis}"))
            if axis not in values:
                raise ProtocolError(f"{self.name}: {query} {axis} answered no value for axis {axis}")
            return values[axis]

    def parameter(self, axis: str, parameter: int) -> float:
        """``SPA? axis 0xID``: a numeric parameter of ``axis`` from the controller's volatile memory.

        Raises
        ------
        ProtocolError
            If the answer is not ``axis 0xID=number`` (a controller error is read with ``ERR?``).
        """
        with self.link.exchange():
            lines = self.query(f"SPA? {axis} 0x{parameter:X}")
            m = _SPA.match(lines[0]) if len(lines) == 1 else None
            if m is None or m.group(1) != axis or int(m.group(2), 0) != parameter:
                raise ProtocolError(f"{self.name}: SPA? {axis} 0x{parameter:X} answered {lines[:2]!r}")
            try:
                return float(m.group(3))
            except ValueError as exc:
                raise ProtocolError(f"{self.name}: SPA? answered a non-number {m.group(3)!r}") from exc

    def motion_mask(self) -> int:
        """Bit mask of moving axes (``#5``)."""
        with self.link.exchange():
            lines = self.query(MOTION_STATUS)
            if len(lines) != 1:
                raise ProtocolError(f"{self.name}: #5 answered {len(lines)} lines")
            return parse_motion_status(lines[0])

    def close(self) -> None:
        """Close the transport."""
        self.link.close()


class PiGcsStage(Stage):
    """One axis of a PI stage on a GCS controller (C-863).

    Parameters
    ----------
    name : str
        Device name.
    transport
        Open transport to the controller.
    axis : str
        GCS axis identifier (``"1"`` on a C-863).
    travel_mm : tuple of float
        Allowed travel, checked before any command; must lie within the controller's ``TMN?``/``TMX?``.
    max_velocity_mm_s : float, optional
        Velocity limit; ``None`` reads it from the controller at initialisation (parameter 0xA,
        the maximum closed-loop velocity).
    velocity_mm_s : float, optional
        Velocity to set at initialisation.
    reference : bool
        Run a reference move (``FRF``) at initialisation if the axis is not referenced.
    timeout_s : float
        Timeout of one exchange.
    """

    driver = "pi-gcs"

    def __init__(
        self,
        name: str,
        transport: Any,
        *,
        axis: str = "1",
        travel_mm: tuple[float, float],
        max_velocity_mm_s: float | None = None,
        velocity_mm_s: float | None = None,
        reference: bool = True,
        timeout_s: float = 1.0,
        settle_timeout_s: float = 2.0,
    ) -> None:
        from_controller = max_velocity_mm_s is None
        super().__init__(
            name,
            travel_mm=travel_mm,
            max_velocity_mm_s=1.0e9 if max_velocity_mm_s is None else max_velocity_mm_s,
            settle_timeout_s=settle_timeout_s,
        )
        self.axis = str(axis)
        if not self.axis.isdigit():
            raise RigError(f"stage {name!r}: GCS axis must be a number, got {axis!r}")
        self.controller = PiGcsController(transport, timeout_s=timeout_s, name=f"stage {name!r} (PI GCS)")
        self.velocity_from_controller = from_controller
        self._velocity_setting = velocity_mm_s
        if not from_controller and velocity_mm_s is not None:
            self.velocity_range.check(velocity_mm_s, f"stage {name!r} velocity")
        self.reference = bool(reference)
        self.identification = ""

    def _do_initialize(self) -> None:
        c = self.controller
        self.identification = " ".join(c.query("*IDN?"))
        c.error_code()  # clear a stale error
        c.command(f"SVO {self.axis} 1")
        if self.velocity_from_controller:
            self.velocity_range = Range(1e-6, self.read_max_velocity(), "mm/s")
            if self._velocity_setting is not None:
                self.velocity_range.check(self._velocity_setting, f"stage {self.name!r} velocity")
        low, high = c.axis_values("TMN?", self.axis), c.axis_values("TMX?", self.axis)
        if self.travel.low < low - 1e-9 or self.travel.high > high + 1e-9:
            raise OutOfRangeError(
                f"stage {self.name!r}: configured travel {self.travel.as_list()} mm exceeds "
                f"the controller's [{low}, {high}] mm"
            )
        if self.reference and c.axis_values("FRF?", self.axis) != 1:
            c.command(f"FRF {self.axis}")
            deadline = time.monotonic() + self.settle_timeout_s + (high - low) / self.velocity_range.high
            while c.axis_values("FRF?", self.axis) != 1 or self._do_is_moving():
                if time.monotonic() > deadline:
                    raise InstrumentTimeout(f"stage {self.name!r}: reference move did not finish")
                time.sleep(0.005)
        if self._velocity_setting is not None:
            self._do_set_velocity(self._velocity_setting)

    def read_max_velocity(self) -> float:
        """The controller's velocity limit in mm/s: parameter 0xA (maximum closed-loop velocity).

        A controller without ``SPA?`` for 0xA (GCS error 54, unknown parameter) is asked ``VEL?``,
        whose current value is then the limit.
        """
        c = self.controller
        try:
            value = c.parameter(self.axis, MAX_VELOCITY_PARAMETER)
        except InstrumentTimeout:
            code = c.error_code()
            if code == 0:
                raise
            value = c.axis_values("VEL?", self.axis)
        if not value > 0 or value != value or value == float("inf"):
            raise ProtocolError(f"stage {self.name!r}: controller reports a velocity limit of {value} mm/s")
        return value

    def links(self) -> tuple[Link, ...]:
        """The serial line to the controller."""
        return (self.controller.link,)

    def _do_safe_state(self) -> None:
        """Nothing to make safe: the stage stays where it is (no parking)."""

    def _do_get_position(self) -> float:
        return self.controller.axis_values("POS?", self.axis)

    def _do_get_velocity(self) -> float:
        return self.controller.axis_values("VEL?", self.axis)

    def _do_set_velocity(self, velocity_mm_s: float) -> None:
        self.controller.command(f"VEL {self.axis} {format_number(velocity_mm_s)}")

    def _do_move_absolute(self, position_mm: float) -> None:
        self.controller.command(f"MOV {self.axis} {format_number(position_mm)}")

    def _do_move_relative(self, delta_mm: float) -> None:
        self.controller.command(f"MVR {self.axis} {format_number(delta_mm)}")

    def _do_is_moving(self) -> bool:
        return bool(self.controller.motion_mask() & (1 << (int(self.axis) - 1)))

    def on_target(self) -> bool:
        """``ONT?``: whether the axis has settled on its target."""
        self._require()
        return self.controller.axis_values("ONT?", self.axis) == 1

    def _do_halt(self) -> None:
        self.controller.command(f"HLT {self.axis}", check=False)
        code = self.controller.error_code()  # HLT sets error 10 by design; anything else is a fault
        if code not in (0, 10):
            raise ControllerError(f"stage {self.name!r}: HLT left GCS error {code}", code)
