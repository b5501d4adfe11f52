"""Device protocols of the microscope's control surface (thesis §4.3.2).

One abstract class per kind of device: :class:`CameraDevice`, :class:`Stage`,
:class:`FocusDrive`, :class:`LightSource`, :class:`Shutter` and
:class:`TriggerController`. Their public methods validate every request
against limits held as data (:class:`Range`), raising
:class:`~scopetwin.instrument.errors.OutOfRangeError` *before* anything is sent, and then
call small private hooks (``_do_move_absolute``, ``_do_configure``, ...) that a
simulated device or a hardware driver implements. Code above this layer
(acquisition, rigs, the CLI) only ever sees these classes.

Units are in the names: millimetres for stage positions, micrometres for the
focus drive (``_um``), seconds (``_s``), milliamperes (``_ma``), hertz (``fps``),
decibels for gain (``_db``) and digital numbers for grey values (``_dn``).

The trigger model follows python-microscope's: a :class:`TriggerType` (what
starts an exposure: software, or an electrical edge such as the FPGA board's
global trigger line) and a :class:`TriggerMode` (one frame per trigger, or bulb:
exposure lasts while the line is high).

Every device keeps what it knows of its own state from the requests it sent
(:meth:`Device.known_state`): a light that was told to go on and never
acknowledged going off *may still be on*; a stage told to move and never seen to
arrive *may still be moving*. When a device stops answering, that is all anyone
knows, and the rig says it (:meth:`scopetwin.instrument.rig.Rig.close`).
"""

from __future__ import annotations

import abc
import enum
import math
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, replace
from typing import Any, ClassVar

import numpy as np
from numpy.typing import NDArray

from scopetwin.instrument.errors import DisconnectedError, InstrumentTimeout, OutOfRangeError

FloatImage = NDArray[np.float32]


class TriggerType(enum.Enum):
    """What starts an exposure (python-microscope's ``TriggerType`` idea)."""

    SOFTWARE = "software"
    RISING_EDGE = "rising-edge"
    FALLING_EDGE = "falling-edge"


class TriggerMode(enum.Enum):
    """How a trigger maps to frames: one frame per trigger, or exposure while the line is high."""

    ONCE = "once"
    BULB = "bulb"


@dataclass(frozen=True)
class Range:
    """A closed interval of allowed values, with its unit, checked before any I/O.

    Parameters
    ----------
    low, high : float
        Inclusive bounds.
    unit : str
        Unit of the bounds (``"mm"``, ``"um"``, ``"s"``, ``"mA"``, ...), used in messages.
    """

    low: float
    high: float
    unit: str = ""

    def __post_init__(self) -> None:
        if not (math.isfinite(self.low) and math.isfinite(self.high)) or self.low > self.high:
            raise OutOfRangeError(f"invalid range [{self.low}, {self.high}] {self.unit}")

    def check(self, value: float, what: str) -> float:
        """Return ``value`` as float if it lies in the range, else raise ``OutOfRangeError`` naming ``what``."""
        try:
            v = float(value)
        except (TypeError, ValueError) as exc:
            raise OutOfRangeError(f"{what}: {value!r} is not a number") from exc
        if not math.isfinite(v) or v < self.low or v > self.high:
            raise OutOfRangeError(f"{what}: {value} {self.unit} is outside [{self.low}, {self.high}] {self.unit}")
        return v

    def as_list(self) -> list[float]:
        """``[low, high]`` for JSON output."""
        return [self.low, self.high]


