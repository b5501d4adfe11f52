"""Renderers for simulated cameras: callables ``WorldState -> irradiance`` (float32, radiance units).

* :class:`FlatTextureRenderer` — pure numpy, no Mitsuba: a fixed texture moved by
  the stage and scaled by the light levels (fast; for device tests).
* :class:`WidefieldRenderer` — the microscope tile of :mod:`scopetwin.scenes.mitsuba.widefield`
  (bent fluorescent sample, 10x / 0.45 thin lens, focus from the focus drive).
* :class:`DeflectometryRenderer` — a Part I setup rendered by
  :func:`scopetwin.scenes.mitsuba.render.render_setup` (cached: the world only scales it by the pattern light); with
  a ``pattern_stage`` the pattern sits where that stage puts it, moved along its normal (one render per position).

:func:`make_renderer` builds one from a rig file's ``renderer`` table.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from scopetwin.instrument.errors import RigError
from scopetwin.instrument.simulated.world import WorldState


def light_sum(state: WorldState, lights: Sequence[str] | None) -> float:
    """Sum of the levels of ``lights`` (all lights when None) in an exposure."""
    names = state.light_levels.keys() if lights is None else lights
    return float(sum(state.light_levels.get(n, 0.0) for n in names))


class FlatTextureRenderer:
    """A random texture of the sample plane, shifted by the stage, scaled by the lights (numpy only).

    Parameters
    ----------
    lights : sequence of str, optional
        Lights that illuminate this camera (default: all).
    stage_x, stage_y : str
        Stage device names whose positions shift the texture.
    pixel_mm : float
        Object-side pixel size (stage mm per pixel).
    peak : float
        Irradiance of the brightest texel at full light.
    seed : int
        Texture seed.
    """

    def __init__(
        self,
        *,
        lights: Sequence[str] | None = None,
        stage_x: str = "x",
        stage_y: str = "y",
        pixel_mm: float = 0.000645,
        peak: float = 1.0,
        seed: int = 0,
    ) -> None:
        self.lights = None if lights is None else list(lights)
        self.stage_x, self.stage_y = stage_x, stage_y
        self.pixel_mm = float(pixel_mm)
        self.peak = float(peak)
        rng = np.random.default_rng(seed)
        lattice = ndimage.gaussian_filter(rng.random((512, 512)), 2.0, mode="wrap")
        lattice = (lattice - lattice.min()) / (lattice.max() - lattice.min())
        self._lattice = (0.2 + 0.8 * lattice).astype(np.float32)

    def __call__(self, state: WorldState) -> NDArray[np.float32]:
        rows, cols = state.sensor_shape
        dx = state.stage_mm.get(self.stage_x, 0.0) / self.pixel_mm
        dy = state.stage_mm.get(self.stage_y, 0.0) / self.pixel_mm
        r = (np.arange(rows) - int(round(dy))) % self._lattice.shape[0]
        c = (np.arange(cols) + int(round(dx))) % self._lattice.shape[1]
        return self._lattice[np.ix_(r, c)] * np.float32(self.peak * light_sum(state, self.lights))


class WidefieldRenderer:
    """The widefield microscope tile (:func:`scopetwin.scenes.mitsuba.widefield.render_tile`) of the world's state.

    Parameters
    ----------
    height_mm : callable
        Substrate height h(x, y) in mm.
    optics : scenes.mitsuba.widefield.WidefieldOptics
        Objective and frame; ``optics.pixels`` must equal the camera's sensor shape (cols, rows).
    lights, stage_x, stage_y, focus : str
        Names of the exciting light(s), the stage axes and the focus drive in the rig.
    seed : int
        Base sampler seed (each frame uses the next one).
    """

    def __init__(
        self,
        height_mm: Any,
        optics: Any,
        *,
        lights: Sequence[str] | None = None,
        stage_x: str = "x",
        stage_y: str = "y",
        focus: str = "focus",
        seed: int = 0,
    ) -> None:
        self.height_mm = height_mm
        self.optics = optics
        self.lights = None if lights is None else list(lights)
        self.stage_x, self.stage_y, self.focus = stage_x, stage_y, focus
        self._seed = int(seed)

    def __call__(self, state: WorldState) -> NDArray[np.float32]:
        from scopetwin.scenes.mitsuba.widefield import render_tile

        level = light_sum(state, self.lights)
        cols, rows = self.optics.pixels
        if (rows, cols) != tuple(state.sensor_shape):
            raise RigError(f"widefield renderer frame {rows}x{cols} differs from camera sensor {state.sensor_shape}")
        if level <= 0:
            return np.zeros(state.sensor_shape, np.float32)
        self._seed += 1
        xy = (state.stage_mm.get(self.stage_x, 0.0), state.stage_mm.get(self.stage_y, 0.0))
        return render_tile(
            self.height_mm, xy, state.focus_um.get(self.focus, 0.0), self.optics, radiance_scale=level, seed=self._seed
        )


class DeflectometryRenderer:
    """A Part I setup (:func:`scopetwin.scenes.setup.load_setup`) rendered once, scaled by the pattern light.

    Parameters
    ----------
    setup : str
        Preset name or TOML path.
    heights : scenes.surface.HeightMap, optional
        Substrate height map (default: a spherical bow of ``bow_um`` over the substrate).
    bow_um : float
        Bow of the default substrate.
    spp, seed : int
        Render quality and seed.
    lights : sequence of str
        Lights that illuminate the pattern.
    pattern_stage : str, optional
        A stage that moves the pattern along its normal N_z: its position (mm) is the pattern's shift from the
        setup's pose (:func:`scopetwin.scenes.pattern_stage.shift_pattern`, thesis §1.3); None: the pattern stays.
    """

    def __init__(
        self,
        setup: str,
        *,
        heights: Any = None,
        bow_um: float = 40.0,
        spp: int = 4,
        seed: int = 0,
        lights: Sequence[str] | None = None,
        pattern_stage: str | None = None,
    ) -> None:
        from scopetwin.scenes.setup import load_setup

        self.setup = load_setup(setup)
        self.heights = heights if heights is not None else self._bow(bow_um)
        self.spp, self.seed = int(spp), int(seed)
        self.lights = None if lights is None else list(lights)
        self.pattern_stage = pattern_stage
        self._images: dict[float, NDArray[np.float32]] = {}

    def _bow(self, bow_um: float) -> Any:
        from scopetwin.scenes.surface import HeightMap

        if self.setup.substrate is None:
            return None
        sx, sy = self.setup.substrate.size
        r2 = (0.5 * sx) ** 2 + (0.5 * sy) ** 2
        return HeightMap.from_function(
            lambda x, y: bow_um * 1e-3 * (1 - (x**2 + y**2) / r2),
            -0.5 * sx,
            0.5 * sx,
            -0.5 * sy,
            0.5 * sy,
            nx=64,
            ny=128,
        )

    def __call__(self, state: WorldState) -> NDArray[np.float32]:
        shift = 0.0 if self.pattern_stage is None else round(float(state.stage_mm.get(self.pattern_stage, 0.0)), 6)
        image = self._images.get(shift)
        if image is None:
            from scopetwin.scenes.mitsuba.render import render_setup
            from scopetwin.scenes.pattern_stage import shift_pattern

            setup = self.setup if shift == 0.0 else shift_pattern(self.setup, shift)
            image = self._images[shift] = render_setup(setup, heights=self.heights, spp=self.spp, seed=self.seed)
        if image.shape != tuple(state.sensor_shape):
            raise RigError(
                f"deflectometry render {image.shape} differs from camera sensor "
                f"{tuple(state.sensor_shape)}: set the camera's sensor_shape to the setup's pixels"
            )
        return image * np.float32(light_sum(state, self.lights))


def make_renderer(spec: dict[str, Any], *, camera: str) -> Any:
    """Build a renderer from a rig file's ``renderer`` table (``kind`` = texture | widefield | deflectometry).

    Raises
    ------
    RigError
        Unknown kind or bad options.
    """
    options = dict(spec)
    kind = options.pop("kind", "texture")
    try:
        if kind == "texture":
            return FlatTextureRenderer(**options)
        if kind == "widefield":
            from scopetwin.scenes.mitsuba.widefield import BentSubstrate, WidefieldOptics

            substrate_opts: dict[str, Any] = {
                k: (tuple(v) if isinstance(v, list) else v) for k, v in options.pop("substrate", {}).items()
            }
            substrate = BentSubstrate(**substrate_opts)
            optics_opts = options.pop("optics", {})
            if "pixels" in optics_opts:
                optics_opts["pixels"] = tuple(optics_opts["pixels"])
            return WidefieldRenderer(substrate, WidefieldOptics(**optics_opts), **options)
        if kind == "deflectometry":
            return DeflectometryRenderer(**options)
    except TypeError as exc:
        raise RigError(f"camera {camera!r}: bad renderer option ({exc})") from exc
    raise RigError(f"camera {camera!r}: unknown renderer kind {kind!r} (texture, widefield, deflectometry)")
