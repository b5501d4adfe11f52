"""Render the Part I setups with Mitsuba 3 (seed §1.10, §2.7, §2.8).

Images are linear irradiance, float32 (row, col): a white pattern texel seen directly
or in a perfect mirror renders as the pattern radiance (1.0 by default); row 0 is the
top image row and pixel (row, col) integrates [col, col+1) x [row, row+1) with a box
filter (the physical pixel), sampled by ``multijitter``.

Loaded scenes are cached per thread (the last few setups / height maps), so rendering
the same scene again with another seed or spp costs only the render itself.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scenes.errors import SetupError
from scenes.mitsuba.scene import Window, scene_dict
from scenes.mitsuba.variant import use
from scenes.setup import Setup
from scenes.surface import HeightMap

__all__ = ["build_scene", "load_scene", "render_setup", "render_window"]

_CACHE_SIZE = 2
_local = threading.local()


def _mono() -> Any:
    """``use("mono")``, remembered per thread.

    :func:`scenes.mitsuba.variant.use` searches the file system for the LLVM and CUDA libraries on
    every call (~70 ms, two calls per render: most of a render's fixed cost); the variant it set is
    kept here and ``use`` is asked again only when the thread's variant has changed since.
    """
    name = getattr(_local, "variant", None)
    if name is not None:
        import mitsuba as mi

        if mi.variant() == name:
            return mi
    mi = use("mono")
    _local.variant = mi.variant()
    return mi


def build_scene(setup: Setup, heights: HeightMap | None = None) -> dict:
    """The Mitsuba scene dictionary of a setup (see :func:`scenes.mitsuba.scene.scene_dict`).

    Raises
    ------
    SetupError
        ``heights`` missing for a deflectometry setup.
    """
    return scene_dict(setup, heights)


def _scene_key(setup: Setup, window: Window | None) -> str:
    data = setup.model_dump(mode="json", exclude={"render", "sensor", "name", "description", "section"})
    return repr((data, None if window is None else tuple(int(w) for w in window)))


def load_scene(setup: Setup, heights: HeightMap | None = None, window: Window | None = None) -> Any:
    """The loaded ``mitsuba.Scene`` of a setup, cached per thread (keyed by setup and height-map identity)."""
    _mono()
    if setup.scene == "deflectometry" and heights is None:
        raise SetupError("a deflectometry render needs the substrate's height map (heights=HeightMap(...))")
    key = _scene_key(setup, window)
    cache: list[tuple[str, Any, Any]] = getattr(_local, "scenes", None) or []
    _local.scenes = cache
    for k, h, scene in cache:
        if k == key and (setup.scene != "deflectometry" or h is heights):
            return scene
    import mitsuba as mi

    scene = mi.load_dict(scene_dict(setup, heights, window=window))
    cache.append((key, heights if setup.scene == "deflectometry" else None, scene))
    del cache[:-_CACHE_SIZE]
    return scene


def render_window(setup: Setup, heights: HeightMap | None = None, spp: int | None = None,
                  seed: int | None = None, window: Window | None = None) -> NDArray[np.float32]:
    """Render a crop (row0, row1, col0, col1) of the image (default: all of it), float32 (rows, cols).

    The pixels are exactly those of the full image (same rays, same box filter); the
    sample pattern differs from a full render with the same seed.
    """
    import drjit as dr

    spp = int(spp or setup.render.spp)
    seed = int(setup.render.seed if seed is None else seed)
    scene = load_scene(setup, heights, window)
    image = scene_render(scene, spp, seed)
    dr.sync_thread()
    return image


def scene_render(scene: Any, spp: int, seed: int) -> NDArray[np.float32]:
    """Render a loaded scene; the single luminance channel as float32 (rows, cols)."""
    mi = _mono()
    img = mi.render(scene, spp=int(spp), seed=int(seed))
    arr = np.asarray(img, dtype=np.float32)
    return np.ascontiguousarray(arr[..., 0] if arr.ndim == 3 else arr)


def render_setup(setup: Setup, heights: HeightMap | None = None, spp: int | None = None,
                 seed: int | None = None) -> NDArray[np.float32]:
    """Render a setup: linear irradiance, float32 (ny, nx), row 0 = top image row.

    Parameters
    ----------
    setup : Setup
        The scene (``deflectometry``, ``target`` or ``mirror``).
    heights : HeightMap, optional
        The substrate's height map over its extents; required for ``deflectometry``.
    spp, seed : int, optional
        Samples per pixel and sampler seed (default ``setup.render``).

    Raises
    ------
    SetupError
        ``heights`` missing for a deflectometry setup.
    """
    return render_window(setup, heights, spp, seed, None)
