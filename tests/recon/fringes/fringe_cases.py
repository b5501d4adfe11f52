"""Synthetic phase-shift measurements from the numpy truth of a known surface (shared by the fringe tests).

The per-pixel truth of the thesis's §1.10 setup (:func:`scopetwin.sim.datasets.maps.part1_maps`: the display point
``pattern_xy`` each pixel sees through the substrate's ROI) is turned into the ideal frames
I = A + B cos(2 pi u_d / p + 2 pi k / N) and captured by the setup's EMVA 1288 sensor (photon and dark noise, ADC).
Pixels that do not see the display through the ROI get the background only (no modulation).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

import scopetwin
from scopetwin.recon.fringes.phase import phase_shifts
from scopetwin.scenes.pattern_stage import shift_pattern
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap
from scopetwin.sim.datasets.maps import part1_maps
from scopetwin.sim.surfaces import make_surface, surface_for

#: A 4x binned camera of the §1.10 setup (340 x 256 px of 18.6 µm): ~26,000 pixels see the display through the ROI.
SMALL_CAMERA = {"camera": {"pixels": [340, 256], "pixel_pitch": 0.0186}}
PERIODS = (64.0, 8.0, 1.0)
#: Background and modulation of the display's radiance (a white texel is 1).
BACKGROUND, MODULATION = 0.5, 0.4


def thesis_setup(surface: dict[str, Any] | None = None, camera: dict[str, Any] | None = None) -> Setup:
    over: dict[str, Any] = dict(camera or SMALL_CAMERA)
    if surface is not None:
        over["substrate"] = {"surface": surface}
    return scopetwin.load_setup("thesis-1.10-deflectometry", over)


def truth(setup: Setup) -> tuple[HeightMap, dict[str, Any]]:
    heights = surface_for(setup)
    assert heights is not None
    return heights, part1_maps(setup, heights)


def seen(maps: dict[str, Any]) -> np.ndarray:
    return np.asarray(maps["roi"] & np.all(np.isfinite(maps["pattern_xy"]), axis=-1))


@dataclass
class Frames:
    x: list[np.ndarray]
    y: list[np.ndarray]


def capture(setup: Setup, maps: dict[str, Any], seed: int, steps: int = 4, periods=PERIODS) -> Frames:
    """The phase-shift frames (DN, float32) of the display points in ``maps``, with sensor noise from ``seed``."""
    ok = seen(maps)
    uv = np.where(ok[..., None], maps["pattern_xy"], 0.0).astype(np.float64)
    sensor = setup.sensor.sensor()
    photons = setup.sensor.photons_per_unit_s
    exposure = sensor.exposure_for(BACKGROUND + MODULATION, photons, 0.8)
    rng = np.random.default_rng(seed)
    deltas = phase_shifts(steps)
    out: dict[int, list[np.ndarray]] = {0: [], 1: []}
    for axis in (0, 1):
        for p in periods:
            phase = 2.0 * np.pi * uv[..., axis] / p
            stack = [
                sensor.capture(
                    np.where(ok, BACKGROUND + MODULATION * np.cos(phase + d), BACKGROUND), photons, exposure, rng
                )
                for d in deltas
            ]
            out[axis].append(np.stack(stack))
    return Frames(out[0], out[1])


def second_position(setup: Setup, heights: HeightMap, shift_mm: float) -> dict[str, Any]:
    return part1_maps(shift_pattern(setup, shift_mm), heights)


def surface_with(spec: dict[str, Any], setup: Setup) -> HeightMap:
    assert setup.substrate is not None
    return make_surface(setup.substrate.surface.model_copy(update=spec), setup.substrate)
