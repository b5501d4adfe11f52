"""Render only the pixels that can see a marker (Part I scenes, pinhole camera).

Most pixels of a deflectometry image see black: the pattern between its markers (two thirds of the plate for the
§1.10 pattern), the holding frame, nothing. A pixel is traced with all its samples only where its rays can meet a
marker; every other pixel is exactly 0, which is what tracing it gives. Which pixels can see a marker is decided by
one ray through each pixel centre of the render window (:func:`lit_pixels`):

* where the centre ray lands on the pattern's plane (directly or in a mirror, :func:`scopetwin.scenes.mitsuba.trace.
  landing`), the landing points of the four neighbouring centres give the map's derivatives J_x, J_y (central
  differences, pattern mm per pixel); the rays of the whole pixel land within 0.5 (|J_x| + |J_y|) of the centre's
  point to first order, and the pixel is traced when its centre's point lies within :data:`FOOTPRINT` times that, plus
  :data:`TEXEL_MARGIN` texels (the texture's bilinear reach), of a marker's disc (the nearest marker's, and the larger
  reference marker's);
* where the map is not smooth on the pixel's four neighbours (one of them, or the centre, does not land: the edges
  of the region of interest, of the mirror, of a pattern seen directly; the window's border), the pixel is traced
  when a centre within :data:`EDGE_PX` pixels lands.

The traced pixels get exactly the render of :func:`scopetwin.scenes.mitsuba.render.scene_render`: ``spp`` samples
of the multi-jittered sampler (Mitsuba's, seeded as Mitsuba's render seeds it, one sequence per pixel) inside the
pixel, the box filter's mean. The decision traces one ray per pixel, a sixteenth of the render at 16 spp; on the
§1.10 frame 46 % of the window's pixels are traced (35 % see light). Tests check on several surfaces that a render of
every pixel is 0 wherever this one skips.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.mitsuba.trace import MirrorScene, landing, radiance
from scopetwin.scenes.pattern import MarkerPattern

#: A pixel is traced where a marker lies within this many first-order footprints of its centre ray's landing point.
FOOTPRINT = 1.5
#: ... plus this many texels: the bilinear texture is non-zero up to one texel diagonal (1.41) outside a disc.
TEXEL_MARGIN = 2.0
#: Where the landing map is not smooth, pixels within this many pixels of a landing centre are traced.
EDGE_PX = 2


def _opaque(mi: Any, values: list[float]) -> list[Any]:
    import drjit as dr

    return [dr.opaque(mi.Float, float(v)) for v in values]


def disc_distance(mi: Any, pattern: MarkerPattern, x: Any, y: Any) -> Any:
    """Distance (pattern mm, Dr.Jit) from local points to the nearest marker's disc and the reference marker's disc,
    whichever is less (negative inside); the pattern's layout enters as opaque values."""
    import drjit as dr

    first = pattern.centers_local(pattern.indices()[:1])[0]
    ref = pattern.centers_local(np.array([pattern.reference_index]))[0]
    x0, y0, px, py, rx, ry, r, r_ref = _opaque(
        mi, [first[0], first[1], pattern.pitch_x, pattern.pitch_y, ref[0], ref[1], pattern.radius, pattern.ref_radius]
    )
    kx = dr.clip(dr.round((x - x0) / px), 0.0, float(pattern.n_x - 1))
    ky = dr.clip(dr.round((y - y0) / py), 0.0, float(pattern.n_y - 1))
    dx, dy = x - dr.fma(kx, px, x0), y - dr.fma(ky, py, y0)
    cell = dr.sqrt(dr.fma(dx, dx, dy * dy)) - r
    return dr.minimum(cell, dr.sqrt(dr.square(x - rx) + dr.square(y - ry)) - r_ref)


def _centre_rays(mi: Any, sensor: Any, width: int, height: int) -> tuple[Any, Any, Any]:
    """The ray through each pixel centre of the crop (row-major), and each pixel's column and row."""
    import drjit as dr

    w, h = _opaque(mi, [width, height])
    idx = dr.arange(mi.UInt32, width * height)
    row = idx // dr.opaque(mi.UInt32, width)
    col = idx - row * dr.opaque(mi.UInt32, width)
    film = mi.Point2f((mi.Float(col) + 0.5) / w, (mi.Float(row) + 0.5) / h)
    ray, _ = sensor.sample_ray(0.0, 0.0, film, mi.Point2f(0.5))
    return ray, mi.Int32(col), mi.Int32(row)


def _neighbour(mi: Any, values: list[Any], col: Any, row: Any, dx: int, dy: int, size: tuple[int, int]) -> list[Any]:
    """``values`` at the pixel (col + dx, row + dy), clamped to the crop."""
    import drjit as dr

    width, height = size
    c = dr.clip(col + dx, 0, dr.opaque(mi.Int32, width - 1))
    r = dr.clip(row + dy, 0, dr.opaque(mi.Int32, height - 1))
    j = mi.UInt32(dr.fma(r, dr.opaque(mi.Int32, width), c))
    return [dr.gather(type(v), v, j) for v in values]


