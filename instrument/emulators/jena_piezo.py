"""Emulator of a piezosystem jena controller with a MIPOS500 (0-400 µm) on a pseudo-terminal.

CR-terminated ASCII (``\\r\\n`` accepted): ``setk,1``/``setk,0`` remote control,
``cl``/``ol`` loop mode, ``wr,<value>`` set position (µm closed loop, volts open
loop; values beyond the actuator's range are clipped, as the amplifier
saturates), ``rd`` answered ``aw,<value>``. Commands that fail are answered
``err,<N>`` (1 unknown command, 4 too many parameters, 5 wrong character in
parameter); a ``wr`` without remote control is refused with ``err,1``.
"""

from __future__ import annotations

from instrument.emulators.base import PtyEmulator


class JenaPiezoEmulator(PtyEmulator):
    """A MIPOS500 on a jena controller.

    Parameters
    ----------
    range_um : tuple of float
        Closed-loop travel of the actuator.
    voltage_range_v : tuple of float
        Open-loop drive voltage range.
    """

    protocol = "jena-piezo"
    terminator = b"\r"

    def __init__(
        self,
        *,
        range_um: tuple[float, float] = (0.0, 400.0),
        voltage_range_v: tuple[float, float] = (-20.0, 130.0),
        seed: int = 0,
    ) -> None:
        super().__init__(seed=seed)
        self.range_um = range_um
        self.voltage_range_v = voltage_range_v
        self.remote = False
        self.closed_loop = False
        self.position_um = 0.0
        self.voltage_v = 0.0
        self.commands: list[str] = []

    def split(self, buffer: bytes) -> tuple[list[bytes], bytes]:
        parts = buffer.replace(b"\n", b"").split(b"\r")
        return parts[:-1], parts[-1]

    def handle(self, request: bytes) -> bytes:
        try:
            text = request.decode("ascii").strip().lower()
        except UnicodeDecodeError:
            return b"err,5\r"
        if not text:
            return b""
        self.commands.append(text)
        head, _, arg = text.partition(",")
        if head == "setk":
            if arg not in ("0", "1"):
                return b"err,5\r"
            self.remote = arg == "1"
            return b""
        if head in ("cl", "ol"):
            if arg:
                return b"err,4\r"
            self.closed_loop = head == "cl"
            return b""
        if head == "rd":
            value = self.position_um if self.closed_loop else self.voltage_v
            return f"aw,{value:.3f}\r".encode()
        if head == "wr":
            if not self.remote:
                return b"err,1\r"
            try:
                value = float(arg)
            except ValueError:
                return b"err,5\r"
            if self.closed_loop:
                self.position_um = min(max(value, self.range_um[0]), self.range_um[1])
            else:
                self.voltage_v = min(max(value, self.voltage_range_v[0]), self.voltage_range_v[1])
                span_v = self.voltage_range_v[1] - self.voltage_range_v[0]
                frac = (self.voltage_v - self.voltage_range_v[0]) / span_v
                self.position_um = self.range_um[0] + frac * (self.range_um[1] - self.range_um[0])
            return b""
        return b"err,1\r"
