"""Render a fringe sequence (phase-measuring deflectometry in the thesis §1.10 setup) with Mitsuba 3.

The scene is the marker render's (:func:`scopetwin.scenes.mitsuba.scene.scene_dict`: the same camera and pixel box
filter, the same substrate or mirror, the same mirror integrator, the same live window as
:func:`scopetwin.scenes.mitsuba.render.render_setup`) with the marker pattern's emitter replaced by the display's
(:func:`scopetwin.scenes.mitsuba.scene.emitter_rectangle` over the display's active area, in the pattern's frame).
The scene is loaded once; each frame only writes the display's texture (:meth:`scopetwin.scenes.fringes.FringeDisplay.
texture`, times the pattern's ``radiance``) into the emitter's bitmap through ``mi.traverse`` and renders again: the
texture is a buffer of the same shape, so every frame launches the kernels the first one compiled (tested).

The substrate's mesh is finer than the marker render's (:data:`FRINGE_VERTICES`, 0.033 x 0.037 mm between vertices
on the 25.2 x 57 mm substrate). Mitsuba interpolates the exact vertex normals linearly across each triangle, which
smooths the mirror's slopes at the vertex spacing: every decoded display point is then the true one plus half the
display-point map's curvature times an effective variance, measured on rendered cut and features sheets (clean
renders against the per-pixel truth ``pattern_xy``) as 0.41-0.46 px^2 along the rows and 1.09-1.25 px^2 along the
columns with the marker render's 256 x 512 vertices (0.10 x 0.11 mm apart: 1.5 rows, 2.5 columns of the §1.10
camera); with 768 x 1536 it is 0.13-0.21 px^2, the pixel's own box (1/12 px^2) and the rest. At the fringes'
display-point noise (about 1.5 µm per pixel) the coarser mesh was the largest error of a reconstruction at two
display positions on those sheets: nanometres of shape, a correlated error no noise model of the decoder covers.
The markers' centroids do not resolve it (docs/rendering.md).

Every frame is rendered with the same sampler seed: a camera pixel integrates the same footprint in each frame, as a
real pixel does; independent seeds would add Monte Carlo noise that differs between the phase steps, which no camera
has (the sensor's own noise is added per frame by :func:`scopetwin.sim.fringes.render_fringes`).
"""

from __future__ import annotations

import time
from collections.abc import Iterator, Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.fringes import FringeDisplay, FringeFrame
from scopetwin.scenes.limits import FLOATS_PER_PIXEL, check_render
from scopetwin.scenes.mitsuba.render import live_window, scene_render
from scopetwin.scenes.mitsuba.scene import TEXEL, emitter_rectangle, scene_dict
from scopetwin.scenes.mitsuba.variant import mitsuba, resolve
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap

__all__ = ["DISPLAY_TEXTURE_KEY", "display_plate", "render_display_image", "render_fringe_frames"]

#: Vertex counts (x, y) of the substrate's mesh in a fringe render: three times the marker render's
#: (:data:`scopetwin.scenes.mitsuba.shapes.DEFAULT_VERTICES`) along each axis (module docstring).
FRINGE_VERTICES = (768, 1536)
#: The scene parameter holding the display's radiance raster.
DISPLAY_TEXTURE_KEY = "pattern.emitter.radiance.data"


def display_plate(setup: Setup, display: FringeDisplay) -> Setup:
    """``setup`` with its pattern plate sized to the display's active area, in the pattern's frame (the live window and
    the emitter's rectangle then bound the display, not the marker plate).

    The markers of that plate are never drawn (the display's emitter replaces them): one marker stands in for the
    grid, so that a display smaller than the setup's marker grid is a valid plate.
    """
    sx, sy = display.size_mm
    data = setup.model_dump()  # validated anew: a model_copy would keep the cached marker pattern of the old plate
    side = 0.1 * min(sx, sy)
    data["pattern"].update(markers=(1, 1), pitch=(0.5 * sx, 0.5 * sy), radius=side, ref_radius=side, size=(sx, sy))
    return Setup.model_validate(data)


def _texture(display: FringeDisplay, frame: FringeFrame, texel: float, radiance: float) -> NDArray[np.float32]:
    tex = display.texture(frame, texel)
    if radiance != 1.0:
        tex *= np.float32(radiance)
    return tex