class Device:
    """Base of every device: a name, a lifecycle and a description.

    ``initialize()`` does the handshake (identification, servo on, remote
    mode); ``shutdown()`` brings the device to its safe state (lights off,
    shutter closed, acquisition stopped) and releases it. Neither moves an axis.
    """

    kind: ClassVar[str] = "device"

    def __init__(self, name: str) -> None:
        self.name = name
        self._initialized = False

    def links(self) -> tuple[Any, ...]:
        """The serial lines (:class:`scopetwin.instrument.transport.Link`) this device talks through (none: simulated
        or not on a serial line)."""
        return ()

    def known_state(self) -> str:
        """What is known of the device's state from the requests sent (for a message when it stops answering)."""
        return ""

    def state_is_safe(self) -> bool:
        """Whether :meth:`known_state` is safe (a light off, a shutter closed, an axis at rest)."""
        return True

    def abandon(self) -> None:
        """Forget the device without sending anything (it stopped answering); :meth:`known_state` stays."""
        self._initialized = False

    # lifecycle -----------------------------------------------------------------------------
    def initialize(self) -> None:
        """Handshake with the device (idempotent)."""
        if not self._initialized:
            self._do_initialize()
            self._initialized = True

    def shutdown(self) -> None:
        """Put the device into its safe state, then release it (idempotent; never moves an axis)."""
        if not self._initialized:
            return
        try:
            self._do_safe_state()
        finally:
            self._initialized = False
            self._do_shutdown()

    @property
    def initialized(self) -> bool:
        """Whether :meth:`initialize` has run and :meth:`shutdown` has not."""
        return self._initialized

    def _require(self) -> None:
        if not self._initialized:
            raise DisconnectedError(f"{self.kind} {self.name!r} is not initialized (or already shut down)")

    def describe(self) -> dict[str, Any]:
        """Name, kind, implementation and limits, as JSON-ready data."""
        return {"name": self.name, "kind": self.kind, "driver": self.driver_name(), **self._limits()}

    def driver_name(self) -> str:
        """Short name of the implementation (``sim``, ``pi-gcs``, ...)."""
        return getattr(self, "driver", type(self).__name__)

    def _limits(self) -> dict[str, Any]:
        return {}

    # hooks ----------------------------------------------------------------------------------
    def _do_initialize(self) -> None:
        """Handshake hook."""

    def _do_safe_state(self) -> None:
        """Safe-state hook (lights off, shutter closed)."""

    def _do_shutdown(self) -> None:
        """Release hook (close transports)."""

    def __enter__(self):
        self.initialize()
        return self

    def __exit__(self, *exc: object) -> None:
        self.shutdown()


# --------------------------------------------------------------------------------------------
class Stage(Device):
    """One linear axis of a lateral stage (thesis §4.2.2: PI M-404.6PD, M-414.3PD on C-863).

    Parameters
    ----------
    name : str
        Device name in the rig.
    travel_mm : tuple of float
        Allowed positions ``(low, high)`` in mm, enforced before any command is sent.
    max_velocity_mm_s : float
        Largest allowed velocity in mm/s (50 for the M-404.6PD, 100 for the M-414.3PD).
    settle_timeout_s : float
        Extra time allowed beyond ``distance / velocity`` when waiting for a move to end.
    """

    kind = "stage"

    def __init__(
        self, name: str, *, travel_mm: tuple[float, float], max_velocity_mm_s: float, settle_timeout_s: float = 2.0
    ) -> None:
        super().__init__(name)
        self.travel = Range(float(travel_mm[0]), float(travel_mm[1]), "mm")
        self.velocity_range = Range(1e-6, float(max_velocity_mm_s), "mm/s")
        self.settle_timeout_s = float(settle_timeout_s)
        self._last_mm: float | None = None  # the position last read or arrived at
        self._target_mm: float | None = None  # the target of a move not yet seen to end

    def _limits(self) -> dict[str, Any]:
        return {"travel_mm": self.travel.as_list(), "max_velocity_mm_s": self.velocity_range.high}

    def known_state(self) -> str:
        """``stage 'x' may still be moving to 100 mm (last read at 12.5 mm)``, or where it was last seen."""
        last = "position never read" if self._last_mm is None else f"last read at {self._last_mm:g} mm"
        if self._target_mm is not None:
            return f"stage {self.name!r} may still be moving to {self._target_mm:g} mm ({last})"
        return f"stage {self.name!r} at rest ({last})"

    def state_is_safe(self) -> bool:
        """At rest: no move under way that was not seen to end."""
        return self._target_mm is None

    def _read_position(self) -> float:
        value = float(self._do_get_position())
        self._last_mm = value
        return value

    @property
    def position_mm(self) -> float:
        """Current position in mm (thesis §4.3.2 'Information: Position')."""
        self._require()
        return self._read_position()

    @property
    def velocity_mm_s(self) -> float:
        """Current velocity setting in mm/s."""
        self._require()
        return float(self._do_get_velocity())

    def set_velocity(self, velocity_mm_s: float) -> None:
        """Set the velocity (mm/s), checked against ``(0, max_velocity_mm_s]`` first."""
        v = self.velocity_range.check(velocity_mm_s, f"stage {self.name!r} velocity")
        self._require()
        self._do_set_velocity(v)

    def move_absolute(self, position_mm: float, wait: bool = True) -> None:
        """Move to ``position_mm``; the target is checked against the travel range before any I/O."""
        target = self.travel.check(position_mm, f"stage {self.name!r} target position")
        self._require()
        start = self._read_position() if wait else target
        self._target_mm = target
        self._do_move_absolute(target)
        if wait:
            self.wait_until_stopped(abs(target - start))

    def move_relative(self, delta_mm: float, wait: bool = True) -> None:
        """Move by ``delta_mm``; the resulting target is checked against the travel range before moving."""
        self._require()
        span = self.travel.high - self.travel.low
        d = Range(-span, span, "mm").check(delta_mm, f"stage {self.name!r} step")
        here = self._read_position()
        self.travel.check(here + d, f"stage {self.name!r} target position ({here} mm + {d} mm)")
        self._target_mm = here + d
        self._do_move_relative(d)
        if wait:
            self.wait_until_stopped(abs(d))

    def is_moving(self) -> bool:
        """Whether the axis is in motion."""
        self._require()
        return bool(self._do_is_moving())

    def wait_until_stopped(self, distance_mm: float = 0.0) -> None:
        """Wait for the move to end; raise ``InstrumentTimeout`` after ``distance/velocity + settle``."""
        velocity = max(self._do_get_velocity(), 1e-9)
        deadline = time.monotonic() + distance_mm / velocity + self.settle_timeout_s
        while self._do_is_moving():
            if time.monotonic() > deadline:
                raise InstrumentTimeout(f"stage {self.name!r} still moving after {distance_mm} mm")
            time.sleep(0.002)
        if self._target_mm is not None:
            self._last_mm, self._target_mm = self._target_mm, None

    def halt(self) -> None:
        """Stop the axis now."""
        self._require()
        self._do_halt()
        self._target_mm, self._last_mm = None, None

    # hooks
    @abc.abstractmethod
    def _do_get_position(self) -> float: ...

    @abc.abstractmethod
    def _do_get_velocity(self) -> float: ...

    @abc.abstractmethod
    def _do_set_velocity(self, velocity_mm_s: float) -> None: ...

    @abc.abstractmethod
    def _do_move_absolute(self, position_mm: float) -> None: ...

    @abc.abstractmethod
    def _do_move_relative(self, delta_mm: float) -> None: ...

    @abc.abstractmethod
    def _do_is_moving(self) -> bool: ...

    @abc.abstractmethod
    def _do_halt(self) -> None: ...


