"""Micro-Manager interop: a rig's camera, stages, focus, lights and shutters as pymmcore-plus Python devices.

Optional dependency: ``pip install scopetwin[mm]`` (pymmcore-plus, useq-schema).

The device classes live at module level and are set up by their pre-initialisation properties, as
Micro-Manager's own device adapters are: ``Rig`` (the rig TOML: an absolute path, or the bare name of a rig
shipped with scopetwin, ``sim-cmu``, found in the installed package; any other relative path is read from the
current folder) and the device's name in the rig. So a
configuration file with ``#py`` lines (:func:`config_text`, ``scopetwin rig RIG mm-config --out X.cfg``)
loads in a plain ``UniMMCore`` with nothing of scopetwin called first::

    from pymmcore_plus.experimental.unicore import UniMMCore
    core = UniMMCore()
    core.loadSystemConfiguration("rigs/sim-cmu.cfg")

Devices bound to the same rig file share one open rig (a :class:`RigSession`): the first to initialise
opens it, the last to shut down closes it (lights off, shutters closed, transports closed); an open rig
handed to :func:`load_into_core` is used as it is and left open. Micro-Manager speaks µm for every stage
and milliseconds for exposures; the devices convert to the rig's mm and s.

What a Micro-Manager user expects is set up as Micro-Manager would:

- every light of the rig is a preset of the config group ``Channel`` (the channel group), named after the
  light: the preset selects the light (property ``Lamp`` of the shutter device ``Light``), and the camera
  switches the selected light on for each exposure (UniMMCore does not apply its auto-shutter around
  Python cameras' snaps);
- the camera's ``Exposure`` property has the rig camera's exposure range as its limits, and exposure
  presets may carry the value as text (``"12.5"``), as Micro-Manager's config files do;
- the pixel size is the camera's ``pixel_size_um`` over its ``magnification`` (both from the rig TOML), as
  the pixel-size preset ``scopetwin``;
- the camera's read-only ``BitDepth`` property is the camera's ADC depth (12 for the thesis's camera), not
  the 16 bits of its buffer, and ``getImageBitDepth()`` reports it: on a :class:`RigCore`, and on a plain
  ``UniMMCore`` that loaded the camera from a configuration file (:func:`report_bit_depth`; UniMMCore itself
  gives the buffer's 16);
- the pixel-size preset's lines are ``#py`` lines like the devices': a plain ``CMMCorePlus`` loads the file
  without the Python devices and without their pixel size.

A device whose rig call fails records the fault in its session (:attr:`RigSession.faults`):
pymmcore-plus's MDA engine logs a failed move and goes on, so :func:`run_mda` checks the faults after
every plane and stops at the first. :func:`run_mda` runs a useq ``MDASequence`` checked against the rig
first (:func:`scopetwin.instrument.mdaplan.check_plan`) and records, for every plane, what the devices
reported; it is the library function behind ``scopetwin rig RIG mda``.
"""

from __future__ import annotations

import atexit
import sys
import threading
import weakref
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from scopetwin.instrument.devices import CameraDevice, FocusDrive, LightSource, Shutter, Stage
from scopetwin.instrument.errors import InstrumentError, RigError
from scopetwin.instrument.interrupts import deferred_signals
from scopetwin.instrument.mdaplan import check_plan, load_sequence
from scopetwin.instrument.ome import POSITION_DECIMALS
from scopetwin.instrument.rig import Rig, load_rig
from scopetwin.shipped import find_rig, rig_names, shipped_rig_name

try:
    from pymmcore_plus.experimental import unicore as _uc
except ImportError as exc:  # pragma: no cover - optional extra
    raise RigError("Micro-Manager interop needs pymmcore-plus: pip install 'scopetwin[mm]'") from exc

__all__ = [
    "RigCamera",
    "RigCore",
    "RigFocus",
    "RigLights",
    "RigSession",
    "RigShutter",
    "RigXYStage",
    "config_text",
    "load_into_core",
    "load_sequence",
    "run_mda",
]

#: The module the configuration files name in their ``#py pyDevice`` lines.
MODULE = "scopetwin.instrument.micromanager"
CHANNEL_GROUP = "Channel"
CAMERA_LABEL = "Camera"
XY_LABEL = "XY"
FOCUS_LABEL = "Z"
LIGHT_LABEL = "Light"
LAMP_PROPERTY = "Lamp"
CURRENT_PROPERTY = "Current_mA"
BIT_DEPTH_PROPERTY = "BitDepth"
RIG_PROPERTY = "Rig"
DEVICE_PROPERTY = "Device"
PIXEL_SIZE_PRESET = "scopetwin"

# pymmcore-plus's base classes (typed as Any: our devices keep Micro-Manager's method names and signatures)
_SimpleCamera: Any = _uc.SimpleCameraDevice
_XYStage: Any = _uc.XYStageDevice
_ZStage: Any = _uc.StageDevice
_ShutterBase: Any = _uc.ShutterDevice
_UniMMCore: Any = _uc.UniMMCore

T = TypeVar("T")


# -- sessions: one open rig shared by the devices bound to it ------------------------------------------------------
@dataclass(eq=False)
class RigSession:
    """One open rig shared by the Micro-Manager devices bound to its file.

    Attributes
    ----------
    key : str
        The resolved rig path (or, for a rig handed over by :func:`load_into_core`, that path and the rig's id).
    rig : Rig
        The open rig.
    owned : bool
        Whether the session opened the rig (and closes it when its last device shuts down).
    users : int
        Devices bound to it.
    light : str or None
        The light the ``Light`` device selected; the camera switches it on for each exposure.
    faults : list of InstrumentError
        Device calls that failed, in order (each exception as the device raised it).
    """

    key: str
    rig: Rig
    owned: bool
    users: int = 0
    light: str | None = None
    faults: list[InstrumentError] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.faults = _FAULTS.setdefault(id(self.rig), self.faults)  # shared by every session on this rig object


