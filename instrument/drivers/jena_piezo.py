"""piezosystem jena driver for the MIPOS500 objective positioner (seed §4.2.3, RS-232).

ASCII commands terminated by CR: ``setk,1`` (remote control on), ``cl`` /
``ol`` (closed / open loop), ``wr,<value>`` (set position: µm in closed loop,
volts in open loop) and ``rd`` (read, answered ``aw,<value>``). Set commands are
silent unless they fail, when the controller answers ``err,<N>``; the driver
therefore follows each set command with ``rd`` and inspects every line up to
the ``aw`` answer. The baud rate differs between controller models
(9600 for the NV40/1 CLE, 19200 or 115200 for others) and is a setting.

:func:`decode_reply` raises only :class:`~instrument.errors.ProtocolError`
(or its subclass :class:`~instrument.errors.ControllerError` for ``err,N``).
"""

from __future__ import annotations

from typing import Any

from instrument.devices import FocusDrive
from instrument.errors import ControllerError, InstrumentError, ProtocolError
from instrument.transport import Link

#: Error numbers of jena's serial controllers.
JENA_ERRORS: dict[int, str] = {
    1: "unknown command",
    2: "too many characters in the command",
    3: "too many characters in the parameter",
    4: "too many parameters",
    5: "wrong character in parameter",
    6: "wrong separator",
    7: "position overload",
}
TERMINATOR = b"\r"


def decode_reply(raw: bytes) -> float:
    """Decode one reply line (CR removed): the value of ``aw,<value>``.

    Raises
    ------
    ControllerError
        For ``err,<N>`` (the code is kept in ``.code``).
    ProtocolError
        For anything else.
    """
    if any(b < 0x20 or b > 0x7E for b in raw):
        raise ProtocolError(f"jena piezo: non-ASCII reply {raw[:40]!r}")
    text = raw.decode("ascii").strip()
    head, sep, value = text.partition(",")
    if not sep:
        raise ProtocolError(f"jena piezo: unexpected reply {text[:40]!r}")
    head = head.strip().lower()
    if head == "err":
        if not value.strip().isdigit() or len(value.strip()) > 6:
            raise ProtocolError(f"jena piezo: malformed error reply {text[:40]!r}")
        code = int(value)
        raise ControllerError(f"jena piezo: controller error {code} ({JENA_ERRORS.get(code, 'unknown')})", code)
    if head != "aw":
        raise ProtocolError(f"jena piezo: unexpected reply {text[:40]!r}")
    try:
        number = float(value)
    except ValueError as exc:
        raise ProtocolError(f"jena piezo: not a number in {text[:40]!r}") from exc
    if number != number or abs(number) == float("inf"):
        raise ProtocolError(f"jena piezo: not a finite number in {text[:40]!r}")
    return number


class JenaPiezoFocus(FocusDrive):
    """The MIPOS500 on a piezosystem jena controller, closed loop, in µm.

    Parameters
    ----------
    name : str
        Device name.
    transport
        Open transport (its baud rate must match the controller model).
    range_um : tuple of float
        Allowed positions, checked before any command (0-400 µm for the MIPOS500).
    timeout_s : float
        Timeout of one exchange.
    tolerance_um, settle_timeout_s : float
        Arrival criterion of a move.
    """

    driver = "jena-piezo"

    def __init__(
        self,
        name: str,
        transport: Any,
        *,
        range_um: tuple[float, float] = (0.0, 400.0),
        timeout_s: float = 1.0,
        tolerance_um: float = 0.05,
        settle_timeout_s: float = 1.0,
    ) -> None:
        super().__init__(name, range_um=range_um, tolerance_um=tolerance_um, settle_timeout_s=settle_timeout_s)
        self.link = Link(transport, timeout_s=timeout_s, name=f"focus {name!r} (jena piezo)")
        self.closed_loop = True

    def _send(self, command: str) -> None:
        self.link.write(command.encode("ascii") + TERMINATOR)

    def _read_value(self) -> float:
        """Send ``rd`` and return the ``aw`` value."""
        with self.link.lock:
            self._send("rd")
            return decode_reply(self.link.read_until(TERMINATOR))

    def set_command(self, command: str) -> None:
        """Send a silent set command followed by ``rd``; raise the ``err,N`` the command caused, if any.

        Lines are read up to the ``aw`` answer of ``rd``, so no stale reply is left on the line.
        """
        with self.link.lock:
            self.link.write(command.encode("ascii") + TERMINATOR + b"rd" + TERMINATOR)
            error: ControllerError | None = None
            for _ in range(4):
                try:
                    decode_reply(self.link.read_until(TERMINATOR))
                    break
                except ControllerError as exc:
                    error = error or exc
            else:
                raise ProtocolError(f"focus {self.name!r}: no 'aw' answer after {command!r}")
            if error is not None:
                raise ControllerError(f"focus {self.name!r}: {command!r} failed: {error}", error.code)

    def set_closed_loop(self, closed: bool) -> None:
        """Switch between closed loop (``cl``, positions in µm) and open loop (``ol``, volts)."""
        self._require()
        self.set_command("cl" if closed else "ol")
        self.closed_loop = bool(closed)

    def _do_initialize(self) -> None:
        self.set_command("setk,1")
        self.set_command("cl")
        self.closed_loop = True

    def _do_get_position_um(self) -> float:
        if not self.closed_loop:
            raise InstrumentError(f"focus {self.name!r} is in open loop: positions are volts, not µm")
        return self._read_value()

    def _do_move_absolute_um(self, position_um: float) -> None:
        if not self.closed_loop:
            raise InstrumentError(f"focus {self.name!r} is in open loop: switch to closed loop to move in µm")
        self.set_command(f"wr,{position_um:.3f}")
