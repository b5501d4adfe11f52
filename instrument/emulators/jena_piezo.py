"""Emulator of a piezosystem jena controller with a MIPOS500 (0-400 µm) on a pseudo-terminal.

The ``model`` selects the dialect of the vendor's documentation (the same table
as :mod:`scopetwin.instrument.drivers.jena_piezo`, written out here independently so that
a test of the driver against the emulator is a test of two readings of the
documents):

- ``nv40-1`` (NV40/1 CLE): ``i1``/``i0`` remote, ``cl``/``ol`` loop,
  ``wr,<value>`` set, ``rd`` answered ``rd,<value>`` CR LF.
- ``nv40-3`` (NV40/3 CLE, channels 0-2): ``setk,<ch>,<0|1>`` remote,
  ``cloop,<ch>,<0|1>`` loop (``cloop,<ch>`` answered ``cloop,<ch>,<0|1>``),
  ``set,<ch>,<value>`` set, ``rk,<ch>`` answered ``rk,<ch>,<value>`` CR.
- ``30dv50``: ``cl,<0|1>`` loop, ``set,<value>`` set, ``mess`` answered
  ``mess,<value>`` CR LF (no remote command: the interface always commands).

Commands end in CR (a following LF is ignored); set commands are silent; a set
value is µm in closed loop and volts in open loop (clipped to the actuator's
range, as the amplifier saturates), and a read answers the same quantity.
Failures are answered ``err,<N>``: 1 unknown command, 4 too many parameters, 5
wrong character in parameter; a set without remote control is refused with
``err,1``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from scopetwin.instrument.emulators.base import PtyEmulator, finite_span

#: Largest travel an emulated piezo may have, µm (the MIPOS500 has 400), and its largest drive voltage, V.
MAX_TRAVEL_UM = 10_000.0
MAX_VOLTAGE_V = 1_000.0

#: Reply terminator by model (the NV40/3 ends its answers in CR only).
REPLY_END = {"nv40-1": b"\r\n", "nv40-3": b"\r", "30dv50": b"\r\n"}


@dataclass
class _Channel:
    remote: bool = False
    closed_loop: bool = False
    position_um: float = 0.0
    voltage_v: float = 0.0


class JenaPiezoEmulator(PtyEmulator):
    """A MIPOS500 on a jena controller of the given model.

    Parameters
    ----------
    model : str
        ``"nv40-1"``, ``"nv40-3"`` or ``"30dv50"``.
    range_um : tuple of float
        Closed-loop travel of the actuator.
    voltage_range_v : tuple of float
        Open-loop drive voltage range (mapped linearly onto ``range_um``).
    """

    protocol = "jena-piezo"
    terminator = b"\r"

    def __init__(
        self,
        *,
        model: str = "nv40-1",
        range_um: tuple[float, float] = (0.0, 400.0),
        voltage_range_v: tuple[float, float] = (-20.0, 130.0),
        seed: int = 0,
        fault: str = "none",
        fault_after: int = 0,
    ) -> None:
        super().__init__(seed=seed, fault=fault, fault_after=fault_after)
        key = str(model).lower().replace("/", "-")
        if key not in REPLY_END:
            raise ValueError(f"unknown jena model {model!r}; choose from {sorted(REPLY_END)}")
        self.model = key
        self.range_um = finite_span(range_um, "range_um", -MAX_TRAVEL_UM, MAX_TRAVEL_UM)
        self.voltage_range_v = finite_span(voltage_range_v, "voltage_range_v", -MAX_VOLTAGE_V, MAX_VOLTAGE_V)
        self.channels = [_Channel() for _ in range(3 if key == "nv40-3" else 1)]
        if key == "30dv50":
            self.channels[0].remote = True
        self.commands: list[str] = []
        self.reply_end = REPLY_END[key]

    # compatibility views of channel 0 -------------------------------------------------------------
    @property
    def remote(self) -> bool:
        """Remote control of channel 0."""
        return self.channels[0].remote

    @property
    def closed_loop(self) -> bool:
        """Loop mode of channel 0."""
        return self.channels[0].closed_loop

    @property
    def position_um(self) -> float:
        """Actuator position of channel 0 (µm)."""
        return self.channels[0].position_um

    def state(self) -> dict[str, Any]:
        """Position (µm), loop and remote of channel 0, and per channel (plus the drive voltage)."""
        first = self.channels[0]
        return {
            "model": self.model,
            "position_um": first.position_um,
            "loop": "closed" if first.closed_loop else "open",
            "remote": first.remote,
            "channels": [
                {
                    "position_um": c.position_um,
                    "voltage_v": c.voltage_v,
                    "loop": "closed" if c.closed_loop else "open",
                    "remote": c.remote,
                }
                for c in self.channels
            ],
        }

    # protocol -------------------------------------------------------------------------------------
    def split(self, buffer: bytes) -> tuple[list[bytes], bytes]:
        parts = buffer.replace(b"\n", b"").split(b"\r")
        return parts[:-1], parts[-1]

    def _reply(self, text: str) -> bytes:
        return text.encode("ascii") + self.reply_end

    def _err(self, code: int) -> bytes:
        return self._reply(f"err,{code}")

    def handle(self, request: bytes) -> bytes:
        try:
            text = request.decode("ascii").strip().lower()
        except UnicodeDecodeError:
            return self._err(5)
        if not text:
            return b""
        self.commands.append(text)
        words = text.split(",")
        try:
            if self.model == "nv40-1":
                return self._nv40_1(words)
            if self.model == "nv40-3":
                return self._nv40_3(words)
            return self._30dv50(words)
        except ValueError:
            return self._err(5)

    def _set(self, ch: _Channel, arg: str) -> bytes:
        if not ch.remote:
            return self._err(1)
        value = float(arg)
        if value != value:
            return self._err(5)
        lo_um, hi_um = self.range_um
        lo_v, hi_v = self.voltage_range_v
        if ch.closed_loop:
            ch.position_um = min(max(value, lo_um), hi_um)
            ch.voltage_v = lo_v + (ch.position_um - lo_um) * (hi_v - lo_v) / (hi_um - lo_um)
        else:
            ch.voltage_v = min(max(value, lo_v), hi_v)
            ch.position_um = lo_um + (ch.voltage_v - lo_v) * (hi_um - lo_um) / (hi_v - lo_v)
        return b""

    @staticmethod
    def _value(ch: _Channel) -> str:
        return f"{ch.position_um if ch.closed_loop else ch.voltage_v:.3f}"

    def _nv40_1(self, words: list[str]) -> bytes:
        ch = self.channels[0]
        head, args = words[0], words[1:]
        if head in ("i1", "i0", "cl", "ol", "rd") and args:
            return self._err(4)
        if head in ("i1", "i0"):
            ch.remote = head == "i1"
            return b""
        if head in ("cl", "ol"):
            ch.closed_loop = head == "cl"
            return b""
        if head == "rd":
            return self._reply(f"rd,{self._value(ch)}")
        if head == "wr":
            if len(args) != 1:
                return self._err(4 if args else 5)
            return self._set(ch, args[0])
        return self._err(1)

    def _channel(self, text: str) -> _Channel | None:
        if not text.isdigit() or int(text) >= len(self.channels):
            return None
        return self.channels[int(text)]

    def _nv40_3(self, words: list[str]) -> bytes:
        head, args = words[0], words[1:]
        if head not in ("setk", "cloop", "set", "rk"):
            return self._err(1)
        if not args:
            return self._err(5)
        ch = self._channel(args[0])
        if ch is None:
            return self._err(5)
        if head == "rk":
            return self._err(4) if len(args) > 1 else self._reply(f"rk,{args[0]},{self._value(ch)}")
        if head == "cloop" and len(args) == 1:
            return self._reply(f"cloop,{args[0]},{int(ch.closed_loop)}")
        if len(args) != 2:
            return self._err(4 if len(args) > 2 else 5)
        if head == "set":
            return self._set(ch, args[1])
        if args[1] not in ("0", "1"):
            return self._err(5)
        if head == "setk":
            ch.remote = args[1] == "1"
        else:
            ch.closed_loop = args[1] == "1"
        return b""

    def _30dv50(self, words: list[str]) -> bytes:
        ch = self.channels[0]
        head, args = words[0], words[1:]
        if head == "mess":
            return self._err(4) if args else self._reply(f"mess,{self._value(ch)}")
        if head == "cl":
            if not args:
                return self._reply(f"cl,{int(ch.closed_loop)}")
            if len(args) != 1 or args[0] not in ("0", "1"):
                return self._err(5 if len(args) == 1 else 4)
            ch.closed_loop = args[0] == "1"
            return b""
        if head == "set":
            if len(args) != 1:
                return self._err(4 if args else 5)
            return self._set(ch, args[0])
        return self._err(1)

    def garbage(self, n: int) -> bytes:
        """Bytes that break the protocol, ending with the model's reply terminator."""
        noise = self._rng.integers(0x80, 0x100, size=max(n, 3), dtype="uint8").tobytes()
        return noise + self.reply_end