_LOCK = threading.RLock()
_OPEN: dict[str, RigSession] = {}  # resolved rig path -> a session opened from a configuration file
_HANDED: dict[str, RigSession] = {}  # resolved rig path -> an open rig handed over by load_into_core, while it loads
_FAULTS: dict[int, list[InstrumentError]] = {}  # id(rig) -> the device faults on that open rig (see faults_of)
_INIT_ERRORS: list[str] = []  # why devices did not initialise (pymmcore-plus logs it and goes on), for load_into_core


def faults_of(rig: Rig) -> list[InstrumentError]:
    """The device calls that failed on open ``rig`` through Micro-Manager devices, in order (clear it to start anew)."""
    return _FAULTS.setdefault(id(rig), [])


def resolve_rig_path(value: str | Path) -> Path:
    """The rig file a ``Rig`` property names: absolute as it is; relative from the current folder, else the shipped
    rig it names (:func:`scopetwin.shipped.find_rig`: ``sim-cmu``, ``rigs/sim-cmu.toml``)."""
    path = Path(value).expanduser()
    candidate = find_rig(path)  # a relative path: the current folder's file, else the shipped one
    if candidate.is_file():
        return candidate.resolve()
    where = "" if path.is_absolute() else f" (looked in {Path.cwd()}; the shipped rigs: {', '.join(rig_names())})"
    raise RigError(f"rig file {str(value)!r} not found{where}")


def _acquire(value: str) -> RigSession:
    """The session of rig file ``value``, opened (loaded and initialised) if no device holds it yet."""
    if not value:
        raise RigError(f"set the device's pre-init property {RIG_PROPERTY!r} to a rig file (e.g. rigs/sim-cmu.toml)")
    key = str(resolve_rig_path(value))
    with _LOCK:
        session = _HANDED.get(key) or _OPEN.get(key)
        if session is None:
            rig = load_rig(key)
            try:
                rig.initialize()
            except BaseException:
                rig.close()
                raise
            session = _OPEN[key] = RigSession(key, rig, owned=True)
        session.users += 1
        return session


def _release(session: RigSession) -> None:
    """One device fewer on ``session``; the last one closes a rig the session opened (lights off first)."""
    with _LOCK:
        session.users -= 1
        if session.users > 0 or not session.owned:
            return
        _OPEN.pop(session.key, None)
    with deferred_signals():
        session.rig.close()


@atexit.register
def _close_open_rigs() -> None:
    """At exit, close every rig a configuration opened and no device shut down: lights off, transports closed."""
    with _LOCK:
        sessions = list(_OPEN.values())
        _OPEN.clear()
    for session in sessions:
        session.rig.close()


@contextmanager
def handed_over(rig: Rig) -> Iterator[RigSession]:
    """While inside, devices whose ``Rig`` property names ``rig``'s file bind to this open ``rig`` (not a new one)."""
    key = str(resolve_rig_path(rig.path))
    session = RigSession(f"{key}#{id(rig)}", rig, owned=False)
    with _LOCK:
        previous = _HANDED.get(key)
        _HANDED[key] = session
    try:
        yield session
    finally:
        with _LOCK:
            if previous is None:
                _HANDED.pop(key, None)
            else:
                _HANDED[key] = previous


# -- the devices ---------------------------------------------------------------------------------------------------
def _pre_init(device: Any, **names: str) -> None:
    """Register the pre-init properties ``Rig`` and ``names`` (property -> default) on ``device``."""
    device.register_property(RIG_PROPERTY, default_value="", is_pre_init=True)
    for prop, default in names.items():
        device.register_property(prop, default_value=default, is_pre_init=True)


class _RigBound:
    """What every rig device shares: binding to its session at initialisation, release at shutdown, faults."""

    session: RigSession | None = None

    def _bind(self, pick: Callable[[Rig], T]) -> T:
        """Bind to the session of the ``Rig`` property's file and pick this device's rig device(s) from it."""
        label = self.get_label()  # type: ignore[attr-defined]
        try:
            session = _acquire(str(self.get_property_value(RIG_PROPERTY)))  # type: ignore[attr-defined]
        except Exception as exc:
            _INIT_ERRORS.append(f"Micro-Manager device {label!r}: {exc}")
            raise
        try:
            picked = pick(session.rig)
        except BaseException as exc:
            _INIT_ERRORS.append(f"Micro-Manager device {label!r}: {exc}")
            _release(session)
            raise
        self.session = session
        return picked

    def _name(self, prop: str = DEVICE_PROPERTY) -> str | None:
        """The value of a device-name property (``None`` when empty: the rig's first of the kind)."""
        return str(self.get_property_value(prop)) or None  # type: ignore[attr-defined]

    def _session(self) -> RigSession:
        if self.session is None:
            raise RigError(f"Micro-Manager device {self.get_label()!r} is not initialized")  # type: ignore[attr-defined]
        return self.session

    def _call(self, what: str, func: Callable[..., T], *args: Any) -> T:
        """``func(*args)``; a device failure is recorded as a fault of the session, then raised."""
        try:
            return func(*args)
        except InstrumentError as exc:
            exc.add_note(f"Micro-Manager device {self.get_label()!r}: {what}")  # type: ignore[attr-defined]
            self._session().faults.append(exc)
            raise

    def shutdown(self) -> None:
        """Release the session (the last device of a session that opened the rig closes it)."""
        session, self.session = self.session, None
        if session is not None:
            _release(session)


