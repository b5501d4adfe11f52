"""Micro-Manager interop: a rig's camera, stages, focus and lights as pymmcore-plus pure-Python devices.

Optional dependency: ``pip install scopetwin[mm]`` (pymmcore-plus, useq-schema).
:func:`load_into_core` wraps the rig's devices in pymmcore-plus's
``experimental.unicore`` device classes and registers them with
``UniMMCore.loadPyDevice``, so ``core.mda.run(useq.MDASequence(...))`` drives the
simulated rig or the hardware alike. Micro-Manager speaks µm for every stage
and milliseconds for exposures; the wrappers convert to the rig's mm and s.

What a Micro-Manager user expects is set up as Micro-Manager would:

- every light of the rig is a preset of the config group ``Channel`` (the channel
  group), named after the light: the preset selects the light (property ``Lamp``
  of the shutter device ``Light``), and the camera switches the selected light on
  for each exposure;
- exposure presets may carry the value as text (``"12.5"``), as Micro-Manager's
  config files do;
- the pixel size is the camera's ``pixel_size_um`` over its ``magnification``
  (both from the rig TOML), as the pixel-size preset ``scopetwin``;
- the image bit depth is the camera's (12 for the seed's camera), not the 16 bits
  of the buffer.

:func:`run_mda` runs a useq ``MDASequence`` (or a YAML/JSON file of one) through
the core and returns a summary of every plane (position, z, exposure, channel);
it is the library function behind ``scopetwin rig RIG mda``.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from scopetwin.instrument.devices import CameraDevice, FocusDrive, LightSource, Stage
from scopetwin.instrument.errors import RigError
from scopetwin.instrument.interrupts import deferred_signals
from scopetwin.instrument.rig import Rig

CHANNEL_GROUP = "Channel"
LIGHT_LABEL = "Light"
LAMP_PROPERTY = "Lamp"
PIXEL_SIZE_PRESET = "scopetwin"


def _unicore() -> Any:
    try:
        from pymmcore_plus.experimental import unicore
    except ImportError as exc:  # pragma: no cover - optional extra
        raise RigError("Micro-Manager interop needs pymmcore-plus: pip install 'scopetwin[mm]'") from exc
    return unicore


def make_device_classes() -> dict[str, type]:
    """Build the wrapper classes and the core class (pymmcore-plus is imported only here)."""
    uc = _unicore()
    # pymmcore-plus's base classes, looked up at run time (the package is an optional extra)
    camera_base: Any = uc.SimpleCameraDevice
    xy_base: Any = uc.XYStageDevice
    stage_base: Any = uc.StageDevice
    shutter_base: Any = uc.ShutterDevice
    core_base: Any = uc.UniMMCore

    class RigLights(shutter_base):
        """Every light of the rig as one Micro-Manager shutter; property ``Lamp`` selects the light.

        Open = the selected light on at its configured current (the maximum if none is set).
        """

        def __init__(self, lights: Mapping[str, LightSource]) -> None:
            super().__init__()
            if not lights:
                raise RigError("Micro-Manager interop needs at least one light in the rig")
            self.lights = dict(lights)
            self.selected = next(iter(self.lights))
            self.register_property(
                LAMP_PROPERTY,
                default_value=self.selected,
                getter=lambda dev: dev.selected,
                setter=lambda dev, value: dev.select(str(value)),
                allowed_values=tuple(self.lights),
            )

        def select(self, name: str) -> None:
            """Select light ``name``; an open shutter hands over to it."""
            if name not in self.lights:
                raise RigError(f"no light {name!r}; lights: {sorted(self.lights)}")
            was_open = self.get_open()
            if was_open and name != self.selected:
                self.lights[self.selected].switch_off()
            self.selected = name
            if was_open:
                self.set_open(True)

        def light(self) -> LightSource:
            """The selected light."""
            return self.lights[self.selected]

        def get_open(self) -> bool:
            return self.light().is_on

        def set_open(self, open: bool) -> None:  # noqa: A002 - pymmcore-plus's signature
            lamp = self.light()
            if open:
                lamp.switch_on(lamp.current_ma or lamp.current_range.high)
            else:
                lamp.switch_off()

    class RigCamera(camera_base):
        """A rig camera as a Micro-Manager camera (exposure in ms, frames as uint16 DN).

        ``lights`` (optional) switches the selected light on for each snap and off afterwards
        (unless it was on already): UniMMCore (pymmcore-plus 0.18) does not apply its auto-shutter
        around Python cameras' snaps.
        """

        def __init__(self, camera: CameraDevice, lights: Any = None) -> None:
            super().__init__()
            self.camera = camera
            self.lights = lights

        def get_exposure(self) -> float:
            return self.camera.exposure_s * 1e3

        def set_exposure(self, exposure: float | str) -> None:
            self.camera.set_exposure_s(float(exposure) * 1e-3)  # presets arrive as text

        def sensor_shape(self) -> tuple[int, int]:
            return self.camera.frame_shape

        def dtype(self) -> Any:
            return np.uint8 if self.camera.bit_depth <= 8 else np.uint16

        def snap(self, buffer: np.ndarray) -> Mapping:
            lamp = None if self.lights is None else self.lights.light()
            switch = lamp is not None and not lamp.is_on
            if switch and lamp is not None:
                lamp.switch_on(lamp.current_ma or lamp.current_range.high)
            try:
                frame = self.camera.grab()
            finally:
                if switch and lamp is not None:
                    lamp.switch_off()
            top = 2**self.camera.bit_depth - 1
            buffer[:] = np.clip(np.rint(frame), 0, top).astype(buffer.dtype)
            meta = {"scopetwin_camera": self.camera.name, "scopetwin_bit_depth": self.camera.bit_depth}
            if lamp is not None:
                meta["scopetwin_light"] = lamp.name
            return meta

    class RigXYStage(xy_base):
        """Two rig stage axes as one Micro-Manager XY stage (µm)."""

        def __init__(self, x: Stage, y: Stage) -> None:
            super().__init__()
            self.x, self.y = x, y

        def set_position_um(self, x: float, y: float) -> None:
            self.x.move_absolute(x * 1e-3)
            self.y.move_absolute(y * 1e-3)

        def get_position_um(self) -> tuple[float, float]:
            return self.x.position_mm * 1e3, self.y.position_mm * 1e3

        def set_origin_x(self) -> None:
            raise NotImplementedError("scopetwin stages keep their hardware origin")

        def set_origin_y(self) -> None:
            raise NotImplementedError("scopetwin stages keep their hardware origin")

        def home(self) -> None:
            raise NotImplementedError("homing is done by the driver at initialisation")

        def stop(self) -> None:
            self.x.halt()
            self.y.halt()

        def set_origin(self) -> None:
            raise NotImplementedError("scopetwin stages keep their hardware origin")

    class RigFocus(stage_base):
        """The rig's focus drive as a Micro-Manager Z stage (µm)."""

        def __init__(self, focus: FocusDrive) -> None:
            super().__init__()
            self.focus = focus

        def set_position_um(self, val: float) -> None:
            self.focus.move_absolute_um(val)

        def get_position_um(self) -> float:
            return self.focus.position_um

        def home(self) -> None:
            raise NotImplementedError("the focus drive has no home move")

        def stop(self) -> None:
            """A piezo settles by itself: nothing to stop."""

        def set_origin(self) -> None:
            raise NotImplementedError("the focus drive keeps its calibrated origin")

    class RigCore(core_base):
        """UniMMCore that reports the rig camera's bit depth (not the 16 bits of its buffer)."""

        rig_cameras: dict[str, CameraDevice]

        def getImageBitDepth(self) -> int:  # noqa: N802 - MMCore's name
            camera = getattr(self, "rig_cameras", {}).get(self.getCameraDevice())
            return int(camera.bit_depth) if camera is not None else int(super().getImageBitDepth())

    return {
        "camera": RigCamera,
        "xy": RigXYStage,
        "focus": RigFocus,
        "lights": RigLights,
        "core": RigCore,
    }