def _near_edge(mi: Any, seen: Any, col: Any, row: Any, size: tuple[int, int]) -> Any:
    """Whether a landing centre lies within :data:`EDGE_PX` pixels (two separable passes)."""
    import drjit as dr

    rows = mi.Bool(seen)
    for dx in range(-EDGE_PX, EDGE_PX + 1):
        if dx:
            rows |= _neighbour(mi, [seen], col, row, dx, 0, size)[0]
    dr.eval(rows)
    out = mi.Bool(rows)
    for dy in range(-EDGE_PX, EDGE_PX + 1):
        if dy:
            out |= _neighbour(mi, [rows], col, row, 0, dy, size)[0]
    return out


def lit_pixels(
    ms: MirrorScene, scene: Any, pattern: MarkerPattern, texel: float, width: int, height: int
) -> NDArray[np.uint32]:
    """The pixels of the ``width`` x ``height`` crop whose rays can meet a marker (module docstring), as row-major
    indices into the crop."""
    import drjit as dr

    mi = ms.mi
    ray, col, row = _centre_rays(mi, scene.sensors()[0], width, height)
    lx, ly, seen = landing(ms, scene, ray, True, on_plate=False)
    x, y = lx * (0.5 * pattern.size_x), ly * (0.5 * pattern.size_y)
    dr.eval(x, y, seen)
    size = (width, height)
    xl, yl, sl = _neighbour(mi, [x, y, seen], col, row, -1, 0, size)
    xr, yr, sr = _neighbour(mi, [x, y, seen], col, row, 1, 0, size)
    xu, yu, su = _neighbour(mi, [x, y, seen], col, row, 0, -1, size)
    xd, yd, sd = _neighbour(mi, [x, y, seen], col, row, 0, 1, size)
    inside = (col > 0) & (row > 0) & (col < dr.opaque(mi.Int32, width - 1)) & (row < dr.opaque(mi.Int32, height - 1))
    smooth = inside & seen & sl & sr & su & sd
    jx = 0.5 * dr.sqrt(dr.square(xr - xl) + dr.square(yr - yl))
    jy = 0.5 * dr.sqrt(dr.square(yd - yu) + dr.square(xd - xu))
    reach = dr.fma(FOOTPRINT * 0.5, jx + jy, TEXEL_MARGIN * texel)
    near = smooth & (disc_distance(mi, pattern, x, y) < reach)
    edge = ~smooth & _near_edge(mi, seen, col, row, size)
    return np.asarray(dr.compress(near | edge), dtype=np.uint32)


def render_pixels(
    ms: MirrorScene, scene: Any, pixels: NDArray[np.uint32] | Any, spp: int, seed: int, width: int
) -> NDArray[np.float32]:
    """The box-filtered value of each given pixel of the crop (row-major indices, numpy or ``UInt32``, crop ``width``
    wide): the mean of ``spp`` multi-jittered samples (the scene's sampler, one sequence of ``spp`` per pixel),
    float32."""
    import drjit as dr

    mi = ms.mi
    n = dr.width(pixels) if isinstance(pixels, mi.UInt32) else len(pixels)
    if n == 0:
        return np.zeros(0, dtype=np.float32)
    sensor = scene.sensors()[0]
    crop = sensor.film().crop_size()
    sampler = sensor.sampler().clone()
    sampler.set_sample_count(spp)
    sampler.set_samples_per_wavefront(spp)
    sampler.seed(seed, n * spp)
    pix = dr.gather(mi.UInt32, mi.UInt32(pixels), dr.arange(mi.UInt32, n * spp) // spp)  # (no copy of a UInt32)
    row = pix // dr.opaque(mi.UInt32, width)
    col = pix - row * dr.opaque(mi.UInt32, width)
    pos = mi.Point2f(mi.Float(col), mi.Float(row)) + sampler.next_2d()
    cw, ch = _opaque(mi, [crop[0], crop[1]])
    ray, _ = sensor.sample_ray(0.0, 0.0, mi.Point2f(pos.x / cw, pos.y / ch), mi.Point2f(0.5))
    value, _ = radiance(ms, scene, ray, True)
    return np.asarray(dr.block_sum(value, spp) * (1.0 / spp), dtype=np.float32)


def render_lit(scene: Any, pattern: MarkerPattern, spp: int, seed: int, texel: float) -> NDArray[np.float32]:
    """The loaded scene's image over its film's crop (rows, cols), float32, tracing only the pixels that can see a
    marker (module docstring); the rest are 0. Needs a pinhole camera (its rays start at one point).

    Which pixels can see a marker depends on the scene alone: it is decided on the scene's first render and kept with
    it (:attr:`MirrorScene.memo`), so that the next render (another seed or sample count) only renders.
    """
    ms = scene.integrator().geometry(scene)
    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    key = ("lit_pixels", float(texel), repr(pattern), width, height)
    if key not in ms.memo:
        pixels = lit_pixels(ms, scene, pattern, texel, width, height)
        ms.memo[key] = (pixels, ms.mi.UInt32(pixels))
    pixels, traced = ms.memo[key]
    image = np.zeros(width * height, dtype=np.float32)
    image[pixels] = render_pixels(ms, scene, traced, spp, seed, width)
    return image.reshape(height, width)
