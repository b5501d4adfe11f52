"""Emulator of a PI GCS 2.0 stage controller (C-863 Mercury class) on a pseudo-terminal.

Speaks what the project's driver (:mod:`scopetwin.instrument.drivers.pi_gcs`) and PI's own
Python client (pipython's ``GCSDevice`` and ``pitools``) send: LF-terminated
commands; set commands are silent and keep an error code for ``ERR?``; queries
answer one line per item, every line but the last ending in a space before the
LF; the single bytes ``#5`` (motion mask), ``#7`` (controller ready) and ``#24``
(stop all) are answered or obeyed at once. Axes move at their velocity in real
time, so ``#5`` and ``ONT?`` change while a move runs.

Like a controller, the emulator is silent where a controller is: after a set
command, after an unknown command (error 2, also for an unknown query) and
after a query on an unknown axis (error 15). Commands understood (GCS 2.0, as
listed by the C-863's ``HLP?``):

``*IDN?``, ``CSV?``, ``VER?``, ``HLP?``, ``HPA?``, ``ERR?``, ``SAI?`` (``SAI? ALL``),
``CST``/``CST?``, ``TRS?``, ``LIM?``, ``RON``/``RON?``, ``SVO``/``SVO?``, ``FRF``/``FRF?``,
``FNL``, ``FPL``, ``POS``/``POS?``, ``MOV``/``MOV?``, ``MVR``, ``ONT?``, ``VEL``/``VEL?``,
``TMN?``, ``TMX?``, ``SPA``/``SPA?``, ``HLT``, ``STP``, ``#5``, ``#7``, ``#24``.

Parameters (``SPA?``/``SPA``, ids of the C-863 manual): 0xA maximum closed-loop
velocity (the largest value ``VEL`` accepts), 0x49 closed-loop velocity (what
``VEL`` sets), 0x3C stage name (what ``CST`` sets).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

from scopetwin.instrument.emulators.base import PtyEmulator, finite_span, number_in

#: Largest travel (mm, either side of the origin) and velocity (mm/s) an emulated PI stage may have.
MAX_TRAVEL_MM = 2_000.0
MAX_VELOCITY_MM_S = 1_000.0

CONTROL_BYTES = {0x05: "#5", 0x07: "#7", 0x18: "#24"}

#: GCS error codes the emulator sets (PI's numbers).
E_PARAM_SYNTAX, E_UNKNOWN_COMMAND, E_MOVE_WITHOUT_REF_OR_NO_SERVO, E_POS_OUT_OF_LIMITS = 1, 2, 5, 7
E_STOP, E_INVALID_AXIS, E_PARAM_OUT_OF_RANGE, E_UNKNOWN_PARAMETER = 10, 15, 17, 54
E_REF_WITH_REF_DISABLED = 50

#: Commands listed by ``HLP?`` (and so reported as supported to pipython), with a description.
COMMANDS: dict[str, str] = {
    "#5": "Request Motion Status",
    "#7": "Request Controller Ready Status",
    "#24": "Stop All Axes",
    "*IDN?": "Get Device Identification",
    "CST": "Set Assignment Of Stages To Axes",
    "CST?": "Get Assignment Of Stages To Axes",
    "CSV?": "Get Current Syntax Version",
    "ERR?": "Get Error Number",
    "FNL": "Fast Reference Move To Negative Limit",
    "FPL": "Fast Reference Move To Positive Limit",
    "FRF": "Fast Reference Move To Reference Switch",
    "FRF?": "Get Referencing Result",
    "HLP?": "Get List Of Available Commands",
    "HLT": "Halt Motion Smoothly",
    "HPA?": "Get List Of Available Parameters",
    "LIM?": "Indicate Limit Switches",
    "MOV": "Set Target Position",
    "MOV?": "Get Target Position",
    "MVR": "Set Target Relative To Current Position",
    "ONT?": "Get On Target State",
    "POS": "Set Real Position",
    "POS?": "Get Real Position",
    "RON": "Set Reference Mode",
    "RON?": "Get Reference Mode",
    "SAI?": "Get List Of Current Axis Identifiers",
    "SPA": "Set Volatile Memory Parameters",
    "SPA?": "Get Volatile Memory Parameters",
    "STP": "Stop All Axes",
    "SVO": "Set Servo Mode",
    "SVO?": "Get Servo Mode",
    "TMN?": "Get Minimum Commandable Position",
    "TMX?": "Get Maximum Commandable Position",
    "TRS?": "Indicate Reference Switch",
    "VEL": "Set Closed-Loop Velocity",
    "VEL?": "Get Closed-Loop Velocity",
    "VER?": "Get Versions Of Firmware And Drivers",
}

#: Parameters listed by ``HPA?``: id -> (data type, description); all per axis.
PARAMETERS: dict[int, tuple[str, str]] = {
    0x0A: ("FLOAT", "Maximum closed-loop velocity (phys. unit/s)"),
    0x3C: ("CHAR", "Stage name"),
    0x49: ("FLOAT", "Closed-loop velocity (phys. unit/s)"),
}


@dataclass
class _Axis:
    low: float
    high: float
    max_velocity: float
    velocity: float
    stage: str = "M-404.6PD"
    start: float = 0.0
    target: float = 0.0
    t0: float = 0.0
    servo: bool = False
    referenced: bool = False
    reference_mode: bool = True
    extra: dict[int, str] = field(default_factory=dict)

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
    """A GCS 2.0 controller with one or more linear axes.

    Parameters
    ----------
    axes : tuple of str
        Axis identifiers (``("1",)`` for a C-863).
    travel_mm : tuple of float
        Hardware travel limits (``TMN?``/``TMX?``), e.g. (0, 150) for an M-404.6PD.
    max_velocity_mm_s : float
        Largest velocity ``VEL`` accepts (parameter 0xA).
    reference_mm : float
        Position after a reference move to the reference switch (``FRF``).
    model : str
        Controller model in the ``*IDN?`` answer.
    stage : str
        Stage name reported by ``CST?``.
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
        stage: str = "M-404.6PD",
        seed: int = 0,
        fault: str = "none",
        fault_after: int = 0,
    ) -> None:
        super().__init__(seed=seed, fault=fault, fault_after=fault_after)
        travel_mm = finite_span(travel_mm, "travel_mm", -MAX_TRAVEL_MM, MAX_TRAVEL_MM)
        max_velocity_mm_s = number_in(max_velocity_mm_s, "max_velocity_mm_s", 1e-6, MAX_VELOCITY_MM_S)
        reference_mm = number_in(reference_mm, "reference_mm", *travel_mm)
        if not axes or not all(isinstance(a, str) and a.isdigit() and len(a) <= 2 for a in axes):
            raise ValueError(f"axes must be a list of GCS axis numbers (1, 2, ...), got {axes!r}")
        self.axes = {
            a: _Axis(travel_mm[0], travel_mm[1], max_velocity_mm_s, max_velocity_mm_s, stage=stage) for a in axes
        }
        self.reference_mm = float(reference_mm)
        self.model = model
        self.error = 0
        self.commands: list[str] = []

    def position_mm(self, axis: str = "1") -> float:
        """Where ``axis`` is now (mm), mid-move included."""
        return self.axes[axis].position(time.monotonic())

    # state for logs ----------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        """Position (mm), servo and referenced of the first axis, and the same per axis (plus target, moving)."""
        now = time.monotonic()
        first = next(iter(self.axes.values()))
        return {
            "position_mm": first.position(now),
            "servo": first.servo,
            "referenced": first.referenced,
            "axes": {
                name: {
                    "position_mm": ax.position(now),
                    "target_mm": ax.target,
                    "servo": ax.servo,
                    "referenced": ax.referenced,
                    "moving": ax.moving(now),
                }
                for name, ax in self.axes.items()
            },
            "error": self.error,
        }

    # framing -----------------------------------------------------------------------------------
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
                return b"\xb1\n"  # 0xB1: controller ready
            self._stop_all(now)
            return b""
        try:
            text = request.decode("ascii").strip()
        except UnicodeDecodeError:
            self._set_error(E_PARAM_SYNTAX)
            return b""
        if not text:
            return b""
        self.commands.append(text)
        words = text.split()
        cmd, args = words[0].upper(), words[1:]
        try:
            return self._dispatch(cmd, args, now)
        except (ValueError, IndexError):
            self._set_error(E_PARAM_SYNTAX)
            return b""

    def _stop_all(self, now: float) -> None:
        for ax in self.axes.values():
            ax.go(ax.position(now), now)
        self._set_error(E_STOP)

    # argument helpers --------------------------------------------------------------------------------
    def _pairs(self, args: list[str]) -> list[tuple[str, str]] | None:
        if not args or len(args) % 2:
            self._set_error(E_PARAM_SYNTAX)
            return None
        pairs = [(args[i], args[i + 1]) for i in range(0, len(args), 2)]
        if any(a not in self.axes for a, _ in pairs):
            self._set_error(E_INVALID_AXIS)
            return None
        return pairs

    def _targets(self, args: list[str]) -> list[tuple[str, float]] | None:
        pairs = self._pairs(args)
        return None if pairs is None else [(a, float(v)) for a, v in pairs]

    def _axes_of(self, args: list[str]) -> list[str] | None:
        names = args or list(self.axes)
        if any(a not in self.axes for a in names):
            self._set_error(E_INVALID_AXIS)
            return None
        return names

    def _param(self, ax: _Axis, pid: int) -> str:
        values: dict[int, object] = {0x0A: ax.max_velocity, 0x3C: ax.stage, 0x49: ax.velocity}
        return _fmt(values[pid])

    # commands ------------------------------------------------------------------------------------
    def _dispatch(self, cmd: str, args: list[str], now: float) -> bytes:
        """Run one GCS command through :attr:`_HANDLERS`; an unknown one sets error 2 and answers nothing."""
        handler = self._HANDLERS.get(cmd)
        if handler is None:
            self._set_error(E_UNKNOWN_COMMAND)
            return b""
        return handler(self, cmd, args, now)

    def _cmd_idn(self, cmd: str, args: list[str], now: float) -> bytes:
        """``*IDN?``: the identification line."""
        return f"(c)2024 Physik Instrumente (PI) GmbH & Co. KG, {self.model}, 0000000001, 1.0.0-emu\n".encode()

    def _cmd_err(self, cmd: str, args: list[str], now: float) -> bytes:
        """``ERR?``: the kept error code, which the query clears."""
        code, self.error = self.error, 0
        return f"{code}\n".encode()

    def _cmd_csv(self, cmd: str, args: list[str], now: float) -> bytes:
        """``CSV?``: the GCS syntax version."""
        return b"2.0\n"

    def _cmd_ver(self, cmd: str, args: list[str], now: float) -> bytes:
        """``VER?``: the firmware version."""
        return self._lines([f"FW_ARM: V1.0.0 scopetwin emulator of the {self.model}"])

    def _cmd_hlp(self, cmd: str, args: list[str], now: float) -> bytes:
        """``HLP?``: the commands of :data:`COMMANDS`."""
        return self._lines(
            ["The following commands are valid:"]
            + [f"{name} {text}" for name, text in COMMANDS.items()]
            + ["end of help"]
        )

    def _cmd_hpa(self, cmd: str, args: list[str], now: float) -> bytes:
        """``HPA?``: the parameters of :data:`PARAMETERS`."""
        lines = ["The following parameters are valid:"]
        lines += [
            f"0x{pid:X}=\t0\t{len(self.axes)}\t{kind}\tmotion\t{text}" for pid, (kind, text) in PARAMETERS.items()
        ]
        return self._lines([*lines, "end of help"])

    def _cmd_sai(self, cmd: str, args: list[str], now: float) -> bytes:
        """``SAI?`` (or ``SAI? ALL``): the axis identifiers."""
        if args and [a.upper() for a in args] != ["ALL"]:
            self._set_error(E_PARAM_SYNTAX)
            return b""
        return self._lines(list(self.axes))

    def _cmd_axis_query(self, cmd: str, args: list[str], now: float) -> bytes:
        """A per-axis query of :attr:`_AXIS_QUERIES` (``POS?``, ``ONT?``, ...): one ``axis=value`` line per axis."""
        names = self._axes_of(args)
        if names is None:
            return b""
        return self._lines([f"{a}={_fmt(self._AXIS_QUERIES[cmd](self.axes[a], now))}" for a in names])

    def _cmd_spa_query(self, cmd: str, args: list[str], now: float) -> bytes:
        """``SPA?``: parameter values."""
        return self._spa_query(args)

    def _cmd_spa(self, cmd: str, args: list[str], now: float) -> bytes:
        """``SPA``: set parameters."""
        self._spa_set(args)
        return b""

    def _cmd_cst(self, cmd: str, args: list[str], now: float) -> bytes:
        """``CST``: name the stage on each axis."""
        for a, stage_name in self._pairs(args) or []:
            self.axes[a].stage = stage_name
        return b""

    def _cmd_svo(self, cmd: str, args: list[str], now: float) -> bytes:
        """``SVO``: servo on or off per axis."""
        for a, v in self._targets(args) or []:
            self.axes[a].servo = bool(int(v))
        return b""

    def _cmd_ron(self, cmd: str, args: list[str], now: float) -> bytes:
        """``RON``: reference mode on or off per axis."""
        for a, v in self._targets(args) or []:
            self.axes[a].reference_mode = bool(int(v))
        return b""

    def _cmd_reference(self, cmd: str, args: list[str], now: float) -> bytes:
        """``FRF``, ``FNL``, ``FPL``: reference moves."""
        self._reference(cmd, args)
        return b""

    def _cmd_pos(self, cmd: str, args: list[str], now: float) -> bytes:
        """``POS``: set the real position (only with reference mode off), which marks the axis referenced."""
        pairs = self._targets(args)
        for a, v in pairs or []:
            ax = self.axes[a]
            if ax.reference_mode:  # POS is only allowed with reference mode off
                self._set_error(E_PARAM_OUT_OF_RANGE)
                return b""
            ax.start = ax.target = v
            ax.t0 = now
            ax.referenced = True
        return b""

    def _cmd_move(self, cmd: str, args: list[str], now: float) -> bytes:
        """``MOV``, ``MVR``: absolute and relative moves."""
        self._move(cmd, args, now)
        return b""

    def _cmd_vel(self, cmd: str, args: list[str], now: float) -> bytes:
        """``VEL``: closed-loop velocities, all within 0 < v <= the maximum or none set."""
        pairs = self._targets(args)
        for a, v in pairs or []:
            if not 0 < v <= self.axes[a].max_velocity:
                self._set_error(E_PARAM_OUT_OF_RANGE)
                return b""
        for a, v in pairs or []:
            ax = self.axes[a]
            ax.go(ax.target, now)  # re-base the running move at the old speed
            ax.velocity = v
        return b""

    def _cmd_hlt(self, cmd: str, args: list[str], now: float) -> bytes:
        """``HLT``: stop the named axes (default all) where they are; sets error 10."""
        for a in self._axes_of(args) or []:
            ax = self.axes[a]
            ax.go(ax.position(now), now)
        self._set_error(E_STOP)
        return b""

    def _cmd_stp(self, cmd: str, args: list[str], now: float) -> bytes:
        """``STP``: stop all axes; sets error 10."""
        self._stop_all(now)
        return b""

    #: Per-axis queries: command -> the value of an axis at time ``now``.
    _AXIS_QUERIES = {
        "POS?": lambda ax, now: ax.position(now),
        "MOV?": lambda ax, now: ax.target,
        "VEL?": lambda ax, now: ax.velocity,
        "ONT?": lambda ax, now: int(not ax.moving(now)),
        "SVO?": lambda ax, now: int(ax.servo),
        "FRF?": lambda ax, now: int(ax.referenced),
        "RON?": lambda ax, now: int(ax.reference_mode),
        "TRS?": lambda ax, now: 1,  # the M-404 / M-414 stages have a reference switch
        "LIM?": lambda ax, now: 1,  # ... and limit switches
        "CST?": lambda ax, now: ax.stage,
        "TMN?": lambda ax, now: ax.low,
        "TMX?": lambda ax, now: ax.high,
    }

    #: The command table: command -> handler(self, cmd, args, now) returning the answer bytes.
    _HANDLERS = {
        "*IDN?": _cmd_idn,
        "ERR?": _cmd_err,
        "CSV?": _cmd_csv,
        "VER?": _cmd_ver,
        "HLP?": _cmd_hlp,
        "HPA?": _cmd_hpa,
        "SAI?": _cmd_sai,
        **dict.fromkeys(_AXIS_QUERIES, _cmd_axis_query),
        "SPA?": _cmd_spa_query,
        "SPA": _cmd_spa,
        "CST": _cmd_cst,
        "SVO": _cmd_svo,
        "RON": _cmd_ron,
        **dict.fromkeys(("FRF", "FNL", "FPL"), _cmd_reference),
        "POS": _cmd_pos,
        **dict.fromkeys(("MOV", "MVR"), _cmd_move),
        "VEL": _cmd_vel,
        "HLT": _cmd_hlt,
        "STP": _cmd_stp,
    }

    def _reference(self, cmd: str, args: list[str]) -> None:
        names = self._axes_of(args)
        for a in names or []:
            ax = self.axes[a]
            if not ax.servo:
                self._set_error(E_MOVE_WITHOUT_REF_OR_NO_SERVO)
                continue
            if not ax.reference_mode:
                self._set_error(E_REF_WITH_REF_DISABLED)
                continue
            position = {"FRF": self.reference_mm, "FNL": ax.low, "FPL": ax.high}[cmd]
            ax.start = ax.target = position
            ax.referenced = True

    def _move(self, cmd: str, args: list[str], now: float) -> None:
        pairs = self._targets(args)
        if pairs is None:
            return
        for a, v in pairs:
            ax = self.axes[a]
            if not (ax.servo and (ax.referenced or not ax.reference_mode)):
                self._set_error(E_MOVE_WITHOUT_REF_OR_NO_SERVO)
                return
            target = v if cmd == "MOV" else ax.target + v
            if not ax.low <= target <= ax.high:
                self._set_error(E_POS_OUT_OF_LIMITS)
                return
        for a, v in pairs:
            ax = self.axes[a]
            ax.go(v if cmd == "MOV" else ax.target + v, now)

    def _spa_items(self, args: list[str]) -> list[tuple[str, int]] | None:
        if len(args) % 2:
            self._set_error(E_PARAM_SYNTAX)
            return None
        items = [(args[i], int(args[i + 1], 0)) for i in range(0, len(args), 2)]
        if not items:
            items = [(a, pid) for a in self.axes for pid in PARAMETERS]
        if any(a not in self.axes for a, _ in items):
            self._set_error(E_INVALID_AXIS)
            return None
        if any(pid not in PARAMETERS for _, pid in items):
            self._set_error(E_UNKNOWN_PARAMETER)
            return None
        return items

    def _spa_query(self, args: list[str]) -> bytes:
        items = self._spa_items(args)
        if items is None:
            return b""
        return self._lines([f"{a} 0x{pid:X}={self._param(self.axes[a], pid)}" for a, pid in items])

    def _spa_set(self, args: list[str]) -> None:
        if not args or len(args) % 3:
            self._set_error(E_PARAM_SYNTAX)
            return
        for i in range(0, len(args), 3):
            a, pid, value = args[i], int(args[i + 1], 0), args[i + 2]
            if a not in self.axes:
                self._set_error(E_INVALID_AXIS)
                return
            if pid not in PARAMETERS:
                self._set_error(E_UNKNOWN_PARAMETER)
                return
            ax = self.axes[a]
            if pid == 0x3C:
                ax.stage = value
                continue
            number = float(value)
            if pid == 0x0A:
                ax.max_velocity = number
            elif pid == 0x49:
                if not 0 < number <= ax.max_velocity:
                    self._set_error(E_PARAM_OUT_OF_RANGE)
                    return
                ax.velocity = number


def _fmt(value: object) -> str:
    return f"{value:.6f}" if isinstance(value, float) else str(value)