def _define_pixel_size(core: Any, size_um: float) -> None:
    """The pixel-size preset ``scopetwin`` with ``size_um`` µm, made current."""
    core.definePixelSizeConfig(PIXEL_SIZE_PRESET)
    core.setPixelSizeUm(PIXEL_SIZE_PRESET, float(size_um))
    core.setPixelSizeConfig(PIXEL_SIZE_PRESET)


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
    """Register the rig's camera (``Camera``), XY stage (``XY``), focus (``Z``) and its lights (the
    shutter ``Light``, one ``Channel`` preset per light) with a ``UniMMCore``.

    Parameters
    ----------
    rig : Rig
        An open rig.
    core : UniMMCore, optional
        The core to load into (default: a new one that reports the camera's bit depth).
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
    classes = make_device_classes()
    core = core if core is not None else classes["core"]()
    cam = rig.camera(camera)
    lights = classes["lights"]({lamp.name: lamp for lamp in rig.lights()})
    if light is not None:
        lights.select(rig.light(light).name)
    core.rig_cameras = {"Camera": cam}
    core.loadPyDevice("Camera", classes["camera"](cam, lights))
    core.loadPyDevice("XY", classes["xy"](rig.stage(stage_x), rig.stage(stage_y)))
    core.loadPyDevice("Z", classes["focus"](rig.focus(focus)))
    core.loadPyDevice(LIGHT_LABEL, lights)
    for label in ("Camera", "XY", "Z", LIGHT_LABEL):
        core.initializeDevice(label)
    core.setShutterDevice(LIGHT_LABEL)
    core.setCameraDevice("Camera")
    core.setXYStageDevice("XY")
    core.setFocusDevice("Z")
    core.defineConfigGroup(CHANNEL_GROUP)
    for name in lights.lights:
        core.defineConfig(CHANNEL_GROUP, name, LIGHT_LABEL, LAMP_PROPERTY, name)
    core.setChannelGroup(CHANNEL_GROUP)
    _define_pixel_size(core, cam.limits.sample_pixel_um)
    return core


def load_sequence(sequence: Any) -> Any:
    """A ``useq.MDASequence`` from a sequence, a dict, or a YAML / JSON file path (µm and ms)."""
    try:
        import useq
    except ImportError as exc:  # pragma: no cover - optional extra
        raise RigError("MDA needs useq-schema: pip install 'scopetwin[mm]'") from exc
    if isinstance(sequence, useq.MDASequence):
        return sequence
    if isinstance(sequence, Mapping):
        return useq.MDASequence(**sequence)
    path = Path(sequence)
    if not path.is_file():
        raise RigError(f"MDA sequence file {str(path)!r} does not exist")
    try:
        return useq.MDASequence.from_file(path)
    except Exception as exc:  # noqa: BLE001 - useq raises pydantic and parser errors alike
        raise RigError(f"cannot read MDA sequence {str(path)!r}: {exc}") from exc


def run_mda(
    rig: Rig,
    sequence: Any,
    *,
    camera: str | None = None,
    output: Any = None,
    on_frame: Callable[[np.ndarray, Any, Mapping], None] | None = None,
    core: Any | None = None,
) -> dict[str, Any]:
    """Run a useq MDA sequence on the rig through pymmcore-plus.

    Parameters
    ----------
    rig : Rig
        An open rig.
    sequence : MDASequence, dict or path
        The acquisition (a YAML or JSON file as Micro-Manager writes them).
    camera : str, optional
        The rig camera to acquire with.
    output : optional
        Passed to ``core.mda.run(..., output=...)``: a path (``.ome.tif``, ``.ome.zarr``) or a
        pymmcore-plus / ome-writers handler.
    on_frame : callable, optional
        Called with ``(image, event, metadata)`` for every plane (e.g. a progress bar).
        SIGINT, SIGTERM or SIGHUP during the run cancel it at the next event boundary: the output
        writers close (the planes acquired so far stay readable), the lights go off, and then the
        signal is delivered to its handler as usual.
    core : UniMMCore, optional
        A core already loaded with :func:`load_into_core`.

    Returns
    -------
    dict
        ``{"planes": n, "pixel_size_um", "bit_depth", "channels": [...], "frames": [{"index", "channel",
        "x_um", "y_um", "z_um", "exposure_ms"}, ...]}``.
    """
    seq = load_sequence(sequence)
    core = core if core is not None else load_into_core(rig, camera=camera)
    frames: list[dict[str, Any]] = []

    def record(image: np.ndarray, event: Any, meta: Mapping) -> None:
        frames.append(
            {
                "index": {str(k): int(v) for k, v in dict(event.index).items()},
                "channel": None if event.channel is None else event.channel.config,
                "x_um": event.x_pos,
                "y_um": event.y_pos,
                "z_um": event.z_pos,
                "exposure_ms": event.exposure if event.exposure is not None else core.getExposure(),
            }
        )
        if on_frame is not None:
            on_frame(image, event, meta)

    core.mda.events.frameReady.connect(record)
    interrupted = threading.Event()
    done = threading.Event()

    def cancel_when_interrupted() -> None:  # the runner's lock is never taken inside a signal handler
        while not done.wait(0.02):
            if interrupted.is_set():
                core.mda.cancel()  # a no-op until the run starts; then it ends at the next event boundary

    watcher = threading.Thread(target=cancel_when_interrupted, name="mda-cancel", daemon=True)
    watcher.start()
    # SIGINT / SIGTERM / SIGHUP cancel the run: the writers close their files (every plane written so far
    # stays readable), the lights go off, then the signal is delivered as usual
    with deferred_signals(on_signal=lambda _signum: interrupted.set()):
        try:
            if output is None:
                core.mda.run(seq)
            else:
                core.mda.run(seq, output=output)
        finally:
            done.set()
            watcher.join()
            core.mda.events.frameReady.disconnect(record)
            rig.lights_off()
    return {
        "planes": len(frames),
        "pixel_size_um": core.getPixelSizeUm(),
        "bit_depth": core.getImageBitDepth(),
        "channels": sorted({f["channel"] for f in frames if f["channel"]}),
        "frames": frames,
    }
