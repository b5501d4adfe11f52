"""Emulator of a PI GCS stage controller (C-863 class) on a pseudo-terminal.

Speaks the subset of GCS the driver uses (see :mod:`instrument.drivers.pi_gcs`):
LF-terminated commands, silent set commands with an error code kept for
``ERR?``, multi-line answers for multi-axis queries (every line but the last
ends with a space), and the single-byte ``#5`` motion status. Axes move at their
velocity in real time, so ``#5`` and ``ONT?`` change while a move runs.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

from instrument.emulators.base import PtyEmulator

CONTROL_BYTES = {0x05: "#5", 0x07: "#7", 0x18: "#24"}


@dataclass
class _Axis:
    low: float
    high: float
    max_velocity: float
    velocity: float
    start: float = 0.0
    target: float = 0.0
    t0: float = 0.0
    servo: bool = False
    referenced: bool = False

    def position(self, now: float) -> float:
        travelled = self.velocity * max(0.0, now - self.t0)
        span = self.target - self.start
        if abs(span) <= travelled:
            return self.target
        return self.start + travelled * (1.0 if span > 0 else -1.0)

    def moving(self, now: float) -> bool:
        return self.position(now) != self.target

    def go(self, target: float, now: float) -> None:
        self.start = self.position(now)
        self.target = target
        self.t0 = now


class PiGcsEmulator(PtyEmulator):
    """A GCS controller with one or more linear axes.

    Parameters
    ----------
    axes : tuple of str
        Axis identifiers (``("1",)`` for a C-863).
    travel_mm : tuple of float
        Hardware travel limits (``TMN?``/``TMX?``), e.g. (0, 150) for an M-404.6PD.
    max_velocity_mm_s : float
        Largest velocity ``VEL`` accepts.
    reference_mm : float
        Position after a reference move.
    model : str
        Controller model in the ``*IDN?`` answer.
    """

    protocol = "pi-gcs"
    terminator = b"\n"

    def __init__(
        self,
        *,
        axes: tuple[str, ...] = ("1",),
        travel_mm: tuple[float, float] = (0.0, 150.0),
        max_velocity_mm_s: float = 50.0,
        reference_mm: float = 0.0,
        model: str = "C-863.11",
        seed: int = 0,
    ) -> None:
        super().__init__(seed=seed)
        self.axes = {a: _Axis(travel_mm[0], travel_mm[1], max_velocity_mm_s, max_velocity_mm_s) for a in axes}
        self.reference_mm = float(reference_mm)
        self.model = model
        self.error = 0
        self.commands: list[str] = []

    def split(self, buffer: bytes) -> tuple[list[bytes], bytes]:
        requests: list[bytes] = []
        line = bytearray()
        for b in buffer:
            if b in CONTROL_BYTES and not line:
                requests.append(bytes([b]))
            elif b == 0x0A:
                requests.append(bytes(line))
                line.clear()
            else:
                line.append(b)
        return requests, bytes(line)

    def _set_error(self, code: int) -> None:
        if self.error == 0:
            self.error = code

    @staticmethod
    def _lines(items: list[str]) -> bytes:
        return ("".join(f"{s} \n" for s in items[:-1]) + f"{items[-1]}\n").encode("ascii")

    def handle(self, request: bytes) -> bytes:
        now = time.monotonic()
        if len(request) == 1 and request[0] in CONTROL_BYTES:
            name = CONTROL_BYTES[request[0]]
            self.commands.append(name)
            if name == "#5":
                mask = sum(1 << i for i, ax in enumerate(self.axes.values()) if ax.moving(now))
                return f"{mask:X}\n".encode()
            if name == "#7":
                return b"\xb1\n"
            for ax in self.axes.values():  # #24: stop all
                ax.go(ax.position(now), now)
            self._set_error(10)
            return b""
        try:
            text = request.decode("ascii").strip()
        except UnicodeDecodeError:
            self._set_error(1)
            return b""
        if not text:
            return b""
        self.commands.append(text)
        words = text.split()
        cmd, args = words[0].upper(), words[1:]
        try:
            return self._dispatch(cmd, args, now)
        except (ValueError, IndexError):
            self._set_error(1)
            return b""

    def _targets(self, args: list[str]) -> list[tuple[str, float]] | None:
        if not args or len(args) % 2:
            self._set_error(1)
            return None
        pairs = [(args[i], float(args[i + 1])) for i in range(0, len(args), 2)]
        if any(a not in self.axes for a, _ in pairs):
            self._set_error(15)
            return None
        return pairs

    def _axes_of(self, args: list[str]) -> list[str] | None:
        names = args or list(self.axes)
        if any(a not in self.axes for a in names):
            self._set_error(15)
            return None
        return names

    def _dispatch(self, cmd: str, args: list[str], now: float) -> bytes:
        if cmd == "*IDN?":
            return f"(c)2024 Physik Instrumente (PI) GmbH & Co. KG, {self.model}, 0000000001, 1.0.0-emu\n".encode()
        if cmd == "ERR?":
            code, self.error = self.error, 0
            return f"{code}\n".encode()
        queries = {
            "POS?": lambda ax: ax.position(now),
            "VEL?": lambda ax: ax.velocity,
            "ONT?": lambda ax: int(not ax.moving(now)),
            "SVO?": lambda ax: int(ax.servo),
            "FRF?": lambda ax: int(ax.referenced),
            "TMN?": lambda ax: ax.low,
            "TMX?": lambda ax: ax.high,
        }
        if cmd in queries:
            names = self._axes_of(args)
            if names is None:
                return b""
            return self._lines([f"{a}={_fmt(queries[cmd](self.axes[a]))}" for a in names])
        if cmd == "SVO":
            pairs = self._targets(args)
            for a, v in pairs or []:
                self.axes[a].servo = bool(int(v))
            return b""
        if cmd == "FRF":
            names = self._axes_of(args)
            for a in names or []:
                ax = self.axes[a]
                if not ax.servo:
                    self._set_error(5)
                    continue
                ax.start = ax.target = self.reference_mm
                ax.referenced = True
            return b""
        if cmd in ("MOV", "MVR"):
            pairs = self._targets(args)
            if pairs is None:
                return b""
            for a, v in pairs:
                ax = self.axes[a]
                if not (ax.servo and ax.referenced):
                    self._set_error(5)
                    return b""
                target = v if cmd == "MOV" else ax.target + v
                if not ax.low <= target <= ax.high:
                    self._set_error(7)
                    return b""
            for a, v in pairs:
                ax = self.axes[a]
                ax.go(v if cmd == "MOV" else ax.target + v, now)
            return b""
        if cmd == "VEL":
            pairs = self._targets(args)
            for a, v in pairs or []:
                if not 0 < v <= self.axes[a].max_velocity:
                    self._set_error(17)
                    return b""
            for a, v in pairs or []:
                ax = self.axes[a]
                ax.go(ax.target, now)  # re-base the running move at the old speed
                ax.velocity = v
            return b""
        if cmd == "HLT":
            names = self._axes_of(args)
            for a in names or []:
                ax = self.axes[a]
                ax.go(ax.position(now), now)
            self._set_error(10)
            return b""
        self._set_error(2)
        return b""


def _fmt(value: float) -> str:
    return f"{value:.6f}" if isinstance(value, float) else str(value)