class RigLights(_RigBound, _ShutterBase):
    """Every light of a rig as one Micro-Manager shutter: ``Lamp`` selects the light, open = it is on.

    Pre-init property ``Rig``: the rig file. ``Current_mA`` is the selected light's drive current (its limits the
    light's rating); the light is switched on at that current (its maximum when none was set).
    """

    def __init__(self) -> None:
        super().__init__()
        _pre_init(self)
        self.lights: dict[str, LightSource] = {}
        self.register_property(LAMP_PROPERTY, default_value="", getter=type(self)._lamp, setter=type(self).select)
        self.register_property(
            CURRENT_PROPERTY, default_value=0.0, getter=type(self)._current, setter=type(self)._set_current
        )

    def initialize(self) -> None:
        self.lights = self._bind(_lights_of)
        self.set_property_allowed_values(LAMP_PROPERTY, tuple(self.lights))
        self.select(next(iter(self.lights)))

    def _lamp(self) -> str:
        return self._session().light or ""

    def select(self, name: str) -> None:
        """Select light ``name``; an open shutter hands over to it."""
        if name not in self.lights:
            raise RigError(f"no light {name!r}; lights: {sorted(self.lights)}")
        session = self._session()
        was_open = session.light is not None and self.get_open()
        if was_open and name != session.light:
            self._call("switch off", self.light().switch_off)
        session.light = name
        self.set_property_limits(CURRENT_PROPERTY, (0.0, self.light().current_range.high))
        if was_open:
            self.set_open(True)

    def light(self) -> LightSource:
        """The selected light."""
        session = self._session()
        if session.light is None:
            raise RigError(f"{self.get_label()}: no light selected")
        return self.lights[session.light]

    def _current(self) -> float:
        lamp = self.light()
        return float(lamp.current_ma or lamp.current_range.high)

    def _set_current(self, value: float) -> None:
        self._call("set current", self.light().set_current_ma, float(value))

    def get_open(self) -> bool:
        return bool(self._call("read state", lambda: self.light().is_on))

    def set_open(self, open: bool) -> None:  # noqa: A002 - pymmcore-plus's signature
        lamp = self.light()
        if open:
            self._call("switch on", lamp.switch_on, lamp.current_ma or lamp.current_range.high)
        else:
            self._call("switch off", lamp.switch_off)


class RigShutter(_RigBound, _ShutterBase):
    """A rig shutter as a Micro-Manager shutter. Pre-init properties ``Rig`` and ``Device`` (its name in the rig)."""

    def __init__(self) -> None:
        super().__init__()
        _pre_init(self, **{DEVICE_PROPERTY: ""})
        self.shutter: Shutter | None = None
        self.register_property(
            "State",
            default_value=0,
            allowed_values=(0, 1),
            getter=lambda dev: int(dev.get_open()),
            setter=lambda dev, value: dev.set_open(bool(int(value))),
        )

    def initialize(self) -> None:
        self.shutter = self._bind(lambda rig: _one_shutter(rig, self._name()))

    def _device(self) -> Shutter:
        self._session()
        assert self.shutter is not None
        return self.shutter

    def get_open(self) -> bool:
        return bool(self._call("read state", lambda: self._device().is_open))

    def set_open(self, open: bool) -> None:  # noqa: A002 - pymmcore-plus's signature
        self._call("open" if open else "close", self._device().open if open else self._device().close)


def _lights_of(rig: Rig) -> dict[str, LightSource]:
    lights = {lamp.name: lamp for lamp in rig.lights()}
    if not lights:
        raise RigError(f"rig {rig.name!r} has no light")
    return lights


def _one_shutter(rig: Rig, name: str | None) -> Shutter:
    shutters = {s.name: s for s in rig.shutters()}
    if not shutters:
        raise RigError(f"rig {rig.name!r} has no shutter")
    if name is None:
        return next(iter(shutters.values()))
    if name not in shutters:
        raise RigError(f"rig {rig.name!r} has no shutter {name!r}; shutters: {sorted(shutters)}")
    return shutters[name]


class RigCamera(_RigBound, _SimpleCamera):
    """A rig camera as a Micro-Manager camera (exposure in ms, frames as uint16 DN).

    Pre-init properties ``Rig`` and ``Device`` (the camera's name in the rig; empty: the first camera). The light
    the ``Light`` device selected is switched on for each snap and off afterwards (unless it was on already).
    """

    def __init__(self) -> None:
        super().__init__()
        _pre_init(self, **{DEVICE_PROPERTY: ""})
        self.camera: CameraDevice | None = None
        self.register_property(
            BIT_DEPTH_PROPERTY, getter=lambda dev: dev._device().bit_depth, is_read_only=True, property_type=int
        )
        report_bit_depth(_calling_core())  # the core loading it from a configuration reports the ADC depth

    def initialize(self) -> None:
        self.camera = self._bind(lambda rig: rig.camera(self._name()))
        exposure = self.camera.limits.exposure_s
        self.set_property_limits("Exposure", (exposure.low * 1e3, exposure.high * 1e3))

    def _device(self) -> CameraDevice:
        self._session()
        assert self.camera is not None
        return self.camera

    def get_exposure(self) -> float:
        return self._device().exposure_s * 1e3

    def set_exposure(self, exposure: float | str) -> None:
        self._call("set exposure", self._device().set_exposure_s, float(exposure) * 1e-3)  # presets come as text

    def sensor_shape(self) -> tuple[int, int]:
        return self._device().frame_shape

    def dtype(self) -> Any:
        return np.uint8 if self._device().bit_depth <= 8 else np.uint16

    def snap(self, buffer: np.ndarray) -> Mapping:
        camera, session = self._device(), self._session()
        lamp = None if session.light is None else session.rig.light(session.light)
        switch = lamp is not None and not lamp.is_on
        if switch and lamp is not None:
            self._call("switch on the light", lamp.switch_on, lamp.current_ma or lamp.current_range.high)
        try:
            frame = self._call("grab", camera.grab)
        finally:
            if switch and lamp is not None:
                self._call("switch off the light", lamp.switch_off)
        top = 2**camera.bit_depth - 1
        buffer[:] = np.clip(np.rint(frame), 0, top).astype(buffer.dtype)
        meta = {"scopetwin_camera": camera.name, "scopetwin_bit_depth": camera.bit_depth}
        if lamp is not None:
            meta["scopetwin_light"] = lamp.name
        return meta


