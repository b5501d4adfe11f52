"""Scene dictionaries of the Part I setups (thesis §1.10, §2.7, §2.8), Mitsuba style.

* ``deflectometry``: thesis camera, marker pattern (area emitter with the pattern's grey
  values as radiance), bent substrate (mirroring ROI, black holding-frame regions);
* ``target``: thesis camera and the calibration target, an emitter in its plane (z = 0)
  shining toward +z;
* ``mirror``: thesis camera, the deflectometry pattern and a perfect flat mirror of
  ``setup.mirror.size`` in the plane z = 0.

The pattern is a ``rectangle`` spanning the plate (to_world columns T_x*size_x/2,
T_y*size_y/2, N_z, r_c): its uv = (local + 1)/2, and the bitmap's row 0 / column 0 is
uv (0, 0), i.e. the plate's (-x, -y) corner, as :meth:`MarkerPattern.texture` lays it out.
Float texture data is passed with ``raw=True`` (no sRGB conversion).
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.mitsuba.integrators import DEFAULT_EPS, integrator_dict
from scopetwin.scenes.mitsuba.sensors import sensor_dict
from scopetwin.scenes.mitsuba.shapes import DEFAULT_VERTICES, MIRROR_BSDF, substrate_shapes
from scopetwin.scenes.mitsuba.variant import mitsuba, resolve
from scopetwin.scenes.pattern import MarkerPattern
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap

#: Texel size of the pattern texture, mm (12.5 µm: indistinguishable from finer, docs/rendering.md).
TEXEL = 0.0125

Window = tuple[int, int, int, int]  # row0, row1, col0, col1 (half-open), as scenes.analytic

_texture_cache: dict[tuple[str, float], NDArray[np.float32]] = {}
_texture_lock = threading.Lock()
_TEXTURE_CACHE_SIZE = 4
#: Texels per block of :func:`marker_texture` (its float64 temporaries: 2 MB).
_TEXTURE_BLOCK = 1 << 18


def marker_texture(pattern: MarkerPattern, texel: float = TEXEL) -> NDArray[np.float32]:
    """Grey-value raster of a pattern, identical to :meth:`MarkerPattern.texture` but separable and fast.

    The marker cell containing a texel is found per axis (nearest index along x depends on x
    only, along y on y only), so the 2-D work is one ``hypot`` per texel; the marker shape is
    g = max(0, 1 - r/r_m) (thesis §1.6.3), 0 off the plate. Row 0 / column 0 is the plate's
    (-x, -y) corner. The rows are computed a block at a time (:data:`_TEXTURE_BLOCK` texels) into the float32
    raster: the float64 temporaries of a whole 4000 x 4000 raster were 0.6 GB of fresh memory per call, most
    of its time.
    """
    nx = max(2, int(np.ceil(pattern.size_x / texel)))
    ny = max(2, int(np.ceil(pattern.size_y / texel)))
    x = (np.arange(nx) + 0.5) / nx * pattern.size_x - 0.5 * pattern.size_x
    y = (np.arange(ny) + 0.5) / ny * pattern.size_y - 0.5 * pattern.size_y
    ix = pattern.nearest_index(np.stack([x, np.zeros_like(x)], axis=-1))[:, 0]
    iy = pattern.nearest_index(np.stack([np.zeros_like(y), y], axis=-1))[:, 1]
    cx = pattern.centers_local(np.stack([ix, np.zeros_like(ix)], axis=-1))[:, 0]
    cy = pattern.centers_local(np.stack([np.zeros_like(iy), iy], axis=-1))[:, 1]
    dx = (x - cx).astype(np.float64)
    dy = (y - cy).astype(np.float64)
    ref_x = ix == 0
    off_x = ~(np.abs(x) <= 0.5 * pattern.size_x)
    off_y = ~(np.abs(y) <= 0.5 * pattern.size_y)
    out = np.empty((ny, nx), dtype=np.float32)
    step = max(1, _TEXTURE_BLOCK // nx)
    buf = np.empty((step, nx))
    for r0 in range(0, ny, step):
        rows = slice(r0, min(r0 + step, ny))
        g = np.hypot(dx[None, :], dy[rows, None], out=buf[: rows.stop - r0])
        ref = np.ix_(iy[rows] == 0, ref_x)  # the reference marker's texels: r / its larger radius
        r_ref = g[ref] / pattern.ref_radius
        np.divide(g, pattern.radius, out=g)
        g[ref] = r_ref
        np.subtract(1.0, g, out=g)
        np.clip(g, 0.0, 1.0, out=g)
        g[off_y[rows]] = 0.0
        g[:, off_x] = 0.0
        out[rows] = g
    return out


def pattern_texture(setup: Setup, texel: float = TEXEL) -> NDArray[np.float32]:
    """Radiance raster of the setup's pattern (grey value x ``pattern.radiance``), cached per pattern."""
    key = (setup.pattern.model_dump_json(), float(texel))
    with _texture_lock:
        tex = _texture_cache.get(key)
    if tex is None:
        tex = marker_texture(setup.marker_pattern, texel)
        if setup.pattern.radiance != 1.0:
            tex *= np.float32(setup.pattern.radiance)
        with _texture_lock:
            while len(_texture_cache) >= _TEXTURE_CACHE_SIZE:
                _texture_cache.pop(next(iter(_texture_cache)))
            _texture_cache[key] = tex
    return tex


