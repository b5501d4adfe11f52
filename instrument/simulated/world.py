"""The virtual world shared by the simulated devices, and the renderer interface.

A :class:`VirtualWorld` holds what the simulated devices read and change: stage
positions (mm), focus positions (µm), light configurations and on-states,
shutters, camera trigger lines, and the global trigger. A simulated camera
asks the world for a :class:`WorldState` snapshot (what its exposure sees)
and passes it to a **renderer**: any callable ``WorldState -> irradiance``
(float32 image, radiance units, the full sensor). The camera then applies the
EMVA 1288 sensor model (:class:`scopetwin.scenes.emva1288.EmvaSensor`).

Light levels in the snapshot are relative radiant outputs (``current /
max_current``), weighted by the fraction of the exposure the light was on: for
a global trigger, a light listening with delay ``d_l`` and duration ``T_l``
overlaps an exposure ``[d_c, d_c + t_exp]`` by ``|[d_l, d_l+T_l] ∩ [d_c, d_c+t_exp]|``
(thesis §4.3.2, 'Global Trigger'). A light behind a closed shutter contributes 0.

Devices outside the world (hardware drivers on in-process emulators, as in
``rigs/emulated-hardware.toml``) are seen through **probes**: callables that
return a light's relative level, a stage position (mm) or a focus position (µm)
from the emulator's state; :func:`scopetwin.instrument.rig.load_rig` registers them, so a
simulated camera sees the board's lights and the stages' positions.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

import numpy as np
from numpy.typing import NDArray

from scopetwin.instrument.devices import LightConfig


@dataclass(frozen=True)
class WorldState:
    """What one exposure of one camera sees.

    Attributes
    ----------
    camera : str
        Name of the exposing camera.
    sensor_shape : tuple of int
        ``(rows, cols)`` the renderer must return.
    exposure_s : float
        Exposure time.
    stage_mm : Mapping[str, float]
        Stage positions by device name.
    focus_um : Mapping[str, float]
        Focus-drive positions by device name.
    light_levels : Mapping[str, float]
        Relative light output by light name, averaged over the exposure (0 = dark, 1 = full current all along).
    """

    camera: str
    sensor_shape: tuple[int, int]
    exposure_s: float
    stage_mm: Mapping[str, float]
    focus_um: Mapping[str, float]
    light_levels: Mapping[str, float]


Renderer = Callable[[WorldState], NDArray[np.float32]]


@dataclass
class SimLightState:
    """A light in the world: limits, configuration and whether it is on."""

    max_current_ma: float
    shutter: str | None = None
    config: LightConfig = field(default_factory=LightConfig)
    on: bool = False


def _overlap(a0: float, a1: float, b0: float, b1: float) -> float:
    return max(0.0, min(a1, b1) - max(a0, b0))


class VirtualWorld:
    """State shared by the simulated devices of one rig (thread-safe).

    Attributes
    ----------
    io_log : list of tuple
        ``(device, operation)`` for every hook that changed or read the world:
        the simulated counterpart of the emulators' byte log.
    events : list of tuple
        ``(kind, name)`` for light switching and triggers, in order.
    """

    def __init__(self) -> None:
        self.lock = threading.RLock()
        self.stage_mm: dict[str, float] = {}
        self.focus_um: dict[str, float] = {}
        self.lights: dict[str, SimLightState] = {}
        self.shutters: dict[str, bool] = {}
        self.camera_lines: dict[int, tuple[bool, float]] = {}
        self.listeners: dict[int, list[Callable[[float, dict[str, tuple[float, float]]], None]]] = {}
        self.io_log: list[tuple[str, str]] = []
        self.events: list[tuple[str, str]] = []
        self.light_probes: dict[str, Callable[[], float]] = {}
        self.stage_probes: dict[str, Callable[[], float]] = {}
        self.focus_probes: dict[str, Callable[[], float]] = {}

    def probed_levels(self) -> dict[str, float]:
        """Relative levels of the lights outside the world, as their probes report them now."""
        return {name: float(probe()) for name, probe in self.light_probes.items()}

    def record(self, device: str, operation: str) -> None:
        """Log one device operation."""
        with self.lock:
            self.io_log.append((device, operation))

    # lights ---------------------------------------------------------------------------------------
    def set_light(self, name: str, on: bool) -> None:
        """Switch a light on or off (logged in :attr:`events`)."""
        with self.lock:
            self.lights[name].on = bool(on)
            self.events.append(("light-on" if on else "light-off", name))

    def any_light_on(self) -> bool:
        """Whether any light is on (probed lights included)."""
        with self.lock:
            return any(light.on for light in self.lights.values()) or any(v > 0 for v in self.probed_levels().values())

    def _shutter_factor(self, light: SimLightState) -> float:
        return 1.0 if light.shutter is None or self.shutters.get(light.shutter, False) else 0.0

    def static_levels(self) -> dict[str, float]:
        """Light levels of lights that are on now, for a software-triggered exposure."""
        with self.lock:
            levels = {
                name: (light.config.current_ma / light.max_current_ma if light.on else 0.0)
                * self._shutter_factor(light)
                for name, light in self.lights.items()
            }
            return {**levels, **self.probed_levels()}

    def levels_for_window(
        self, start_s: float, exposure_s: float, intervals: Mapping[str, tuple[float, float]]
    ) -> dict[str, float]:
        """Light levels for an exposure ``[start_s, start_s + exposure_s]`` after a trigger.

        ``intervals`` gives each triggered light's on-interval relative to the trigger;
        lights already on (and not in ``intervals``) count as on throughout.
        """
        with self.lock:
            levels = {}
            for name, light in self.lights.items():
                if name in intervals:
                    t0, t1 = intervals[name]
                elif light.on:
                    t0, t1 = -np.inf, np.inf
                else:
                    levels[name] = 0.0
                    continue
                fraction = _overlap(t0, t1, start_s, start_s + exposure_s) / max(exposure_s, 1e-12)
                levels[name] = fraction * light.config.current_ma / light.max_current_ma * self._shutter_factor(light)
            return {**levels, **self.probed_levels()}  # probed lights: as they are now, all along

    # triggers ---------------------------------------------------------------------------------------
    def fire_global_trigger(self) -> None:
        """Fire the global trigger: listening lights switch on after their delay, listening
        camera lines expose, and lights with a duration are off again afterwards."""
        with self.lock:
            self.events.append(("global-trigger", ""))
            intervals: dict[str, tuple[float, float]] = {}
            for name, light in self.lights.items():
                cfg = light.config
                if cfg.listen_global_trigger:
                    end = cfg.global_trigger_delay_s + cfg.duration_s if cfg.use_duration else np.inf
                    intervals[name] = (cfg.global_trigger_delay_s, end)
                    self.set_light(name, True)
            for line, (listen, delay) in sorted(self.camera_lines.items()):
                if listen:
                    for callback in list(self.listeners.get(line, [])):
                        callback(delay, intervals)
            for name, (_, end) in intervals.items():
                if np.isfinite(end):
                    self.set_light(name, False)

    def pulse_camera_line(self, line: int) -> None:
        """A single trigger pulse on one camera line (lights as they are now)."""
        with self.lock:
            self.events.append(("camera-pulse", str(line)))
            for callback in list(self.listeners.get(line, [])):
                callback(0.0, {})

    def snapshot(
        self, camera: str, sensor_shape: tuple[int, int], exposure_s: float, light_levels: Mapping[str, float]
    ) -> WorldState:
        """A frozen :class:`WorldState` for one exposure."""
        with self.lock:
            return WorldState(
                camera,
                (int(sensor_shape[0]), int(sensor_shape[1])),
                float(exposure_s),
                MappingProxyType({**self.stage_mm, **{n: float(p()) for n, p in self.stage_probes.items()}}),
                MappingProxyType({**self.focus_um, **{n: float(p()) for n, p in self.focus_probes.items()}}),
                MappingProxyType(dict(light_levels)),
            )