class RigXYStage(_RigBound, _XYStage):
    """Two rig stage axes as one Micro-Manager XY stage (µm). Pre-init properties ``Rig``, ``X`` and ``Y``."""

    def __init__(self) -> None:
        super().__init__()
        _pre_init(self, X="x", Y="y")
        self.axes: tuple[Stage, Stage] | None = None

    def initialize(self) -> None:
        self.axes = self._bind(lambda rig: (rig.stage(str(self._name("X"))), rig.stage(str(self._name("Y")))))

    def _axes(self) -> tuple[Stage, Stage]:
        self._session()
        assert self.axes is not None
        return self.axes

    def set_position_um(self, x: float, y: float) -> None:
        sx, sy = self._axes()
        self._call("move", sx.move_absolute, x * 1e-3)
        self._call("move", sy.move_absolute, y * 1e-3)

    def get_position_um(self) -> tuple[float, float]:
        sx, sy = self._axes()
        x_um, y_um = self._call("read position", lambda: (sx.position_mm * 1e3, sy.position_mm * 1e3))
        # 75100.0, not the 75100.00000000001 of 75.1 mm in µm
        return round(x_um, POSITION_DECIMALS), round(y_um, POSITION_DECIMALS)

    def set_origin_x(self) -> None:
        raise NotImplementedError("scopetwin stages keep their hardware origin")

    def set_origin_y(self) -> None:
        raise NotImplementedError("scopetwin stages keep their hardware origin")

    def home(self) -> None:
        raise NotImplementedError("homing is done by the driver at initialisation")

    def stop(self) -> None:
        for axis in self._axes():
            self._call("halt", axis.halt)

    def set_origin(self) -> None:
        raise NotImplementedError("scopetwin stages keep their hardware origin")


class RigFocus(_RigBound, _ZStage):
    """The rig's focus drive as a Micro-Manager Z stage (µm). Pre-init properties ``Rig`` and ``Device``."""

    def __init__(self) -> None:
        super().__init__()
        _pre_init(self, **{DEVICE_PROPERTY: ""})
        self.focus: FocusDrive | None = None

    def initialize(self) -> None:
        self.focus = self._bind(lambda rig: rig.focus(self._name()))

    def _device(self) -> FocusDrive:
        self._session()
        assert self.focus is not None
        return self.focus

    def set_position_um(self, val: float) -> None:
        self._call("move", self._device().move_absolute_um, val)

    def get_position_um(self) -> float:
        return float(self._call("read position", lambda: self._device().position_um))

    def home(self) -> None:
        raise NotImplementedError("the focus drive has no home move")

    def stop(self) -> None:
        """A piezo settles by itself: nothing to stop."""

    def set_origin(self) -> None:
        raise NotImplementedError("the focus drive keeps its calibrated origin")


class RigCore(_UniMMCore):
    """UniMMCore that reports a Python camera's ``BitDepth`` property as the image bit depth (not its buffer's 16)."""

    def getImageBitDepth(self) -> int:  # noqa: N802 - MMCore's name
        return camera_bit_depth(self) or int(super().getImageBitDepth())


def rig_camera_bit_depth(core: Any) -> int | None:
    """The ADC depth of the core's current camera when that is a :class:`RigCamera`, else ``None``."""
    camera = core.getCameraDevice()
    if camera and core.isPyDevice(camera) and core.getDeviceLibrary(camera) == MODULE:
        return int(core.getProperty(camera, BIT_DEPTH_PROPERTY))
    return None


def _calling_core(frames: int = 32) -> Any | None:
    """The ``UniMMCore`` whose method is running further up this thread's stack (a configuration's ``#py pyDevice``
    line runs ``UniMMCore.loadDevice``, which makes the device), or ``None``."""
    frame = sys._getframe(1)
    for _ in range(frames):
        owner = frame.f_locals.get("self")
        if isinstance(owner, _UniMMCore):
            return owner
        if frame.f_back is None:
            break
        frame = frame.f_back
    return None


