"""Simulated devices: the device protocols of :mod:`scopetwin.instrument.devices` acting on a :class:`VirtualWorld`.

Stages and the focus drive move instantly; lights, shutters and triggers change
the world; the camera renders the world's state through a renderer and the
EMVA 1288 sensor model (:class:`scopetwin.scenes.emva1288.EmvaSensor`): exposure scales
signal and shot noise, the full well and the ADC saturate (12 bit by default),
gain (dB) scales the system gain, and hardware-triggered exposures happen when
the world's global trigger fires on the camera's line.

Fault injection for tests: :meth:`SimDevice.inject_fault` makes a device
time out, drop frames (cameras) or lose its connection after a number of
successful operations.
"""

from __future__ import annotations

import collections
import dataclasses
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.instrument.devices import (
    CameraDevice,
    CameraLimits,
    FocusDrive,
    LightConfig,
    LightSource,
    Roi,
    Shutter,
    Stage,
    TriggerController,
    TriggerMode,
    TriggerType,
)
from scopetwin.instrument.errors import DisconnectedError, InstrumentTimeout, OutOfRangeError
from scopetwin.instrument.simulated.world import Renderer, SimLightState, VirtualWorld, WorldState
from scopetwin.scenes.emva1288 import EmvaSensor

FAULTS = ("timeout", "disconnect", "drop")


class SimDevice:
    """Mixin: world access, operation log and fault injection for simulated devices."""

    driver = "sim"
    world: VirtualWorld
    name: str

    def _sim_init(self, world: VirtualWorld, timeout_s: float) -> None:
        self.world = world
        self.timeout_s = float(timeout_s)
        self._fault: str | None = None
        self._fault_after = 0

    def inject_fault(self, fault: str | None, after: int = 0) -> None:
        """Fail every operation after ``after`` more successful ones: ``timeout``, ``disconnect`` or
        (cameras) ``drop`` (frames never arrive). ``None`` clears the fault."""
        if fault is not None and fault not in FAULTS:
            raise OutOfRangeError(f"unknown fault {fault!r}; choose from {FAULTS}")
        self._fault, self._fault_after = fault, int(after)

    def _io(self, operation: str) -> None:
        """Log one operation and apply an injected fault."""
        fault = self._fault
        if fault is not None and fault != "drop":
            if self._fault_after <= 0:
                if fault == "timeout":
                    time.sleep(self.timeout_s)
                    raise InstrumentTimeout(f"{self.name!r}: no answer within {self.timeout_s} s (injected)")
                raise DisconnectedError(f"{self.name!r}: connection lost (injected)")
            self._fault_after -= 1
        self.world.record(self.name, operation)


class SimStage(SimDevice, Stage):
    """A stage axis that moves instantly in the virtual world."""

    def __init__(
        self,
        name: str,
        world: VirtualWorld,
        *,
        travel_mm: tuple[float, float],
        max_velocity_mm_s: float,
        position_mm: float | None = None,
        timeout_s: float = 1.0,
        **_: Any,
    ) -> None:
        Stage.__init__(self, name, travel_mm=travel_mm, max_velocity_mm_s=max_velocity_mm_s)
        self._sim_init(world, timeout_s)
        start = self.travel.low if position_mm is None else self.travel.check(position_mm, f"stage {name!r} start")
        world.stage_mm.setdefault(name, start)
        self._velocity = self.velocity_range.high

    def _do_get_position(self) -> float:
        self._io("position")
        return self.world.stage_mm[self.name]

    def _do_get_velocity(self) -> float:
        return self._velocity

    def _do_set_velocity(self, velocity_mm_s: float) -> None:
        self._io("velocity")
        self._velocity = velocity_mm_s

    def _do_move_absolute(self, position_mm: float) -> None:
        self._io("move")
        self.world.stage_mm[self.name] = position_mm

    def _do_move_relative(self, delta_mm: float) -> None:
        self._io("move")
        self.world.stage_mm[self.name] += delta_mm

    def _do_is_moving(self) -> bool:
        return False

    def _do_halt(self) -> None:
        self._io("halt")


class SimFocus(SimDevice, FocusDrive):
    """A focus drive (µm) that moves instantly in the virtual world."""

    def __init__(
        self,
        name: str,
        world: VirtualWorld,
        *,
        range_um: tuple[float, float] = (0.0, 400.0),
        position_um: float | None = None,
        timeout_s: float = 1.0,
        **_: Any,
    ) -> None:
        FocusDrive.__init__(self, name, range_um=range_um)
        self._sim_init(world, timeout_s)
        start = self.range.low if position_um is None else self.range.check(position_um, f"focus {name!r} start")
        world.focus_um.setdefault(name, start)

    def _do_get_position_um(self) -> float:
        self._io("position")
        return self.world.focus_um[self.name]

    def _do_move_absolute_um(self, position_um: float) -> None:
        self._io("move")
        self.world.focus_um[self.name] = position_um


