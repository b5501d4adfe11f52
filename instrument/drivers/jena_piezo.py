"""piezosystem jena driver for the MIPOS500 objective positioner (thesis §4.2.3, RS-232).

The controllers of the MIPOS500 speak related but different ASCII dialects; the
rig's ``model`` key selects one (:data:`DIALECTS`). Every command ends in CR; set
commands are silent unless they fail, when the controller answers an error line
``err,<N>``; queries are answered ``<command>,<value>`` (NV40/3: with the channel).

=========  ==================  ===========================  ======================  =============  ==========
model      remote on / off     closed / open loop           set position            read           reply end
=========  ==================  ===========================  ======================  =============  ==========
nv40-1     ``i1`` / ``i0``     ``cl`` / ``ol``              ``wr,<value>``          ``rd``         CR LF
nv40-3     ``setk,<ch>,1/0``   ``cloop,<ch>,1`` / ``,0``    ``set,<ch>,<value>``    ``rk,<ch>``    CR
30dv50     (none)              ``cl,1`` / ``cl,0``          ``set,<value>``         ``mess``       CR LF
=========  ==================  ===========================  ======================  =============  ==========

Default line settings: NV40/1 CLE 9600 baud without handshake; NV40/3 19200 baud
and 30DV50 115200 baud, both with XON/XOFF software handshake (the rig may
override ``baudrate`` and ``xonxoff``). The set value is µm in closed loop and
volts in open loop; the read answers the same quantity. In open loop the driver
maps volts to µm linearly over the actuator's voltage range (the MIPOS500 on an
NV40: -20 to 130 V for 0-400 µm), as the vendor's own Micro-Manager adapters do:
positions are then estimates (no sensor feedback, piezo hysteresis).

The driver follows each set command with the read command and inspects every
line up to the read's answer, so a failing command is reported and no stale
reply is left on the line.

:func:`decode_reply` raises only :class:`~scopetwin.instrument.errors.ProtocolError`
(or its subclass :class:`~scopetwin.instrument.errors.ControllerError` for ``err,N``).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from scopetwin.instrument.devices import FocusDrive, Range
from scopetwin.instrument.errors import ControllerError, InstrumentError, OutOfRangeError, ProtocolError, RigError
from scopetwin.instrument.transport import Link

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


@dataclass(frozen=True)
class JenaDialect:
    """One controller model's command set and line settings (see the module table).

    ``{ch}`` in a template is the channel, ``{value}`` the set value (already formatted).
    """

    model: str
    remote_on: str | None
    remote_off: str | None
    closed_loop: str
    open_loop: str
    set_position: str
    value_format: str
    read: str
    reply_head: str
    reply_has_channel: bool
    reply_terminator: bytes
    baudrate: int
    xonxoff: bool
    channels: int = 1


DIALECTS: dict[str, JenaDialect] = {
    "nv40-1": JenaDialect(
        model="nv40-1",
        remote_on="i1",
        remote_off="i0",
        closed_loop="cl",
        open_loop="ol",
        set_position="wr,{value}",
        value_format="{:.3f}",
        read="rd",
        reply_head="rd",
        reply_has_channel=False,
        reply_terminator=b"\r\n",
        baudrate=9600,
        xonxoff=False,
    ),
    "nv40-3": JenaDialect(
        model="nv40-3",
        remote_on="setk,{ch},1",
        remote_off="setk,{ch},0",
        closed_loop="cloop,{ch},1",
        open_loop="cloop,{ch},0",
        set_position="set,{ch},{value}",
        value_format="{:.3f}",
        read="rk,{ch}",
        reply_head="rk",
        reply_has_channel=True,
        reply_terminator=b"\r",
        baudrate=19200,
        xonxoff=True,
        channels=3,
    ),
    "30dv50": JenaDialect(
        model="30dv50",
        remote_on=None,
        remote_off=None,
        closed_loop="cl,1",
        open_loop="cl,0",
        set_position="set,{value}",
        value_format="{:.6f}",
        read="mess",
        reply_head="mess",
        reply_has_channel=False,
        reply_terminator=b"\r\n",
        baudrate=115200,
        xonxoff=True,
    ),
}


def dialect_of(model: str) -> JenaDialect:
    """The dialect of ``model`` (case-insensitive, ``/`` accepted for ``-``).

    Raises
    ------
    RigError
        For a model the driver does not know.
    """
    key = model.strip().lower().replace("/", "-").replace(" ", "")
    if key not in DIALECTS:
        raise RigError(f"jena piezo: unknown model {model!r}; choose from {sorted(DIALECTS)}")
    return DIALECTS[key]


def _finite(text: str, line: str) -> float:
    try:
        number = float(text)
    except ValueError as exc:
        raise ProtocolError(f"jena piezo: not a number in {line[:40]!r}") from exc
    if number != number or abs(number) == float("inf"):
        raise ProtocolError(f"jena piezo: not a finite number in {line[:40]!r}")
    return number


def decode_reply(raw: bytes, dialect: JenaDialect | None = None, channel: int = 0) -> float:
    """Decode one reply line (terminator removed): the value of the read command's answer.

    Parameters
    ----------
    raw : bytes
        The line without its terminator (a trailing CR or LF is ignored).
    dialect : JenaDialect, optional
        The controller's dialect (default NV40/1: ``rd,<value>``).
    channel : int
        The channel an NV40/3 answer must name.

    Raises
    ------
    ControllerError
        For ``err,<N>`` (the code is kept in ``.code``).
    ProtocolError
        For anything else.
    """
    d = dialect or DIALECTS["nv40-1"]
    if any(b < 0x20 or b > 0x7E for b in raw.rstrip(b"\r\n")):
        raise ProtocolError(f"jena piezo: non-ASCII reply {raw[:40]!r}")
    text = raw.decode("ascii").strip()
    parts = [p.strip() for p in text.split(",")]
    head = parts[0].lower()
    if head in ("err", "error"):
        if len(parts) != 2 or not parts[1].isdigit() or len(parts[1]) > 6:
            raise ProtocolError(f"jena piezo: malformed error reply {text[:40]!r}")
        code = int(parts[1])
        raise ControllerError(f"jena piezo: controller error {code} ({JENA_ERRORS.get(code, 'unknown')})", code)
    if head != d.reply_head:
        raise ProtocolError(f"jena piezo: expected '{d.reply_head},...', got {text[:40]!r}")
    if d.reply_has_channel:
        if len(parts) != 3 or parts[1] != str(channel):
            raise ProtocolError(f"jena piezo: expected '{d.reply_head},{channel},<value>', got {text[:40]!r}")
        return _finite(parts[2], text)
    if len(parts) != 2:
        raise ProtocolError(f"jena piezo: expected '{d.reply_head},<value>', got {text[:40]!r}")
    return _finite(parts[1], text)


class JenaPiezoFocus(FocusDrive):
    """The MIPOS500 on a piezosystem jena controller, in µm (closed loop by default).

    Parameters
    ----------
    name : str
        Device name.
    transport
        Open transport (baud rate and XON/XOFF as the model needs: :attr:`JenaDialect.baudrate`).
    model : str
        ``"nv40-1"``, ``"nv40-3"`` or ``"30dv50"`` (:data:`DIALECTS`).
    channel : int
        Channel of a multi-channel controller (NV40/3: 0-2).
    range_um : tuple of float
        Allowed positions, checked before any command (0-400 µm for the MIPOS500).
    voltage_range_v : tuple of float
        Drive voltage range of the actuator over ``range_um`` (open-loop conversion).
    closed_loop : bool
        Loop mode set at initialisation.
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
        model: str = "nv40-1",
        channel: int = 0,
        range_um: tuple[float, float] = (0.0, 400.0),
        voltage_range_v: tuple[float, float] = (-20.0, 130.0),
        closed_loop: bool = True,
        timeout_s: float = 1.0,
        tolerance_um: float = 0.05,
        settle_timeout_s: float = 1.0,
    ) -> None:
        super().__init__(name, range_um=range_um, tolerance_um=tolerance_um, settle_timeout_s=settle_timeout_s)
        self.dialect = dialect_of(model)
        if channel not in range(self.dialect.channels):
            raise RigError(f"focus {name!r}: channel {channel} not in 0..{self.dialect.channels - 1} of a {model}")
        self.channel = int(channel)
        self.voltage_range = Range(float(voltage_range_v[0]), float(voltage_range_v[1]), "V")
        if self.voltage_range.high <= self.voltage_range.low:
            raise RigError(f"focus {name!r}: voltage_range_v must rise, got {voltage_range_v}")
        self.link = Link(transport, timeout_s=timeout_s, name=f"focus {name!r} (jena piezo {self.dialect.model})")
        self.closed_loop = bool(closed_loop)
        self._initial_loop = bool(closed_loop)

    def _limits(self) -> dict[str, Any]:
        return {**super()._limits(), "model": self.dialect.model, "closed_loop": self.closed_loop}

    def links(self) -> tuple[Link, ...]:
        """The serial line to the amplifier."""
        return (self.link,)

    # wire --------------------------------------------------------------------------------------
    def _format(self, template: str, value: float | None = None) -> str:
        text = "" if value is None else self.dialect.value_format.format(value)
        return template.format(ch=self.channel, value=text)

    def _read_raw(self) -> float:
        """Send the read command and return its value (µm in closed loop, volts in open loop)."""
        with self.link.exchange():
            self.link.write(self._format(self.dialect.read).encode("ascii") + TERMINATOR)
            line = self.link.read_until(self.dialect.reply_terminator)
            return decode_reply(line, self.dialect, self.channel)

    def set_command(self, command: str) -> None:
        """Send a silent set command followed by the read command; raise the ``err,N`` it caused, if any.

        Lines are read up to the read command's answer, so no stale reply is left on the line.
        """
        read = self._format(self.dialect.read)
        with self.link.exchange():
            self.link.write(command.encode("ascii") + TERMINATOR + read.encode("ascii") + TERMINATOR)
            error: ControllerError | None = None
            for _ in range(4):
                try:
                    decode_reply(self.link.read_until(self.dialect.reply_terminator), self.dialect, self.channel)
                    break
                except ControllerError as exc:
                    error = error or exc
            else:
                raise ProtocolError(f"focus {self.name!r}: no answer to {read!r} after {command!r}")
            if error is not None:
                raise ControllerError(f"focus {self.name!r}: {command!r} failed: {error}", error.code)

    # conversions ----------------------------------------------------------------------------------
    def volts_to_um(self, volts: float) -> float:
        """Open loop: the position a drive voltage gives (linear over the actuator's ranges)."""
        v, r = self.voltage_range, self.range
        return r.low + (volts - v.low) * (r.high - r.low) / (v.high - v.low)

    def um_to_volts(self, position_um: float) -> float:
        """Open loop: the drive voltage for a position (inverse of :meth:`volts_to_um`)."""
        v, r = self.voltage_range, self.range
        return v.low + (position_um - r.low) * (v.high - v.low) / (r.high - r.low)

    # device hooks ----------------------------------------------------------------------------------
    def set_remote(self, on: bool) -> None:
        """Switch remote control on or off (a no-op on models without it)."""
        template = self.dialect.remote_on if on else self.dialect.remote_off
        if template is not None:
            self.set_command(self._format(template))

    def set_closed_loop(self, closed: bool) -> None:
        """Switch between closed loop (positions in µm) and open loop (drive voltage)."""
        self._require()
        self._set_loop(closed)

    def _set_loop(self, closed: bool) -> None:
        self.set_command(self._format(self.dialect.closed_loop if closed else self.dialect.open_loop))
        self.closed_loop = bool(closed)

    def read_volts(self) -> float:
        """Open loop: the drive voltage the controller reports."""
        self._require()
        if self.closed_loop:
            raise OutOfRangeError(f"focus {self.name!r} is in closed loop: its read answers µm, not volts")
        return self._read_raw()

    def _do_initialize(self) -> None:
        self.set_remote(True)
        self._set_loop(self._initial_loop)

    def _do_shutdown(self) -> None:
        """Hand control back to the front panel (the actuator stays where it is)."""
        try:
            self.set_remote(False)
        except InstrumentError:
            pass  # releasing must not raise: the line may already be gone

    def _do_get_position_um(self) -> float:
        value = self._read_raw()
        return value if self.closed_loop else self.volts_to_um(value)

    def _do_move_absolute_um(self, position_um: float) -> None:
        value = (
            position_um
            if self.closed_loop
            else self.voltage_range.check(self.um_to_volts(position_um), f"focus {self.name!r} drive voltage")
        )
        self.set_command(self._format(self.dialect.set_position, value))