def report_bit_depth(core: Any) -> None:
    """Make ``core.getImageBitDepth()`` report a :class:`RigCamera`'s ADC depth while one is the current camera.

    UniMMCore takes a Python camera's bit depth from its buffer's dtype (16 for ``uint16``) and gives a camera no way
    to state its own, and its class (a SWIG type) cannot be changed: the method is replaced on this core only. Every
    other camera keeps UniMMCore's answer. :class:`RigCore` needs none of this.
    """
    if core is None or isinstance(core, RigCore) or "getImageBitDepth" in vars(core):
        return
    owner = weakref.ref(core)
    buffer_depth = type(core).getImageBitDepth

    def getImageBitDepth() -> int:  # noqa: N802 - MMCore's name
        this = owner()
        if this is None:  # pragma: no cover - the core is being collected
            return 0
        depth = rig_camera_bit_depth(this)
        return depth if depth is not None else int(buffer_depth(this))

    getImageBitDepth.__doc__ = buffer_depth.__doc__
    core.getImageBitDepth = getImageBitDepth


def camera_bit_depth(core: Any) -> int | None:
    """The current camera's ``BitDepth`` property (a :class:`RigCamera`'s ADC depth), or ``None`` without one."""
    camera = core.getCameraDevice()
    if camera and core.hasProperty(camera, BIT_DEPTH_PROPERTY):
        return int(core.getProperty(camera, BIT_DEPTH_PROPERTY))
    return None


# -- configuration files -------------------------------------------------------------------------------------------
def config_rig_path(path: str | Path) -> str:
    """How a configuration names a rig file: a rig shipped with scopetwin by its bare name (``sim-cmu``, found in the
    installed package wherever the configuration is loaded), any other by its absolute path (a configuration means
    the same rig from every folder, as Micro-Manager's own configurations name their hardware)."""
    resolved = resolve_rig_path(path)
    return shipped_rig_name(resolved) or str(resolved)


def _header(rig: Rig, camera: CameraDevice, rig_path: str) -> list[str]:
    lim = camera.limits
    lights = ", ".join(f"{lamp.name}" for lamp in rig.lights()) or "none"
    na = rig.optics.get(camera.name, {}).get("numerical_aperture")
    return [
        f"# Micro-Manager configuration of the scopetwin rig {rig.name!r} (Rig {rig_path}), written by scopetwin.",
        "# Its devices are pymmcore-plus Python devices (the '#py' lines, comments to Micro-Manager's C++",
        "# core): load it with pymmcore-plus's UniMMCore().loadSystemConfiguration('THIS.cfg'). A Rig without",
        "# a folder is a rig shipped with scopetwin, found in the installed package; others are absolute paths.",
        f"# Camera {camera.name!r}: {lim.sensor_shape[1]}x{lim.sensor_shape[0]} px, {camera.bit_depth} bit, exposure "
        f"{lim.exposure_s.low * 1e3:g}..{lim.exposure_s.high * 1e3:g} ms (the limits of its Exposure property),",
        f"# {lim.sample_pixel_um:g} um per pixel on the sample ({lim.pixel_size_um:g} um pixels behind "
        f"{lim.magnification:g}x{'' if na is None else f' / NA {na:g}'}).",
        f"# Lights, one preset each of group {CHANNEL_GROUP!r}: {lights}.",
    ]


def _devices(
    rig: Rig, camera: str, stages: tuple[str, str], focus: str | None
) -> list[tuple[str, str, dict[str, str]]]:
    """(label, class, pre-init properties) of every device the configuration loads."""
    devices = [(CAMERA_LABEL, "RigCamera", {DEVICE_PROPERTY: camera})]
    names = {d.name for d in rig.of_kind("stage")}
    if set(stages) <= names:
        devices.append((XY_LABEL, "RigXYStage", {"X": stages[0], "Y": stages[1]}))
    if focus is not None:
        devices.append((FOCUS_LABEL, "RigFocus", {DEVICE_PROPERTY: focus}))
    if rig.lights():
        devices.append((LIGHT_LABEL, "RigLights", {}))
    used = {label for label, _, _ in devices}
    devices += [(s.name, "RigShutter", {DEVICE_PROPERTY: s.name}) for s in rig.shutters() if s.name not in used]
    return devices


def config_text(
    rig: Rig,
    *,
    camera: str | None = None,
    stage_x: str = "x",
    stage_y: str = "y",
    focus: str | None = None,
    light: str | None = None,
) -> str:
    """The Micro-Manager configuration (``.cfg``) of ``rig``: devices, the ``Channel`` group, pixel size, roles.

    The rig need not be initialised (nothing is sent to a device). The camera (default: the first) is ``Camera``,
    stages ``stage_x`` / ``stage_y`` the XY stage ``XY`` (left out when the rig lacks them), the focus drive (default:
    the first) ``Z``, every light a preset of ``Channel`` on the shutter ``Light``, every rig shutter a shutter of its
    own name. ``light`` is selected at start (default: the first).

    Raises
    ------
    RigError
        A device name or the rig path that a ``.cfg`` field cannot hold (:func:`config_field_problem`: a line
        break, a comma, a NUL, white space at either end), before any line is made.
    """
    cam = rig.camera(camera)
    focus_name = rig.focus(focus).name if focus is not None or rig.of_kind("focus") else None
    rig_path = config_rig_path(rig.path)
    # every name that becomes a field of a line (labels, property values, presets), checked before any line is made
    check_config_fields([("rig path", rig_path), *((f"{d.kind} name", d.name) for d in rig.devices.values())])
    devices = _devices(rig, cam.name, (stage_x, stage_y), focus_name)
    lines = [*_header(rig, cam, rig_path), "", "Property,Core,Initialize,0"]
    lines += [f"#py pyDevice,{label},{MODULE},{cls}" for label, cls, _ in devices]
    for label, _, props in devices:
        lines += [f"#py Property,{label},{RIG_PROPERTY},{rig_path}"]
        lines += [f"#py Property,{label},{prop},{value}" for prop, value in props.items()]
    lines += ["Property,Core,Initialize,1", ""]
    if rig.lights():
        lines += [f"#py ConfigGroup,{CHANNEL_GROUP},{n},{LIGHT_LABEL},{LAMP_PROPERTY},{n}" for n in _light_names(rig)]
        lines += [f"#py Property,{LIGHT_LABEL},{LAMP_PROPERTY},{rig.light(light).name}"]
        lines += [f"#py Property,Core,ChannelGroup,{CHANNEL_GROUP}"]
    # The pixel-size preset calibrates the Python camera, so its lines are '#py' lines too: a plain CMMCorePlus, which
    # loads none of the Python devices, skips them (its parser also refuses the preset's empty value). In UniMMCore the
    # preset is matched by the C++ core, whose Core-Camera property stays empty while the camera is a Python device.
    lines += [
        f"#py ConfigPixelSize,{PIXEL_SIZE_PRESET},Core,Camera,",
        f"#py PixelSize_um,{PIXEL_SIZE_PRESET},{cam.limits.sample_pixel_um!r}",
    ]
    roles = {"Camera": CAMERA_LABEL, "XYStage": XY_LABEL, "Focus": FOCUS_LABEL, "Shutter": LIGHT_LABEL}
    labels = {label for label, _, _ in devices}
    lines += [f"#py Property,Core,{role},{label}" for role, label in roles.items() if label in labels]
    lines += ["Property,Core,AutoShutter,1", ""]
    return "\n".join(lines)