def pattern_to_world(pattern: MarkerPattern) -> NDArray[np.float64]:
    """4x4 matrix mapping Mitsuba's rectangle [-1, 1]^2 onto the pattern plate (float64)."""
    f = pattern.frame
    m = np.eye(4)
    m[:3, 0] = f.tx * (0.5 * pattern.size_x)
    m[:3, 1] = f.ty * (0.5 * pattern.size_y)
    m[:3, 2] = f.nz
    m[:3, 3] = f.origin
    return m


def pattern_dict(setup: Setup, texel: float = TEXEL, variant: str | None = None) -> dict[str, Any]:
    """The pattern (or calibration target): a rectangle carrying an area emitter with the marker raster.

    The area emitter emits on the side of the pattern's N_z only. ``variant``: the Mitsuba variant
    (default ``choose("mono")``).
    """
    return emitter_rectangle(setup.marker_pattern, pattern_texture(setup, texel), variant)


def emitter_rectangle(pattern: MarkerPattern, tex: NDArray[np.float32], variant: str | None = None) -> dict[str, Any]:
    """A rectangle spanning ``pattern``'s plate with an area emitter whose radiance is the raster ``tex`` (rows,
    cols; row 0 / column 0 the plate's (-x, -y) corner), emitting on the side of N_z only: the marker pattern's and
    a fringe display's (:mod:`scopetwin.scenes.mitsuba.fringes`) emitter. ``variant``: the Mitsuba variant."""
    mi = mitsuba(resolve(variant, "mono"))
    return {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f(pattern_to_world(pattern)),
        "bsdf": {"type": "diffuse", "reflectance": {"type": "uniform", "value": 0.0}},
        "emitter": {
            "type": "area",
            "radiance": {
                "type": "bitmap",
                "data": mi.TensorXf(tex[:, :, None]),
                "raw": True,
                "filter_type": "bilinear",
                "wrap_mode": "clamp",
            },
        },
    }


def mirror_dict(size: tuple[float, float], variant: str | None = None) -> dict[str, Any]:
    """A perfect flat mirror of ``size`` (x, y) mm in the plane z = 0, centred on the origin (§2.7.2).

    ``variant``: the Mitsuba variant (default ``choose("mono")``).
    """
    mi = mitsuba(resolve(variant, "mono"))
    m = np.diag([0.5 * float(size[0]), 0.5 * float(size[1]), 1.0, 1.0])
    return {"type": "rectangle", "to_world": mi.ScalarTransform4f(m), "bsdf": dict(MIRROR_BSDF)}


def scene_dict(
    setup: Setup,
    heights: HeightMap | None = None,
    spp: int | None = None,
    seed: int | None = None,
    window: Window | None = None,
    eps: float = DEFAULT_EPS,
    vertices: tuple[int, int] = DEFAULT_VERTICES,
    texel: float = TEXEL,
    variant: str | None = None,
    emitter: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """The Mitsuba scene dictionary of a setup.

    Parameters
    ----------
    setup : Setup
        ``scene`` selects deflectometry / target / mirror (module docstring).
    heights : HeightMap, optional
        The substrate surface; required for ``deflectometry``.
    spp, seed : int, optional
        Sampler settings (default ``setup.render``).
    window : (row0, row1, col0, col1), optional
        Render only this crop of the image (half-open pixel ranges).
    eps : float
        Start offset of reflected rays along their direction, mm.
    vertices : (int, int)
        Heightfield vertex counts over the whole substrate.
    texel : float
        Pattern texel size, mm.
    variant : str, optional
        Mitsuba variant the dictionary's objects are built in (default ``choose("mono")``).
    emitter : dict, optional
        The emitter in the pattern plane (:func:`emitter_rectangle`) in place of the marker pattern, e.g. a fringe
        display (default: :func:`pattern_dict`).

    Raises
    ------
    SetupError
        A deflectometry setup without ``heights``, or a window outside the image.
    """
    variant = resolve(variant, "mono")
    cam = setup.camera_model
    if window is not None:
        r0, r1, c0, c1 = window
        if not (0 <= r0 < r1 <= cam.ny and 0 <= c0 < c1 <= cam.nx):
            raise SetupError(f"render window {tuple(window)} lies outside the {cam.ny} x {cam.nx} image")
    spp = int(spp or setup.render.spp)
    seed = int(setup.render.seed if seed is None else seed)
    scene: dict[str, Any] = {
        "type": "scene",
        "integrator": integrator_dict(eps, variant),
        "sensor": sensor_dict(cam, spp, seed, window, variant),
        "pattern": pattern_dict(setup, texel, variant) if emitter is None else emitter,
    }
    if setup.scene == "deflectometry":
        if heights is None:
            raise SetupError("a deflectometry render needs the substrate's height map (heights=HeightMap(...))")
        sub = setup.substrate
        assert sub is not None  # guaranteed by Setup validation
        scene.update(substrate_shapes(heights, sub.size, sub.roi_length, vertices, variant))
    elif setup.scene == "mirror":
        assert setup.mirror is not None  # guaranteed by Setup validation
        scene["mirror"] = mirror_dict(setup.mirror.size, variant)
    return scene
