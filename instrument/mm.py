"""Micro-Manager interop: a rig's camera, stages and focus as pymmcore-plus pure-Python devices.

Optional dependency: ``pip install scopetwin[mm]`` (pymmcore-plus, useq-schema).
:func:`load_into_core` wraps the rig's devices in pymmcore-plus's
``experimental.unicore`` device classes and registers them with
``UniMMCore.loadPyDevice``, so ``core.mda.run(useq.MDASequence(...))`` drives the
simulated rig or the hardware alike. Micro-Manager speaks µm for every stage
and milliseconds for exposures; the wrappers convert to the rig's mm and s.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from instrument.errors import RigError
from instrument.rig import Rig


def _unicore() -> Any:
    try:
        from pymmcore_plus.experimental import unicore
    except ImportError as exc:  # pragma: no cover - optional extra
        raise RigError("Micro-Manager interop needs pymmcore-plus: pip install 'scopetwin[mm]'") from exc
    return unicore


def make_device_classes() -> dict[str, type]:
    """Build the wrapper classes (pymmcore-plus is imported only here)."""
    uc = _unicore()

    class RigCamera(uc.SimpleCameraDevice):
        """A rig camera as a Micro-Manager camera (exposure in ms, frames as uint16 DN).

        ``light`` (optional) is switched on for each snap and off afterwards: UniMMCore
        (pymmcore-plus 0.18) does not apply its auto-shutter around Python cameras' snaps.
        """

        def __init__(self, camera: Any, light: Any = None) -> None:
            super().__init__()
            self.camera = camera
            self.light = light

        def get_exposure(self) -> float:
            return self.camera.exposure_s * 1e3

        def set_exposure(self, exposure: float) -> None:
            self.camera.set_exposure_s(exposure * 1e-3)

        def sensor_shape(self) -> tuple[int, int]:
            return self.camera.frame_shape

        def dtype(self) -> Any:
            return np.uint16

        def snap(self, buffer: np.ndarray) -> Mapping:
            if self.light is None:
                frame = self.camera.grab()
            else:
                self.light.switch_on(self.light.current_ma or self.light.current_range.high)
                try:
                    frame = self.camera.grab()
                finally:
                    self.light.switch_off()
            buffer[:] = np.clip(np.rint(frame), 0, 65535).astype(np.uint16)
            return {"scopetwin_camera": self.camera.name}

    class RigXYStage(uc.XYStageDevice):
        """Two rig stage axes as one Micro-Manager XY stage (µm)."""

        def __init__(self, x: Any, y: Any) -> None:
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

    class RigFocus(uc.StageDevice):
        """The rig's focus drive as a Micro-Manager Z stage (µm)."""

        def __init__(self, focus: Any) -> None:
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

    class RigLightShutter(uc.ShutterDevice):
        """A rig light as a Micro-Manager shutter: open = light on (auto-shutter lights only exposures)."""

        def __init__(self, light: Any) -> None:
            super().__init__()
            self.light = light

        def get_open(self) -> bool:
            return self.light.is_on

        def set_open(self, open: bool) -> None:  # noqa: A002 - pymmcore-plus's signature
            if open:
                self.light.switch_on(self.light.current_ma or self.light.current_range.high)
            else:
                self.light.switch_off()

    return {"camera": RigCamera, "xy": RigXYStage, "focus": RigFocus, "shutter": RigLightShutter}


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
    """Register the rig's camera (``Camera``), XY stage (``XY``), focus (``Z``) and a light as the
    shutter (``Light``) with a ``UniMMCore``.

    Returns the core, with them set as the current camera, XY stage, focus and shutter device.
    """
    uc = _unicore()
    core = core or uc.UniMMCore()
    classes = make_device_classes()
    lamp = rig.light(light)
    core.loadPyDevice("Camera", classes["camera"](rig.camera(camera), lamp))
    core.loadPyDevice("XY", classes["xy"](rig.stage(stage_x), rig.stage(stage_y)))
    core.loadPyDevice("Z", classes["focus"](rig.focus(focus)))
    core.loadPyDevice("Light", classes["shutter"](lamp))
    for label in ("Camera", "XY", "Z", "Light"):
        core.initializeDevice(label)
    core.setShutterDevice("Light")
    core.setCameraDevice("Camera")
    core.setXYStageDevice("XY")
    core.setFocusDevice("Z")
    return core