def config_field_problem(value: str) -> str | None:
    """Why ``value`` cannot be one field of a Micro-Manager ``.cfg`` line, or None.

    The format has no quoting: a comma ends the field, a line break ends the line (and a name holding one could
    write lines of its own, such as ``#py pyDevice,...``), a NUL or another control character ends or corrupts the
    line, and Micro-Manager refuses a file whose name begins or ends with white space.
    """
    if not value:
        return "is empty"
    bad = sorted({c for c in value if not c.isprintable() and c != " "})
    if bad:
        return f"holds the control character(s) {', '.join(repr(c) for c in bad)} (line breaks, NUL)"
    if "," in value:
        return "holds a comma (the .cfg field separator)"
    if value != value.strip():
        return "begins or ends with white space"
    return None


def check_config_fields(fields: Iterable[tuple[str, str]]) -> None:
    """Refuse any ``(what, value)`` of ``fields`` that a ``.cfg`` line cannot hold (:func:`config_field_problem`).

    Raises
    ------
    RigError
        One line naming the first such field, its value and the reason; nothing is written.
    """
    for what, value in fields:
        problem = config_field_problem(value)
        if problem is not None:
            raise RigError(f"{what} {value!r} {problem}: a Micro-Manager configuration cannot hold it; rename it")


def _light_names(rig: Rig) -> list[str]:
    return [lamp.name for lamp in rig.lights()]


# -- a core on an open rig ------------------------------------------------------------------------------------------
def load_configuration(core: Any, text: str) -> None:
    """Load configuration ``text`` into ``core`` (as ``loadSystemConfiguration`` does with a file).

    Raises
    ------
    RigError
        A device that did not initialise (its error), or a line the core refused.
    """
    import tempfile

    with tempfile.TemporaryDirectory(prefix="scopetwin-mm-") as folder:
        path = Path(folder) / "rig.cfg"
        path.write_text(text)
        try:
            core.loadSystemConfiguration(str(path))
        except Exception as exc:  # noqa: BLE001 - pymmcore-plus wraps the failing line's error
            raise RigError(_load_error(exc)) from exc


def _load_error(exc: BaseException) -> str:
    """The device's own error behind pymmcore-plus's wrapping ('Error in configuration file ... Device ... not
    initialized')."""
    cause: BaseException | None = exc
    while cause is not None and not isinstance(cause, InstrumentError):
        cause = cause.__cause__ or cause.__context__
    if cause is not None:
        return str(cause)
    return " ".join(str(exc).split())


def load_into_core(
    rig: Rig,
    core: Any | None = None,
    *,
    camera: str | None = None,
    stage_x: str = "x",
    stage_y: str = "y",
    focus: str | None = None,
    light: str | None = None,
) -> Any:
    """The open ``rig`` as Micro-Manager devices of a core, loaded from :func:`config_text` (the same configuration
    ``scopetwin rig RIG mm-config`` writes), bound to this open rig.

    Parameters
    ----------
    rig : Rig
        An open rig (it stays open: the core's devices use it and leave it open).
    core : UniMMCore, optional
        The core to load into (its devices are unloaded first; default: a new :class:`RigCore`).
    camera, focus : str, optional
        Device names (default: the first of each kind).
    stage_x, stage_y : str
        The stage axes of the XY stage.
    light : str, optional
        The light selected at first (default: the first).

    Returns
    -------
    UniMMCore
        With the devices current, ``Channel`` as channel group, the pixel size and autoshutter set.
    """
    core = core if core is not None else RigCore()
    text = config_text(rig, camera=camera, stage_x=stage_x, stage_y=stage_y, focus=focus, light=light)
    with handed_over(rig):
        _INIT_ERRORS.clear()
        try:
            load_configuration(core, text)
            failed = [
                label
                for label in core.getLoadedDevices()
                if core.isPyDevice(label) and core.getDeviceInitializationState(label).name != "InitializedSuccessfully"
            ]
            if failed:
                raise RigError(f"Micro-Manager device(s) {failed} did not initialise")
        except RigError as exc:
            raise RigError(_INIT_ERRORS[0] if _INIT_ERRORS else str(exc)) from exc
    return core


