"""python-microscope adapters: a rig's devices as ``microscope.abc`` devices (Cockpit and its clients).

Optional dependency: ``pip install microscope``. :func:`microscope_devices` wraps
the devices of an open rig in python-microscope's device classes, in
python-microscope's units: cameras expose in seconds and deliver uint16 frames;
light sources take a power in [0, 1] (the fraction of the light's maximum
current); stages and the focus drive (a one-axis stage named ``z``) move in
micrometres, as Cockpit expects. The wrappers never own the rig's devices:
``shutdown`` switches a light off or stops a camera's acquisition but leaves
the rig device to :func:`scopetwin.instrument.rig.open_rig`. :func:`serve_devices` is the
library function behind ``scopetwin rig RIG serve``: python-microscope's device
server (Pyro) on 127.0.0.1 only.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from scopetwin.instrument.devices import CameraDevice, FocusDrive, LightSource, Stage
from scopetwin.instrument.errors import InstrumentError, RigError
from scopetwin.instrument.rig import Rig

LOCALHOST = "127.0.0.1"


def _microscope() -> tuple[Any, Any]:
    try:
        import microscope
        import microscope.abc
    except ImportError as exc:  # pragma: no cover - optional dependency
        raise RigError("python-microscope adapters need the package: pip install microscope") from exc
    return microscope, microscope.abc


def make_device_classes() -> dict[str, type]:
    """Build the adapter classes (python-microscope is imported only here)."""
    m, mabc = _microscope()
    light_base: Any = mabc.LightSource
    camera_base: Any = mabc.Camera
    stage_base: Any = mabc.Stage
    axis_base: Any = mabc.StageAxis

    class RigLightSource(light_base):
        """A rig light as a python-microscope light source: power = current / maximum current.

        Only software triggering in bulb mode: ``enable`` switches the light on, ``disable`` off.
        """

        def __init__(self, light: LightSource, **kwargs: Any) -> None:
            super().__init__(**kwargs)
            self.light = light
            self.light.switch_off()

        @property
        def trigger_type(self) -> Any:
            return m.TriggerType.SOFTWARE

        @property
        def trigger_mode(self) -> Any:
            return m.TriggerMode.BULB

        def set_trigger(self, ttype: Any, tmode: Any) -> None:
            if ttype is not m.TriggerType.SOFTWARE or tmode is not m.TriggerMode.BULB:
                raise m.UnsupportedFeatureError("scopetwin lights trigger in software, bulb mode only")

        def _do_trigger(self) -> None:
            raise m.UnsupportedFeatureError("a light in bulb mode is switched by enable/disable")

        def get_status(self) -> list[str]:
            on = "on" if self.light.is_on else "off"
            return [f"{self.light.name}: {on}", f"current {self.light.current_ma:g} mA"]

        def get_is_on(self) -> bool:
            return bool(self.light.is_on)

        def _current_for(self, power: float) -> float:
            return float(power) * self.light.current_range.high

        def _do_get_power(self) -> float:
            if not self.light.is_on:
                return 0.0
            return float(self.light.current_ma / self.light.current_range.high)

        def _do_set_power(self, power: float) -> None:
            if self.light.is_on:
                self.light.switch_on(self._current_for(power))
            else:
                self.light.set_current_ma(self._current_for(power))

        def _do_enable(self) -> bool:
            self.light.switch_on(self._current_for(self.get_set_power()))
            return True

        def _do_disable(self) -> None:
            # python-microscope disables again from __del__, after the rig may have closed (lights off already)
            if self.light.initialized:
                self.light.switch_off()

        def _do_shutdown(self) -> None:
            # python-microscope also shuts down from __del__: never raise, the rig closes the line anyway
            if self.light.initialized:
                with contextlib.suppress(InstrumentError):
                    self.light.switch_off()

    class RigCamera(camera_base):
        """A rig camera as a python-microscope camera: software trigger, one frame per trigger."""

        def __init__(self, camera: CameraDevice, **kwargs: Any) -> None:
            super().__init__(**kwargs)
            self.camera = camera
            self._triggered = 0
            self._lock = threading.Lock()
            self.add_setting(
                "bit depth",
                "enum",
                lambda: self.camera.bit_depth,
                lambda bits: self.camera.set_bit_depth(int(bits)),
                lambda: list(self.camera.limits.bit_depths),
            )

        @property
        def trigger_type(self) -> Any:
            return m.TriggerType.SOFTWARE

        @property
        def trigger_mode(self) -> Any:
            return m.TriggerMode.ONCE

        def set_trigger(self, ttype: Any, tmode: Any) -> None:
            if ttype is not m.TriggerType.SOFTWARE or tmode is not m.TriggerMode.ONCE:
                raise m.UnsupportedFeatureError("the python-microscope adapter triggers in software, once")

        def _do_trigger(self) -> None:
            with self._lock:
                if self._acquiring:
                    self._triggered += 1

        def soft_trigger(self) -> None:
            self.trigger()

        def _fetch_data(self) -> Any:
            with self._lock:
                if not (self._acquiring and self._triggered > 0):
                    return None
                self._triggered -= 1
            frame = self.camera.grab()
            return np.clip(np.rint(frame), 0, 65535).astype(np.uint16)

        def _do_enable(self) -> bool:
            with self._lock:
                self._triggered = 0
                self._acquiring = True
            return True

        def _do_disable(self) -> None:
            self.abort()

        def abort(self) -> None:
            with self._lock:
                self._acquiring = False
                self._triggered = 0

        def _do_shutdown(self) -> None:
            self.abort()

        def set_exposure_time(self, value: float) -> None:
            self.camera.set_exposure_s(float(value))

        def get_exposure_time(self) -> float:
            return float(self.camera.exposure_s)

        def get_cycle_time(self) -> float:
            return float(self.camera.exposure_s)

        def _get_sensor_shape(self) -> tuple[int, int]:
            rows, cols = self.camera.sensor_shape
            return cols, rows  # python-microscope: (width, height)

        def _get_binning(self) -> Any:
            return m.Binning(self.camera.binning, self.camera.binning)

        def _set_binning(self, binning: Any) -> bool:
            if binning.h != binning.v:
                raise m.UnsupportedFeatureError("scopetwin cameras bin square only")
            self.camera.set_binning(int(binning.h))
            return True

        def _get_roi(self) -> Any:
            roi = self.camera.roi
            return m.ROI(roi.col, roi.row, roi.cols, roi.rows)

        def _set_roi(self, roi: Any) -> bool:
            self.camera.set_roi(int(roi.top), int(roi.left), int(roi.height), int(roi.width))
            return True

    class RigAxis(axis_base):
        """One rig axis in micrometres: a stage (mm inside) or the focus drive (µm inside)."""

        def __init__(self, device: Stage | FocusDrive) -> None:
            super().__init__()
            self.device = device

        @property
        def limits(self) -> Any:
            if isinstance(self.device, Stage):
                return m.AxisLimits(self.device.travel.low * 1e3, self.device.travel.high * 1e3)
            return m.AxisLimits(self.device.range.low, self.device.range.high)

        @property
        def position(self) -> float:
            if isinstance(self.device, Stage):
                return float(self.device.position_mm * 1e3)
            return float(self.device.position_um)

        def move_to(self, pos: float) -> None:
            lim = self.limits
            target = min(max(float(pos), lim.lower), lim.upper)  # python-microscope clips to the limits
            if isinstance(self.device, Stage):
                self.device.move_absolute(target * 1e-3)
            else:
                self.device.move_absolute_um(target)

        def move_by(self, delta: float) -> None:
            self.move_to(self.position + float(delta))

    class RigStage(stage_base):
        """Rig axes as one python-microscope stage (µm); never homes on enable."""

        def __init__(self, axes: Mapping[str, Stage | FocusDrive], **kwargs: Any) -> None:
            super().__init__(**kwargs)
            self._axes = {name: RigAxis(device) for name, device in axes.items()}

        @property
        def axes(self) -> Mapping[str, Any]:
            return self._axes

        def may_move_on_enable(self) -> bool:
            return False  # the drivers reference at rig initialisation, not on enable

        def move_by(self, delta: Mapping[str, float]) -> None:
            for name, d in delta.items():
                self._axes[name].move_by(d)

        def move_to(self, position: Mapping[str, float]) -> None:
            for name, p in position.items():
                self._axes[name].move_to(p)

        def _do_shutdown(self) -> None:
            """Axes stay where they are."""

    return {"light": RigLightSource, "camera": RigCamera, "stage": RigStage, "axis": RigAxis}


def microscope_devices(rig: Rig, *, stage_x: str = "x", stage_y: str = "y") -> dict[str, Any]:
    """The rig's cameras, lights, XY stage and focus drive as python-microscope devices.

    Parameters
    ----------
    rig : Rig
        An open rig.
    stage_x, stage_y : str
        The stage axes of the XY stage (``"xy"``: axes ``x`` and ``y``); other stages become
        one-axis stages under their own names.

    Returns
    -------
    dict
        Name -> ``microscope.abc.Device``: every camera and light under its rig name, ``"xy"``
        for the XY stage, and the focus drive under its rig name as a one-axis stage (axis ``z``).
    """
    classes = make_device_classes()
    out: dict[str, Any] = {}
    stages = {d.name: d for d in rig.devices.values() if isinstance(d, Stage)}
    for device in rig.devices.values():
        if isinstance(device, CameraDevice):
            out[device.name] = classes["camera"](device)
        elif isinstance(device, LightSource):
            out[device.name] = classes["light"](device)
        elif isinstance(device, FocusDrive):
            out[device.name] = classes["stage"]({"z": device})
    if stage_x in stages and stage_y in stages:
        out["xy"] = classes["stage"]({"x": stages.pop(stage_x), "y": stages.pop(stage_y)})
    for name, stage in stages.items():
        out[name] = classes["stage"]({name: stage})
    return out


def serve_devices(
    devices: Mapping[str, Any],
    *,
    port: int = 8000,
    stop: threading.Event | None = None,
    ready: Callable[[dict[str, str]], None] | None = None,
) -> dict[str, str]:
    """Expose ``devices`` through Pyro (python-microscope's transport) on 127.0.0.1 until ``stop`` is set.

    Each device gets its own daemon on ``port``, ``port + 1``, ... (the layout of python-microscope's
    device server, one port per device; ``port = 0``: a free port each). ``ready`` receives name -> Pyro
    URI once the daemons run, so a client (``microscope.clients.Client(uri)``, Cockpit) can connect.
    Without ``stop`` it serves until the process ends. Returns the URIs.

    Raises
    ------
    RigError
        A port outside 0..65535 (for the last device), or a port already in use.
    """
    _, mabc = _microscope()
    import Pyro4  # type: ignore[import-untyped]  # Pyro4 ships no type information

    Pyro4.config.SERIALIZERS_ACCEPTED.add("pickle")
    Pyro4.config.SERIALIZER = "pickle"
    Pyro4.config.REQUIRE_EXPOSE = False
    uris: dict[str, str] = {}
    daemons = []
    try:
        if int(port) < 0 or int(port) + len(devices) - 1 > 65535:
            raise RigError(f"device server ports {port}..{int(port) + len(devices) - 1} are outside 0..65535")
        for i, (name, device) in enumerate(devices.items()):
            try:
                daemon = Pyro4.Daemon(host=LOCALHOST, port=int(port) + i if port else 0)
            except OSError as exc:
                raise RigError(f"cannot serve {name!r} on {LOCALHOST}:{int(port) + i}: {exc.strerror or exc}") from None
            daemons.append(daemon)
            uris[name] = str(daemon.register(device, objectId=name))
            if isinstance(device, mabc.Stage):  # as python-microscope's device server: axes travel as proxies
                for axis in device.axes.values():
                    daemon.register(axis)
        for d in daemons:
            threading.Thread(target=d.requestLoop, daemon=True, name="pyro-daemon").start()
        if ready is not None:
            ready(dict(uris))
        (stop or threading.Event()).wait()
    finally:
        for d in daemons:
            d.shutdown()
    return uris