# --------------------------------------------------------------------------------------------
class FocusDrive(Device):
    """Objective positioner (thesis §4.2.3: piezosystem jena MIPOS500, 0-400 µm closed loop).

    Parameters
    ----------
    name : str
        Device name in the rig.
    range_um : tuple of float
        Allowed positions in µm, enforced before any command is sent.
    tolerance_um : float
        A move has arrived when the read-back position is within this distance of the target.
    settle_timeout_s : float
        How long a move may take to arrive.
    """

    kind = "focus"

    def __init__(
        self,
        name: str,
        *,
        range_um: tuple[float, float] = (0.0, 400.0),
        tolerance_um: float = 0.05,
        settle_timeout_s: float = 1.0,
    ) -> None:
        super().__init__(name)
        self.range = Range(float(range_um[0]), float(range_um[1]), "um")
        self.tolerance_um = float(tolerance_um)
        self.settle_timeout_s = float(settle_timeout_s)
        self._last_um: float | None = None  # the position last read
        self._target_um: float | None = None  # the target of a move not yet seen to arrive

    def _limits(self) -> dict[str, Any]:
        return {"range_um": self.range.as_list()}

    def known_state(self) -> str:
        """``focus 'z' may still be moving to 300 um (last read at 12 um)``, or where it was last seen."""
        last = "position never read" if self._last_um is None else f"last read at {self._last_um:g} um"
        if self._target_um is not None:
            return f"focus {self.name!r} may still be moving to {self._target_um:g} um ({last})"
        return f"focus {self.name!r} at rest ({last})"

    def state_is_safe(self) -> bool:
        """At rest: no move under way that was not seen to arrive."""
        return self._target_um is None

    def _read_position_um(self) -> float:
        value = float(self._do_get_position_um())
        self._last_um = value
        return value

    @property
    def position_um(self) -> float:
        """Current position in µm."""
        self._require()
        return self._read_position_um()

    def move_absolute_um(self, position_um: float, wait: bool = True) -> None:
        """Move to ``position_um``, checked against ``range_um`` before any I/O."""
        target = self.range.check(position_um, f"focus {self.name!r} target")
        self._require()
        self._target_um = target
        self._do_move_absolute_um(target)
        if wait:
            deadline = time.monotonic() + self.settle_timeout_s
            while abs(self._read_position_um() - target) > self.tolerance_um:
                if time.monotonic() > deadline:
                    raise InstrumentTimeout(f"focus {self.name!r} did not reach {target} um")
                time.sleep(0.002)
            self._target_um = None

    def move_relative_um(self, delta_um: float, wait: bool = True) -> None:
        """Move by ``delta_um``; the target is checked against ``range_um`` before moving."""
        self._require()
        here = self._read_position_um()
        self.move_absolute_um(self.range.check(here + float(delta_um), f"focus {self.name!r} target"), wait)

    @abc.abstractmethod
    def _do_get_position_um(self) -> float: ...

    @abc.abstractmethod
    def _do_move_absolute_um(self, position_um: float) -> None: ...


# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LightConfig:
    """Settings of one light source (thesis §4.3.2 'Light sources', Table 4.2 fields).

    Attributes
    ----------
    current_ma : float
        Drive current in mA.
    duration_s : float
        On-time after a trigger when ``use_duration`` is set.
    use_duration : bool
        If False a trigger switches the light on until :meth:`LightSource.switch_off`.
    listen_global_trigger : bool
        Whether the global trigger switches this light on.
    global_trigger_delay_s : float
        Delay between the global trigger and switching on.
    """

    current_ma: float = 0.0
    duration_s: float = 0.0
    use_duration: bool = False
    listen_global_trigger: bool = False
    global_trigger_delay_s: float = 0.0


MAX_TIMER_S = (2**32 - 1) * 1e-6  # 32-bit µs counters of Table 4.2


class LightSource(Device):
    """A current-controlled LED or a shuttered halogen source (thesis §4.1.1, §4.3.2).

    Parameters
    ----------
    name : str
        Device name in the rig.
    max_current_ma : float
        Largest allowed drive current in mA (the LED's rating), enforced before any I/O.
    """

    kind = "light"

    def __init__(self, name: str, *, max_current_ma: float) -> None:
        super().__init__(name)
        self.current_range = Range(0.0, float(max_current_ma), "mA")
        self.timer_range = Range(0.0, MAX_TIMER_S, "s")
        self._config = LightConfig()
        self._maybe_on = False  # told to go on and not acknowledged off since

    def _limits(self) -> dict[str, Any]:
        return {"max_current_ma": self.current_range.high}

    def known_state(self) -> str:
        """``light 'halogen' may still be on`` unless it acknowledged switching off (drivers switch off on
        initialisation)."""
        return f"light {self.name!r} " + ("may still be on" if self._maybe_on else "off")

    def state_is_safe(self) -> bool:
        """Off: every request to go on was followed by an acknowledged switch-off."""
        return not self._maybe_on

    @property
    def config(self) -> LightConfig:
        """The last configuration sent."""
        return self._config

    @property
    def current_ma(self) -> float:
        """Configured drive current in mA."""
        return self._config.current_ma

    def configure(self, **changes: Any) -> LightConfig:
        """Change any :class:`LightConfig` field; all values are validated before one byte is sent."""
        unknown = set(changes) - set(asdict(self._config))
        if unknown:
            raise OutOfRangeError(f"light {self.name!r}: unknown setting(s) {sorted(unknown)}")
        cfg = replace(self._config, **changes)
        cfg = LightConfig(
            current_ma=self.current_range.check(cfg.current_ma, f"light {self.name!r} current"),
            duration_s=self.timer_range.check(cfg.duration_s, f"light {self.name!r} duration"),
            use_duration=bool(cfg.use_duration),
            listen_global_trigger=bool(cfg.listen_global_trigger),
            global_trigger_delay_s=self.timer_range.check(
                cfg.global_trigger_delay_s, f"light {self.name!r} global trigger delay"
            ),
        )
        self._require()
        self._do_configure(cfg)
        self._config = cfg
        return cfg

    def set_current_ma(self, current_ma: float) -> None:
        """Set the drive current (mA), checked against ``max_current_ma`` first."""
        self.configure(current_ma=current_ma)

    def trigger(self) -> None:
        """Switch on now (for ``duration_s`` if ``use_duration``, else until switched off)."""
        self._require()
        self._maybe_on = True
        self._do_trigger()

    def switch_on(self, current_ma: float | None = None) -> None:
        """Configure a continuous on-state (optionally with a new current) and trigger."""
        changes: dict[str, Any] = {"use_duration": False}
        if current_ma is not None:
            changes["current_ma"] = current_ma
        self.configure(**changes)
        self.trigger()

    def switch_off(self) -> None:
        """Switch off now."""
        self._require()
        self._switch_off_now()

    def _switch_off_now(self) -> None:
        self._do_switch_off()
        self._maybe_on = False

    @property
    def is_on(self) -> bool:
        """Whether the source is emitting."""
        self._require()
        return bool(self._do_is_on())

    def _do_safe_state(self) -> None:
        self._switch_off_now()

    @abc.abstractmethod
    def _do_configure(self, config: LightConfig) -> None: ...

    @abc.abstractmethod
    def _do_trigger(self) -> None: ...

    @abc.abstractmethod
    def _do_switch_off(self) -> None: ...

    @abc.abstractmethod
    def _do_is_on(self) -> bool: ...