class SimLight(SimDevice, LightSource):
    """A light source in the virtual world; ``shutter`` names the shutter in front of it (halogen)."""

    def __init__(
        self,
        name: str,
        world: VirtualWorld,
        *,
        max_current_ma: float,
        shutter: str | None = None,
        timeout_s: float = 1.0,
        **_: Any,
    ) -> None:
        LightSource.__init__(self, name, max_current_ma=max_current_ma)
        self._sim_init(world, timeout_s)
        world.lights[name] = SimLightState(max_current_ma=float(max_current_ma), shutter=shutter)

    def _do_configure(self, config: LightConfig) -> None:
        self._io("configure")
        self.world.lights[self.name].config = config

    def _do_trigger(self) -> None:
        self._io("trigger")
        light = self.world.lights[self.name]
        if light.config.use_duration:
            # an instantaneous world: a timed pulse is over before anything can look at it again
            self.world.events.append(("light-pulse", self.name))
        else:
            self.world.set_light(self.name, True)

    def _do_switch_off(self) -> None:
        self._io("switch-off")
        self.world.set_light(self.name, False)

    def _do_is_on(self) -> bool:
        self._io("state")
        return self.world.lights[self.name].on


class SimShutter(SimDevice, Shutter):
    """A shutter in the virtual world."""

    def __init__(self, name: str, world: VirtualWorld, *, timeout_s: float = 1.0, **_: Any) -> None:
        Shutter.__init__(self, name)
        self._sim_init(world, timeout_s)
        world.shutters[name] = False

    def _do_set_open(self, is_open: bool) -> None:
        self._io("set")
        self.world.shutters[self.name] = bool(is_open)

    def _do_is_open(self) -> bool:
        self._io("state")
        return self.world.shutters[self.name]


class SimTrigger(SimDevice, TriggerController):
    """The FPGA board's trigger section in the virtual world."""

    def __init__(
        self, name: str, world: VirtualWorld, *, n_camera_lines: int = 4, timeout_s: float = 1.0, **_: Any
    ) -> None:
        TriggerController.__init__(self, name, n_camera_lines=n_camera_lines)
        self._sim_init(world, timeout_s)

    def _do_configure_camera_line(self, line: int, listen: bool, delay_s: float) -> None:
        self._io("configure-line")
        self.world.camera_lines[line] = (listen, delay_s)

    def _do_trigger_camera(self, line: int) -> None:
        self._io("pulse")
        self.world.pulse_camera_line(line)

    def _do_fire(self) -> None:
        self._io("fire")
        self.world.fire_global_trigger()