# -- MDA -------------------------------------------------------------------------------------------------------------
def _rig_device(core: Any, label: str, prop: str = DEVICE_PROPERTY) -> str | None:
    return str(core.getProperty(label, prop)) or None if label and core.hasProperty(label, prop) else None


def _setting_check(core: Any) -> Callable[[str, str, str], None]:
    """``(device, property, value)`` -> raises ``ValueError`` naming the limit or the allowed values."""

    def check(device: str, prop: str, value: str) -> None:
        if core.hasPropertyLimits(device, prop):
            low, high = core.getPropertyLowerLimit(device, prop), core.getPropertyUpperLimit(device, prop)
            if not low <= float(value) <= high:
                raise ValueError(f"outside [{low:g}, {high:g}]")
        allowed = core.getAllowedPropertyValues(device, prop)
        if allowed and str(value) not in allowed:
            raise ValueError(f"not one of {list(allowed)}")

    return check


def plan_limits(core: Any, rig: Rig) -> Any:
    """What ``rig`` allows an MDA on ``core`` (loaded by :func:`load_into_core`), and where its devices are now."""
    from scopetwin.instrument.devices import Range
    from scopetwin.instrument.mdaplan import PlanLimits

    camera = rig.camera(_rig_device(core, core.getCameraDevice()))
    x_um = y_um = z_um = None
    now: list[float | None] = [None, None, None]
    if xy := core.getXYStageDevice():
        sx, sy = rig.stage(str(core.getProperty(xy, "X"))), rig.stage(str(core.getProperty(xy, "Y")))
        x_um, y_um = (Range(s.travel.low * 1e3, s.travel.high * 1e3, "um") for s in (sx, sy))
        now[0], now[1] = core.getXYPosition()
    if z := core.getFocusDevice():
        z_um = rig.focus(_rig_device(core, z)).range
        now[2] = core.getPosition()
    group = core.getChannelGroup()
    presets = {}
    for preset in core.getAvailableConfigs(group) if group else ():
        data = core.getConfigData(group, preset, native=True)
        settings = (data.getSetting(i) for i in range(data.size()))
        presets[preset] = {(s.getDeviceLabel(), s.getPropertyName()): s.getPropertyValue() for s in settings}
    exposure = camera.limits.exposure_s
    return PlanLimits(
        x_um=x_um,
        y_um=y_um,
        z_um=z_um,
        exposure_ms=Range(exposure.low * 1e3, exposure.high * 1e3, "ms"),
        frame_shape=(int(core.getImageHeight()), int(core.getImageWidth())),
        pixel_size_um=float(core.getPixelSizeUm()) or camera.limits.sample_pixel_um,
        bytes_per_pixel=int(core.getBytesPerPixel()),
        channel_group=group or CHANNEL_GROUP,
        presets=presets,
        check_setting=_setting_check(core),
        now_um=(now[0], now[1], now[2]),
        exposure_now_ms=float(core.getExposure()),
    )


def _acquisition_info(core: Any, rig: Rig, seq: Any, limits: Any) -> Any:
    """Shape, type, bit depth, pixel size, channels (each preset's light and its wavelengths) and optics."""
    from scopetwin.instrument.ome import AcquisitionInfo, ChannelInfo

    camera = rig.camera(_rig_device(core, core.getCameraDevice()))
    channels = []
    for channel in seq.channels:
        settings = (limits.presets or {}).get(channel.config, {})
        light = settings.get((LIGHT_LABEL, LAMP_PROPERTY))
        optics = rig.optics.get(str(light), {})
        channels.append(ChannelInfo(channel.config, light, optics.get("wavelength_nm"), optics.get("emission_nm")))
    return AcquisitionInfo(
        shape=limits.frame_shape,
        dtype=f"uint{8 * limits.bytes_per_pixel}",
        bit_depth=camera_bit_depth(core) or int(core.getImageBitDepth()),
        pixel_size_um=limits.pixel_size_um,
        channels=tuple(channels),
        camera=camera.name,
        rig=rig.name,
        magnification=camera.limits.magnification,
        numerical_aperture=rig.optics.get(camera.name, {}).get("numerical_aperture"),
    )


def _reported(core: Any, meta: Mapping) -> dict[str, Any]:
    """What the devices report now: stage (µm), focus (µm), exposure (ms), the channel preset that matches."""
    x_um = y_um = z_um = None
    if core.getXYStageDevice():
        x_um, y_um = (float(v) for v in core.getXYPosition())
    if core.getFocusDevice():
        z_um = float(core.getPosition())
    group = core.getChannelGroup()
    elapsed = meta.get("runner_time_ms") if isinstance(meta, Mapping) else None
    return {
        "channel": (core.getCurrentConfig(group) or None) if group else None,
        "x_um": x_um,
        "y_um": y_um,
        "z_um": z_um,
        "exposure_ms": float(core.getExposure()),
        "elapsed_s": None if elapsed is None else float(elapsed) * 1e-3,
    }


