"""Render the Part I setups with Mitsuba 3 (thesis §1.10, §2.7, §2.8).

Images are linear irradiance, float32 (row, col): a white pattern texel seen directly
or in a perfect mirror renders as the pattern radiance (1.0 by default); row 0 is the
top image row and pixel (row, col) integrates [col, col+1) x [row, row+1) with a box
filter (the physical pixel), sampled by ``multijitter``.

Loaded scenes are cached per thread (the last few setups / height maps, per variant), so rendering
the same scene again with another seed or spp costs only the render itself. Every function takes the
Mitsuba ``variant`` explicitly (default ``choose("mono")``, resolved at call time) and sets it for the call.

Pixels that provably see nothing are not traced: :func:`live_window` bounds the image of
everything that can send light to the camera (the substrate's ROI, the mirror, the pattern
plate) and :func:`render_setup` renders that window only, leaving the rest exactly 0 — which
is what a full render gives there (tested). Within the window it traces only the pixels whose rays
can meet a marker (:func:`render_marked`, :mod:`scopetwin.scenes.mitsuba.lit`), again leaving
exactly 0 where a render of every pixel gives 0 (tested).
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.limits import check_render
from scopetwin.scenes.mitsuba.scene import TEXEL, Window, scene_dict
from scopetwin.scenes.mitsuba.variant import mitsuba, render_complete, resolve
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap

__all__ = ["build_scene", "live_window", "load_scene", "render_marked", "render_setup", "render_window"]

_CACHE_SIZE = 2
_local = threading.local()

#: Heights of a substrate are bounded by this (mm, rounded up to a multiple) when the live window is
#: computed, so that the window — and with it the compiled kernels and the cached scene — stays the
#: same for every surface of ordinary size.
_Z_STEP = 0.5
_EDGE_SAMPLES = 256
_MARGIN_PX = 2


def _edges(corners: NDArray[np.float64], pairs: list[tuple[int, int]]) -> NDArray[np.float64]:
    t = np.linspace(0.0, 1.0, _EDGE_SAMPLES)[:, None]
    return np.concatenate([corners[a] + t * (corners[b] - corners[a]) for a, b in pairs])


def _box_edges(x: tuple[float, float], y: tuple[float, float], z: tuple[float, float]) -> NDArray[np.float64]:
    corners = np.array([[x[i & 1], y[(i >> 1) & 1], z[i >> 2]] for i in range(8)], dtype=np.float64)
    pairs = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]
    return _edges(corners, pairs)


def _plate_edges(setup: Setup) -> NDArray[np.float64]:
    pat = setup.marker_pattern
    hx, hy = 0.5 * pat.size_x, 0.5 * pat.size_y
    local = np.array([[-hx, -hy, 0.0], [hx, -hy, 0.0], [hx, hy, 0.0], [-hx, hy, 0.0]])
    return _edges(pat.frame.to_global(local), [(0, 1), (1, 2), (2, 3), (3, 0)])


def live_window(setup: Setup, heights: HeightMap | None = None) -> Window | None:
    """The pixel window outside which the image is provably black, or None (render everything).

    Bounds the image of the light-carrying objects — the substrate's ROI box (heights bounded by a
    multiple of 0.5 mm), the flat mirror, the pattern plate seen directly — from densely sampled
    edges projected through the camera model (distortion included), each clipped to the image,
    padded by 2 px. None for a thin-lens camera (defocus spreads light), when an object reaches
    behind the camera, or when the window would cover most of the image anyway.
    """
    cam = setup.camera_model
    if cam.lens is not None:
        return None
    objects = [_plate_edges(setup)]
    if setup.scene == "deflectometry" and setup.substrate is not None and heights is not None:
        sub = setup.substrate
        z = max(float(np.abs(heights.z).max()), 1e-9)
        z = _Z_STEP * np.ceil(z / _Z_STEP)
        objects.append(
            _box_edges((-0.5 * sub.size[0], 0.5 * sub.size[0]), (-0.5 * sub.roi_length, 0.5 * sub.roi_length), (-z, z))
        )
    elif setup.scene == "mirror" and setup.mirror is not None:
        mx, my = setup.mirror.size
        objects.append(_box_edges((-0.5 * mx, 0.5 * mx), (-0.5 * my, 0.5 * my), (0.0, 0.0)))
    r0, r1, c0, c1 = cam.ny, 0, cam.nx, 0
    for pts in objects:
        px = cam.project(pts)
        if not np.all(np.isfinite(px)):
            return None
        lo = np.floor(px.min(axis=0)).astype(int) - _MARGIN_PX
        hi = np.ceil(px.max(axis=0)).astype(int) + _MARGIN_PX
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, [cam.nx, cam.ny])
        if np.any(hi <= lo):
            continue  # projects outside the image
        c0, r0 = min(c0, int(lo[0])), min(r0, int(lo[1]))
        c1, r1 = max(c1, int(hi[0])), max(r1, int(hi[1]))
    if r1 <= r0 or c1 <= c0:
        return None
    if (r1 - r0) * (c1 - c0) > 0.8 * cam.nx * cam.ny:
        return None
    return (r0, r1, c0, c1)


def build_scene(setup: Setup, heights: HeightMap | None = None, variant: str | None = None) -> dict:
    """The Mitsuba scene dictionary of a setup (see :func:`scopetwin.scenes.mitsuba.scene.scene_dict`).

    Raises
    ------
    SetupError
        ``heights`` missing for a deflectometry setup.
    """
    return scene_dict(setup, heights, variant=variant)


def _scene_key(setup: Setup, window: Window | None, variant: str) -> str:
    data = setup.model_dump(mode="json", exclude={"render", "sensor", "name", "description", "section"})
    return repr((variant, data, None if window is None else tuple(int(w) for w in window)))


def load_scene(
    setup: Setup, heights: HeightMap | None = None, window: Window | None = None, variant: str | None = None
) -> Any:
    """The loaded ``mitsuba.Scene`` of a setup, cached per thread (keyed by variant, setup and height-map identity).

    ``variant``: the Mitsuba variant (default ``choose("mono")``).
    """
    variant = resolve(variant, "mono")
    mi = mitsuba(variant)
    if setup.scene == "deflectometry" and heights is None:
        raise SetupError("a deflectometry render needs the substrate's height map (heights=HeightMap(...))")
    key = _scene_key(setup, window, variant)
    cache: list[tuple[str, Any, Any]] = getattr(_local, "scenes", None) or []
    _local.scenes = cache
    for k, h, scene in cache:
        if k == key and (setup.scene != "deflectometry" or h is heights):
            return scene
    scene = mi.load_dict(scene_dict(setup, heights, window=window, variant=variant))
    cache.append((key, heights if setup.scene == "deflectometry" else None, scene))
    del cache[:-_CACHE_SIZE]
    return scene


def render_window(
    setup: Setup,
    heights: HeightMap | None = None,
    spp: int | None = None,
    seed: int | None = None,
    window: Window | None = None,
    variant: str | None = None,
) -> NDArray[np.float32]:
    """Render a crop (row0, row1, col0, col1) of the image (default: all of it), float32 (rows, cols).

    The pixels are exactly those of the full image (same rays, same box filter); the
    sample pattern differs from a full render with the same seed. ``variant``: the Mitsuba
    variant (default ``choose("mono")``).
    """
    import drjit as dr

    variant = resolve(variant, "mono")
    spp = int(spp or setup.render.spp)
    seed = int(setup.render.seed if seed is None else seed)
    scene = load_scene(setup, heights, window, variant)
    image = scene_render(scene, spp, seed, variant)
    dr.sync_thread()
    return image


def scene_render(scene: Any, spp: int, seed: int, variant: str | None = None) -> NDArray[np.float32]:
    """Render a loaded scene (built in ``variant``, default ``choose("mono")``); luminance as float32 (rows, cols)."""
    mi = mitsuba(resolve(variant, "mono"))
    img = render_complete(mi, scene, spp=int(spp), seed=int(seed))
    arr = np.asarray(img, dtype=np.float32)
    return np.ascontiguousarray(arr[..., 0] if arr.ndim == 3 else arr)


def render_setup(
    setup: Setup,
    heights: HeightMap | None = None,
    spp: int | None = None,
    seed: int | None = None,
    variant: str | None = None,
) -> NDArray[np.float32]:
    """Render a setup: linear irradiance, float32 (ny, nx), row 0 = top image row.

    Parameters
    ----------
    setup : Setup
        The scene (``deflectometry``, ``target`` or ``mirror``).
    heights : HeightMap, optional
        The substrate's height map over its extents; required for ``deflectometry``.
    spp, seed : int, optional
        Samples per pixel and sampler seed (default ``setup.render``).
    variant : str, optional
        Mitsuba variant (default ``choose("mono")``, resolved now).

    Raises
    ------
    SetupError
        ``heights`` missing for a deflectometry setup.
    LimitError
        The image or the render work exceeds the memory available or the render time limit
        (:func:`scopetwin.scenes.limits.check_render`), checked before anything is allocated.
    """
    cam = setup.camera_model
    check_render(cam.nx, cam.ny, int(spp or setup.render.spp), f"render {setup.name}")
    if cam.lens is not None:  # a thin lens's rays start across its aperture: every pixel is traced
        return render_window(setup, heights, spp, seed, None, variant)
    window = live_window(setup, heights) if (setup.scene != "deflectometry" or heights is not None) else None
    # every pixel of the live window, not only those that can see a marker (render_marked: 2x faster, the same
    # image up to its sample streams, which moves centroids by the render's own noise and flips reconstructions
    # that sit on the edge of converging)
    crop = render_window(setup, heights, spp, seed, window, variant)
    if window is None:
        return crop
    r0, r1, c0, c1 = window
    image = np.zeros((cam.ny, cam.nx), dtype=np.float32)
    image[r0:r1, c0:c1] = crop
    return image


def render_marked(
    setup: Setup,
    heights: HeightMap | None = None,
    spp: int | None = None,
    seed: int | None = None,
    window: Window | None = None,
    variant: str | None = None,
) -> NDArray[np.float32]:
    """Render a crop of a pinhole camera's image (default: all of it) tracing only the pixels whose rays can meet a
    marker (:mod:`scopetwin.scenes.mitsuba.lit`); the others are exactly 0, as a render of them gives.

    The traced pixels are rendered as :func:`render_window` renders them (the same rays, sampler and box filter);
    the sample pattern differs from its render with the same seed.

    Raises
    ------
    SetupError
        ``heights`` missing for a deflectometry setup, or a thin-lens camera.
    """
    from scopetwin.scenes.mitsuba.lit import render_lit

    if setup.camera_model.lens is not None:
        raise SetupError("render_marked needs a pinhole camera: a thin lens's rays do not start at one point")
    variant = resolve(variant, "mono")
    spp = int(spp or setup.render.spp)
    seed = int(setup.render.seed if seed is None else seed)
    scene = load_scene(setup, heights, window, variant)
    return render_lit(scene, setup.marker_pattern, spp, seed, TEXEL)