# --------------------------------------------------------------------------------------------
class Shutter(Device):
    """Mechanical shutter of the halogen source (thesis §4.1.1, driven by two TTL outputs, §4.3.1)."""

    kind = "shutter"
    _maybe_open = False  # told to open and not acknowledged closed since

    def known_state(self) -> str:
        """``shutter 's' may still be open`` unless it acknowledged closing."""
        return f"shutter {self.name!r} " + ("may still be open" if self._maybe_open else "closed")

    def state_is_safe(self) -> bool:
        """Closed: every request to open was followed by an acknowledged close."""
        return not self._maybe_open

    def open(self) -> None:
        """Open the shutter (light passes)."""
        self._require()
        self._maybe_open = True
        self._do_set_open(True)

    def close(self) -> None:
        """Close the shutter."""
        self._require()
        self._do_set_open(False)
        self._maybe_open = False

    @property
    def is_open(self) -> bool:
        """Whether the shutter is open."""
        self._require()
        return bool(self._do_is_open())

    def _do_safe_state(self) -> None:
        self._do_set_open(False)
        self._maybe_open = False

    @abc.abstractmethod
    def _do_set_open(self, is_open: bool) -> None: ...

    @abc.abstractmethod
    def _do_is_open(self) -> bool: ...


# --------------------------------------------------------------------------------------------
class TriggerController(Device):
    """Global trigger and camera trigger lines of the FPGA board (thesis §4.3.1, 'Global Trigger').

    Parameters
    ----------
    name : str
        Device name in the rig.
    n_camera_lines : int
        Number of camera trigger outputs (four D-Sub connectors on the thesis's board).
    """

    kind = "trigger"

    def __init__(self, name: str, *, n_camera_lines: int = 4) -> None:
        super().__init__(name)
        self.line_range = Range(0, int(n_camera_lines) - 1, "")
        self.delay_range = Range(0.0, MAX_TIMER_S, "s")

    def _limits(self) -> dict[str, Any]:
        return {"n_camera_lines": int(self.line_range.high) + 1}

    def _line(self, line: int) -> int:
        value = self.line_range.check(line, f"trigger {self.name!r} camera line")
        if value != int(value):
            raise OutOfRangeError(f"trigger {self.name!r}: camera line {line} is not an integer")
        return int(value)

    def configure_camera_line(
        self, line: int, listen_global_trigger: bool, global_trigger_delay_s: float = 0.0
    ) -> None:
        """Make camera line ``line`` follow the global trigger after ``global_trigger_delay_s``."""
        index = self._line(line)
        delay = self.delay_range.check(global_trigger_delay_s, f"trigger {self.name!r} line {line} delay")
        self._require()
        self._do_configure_camera_line(index, bool(listen_global_trigger), delay)

    def trigger_camera(self, line: int) -> None:
        """Pulse one camera trigger line now."""
        index = self._line(line)
        self._require()
        self._do_trigger_camera(index)

    def fire(self) -> None:
        """Fire the global trigger: every listening light and camera line starts after its delay."""
        self._require()
        self._do_fire()

    @abc.abstractmethod
    def _do_configure_camera_line(self, line: int, listen: bool, delay_s: float) -> None: ...

    @abc.abstractmethod
    def _do_trigger_camera(self, line: int) -> None: ...

    @abc.abstractmethod
    def _do_fire(self) -> None: ...


# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraLimits:
    """What a camera model allows; every setter checks against these before any I/O.

    Attributes
    ----------
    sensor_shape : tuple of int
        ``(rows, cols)`` of the full sensor (1040 x 1392 for the scA1400-30gm, thesis §4.1.4).
    pixel_size_um : float
        Pixel pitch in µm (6.45 for the ICX285AL).
    magnification : float
        Magnification of the optics in front of the sensor (10 for the thesis's 10x objective with its
        tube lens, §4.1.2): an image pixel covers ``pixel_size_um / magnification`` of the sample.
    exposure_s, gain_db, black_level_dn, fps : Range
        Allowed settings.
    bit_depths : tuple of int
        ADC depths the camera can deliver (12 bit for the thesis's camera).
    binnings : tuple of int
        Allowed (square) binning factors.
    """

    sensor_shape: tuple[int, int] = (1040, 1392)
    pixel_size_um: float = 6.45
    magnification: float = 1.0
    exposure_s: Range = field(default_factory=lambda: Range(20e-6, 10.0, "s"))
    gain_db: Range = field(default_factory=lambda: Range(0.0, 24.0, "dB"))
    black_level_dn: Range = field(default_factory=lambda: Range(0.0, 255.0, "DN"))
    fps: Range = field(default_factory=lambda: Range(0.1, 30.0, "Hz"))
    bit_depths: tuple[int, ...] = (8, 12)
    binnings: tuple[int, ...] = (1, 2, 4)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.magnification) and self.magnification > 0):
            raise OutOfRangeError(f"camera magnification must be a positive number, got {self.magnification}")

    @property
    def sample_pixel_um(self) -> float:
        """Size of one (unbinned) image pixel on the sample, in µm."""
        return self.pixel_size_um / self.magnification


@dataclass(frozen=True)
class Roi:
    """Region of interest on the sensor, in unbinned pixels: top-left ``(row, col)`` and size."""

    row: int
    col: int
    rows: int
    cols: int