def _writer(output: Any, seq: Any, core: Any, rig: Rig, limits: Any, single_file: bool) -> Any:
    """An :class:`~scopetwin.instrument.ome.OmeOutput` for an output path, else ``None``."""
    from scopetwin.instrument.mdaplan import _grid_extent, _grid_of, _positions, plan_size
    from scopetwin.instrument.ome import TIFF_SUFFIXES, ZARR_SUFFIX, OmeOutput, layout_of

    if not isinstance(output, str | Path) or not str(output).lower().endswith((*TIFF_SUFFIXES, ZARR_SUFFIX)):
        return None
    grids = [_grid_of(seq, position) for position in _positions(seq)]
    points = [_grid_extent(grid, limits)[0] if grid is not None else 1 for grid in grids]
    layout = layout_of(seq, plan_size(seq, limits).sizes, points)
    return OmeOutput(output, layout, _acquisition_info(core, rig, seq, limits), single_file=single_file)


def _run_cancellable(core: Any, seq: Any, output: Any) -> None:
    """``core.mda.run``; SIGINT / SIGTERM / SIGHUP cancel it at the next event boundary, then are delivered."""
    interrupted = threading.Event()
    done = threading.Event()

    def cancel_when_interrupted() -> None:  # the runner's lock is never taken inside a signal handler
        while not done.wait(0.02):
            if interrupted.is_set():
                core.mda.cancel()  # a no-op until the run starts; then it ends at the next event boundary

    watcher = threading.Thread(target=cancel_when_interrupted, name="mda-cancel", daemon=True)
    watcher.start()
    with deferred_signals(on_signal=lambda _signum: interrupted.set()):
        try:
            if output is None:
                core.mda.run(seq)
            else:
                core.mda.run(seq, output=output)
        finally:
            done.set()
            watcher.join()


def _recorder(
    core: Any, faults: list[InstrumentError], frames: list[dict[str, Any]], writer: Any, on_frame: Callable | None
) -> Callable[[np.ndarray, Any, Mapping], None]:
    """The frame handler of :func:`run_mda`: after a device fault, cancel and keep nothing; else record what the
    devices report, write the plane, call ``on_frame``."""

    def record(image: np.ndarray, event: Any, meta: Mapping) -> None:
        if faults:
            core.mda.cancel()
            return
        reported = _reported(core, meta)
        index = {str(k): int(v) for k, v in dict(event.index).items()}
        frames.append({"index": index, **reported})
        if writer is not None:
            writer.append(image, index, reported)
        if on_frame is not None:
            on_frame(image, event, meta)

    return record


def run_mda(
    rig: Rig,
    sequence: Any,
    *,
    camera: str | None = None,
    output: Any = None,
    on_frame: Callable[[np.ndarray, Any, Mapping], None] | None = None,
    core: Any | None = None,
    single_file: bool = False,
) -> dict[str, Any]:
    """Run a useq MDA sequence on the rig through pymmcore-plus, checked against the rig's limits first.

    Parameters
    ----------
    rig : Rig
        An open rig.
    sequence : MDASequence, dict or path
        The acquisition (a YAML or JSON file as Micro-Manager writes them).
    camera : str, optional
        The rig camera to acquire with.
    output : optional
        A path ``X.ome.tif`` / ``X.ome.tiff`` / ``X.ome.zarr`` (written by :class:`~scopetwin.instrument.ome.OmeOutput`
        with the rig's metadata), or anything else ``core.mda.run(..., output=...)`` takes (pymmcore-plus's own
        writers, an ome-writers ``AcquisitionSettings``, a handler).
    on_frame : callable, optional
        Called with ``(image, event, metadata)`` for every plane (e.g. a progress bar).
    core : UniMMCore, optional
        A core already loaded with :func:`load_into_core`.
    single_file : bool
        OME-TIFF: all positions in one multi-series file.

    SIGINT, SIGTERM or SIGHUP during the run cancel it at the next event boundary: the output closes (the planes
    acquired so far stay readable), the lights go off, and then the signal is delivered to its handler as usual.

    Returns
    -------
    dict
        ``{"planes", "pixel_size_um", "bit_depth", "channels", "estimate": {"planes", "bytes", "seconds", "sizes"},
        "files", "frames": [{"index", "channel", "x_um", "y_um", "z_um", "exposure_ms", "elapsed_s"}, ...]}``: every
        frame as the devices reported it (stage, focus and exposure read back; the channel preset that matched).

    Raises
    ------
    RigError
        A plan without events, or out of the rig's limits (before anything moves).
    InstrumentError
        A device that failed during the run, as it raised it: a failed move that pymmcore-plus's engine logged and
        went on from stops the run at the plane after it (that plane is neither written nor recorded).
    """
    seq = load_sequence(sequence)
    if next(iter(seq), None) is None:  # useq's first event only: an empty plan has none
        raise RigError("the MDA sequence has no events: nothing to acquire")
    core = core if core is not None else load_into_core(rig, camera=camera)
    limits = plan_limits(core, rig)
    size = check_plan(seq, limits)
    writer = _writer(output, seq, core, rig, limits, single_file)
    faults = faults_of(rig)
    faults.clear()
    frames: list[dict[str, Any]] = []
    record = _recorder(core, faults, frames, writer, on_frame)
    core.mda.events.frameReady.connect(record)
    try:
        _run_cancellable(core, seq, None if writer is not None else output)
    finally:
        core.mda.events.frameReady.disconnect(record)
        files = writer.close() if writer is not None else []
        rig.lights_off()
    if faults:
        raise faults[0]
    estimate = {"planes": size.planes, "bytes": size.bytes, "seconds": size.seconds, "sizes": size.sizes}
    return {
        "planes": len(frames),
        "pixel_size_um": core.getPixelSizeUm(),
        "bit_depth": core.getImageBitDepth(),
        "channels": sorted({f["channel"] for f in frames if f["channel"]}),
        "estimate": estimate,
        "files": files,
        "frames": frames,
    }