def bin_image(image: NDArray[np.float32], binning: int) -> NDArray[np.float32]:
    """Sum ``binning x binning`` blocks (charge binning), dropping incomplete edge blocks."""
    if binning == 1:
        return image
    rows, cols = (s // binning for s in image.shape)
    view = image[: rows * binning, : cols * binning].reshape(rows, binning, cols, binning)
    return view.sum(axis=(1, 3), dtype=np.float64).astype(np.float32)


class SimCamera(SimDevice, CameraDevice):
    """A camera that renders the virtual world and applies the EMVA 1288 model.

    Parameters
    ----------
    name : str
        Device name.
    world : VirtualWorld
        The shared world.
    renderer : callable
        ``WorldState -> irradiance`` (float32, ``sensor_shape``, radiance units).
    emva : EmvaSensor
        EMVA 1288 sensor physics (:mod:`scopetwin.scenes.emva1288`) at 0 dB gain and 12 bit (its ``bit_depth`` is
        the ADC's); the rig file's ``sensor`` table holds its fields.
    photons_per_unit_s : float
        Photons per pixel and second at irradiance 1.
    limits : CameraLimits
        Allowed settings; ``sensor_shape`` must match what the renderer returns.
    trigger_line : int
        Camera line of the trigger board this camera listens to.
    seed : int
        Seed of the noise generator (frames are reproducible).
    serial_number : str
        Reported serial number.
    """

    def __init__(
        self,
        name: str,
        world: VirtualWorld,
        *,
        renderer: Renderer,
        emva: EmvaSensor | None = None,
        photons_per_unit_s: float = 1.0e6,
        limits: CameraLimits | None = None,
        trigger_line: int = 0,
        seed: int = 0,
        serial_number: str = "SIM-0001",
        timeout_s: float = 1.0,
        **_: Any,
    ) -> None:
        CameraDevice.__init__(self, name, limits=limits, timeout_s=timeout_s)
        self._sim_init(world, timeout_s)
        self.renderer = renderer
        self.emva = emva or EmvaSensor()
        self.photons_per_unit_s = float(photons_per_unit_s)
        self.trigger_line = int(trigger_line)
        self._rng = np.random.default_rng(seed)
        self._serial = serial_number
        self._frames: collections.deque[NDArray[np.float32]] = collections.deque()
        self._black_level_dn = self.emva.black_level_dn
        self.frames_rendered = 0

    # settings hooks: the world is instantaneous, the base class keeps the values
    def _do_get_serial_number(self) -> str:
        return self._serial

    def _do_set_roi(self, roi: Roi) -> None:
        self._io("roi")

    def _do_set_binning(self, binning: int) -> None:
        self._io("binning")

    def _do_set_bit_depth(self, bits: int) -> None:
        self._io("bit-depth")

    def _do_set_exposure_s(self, exposure_s: float) -> float:
        self._io("exposure")
        return exposure_s

    def _do_set_gain_db(self, gain_db: float) -> None:
        self._io("gain")

    def _do_set_black_level_dn(self, black_level_dn: float) -> None:
        self._io("black-level")

    def _do_set_fps(self, fps: float) -> None:
        self._io("fps")

    def _do_set_trigger(self, trigger_type: TriggerType, trigger_mode: TriggerMode, delay_s: float) -> None:
        self._io("trigger")

    def _do_arm(self) -> None:
        self._io("arm")
        self._frames.clear()
        self.world.listeners.setdefault(self.trigger_line, []).append(self._on_trigger)

    def _do_disarm(self) -> None:
        listeners = self.world.listeners.get(self.trigger_line, [])
        if self._on_trigger in listeners:
            listeners.remove(self._on_trigger)
        self._frames.clear()

    def _on_trigger(self, line_delay_s: float, intervals: dict[str, tuple[float, float]]) -> None:
        if self.listen_global_trigger:
            start = line_delay_s + self.global_trigger_delay_s
            levels = self.world.levels_for_window(start, self.exposure_s, intervals)
            self._expose(levels)

    def _do_software_trigger(self) -> None:
        self._io("software-trigger")
        self._expose(self.world.static_levels())

    def effective_emva(self) -> EmvaSensor:
        """The EMVA 1288 model at the current gain, black level and bit depth."""
        base = self.emva
        scale = 10 ** (self.gain_db / 20.0) * 2.0 ** (self.bit_depth - base.bit_depth)
        return dataclasses.replace(
            base, gain_dn_per_e=base.gain_dn_per_e * scale, bit_depth=self.bit_depth, black_level_dn=self.black_level_dn
        )

    def render_irradiance(self, levels: dict[str, float]) -> NDArray[np.float32]:
        """The renderer's irradiance for the world as this exposure sees it, cropped to the ROI and binned."""
        state: WorldState = self.world.snapshot(self.name, self.limits.sensor_shape, self.exposure_s, levels)
        image = np.asarray(self.renderer(state), dtype=np.float32)
        if image.shape != tuple(self.limits.sensor_shape):
            raise OutOfRangeError(
                f"camera {self.name!r}: renderer returned {image.shape}, sensor is {tuple(self.limits.sensor_shape)}"
            )
        roi = self.roi
        return bin_image(image[roi.row : roi.row + roi.rows, roi.col : roi.col + roi.cols], self.binning)

    def _expose(self, levels: dict[str, float]) -> None:
        if self._fault == "drop" and self._fault_after <= 0:
            return
        if self._fault == "drop":
            self._fault_after -= 1
        irradiance = self.render_irradiance(levels)
        frame = self.effective_emva().capture(irradiance, self.photons_per_unit_s, self.exposure_s, self._rng)
        self.frames_rendered += 1
        self._frames.append(frame)

    def _do_read_frame(self, timeout_s: float) -> NDArray[np.float32]:
        self._io("read")
        if self._frames:
            return self._frames.popleft()
        time.sleep(min(timeout_s, self.timeout_s))
        raise InstrumentTimeout(f"camera {self.name!r}: no frame within {timeout_s:.3g} s")