def render_fringe_frames(
    setup: Setup,
    heights: HeightMap | None,
    frames: Sequence[FringeFrame],
    display: FringeDisplay,
    spp: int,
    seed: int,
    variant: str | None = None,
    texel: float = TEXEL,
) -> tuple[NDArray[np.float32], list[float]]:
    """Render every frame of a fringe sequence: linear irradiance, float32 (K, ny, nx), row 0 = top image row.

    Parameters
    ----------
    setup : Setup
        A deflectometry or mirror setup; the display lies in its pattern's plane and frame.
    heights : HeightMap, optional
        The substrate's height map (deflectometry).
    frames : sequence of FringeFrame
        What the display shows, in order.
    display : FringeDisplay
        The display model.
    spp, seed : int
        Samples per pixel and the sampler seed of every frame (module docstring).
    variant : str, optional
        Mitsuba variant (default ``choose("mono")``).
    texel : float
        Texel size of the display's raster, mm.

    Returns
    -------
    images : ndarray
        (K, ny, nx) float32.
    seconds : list of float
        Wall time of each frame: its texture, the parameter update and the render (the scene's load counts to the
        first).

    Raises
    ------
    SetupError
        No frames, a target scene, or a deflectometry setup without ``heights``.
    LimitError
        The K images or the render time exceed this machine's limits (checked before anything is rendered).
    """
    if not frames:
        raise SetupError("a fringe render needs at least one frame")
    radiance = float(setup.pattern.radiance)
    textures = (_texture(display, frame, texel, radiance) for frame in frames)
    return _render_textures(setup, heights, display, textures, len(frames), spp, seed, variant)


def render_display_image(
    setup: Setup,
    heights: HeightMap | None,
    display: FringeDisplay,
    values: NDArray[np.float64],
    spp: int,
    seed: int,
    variant: str | None = None,
    texel: float = TEXEL,
) -> NDArray[np.float32]:
    """Render the scene with the display showing an image of ideal values per display pixel (e.g. the marker pattern,
    :meth:`scopetwin.scenes.fringes.FringeDisplay.marker_values`, for the setup calibration of thesis §2.7 with the
    display as the pattern): linear irradiance, float32 (ny, nx).

    The display's texture is :meth:`~scopetwin.scenes.fringes.FringeDisplay.image_texture` times the pattern's
    ``radiance``; scene, live window and errors as :func:`render_fringe_frames`.
    """
    tex = display.image_texture(values, texel)
    radiance = float(setup.pattern.radiance)
    if radiance != 1.0:
        tex *= np.float32(radiance)
    images, _ = _render_textures(setup, heights, display, iter([tex]), 1, spp, seed, variant)
    return images[0]


def _render_textures(
    setup: Setup,
    heights: HeightMap | None,
    display: FringeDisplay,
    textures: Iterator[NDArray[np.float32]],
    k: int,
    spp: int,
    seed: int,
    variant: str | None,
) -> tuple[NDArray[np.float32], list[float]]:
    """Render ``k`` display textures (each made when its frame is due) in one loaded scene (module docstring)."""
    import drjit as dr

    if setup.scene == "target":
        raise SetupError("a fringe display is rendered in a deflectometry or mirror setup, not a target scene")
    if setup.scene == "deflectometry" and heights is None:
        raise SetupError("a deflectometry render needs the substrate's height map (heights=HeightMap(...))")
    cam = setup.camera_model
    check_render(
        cam.nx, cam.ny, int(spp) * k, f"render {setup.name}, {k} display frames", "setup", FLOATS_PER_PIXEL + k
    )
    variant = resolve(variant, "mono")
    mi = mitsuba(variant)
    plate = display_plate(setup, display)
    window = None if cam.lens is not None else live_window(plate, heights)
    t0 = time.perf_counter()
    first = emitter_rectangle(plate.marker_pattern, next(textures), variant)
    scene: Any = mi.load_dict(
        scene_dict(plate, heights, spp, seed, window, vertices=FRINGE_VERTICES, variant=variant, emitter=first)
    )
    params = mi.traverse(scene)
    if DISPLAY_TEXTURE_KEY not in params:  # pragma: no cover - the scene dictionary names it
        raise SetupError(f"the loaded scene has no parameter {DISPLAY_TEXTURE_KEY!r}")
    images = np.zeros((k, cam.ny, cam.nx), dtype=np.float32)
    seconds = []
    r0, r1, c0, c1 = (0, cam.ny, 0, cam.nx) if window is None else window
    for i in range(k):
        if i > 0:
            params[DISPLAY_TEXTURE_KEY] = mi.TensorXf(next(textures)[:, :, None])
            params.update()
        images[i, r0:r1, c0:c1] = scene_render(scene, spp, seed, variant)
        dr.sync_thread()
        t1 = time.perf_counter()
        seconds.append(t1 - t0)
        t0 = t1
    return images, seconds