class CameraDevice(Device):
    """A monochrome camera device (thesis §4.1.4, control surface of §4.3.2 'Cameras').

    The device that delivers frames; not to be confused with :class:`scopetwin.scenes.camera.Camera`, the
    thesis's pinhole camera *model* (§1.6.2) that calibration estimates.

    Frames come back as float32 digital numbers, shape ``(rows, cols)`` of the
    binned ROI, whatever the world behind the camera.

    Parameters
    ----------
    name : str
        Device name in the rig.
    limits : CameraLimits
        The model's allowed settings.
    timeout_s : float
        Longest wait for a frame beyond its exposure time.
    """

    kind = "camera"

    def __init__(self, name: str, *, limits: CameraLimits | None = None, timeout_s: float = 2.0) -> None:
        super().__init__(name)
        self.limits = limits or CameraLimits()
        self.timeout_s = float(timeout_s)
        rows, cols = self.limits.sensor_shape
        self._roi = Roi(0, 0, rows, cols)
        self._binning = 1
        self._bit_depth = max(self.limits.bit_depths)
        self._exposure_s = min(max(0.01, self.limits.exposure_s.low), self.limits.exposure_s.high)
        self._gain_db = self.limits.gain_db.low
        self._black_level_dn = self.limits.black_level_dn.low
        self._fps = self.limits.fps.high
        self._trigger = (TriggerType.SOFTWARE, TriggerMode.ONCE)
        self._global_trigger_delay_s = 0.0
        self._armed = False

    def _limits(self) -> dict[str, Any]:
        lim = self.limits
        return {
            "sensor_shape": list(lim.sensor_shape),
            "pixel_size_um": lim.pixel_size_um,
            "magnification": lim.magnification,
            "exposure_s": lim.exposure_s.as_list(),
            "bit_depths": list(lim.bit_depths),
        }

    # information ------------------------------------------------------------------------------
    @property
    def serial_number(self) -> str:
        """Serial number of the camera."""
        self._require()
        return str(self._do_get_serial_number())

    @property
    def sensor_shape(self) -> tuple[int, int]:
        """Full sensor size ``(rows, cols)``."""
        return self.limits.sensor_shape

    @property
    def frame_shape(self) -> tuple[int, int]:
        """Shape of the frames :meth:`grab` returns (binned ROI)."""
        return self._roi.rows // self._binning, self._roi.cols // self._binning

    @property
    def saturation_dn(self) -> float:
        """Largest digital number at the current bit depth."""
        return float(2**self._bit_depth - 1)

    # parameters -------------------------------------------------------------------------------
    @property
    def roi(self) -> Roi:
        """Current region of interest (unbinned sensor pixels)."""
        return self._roi

    def set_roi(self, row: int, col: int, rows: int, cols: int) -> None:
        """Set the image size and offset, checked against the sensor and the binning first."""
        srows, scols = self.limits.sensor_shape
        Range(1, srows, "px").check(rows, f"camera {self.name!r} ROI rows")
        Range(1, scols, "px").check(cols, f"camera {self.name!r} ROI cols")
        Range(0, srows - int(rows), "px").check(row, f"camera {self.name!r} ROI row offset")
        Range(0, scols - int(cols), "px").check(col, f"camera {self.name!r} ROI col offset")
        roi = Roi(int(row), int(col), int(rows), int(cols))
        self._require()
        self._do_set_roi(roi)
        self._roi = roi

    @property
    def binning(self) -> int:
        """Square binning factor."""
        return self._binning

    def set_binning(self, binning: int) -> None:
        """Set the binning factor (one of ``limits.binnings``)."""
        if binning not in self.limits.binnings:
            raise OutOfRangeError(f"camera {self.name!r}: binning {binning} not in {self.limits.binnings}")
        self._require()
        self._do_set_binning(int(binning))
        self._binning = int(binning)

    @property
    def bit_depth(self) -> int:
        """ADC bit depth of delivered frames."""
        return self._bit_depth

    def set_bit_depth(self, bits: int) -> None:
        """Set the bit depth (one of ``limits.bit_depths``)."""
        if bits not in self.limits.bit_depths:
            raise OutOfRangeError(f"camera {self.name!r}: bit depth {bits} not in {self.limits.bit_depths}")
        self._require()
        self._do_set_bit_depth(int(bits))
        self._bit_depth = int(bits)

    @property
    def exposure_s(self) -> float:
        """Exposure time in seconds."""
        return self._exposure_s

    def set_exposure_s(self, exposure_s: float) -> None:
        """Set the exposure time (s), checked against ``limits.exposure_s`` first."""
        value = self.limits.exposure_s.check(exposure_s, f"camera {self.name!r} exposure")
        self._require()
        self._exposure_s = float(self._do_set_exposure_s(value) or value)

    @property
    def gain_db(self) -> float:
        """Analogue gain in dB."""
        return self._gain_db

    def set_gain_db(self, gain_db: float) -> None:
        """Set the gain (dB), checked against ``limits.gain_db`` first."""
        value = self.limits.gain_db.check(gain_db, f"camera {self.name!r} gain")
        self._require()
        self._do_set_gain_db(value)
        self._gain_db = value

    @property
    def black_level_dn(self) -> float:
        """Black level (offset) in DN."""
        return self._black_level_dn

    def set_black_level_dn(self, black_level_dn: float) -> None:
        """Set the black level (DN), checked against ``limits.black_level_dn`` first."""
        value = self.limits.black_level_dn.check(black_level_dn, f"camera {self.name!r} black level")
        self._require()
        self._do_set_black_level_dn(value)
        self._black_level_dn = value

    @property
    def fps(self) -> float:
        """Frame rate for streaming, in Hz."""
        return self._fps

    def set_fps(self, fps: float) -> None:
        """Set the streaming frame rate (Hz), checked against ``limits.fps`` first."""
        value = self.limits.fps.check(fps, f"camera {self.name!r} frame rate")
        self._require()
        self._do_set_fps(value)
        self._fps = value

    @property
    def trigger(self) -> tuple[TriggerType, TriggerMode]:
        """Current ``(TriggerType, TriggerMode)``."""
        return self._trigger

    @property
    def listen_global_trigger(self) -> bool:
        """Whether exposures start on the hardware (global) trigger line."""
        return self._trigger[0] is not TriggerType.SOFTWARE

    @property
    def global_trigger_delay_s(self) -> float:
        """Delay between trigger edge and exposure start, in seconds."""
        return self._global_trigger_delay_s

    def set_trigger(
        self, trigger_type: TriggerType, trigger_mode: TriggerMode = TriggerMode.ONCE, delay_s: float = 0.0
    ) -> None:
        """Choose what starts an exposure; ``delay_s`` is the global trigger delay (thesis §4.3.2)."""
        if not isinstance(trigger_type, TriggerType) or not isinstance(trigger_mode, TriggerMode):
            raise OutOfRangeError(f"camera {self.name!r}: trigger must be a TriggerType and a TriggerMode")
        if trigger_mode is TriggerMode.BULB and trigger_type is TriggerType.SOFTWARE:
            raise OutOfRangeError(f"camera {self.name!r}: bulb mode needs a hardware trigger")
        delay = Range(0.0, MAX_TIMER_S, "s").check(delay_s, f"camera {self.name!r} trigger delay")
        self._require()
        self._do_set_trigger(trigger_type, trigger_mode, delay)
        self._trigger = (trigger_type, trigger_mode)
        self._global_trigger_delay_s = delay

    # operation ---------------------------------------------------------------------------------
    def arm(self) -> None:
        """Start acquisition so that triggered frames are buffered (needed before hardware triggers)."""
        self._require()
        if not self._armed:
            self._do_arm()
            self._armed = True

    def disarm(self) -> None:
        """Stop acquisition and drop buffered frames."""
        if self._armed:
            self._armed = False
            self._do_disarm()

    def grab(self, timeout_s: float | None = None) -> FloatImage:
        """Return one frame (float32 DN): software-triggered now, or the next hardware-triggered one.

        Raises
        ------
        InstrumentTimeout
            If no frame arrives within ``exposure_s + timeout_s``.
        """
        self._require()
        wait = self._exposure_s + (self.timeout_s if timeout_s is None else float(timeout_s))
        if self._trigger[0] is TriggerType.SOFTWARE:
            was_armed = self._armed
            self.arm()
            try:
                self._do_software_trigger()
                frame = self._do_read_frame(wait)
            finally:
                if not was_armed:
                    self.disarm()
        else:
            if not self._armed:
                raise InstrumentTimeout(f"camera {self.name!r} listens to a hardware trigger but is not armed")
            frame = self._do_read_frame(wait)
        return np.asarray(frame, dtype=np.float32)

    def stream(self, n_frames: int, timeout_s: float | None = None) -> Iterator[FloatImage]:
        """Yield ``n_frames`` frames at the configured frame rate (software trigger) or as triggered."""
        Range(1, 1e9, "frames").check(n_frames, f"camera {self.name!r} frame count")
        period = 1.0 / self._fps
        self.arm()
        try:
            for _ in range(int(n_frames)):
                t0 = time.monotonic()
                yield self.grab(timeout_s)
                if self._trigger[0] is TriggerType.SOFTWARE:
                    time.sleep(max(0.0, period - (time.monotonic() - t0)))
        finally:
            self.disarm()

    def _do_safe_state(self) -> None:
        self.disarm()

    # hooks
    @abc.abstractmethod
    def _do_get_serial_number(self) -> str: ...

    @abc.abstractmethod
    def _do_set_roi(self, roi: Roi) -> None: ...

    @abc.abstractmethod
    def _do_set_binning(self, binning: int) -> None: ...

    @abc.abstractmethod
    def _do_set_bit_depth(self, bits: int) -> None: ...

    @abc.abstractmethod
    def _do_set_exposure_s(self, exposure_s: float) -> float | None: ...

    @abc.abstractmethod
    def _do_set_gain_db(self, gain_db: float) -> None: ...

    @abc.abstractmethod
    def _do_set_black_level_dn(self, black_level_dn: float) -> None: ...

    @abc.abstractmethod
    def _do_set_fps(self, fps: float) -> None: ...

    @abc.abstractmethod
    def _do_set_trigger(self, trigger_type: TriggerType, trigger_mode: TriggerMode, delay_s: float) -> None: ...

    @abc.abstractmethod
    def _do_arm(self) -> None: ...

    @abc.abstractmethod
    def _do_disarm(self) -> None: ...

    @abc.abstractmethod
    def _do_software_trigger(self) -> None: ...

    @abc.abstractmethod
    def _do_read_frame(self, timeout_s: float) -> NDArray: ...


DEVICE_CLASSES: dict[str, type[Device]] = {
    "camera": CameraDevice,
    "stage": Stage,
    "focus": FocusDrive,
    "light": LightSource,
    "shutter": Shutter,
    "trigger": TriggerController,
}
