"""Per-pixel truth aligned with the image: one multi-channel EXR per sample, ``maps.exr`` (format ``maps/1``).

Every map is exact for the ray through each pixel's centre (continuous pixel coordinates (col + 0.5, row + 0.5),
docs/contract.md "Camera"), traced with the project's own float64 ray model of thesis §1.6 — the camera's chief ray
(§1.6.2; a thin lens does not move it), the secant intersection with the substrate (§1.6.4, eq. 1.6), the
reflection (§1.6.5) and the pattern plane (§1.6.3) — vectorised over the pixels with numpy (for a substrate, over
the box of pixels whose rays can meet it); nothing is supersampled. It is the model :mod:`scopetwin.scenes.analytic`
renders with and :mod:`scopetwin.sim.truth` finds the marker images with, so the maps, the marker truth and the image
agree.

Channels (layer ``name`` with components ``name.X`` ... as EXR layers; float32; NaN where a value does not exist):

==============  ==========  =====================================================================================
layer           components  holds (Part I samples)
==============  ==========  =====================================================================================
``mask``        1           1 where the pixel's ray meets the reflecting element (the substrate, the mirror) or,
                            in a calibration view, the target plate; else 0
``roi``         1           deflectometry: 1 where that point lies in the region of interest between the holding
                            frame's two supports (only there the substrate reflects into the camera, §1.10)
``point``       X, Y, Z     world mm: where the ray first meets the substrate / mirror / target
``surface_xy``  X, Y        substrate (base-plane) mm of that point (deflectometry and mirror)
``height``      1           mm: the true surface h(x, y) at ``surface_xy`` (NaN off the substrate)
``normal``      X, Y, Z     the unit surface normal there, world frame
``pattern_xy``  X, Y        pattern-plane mm (the pattern's own T_x, T_y from its centre) where the reflected ray
                            (in a calibration view: the ray itself) meets the pattern plane from its emitting side;
                            NaN where it misses
``marker``      I, J        the index (i, j) (docs/contract.md "Marker indices") of the marker whose spot the pixel
                            sees: ``pattern_xy`` inside that marker's disc, on the plate, through the reflecting
                            region; NaN elsewhere (deflectometry indices may be negative, so no integer marks
                            "none" here)
``marker_id``   1           the marker's position in ``truth.json``'s ``markers`` list (an integer), -1 elsewhere
==============  ==========  =====================================================================================

Four-channel (``cmu``) samples hold ``object_xy_<channel>`` (X, Y): object-plane mm of each pixel centre of that
channel's image, by the inverse of the channel's object -> pixel map in ``truth.json`` (an affine map fitted to the
numpy tracer's spot centroids of a 3 x 3 object grid; its fit residual is ``object_to_pixel_residual_px`` there).
GRIN samples hold ``object_xy`` (X, Y): the object-plane point (the array's x, y, mm) whose chief ray, traced
through the objective by the RKN tracer, meets the image plane at the pixel centre (:func:`grin_object_maps`); NaN
beyond the heights whose chief ray passes the objective.

The file's header carries ``scopetwin_format`` = ``maps/1`` and ``scopetwin_maps``, a JSON list of its layers with
their components and units. Its compression is lossless, Zstandard by default (:data:`MAPS_COMPRESSION`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.errors import FileFormatError
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap

MAPS_FILE = "maps.exr"
MAPS_FORMAT = "maps"
MAPS_VERSION = 1
FORMAT_ATTRIBUTE = "scopetwin_format"
#: The lossless compressions a ``maps.exr`` may be written with (``[dataset] maps_compression``), by name: Zstandard
#: (OpenEXR 3.5 and later read it) by default, ZIP for readers built on older OpenEXR libraries. Measured on one
#: sample of ``examples/datasets/01-deflectometry-small.toml`` (17 channels of 680 x 512 px; the minimum of 4 runs):
#: ZIP writes in 81-84 ms to 3.5 MB and decodes in 37 ms, Zstandard writes in 58-60 ms to 1.6 MB and decodes in
#: 14 ms; HTJ2K writes in 63-70 ms to 2.4-2.5 MB (``benchmarks/dataset_truth_maps.py`` prints every lossless one).
MAPS_COMPRESSION = ("zstd", "zip")
#: 4-byte numbers per pixel and channel while a ``maps.exr`` is read (the decoded channel, the stacked layer, its
#: converted copy): the estimate its declared size is checked with before decoding.
FLOATS_PER_MAP_CHANNEL = 3


@dataclass(frozen=True)
class Layer:
    """One map: its components (EXR channel suffixes), unit and meaning."""

    components: tuple[str, ...]
    unit: str
    text: str


#: The layers of a Part I sample's maps, in the order they are documented and returned.
LAYERS: dict[str, Layer] = {
    "mask": Layer((), "", "the pixel's ray meets the reflecting element (or the target plate): 1, else 0"),
    "roi": Layer((), "", "deflectometry: the point lies in the region of interest (reflects into the camera)"),
    "point": Layer(("X", "Y", "Z"), "mm", "world point where the ray first meets the substrate/mirror/target"),
    "surface_xy": Layer(("X", "Y"), "mm", "substrate base-plane coordinates of that point"),
    "height": Layer((), "mm", "true surface height h at surface_xy"),
    "normal": Layer(("X", "Y", "Z"), "", "unit surface normal there, world frame"),
    "pattern_xy": Layer(("X", "Y"), "mm", "pattern-plane coordinates where the (reflected) ray meets the pattern"),
    "marker": Layer(("I", "J"), "", "index (i, j) of the marker whose spot the pixel sees"),
    "marker_id": Layer((), "", "that marker's position in truth.json's markers list, -1 elsewhere"),
}
#: Layers that are integers or flags when read back (the EXR stores float32).
INTEGER_LAYERS = {"marker_id": np.int32}
BOOL_LAYERS = ("mask", "roi")
OBJECT_LAYER = Layer(("X", "Y"), "mm", "object-plane coordinates of the pixel centre (inverse object->pixel map)")


def _pixel_rays(
    setup: Setup, box: tuple[int, int, int, int] | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.intp] | None, tuple[int, int]]:
    """Chief rays (origin, unit direction) through the pixel centres of ``box`` (rows r0:r1, columns c0:c1; default
    every pixel), rows then columns; their flat indices in the image (None: every pixel, in order); (rows, cols)."""
    cam = setup.camera_model
    if box is None:
        o, d = cam.rays(cam.pixel_centers().reshape(-1, 2))
        return o, d, None, (cam.ny, cam.nx)
    r0, r1, c0, c1 = box
    o, d = cam.rays(cam.pixel_centers(slice(r0, r1), slice(c0, c1)).reshape(-1, 2))
    rows, cols = np.mgrid[r0:r1, c0:c1]
    return o, d, (rows * cam.nx + cols).ravel(), (cam.ny, cam.nx)


#: Samples per edge of the rectangle whose image bounds the pixels that can meet the substrate.
_EDGE_SAMPLES = 256


def _substrate_box(setup: Setup, sub: Any, heights: HeightMap) -> tuple[int, int, int, int] | None:
    """The pixels (rows r0:r1, columns c0:c1) outside which no ray can meet the substrate; None: any pixel may.

    :func:`_substrate_hits` traces the rays whose base-plane hit lies within the substrate grown by the ray's
    horizontal run over the surface's height range; this box bounds the image of the substrate grown by the largest
    such run (of the rays through the image's border pixels, where a pinhole camera's most oblique rays are, plus
    5 %), from densely sampled edges (distortion included), padded by 2 px. None where part of that rectangle lies
    behind the camera.
    """
    cam = setup.camera_model
    border = np.concatenate(
        [
            cam.pixel_centers(slice(0, 1)).reshape(-1, 2),
            cam.pixel_centers(slice(cam.ny - 1, cam.ny)).reshape(-1, 2),
            cam.pixel_centers(None, slice(0, 1)).reshape(-1, 2),
            cam.pixel_centers(None, slice(cam.nx - 1, cam.nx)).reshape(-1, 2),
        ]
    )
    ld = _vectors(sub.frame, cam.rays(border)[1], inverse=True)
    with np.errstate(divide="ignore"):
        run = float(np.max(np.hypot(ld[:, 0], ld[:, 1]) / np.abs(ld[:, 2])))
    grow = 1.05 * run * (2.0 * float(np.abs(heights.z).max()) + 1e-6)
    if not np.isfinite(grow):
        return None
    hx, hy = 0.5 * sub.size_x + grow, 0.5 * sub.size_y + grow
    corners = np.array([[-hx, -hy, 0.0], [hx, -hy, 0.0], [hx, hy, 0.0], [-hx, hy, 0.0]])
    t = np.linspace(0.0, 1.0, _EDGE_SAMPLES)[:, None]
    edges = np.concatenate([corners[i] + t * (corners[(i + 1) % 4] - corners[i]) for i in range(4)])
    px = cam.project(_to_global(sub.frame, edges))
    if not np.all(np.isfinite(px)):
        return None
    c0, r0 = np.maximum(np.floor(px.min(axis=0)).astype(int) - 2, 0)
    c1, r1 = np.minimum(np.ceil(px.max(axis=0)).astype(int) + 2, [cam.nx, cam.ny])
    return int(r0), int(max(r1, r0)), int(c0), int(max(c1, c0))


def _mul(v: NDArray[np.float64], m: NDArray[np.float64]) -> NDArray[np.float64]:
    """``v @ m`` for (n, 3) rows and a 3 x 3 matrix, as three broadcasts (numpy's matmul is slow for this shape)."""
    return v[:, :1] * m[0] + v[:, 1:2] * m[1] + v[:, 2:3] * m[2]


def _identity(frame: Any) -> bool:
    """Whether a frame is the global one (the substrate's always is, §1.10): no transform is needed."""
    return bool(np.array_equal(frame.rotation, np.eye(3)) and not np.any(frame.origin))


def _to_local(frame: Any, p: NDArray[np.float64]) -> NDArray[np.float64]:
    return p if _identity(frame) else _mul(p - frame.origin, frame.rotation.T)


def _to_global(frame: Any, q: NDArray[np.float64]) -> NDArray[np.float64]:
    return q if _identity(frame) else frame.origin + _mul(q, frame.rotation)


def _vectors(frame: Any, v: NDArray[np.float64], inverse: bool) -> NDArray[np.float64]:
    """Direction vectors into the frame (``inverse``) or out of it."""
    if _identity(frame):
        return v
    return _mul(v, frame.rotation.T if inverse else frame.rotation)


@dataclass(frozen=True)
class _Hits:
    """The pixels whose ray meets the reflecting element (or the target): their indices and what is known there."""

    idx: NDArray[np.intp]  # the pixels (flat indices) on the element
    point: NDArray[np.float64]  # (k, 3) world points
    seen: NDArray[np.bool_]  # (k,) the point can send light to the camera (deflectometry: in the ROI)
    local: NDArray[np.float64] | None = None  # (k, 3) substrate / mirror coordinates
    normal: NDArray[np.float64] | None = None  # (k, 3) world unit normals (a reflecting element)
    height: NDArray[np.float64] | None = None  # (k,) h at local x, y


def part1_maps(setup: Setup, heights: HeightMap | None = None) -> dict[str, NDArray[Any]]:
    """The per-pixel maps of a Part I setup (module docstring), as :func:`read_maps` returns them from the file.

    The trace itself runs in float64; its results are rounded to float32 (the EXR's type) once, at the end.

    Parameters
    ----------
    setup : Setup
        A deflectometry, mirror or calibration-target setup.
    heights : HeightMap, optional
        The substrate's true height map (deflectometry).

    Returns
    -------
    dict
        Layer name -> array (rows, cols) or (rows, cols, k): ``mask``/``roi`` bool, ``marker_id`` int32 (-1 where no
        marker is seen), the rest float32 with NaN where undefined.
    """
    from scopetwin.scenes.analytic import AnalyticScene
    from scopetwin.scenes.geometry import intersect_plane, reflect

    scene = AnalyticScene(setup, heights)
    pattern = scene.pattern
    if setup.scene == "target":
        o, d, flat, shape = _pixel_rays(setup)
        hits = _target_hits(pattern, o, d)
    elif setup.scene == "mirror":
        o, d, flat, shape = _pixel_rays(setup)
        hits = _mirror_hits(setup, o, d)
    else:
        assert scene.substrate is not None and heights is not None
        o, d, flat, shape = _pixel_rays(setup, _substrate_box(setup, scene.substrate, heights))
        hits = _substrate_hits(scene.substrate, heights, o, d)
    n = shape[0] * shape[1]
    d = d[hits.idx]  # the rays that meet the element, in the order of their pixels
    k = hits.idx if flat is None else flat[hits.idx]
    if hits.normal is None:  # a calibration view: the ray itself meets the pattern (the target)
        xy, reaches = _to_local(pattern.frame, hits.point)[:, :2], np.ones(len(k), dtype=bool)
    else:
        refl = reflect(d, hits.normal)
        lam = intersect_plane(hits.point, refl, pattern.frame)
        reaches = ((refl @ pattern.frame.nz) < 0) & np.isfinite(lam) & (lam > 0)
        xy = _to_local(pattern.frame, hits.point + np.where(reaches, lam, 0.0)[:, None] * refl)[:, :2]

    def layer(values: Any, where: NDArray[np.intp], fill: Any = np.nan, dtype: Any = np.float32) -> NDArray[Any]:
        values = np.asarray(values)
        out = np.full((n, *values.shape[1:]), fill, dtype=dtype)
        out[where] = values
        return out

    maps: dict[str, NDArray[Any]] = {"mask": layer(True, k, False, bool)}
    if setup.scene == "deflectometry":
        maps["roi"] = layer(hits.seen, k, False, bool)
    maps["point"] = layer(hits.point, k)
    if hits.local is not None and hits.normal is not None and hits.height is not None:
        maps["surface_xy"] = layer(hits.local[:, :2], k)
        maps["height"] = layer(hits.height, k)
        maps["normal"] = layer(hits.normal, k)
    maps["pattern_xy"] = layer(xy[reaches], k[reaches])
    seen = reaches & hits.seen
    ij, position = _markers(pattern, xy[seen])
    found = position >= 0
    maps["marker"] = layer(ij[found].astype(np.float64), k[seen][found])
    maps["marker_id"] = layer(position[found], k[seen][found], -1, INTEGER_LAYERS["marker_id"])
    return {name: maps[name].reshape(*shape, *maps[name].shape[1:]) for name in LAYERS if name in maps}


def _target_hits(pattern: Any, o: NDArray[np.float64], d: NDArray[np.float64]) -> _Hits:
    """Rays that meet the target plate from its emitting side (a calibration view)."""
    from scopetwin.scenes.geometry import intersect_plane

    lam = intersect_plane(o, d, pattern.frame)
    ok = ((d @ pattern.frame.nz) < 0) & np.isfinite(lam) & (lam > 0)
    p = o + np.where(ok, lam, 0.0)[:, None] * d
    xy = _to_local(pattern.frame, p)
    idx = np.flatnonzero(ok & (np.abs(xy[:, 0]) <= 0.5 * pattern.size_x) & (np.abs(xy[:, 1]) <= 0.5 * pattern.size_y))
    return _Hits(idx, p[idx], np.ones(len(idx), dtype=bool))


def _mirror_hits(setup: Setup, o: NDArray[np.float64], d: NDArray[np.float64]) -> _Hits:
    """Rays that meet the flat mirror z = 0 from above (thesis §2.7.2)."""
    from scopetwin.scenes.geometry import Frame, intersect_plane

    assert setup.mirror is not None
    lam = intersect_plane(o, d, Frame.identity())
    ok = np.isfinite(lam) & (lam > 0) & (d[:, 2] < 0)
    p = o + np.where(ok, lam, 0.0)[:, None] * d
    sx, sy = setup.mirror.size
    idx = np.flatnonzero(ok & (np.abs(p[:, 0]) <= 0.5 * sx) & (np.abs(p[:, 1]) <= 0.5 * sy))
    k = len(idx)
    normal = np.tile([0.0, 0.0, 1.0], (k, 1))
    return _Hits(idx, p[idx], np.ones(k, dtype=bool), p[idx], normal, np.zeros(k))


def _substrate_hits(sub: Any, heights: HeightMap, o: NDArray[np.float64], d: NDArray[np.float64]) -> _Hits:
    """Where rays first meet the substrate (thesis §1.6.4); ``seen``: the point lies in the ROI.

    Only rays that can reach the substrate are traced: those whose base-plane hit lies within the substrate grown by
    the largest horizontal run of a ray over the surface's height range (the spline overshoots its nodes by less than
    their range, so twice the largest node height bounds it). The secant iteration is the renderer's
    (:meth:`scopetwin.scenes.surface.Substrate.intersect`), on the same spline (:meth:`HeightMap.cells`), started on the
    base plane, run as one compiled kernel where Dr.Jit's LLVM backend is available (the same hits:
    :mod:`scopetwin.scenes.mitsuba.secant`; a sample's renderer has started that backend already).
    """
    lo, ld = _to_local(sub.frame, o), _vectors(sub.frame, d, inverse=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam_plane = -lo[:, 2] / ld[:, 2]
        run = np.hypot(ld[:, 0], ld[:, 1]) / np.abs(ld[:, 2])
    base = lo + np.where(np.isfinite(lam_plane), lam_plane, 0.0)[:, None] * ld
    reach = 2.0 * float(np.abs(heights.z).max()) + 1e-6
    grow = np.where(np.isfinite(run), run, np.inf) * reach
    cand = np.flatnonzero(
        np.isfinite(lam_plane)
        & (lam_plane > 0)
        & (np.abs(base[:, 0]) <= 0.5 * sub.size_x + grow)
        & (np.abs(base[:, 1]) <= 0.5 * sub.size_y + grow)
    )
    lam, ok, h, hx, hy = heights.cells().intersect(lo[cand], ld[cand], lam_plane[cand], compiled=True)
    ok &= lam > 0
    local = lo[cand] + np.where(ok, lam, 0.0)[:, None] * ld[cand]
    on = ok & sub.on_substrate(local[:, 0], local[:, 1])
    local, h, hx, hy = local[on], h[on], hx[on], hy[on]
    n_local = np.stack([-hx, -hy, np.ones_like(hx)], axis=-1) / np.sqrt(1.0 + hx * hx + hy * hy)[:, None]
    roi = sub.in_roi(local[:, 0], local[:, 1])
    normal = _vectors(sub.frame, n_local, inverse=False)
    return _Hits(cand[on], _to_global(sub.frame, local), roi, local, normal, h)


def _markers(pattern: Any, xy: NDArray[np.float64]) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """(i, j) and list position (-1: none) of the marker whose spot each pattern point is in.

    The same rule as the rendered grey value (:meth:`scopetwin.scenes.pattern.MarkerPattern.grey_local`): the
    nearest marker cell, strictly inside its disc, on the plate.
    """
    ij = pattern.nearest_index(xy)
    rel = xy - pattern.centers_local(ij)
    inside = np.hypot(rel[:, 0], rel[:, 1]) < pattern.radii(ij)
    on_plate = (np.abs(xy[:, 0]) <= 0.5 * pattern.size_x) & (np.abs(xy[:, 1]) <= 0.5 * pattern.size_y)
    first_i, first_j = (int(v) for v in pattern.indices()[0])
    position = (ij[:, 1] - first_j) * pattern.n_x + (ij[:, 0] - first_i)  # indices() runs i fastest
    return ij, np.where(inside & on_plate, position, -1)


def cmu_object_maps(channels: dict[str, Any], height: int, width: int) -> dict[str, NDArray[np.float64]]:
    """``object_xy_<channel>`` (rows, cols, 2), mm: each pixel centre through the inverse of the channel's affine
    object -> pixel map (``truth.json`` ``channels.<ch>.object_to_pixel``, (col, row) = A (x, y, 1))."""
    cc, rr = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    px = np.stack([cc, rr], axis=-1)
    out = {}
    for ch, entry in channels.items():
        a = np.asarray(entry["object_to_pixel"], dtype=np.float64)
        inv = np.linalg.inv(a[:, :2])
        out[f"object_xy_{ch}"] = (px - a[:, 2]) @ inv.T
    return out


def _chief_rays(stack: Any, heights: NDArray[np.float64], iterations: int = 40) -> NDArray[np.float64]:
    """T_y of the ray from each object height (along y) through the centre of the stop (the back face of rod 1), by a
    secant iteration on all heights at once (as :func:`scopetwin.scenes.grin.analysis.chief_ray` does for one)."""
    from scopetwin.scenes.grin.rkn import trace_stack

    n_stop = next(i for i, layer in enumerate(stack.layers) if layer.name == "rod1") + 1
    free = stack.with_stop_radius(None)
    zeros = np.zeros_like(heights)

    def y_at_stop(t: NDArray[np.float64]) -> NDArray[np.float64]:
        st = trace_stack(free, zeros, heights, zeros, t, until_layer=n_stop)
        return np.where(st.alive, st.y, np.nan)

    a, b = zeros.copy(), -0.1 * np.sign(heights)
    fa, fb = y_at_stop(a), y_at_stop(b)
    for _ in range(iterations):
        den = fb - fa
        ok = np.isfinite(den) & (den != 0) & (np.abs(fb) >= 1e-13)
        if not ok.any():
            break
        c = np.where(ok, b - fb * (b - a) / np.where(ok, den, 1.0), b)
        a, fa = np.where(ok, b, a), np.where(ok, fb, fa)
        b, fb = c, np.where(ok, y_at_stop(c), fb)
    return np.where(heights == 0, 0.0, np.where(np.abs(fb) < 1e-9, b, np.nan))


def grin_object_maps(
    setup: Any, stack: Any, width: int, height: int, centre: tuple[float, float], samples: int = 96
) -> dict[str, NDArray[np.float64]]:
    """``object_xy`` (rows, cols, 2), mm: the object-plane point (the array's x, y) whose chief ray — through the
    centre of the objective's stop, traced by the RKN tracer of :mod:`scopetwin.scenes.grin.rkn` (thesis §8.3) — meets
    the image plane at each pixel centre of a GRIN image rendered with ``stack`` (its image distance) and sensor
    centre ``centre`` (:func:`scopetwin.scenes.mitsuba.grin.render_image`). Each pixel belongs to the nearest
    objective, as the renderer's pupil sensor assigns it; an objective is rotationally symmetric about its axis, so
    the map is its chief ray's image height as a function of object height (``samples`` heights out to 1.5 field
    radii), inverted. NaN beyond the heights whose chief ray passes the objective."""
    from scopetwin.scenes.camera import PixelGrid
    from scopetwin.scenes.grin.rkn import trace_stack

    field = 1.5 * setup.object.field_radius
    h = np.linspace(0.0, field, samples)
    t = _chief_rays(stack, h)
    good = np.isfinite(t)
    st = trace_stack(
        stack.with_stop_radius(None), np.zeros(int(good.sum())), h[good], np.zeros(int(good.sum())), t[good]
    )
    _, y_img = st.at(stack.layers[-1].thickness)
    keep = st.alive & np.isfinite(y_img)
    h_obj, r_img = h[good][keep], y_img[keep]
    sign = -1.0 if np.median(r_img[1:] / h_obj[1:]) < 0 else 1.0  # an inverted image: the object lies opposite
    r_img = np.abs(r_img)
    order = np.argsort(r_img)
    r_img, h_obj = r_img[order], h_obj[order]
    grid = PixelGrid(int(width), int(height), setup.camera.pitch_mm, centre)
    cc, rr = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    u, v = grid.uv(cc, rr)
    arr = setup.array
    x0, y0 = -0.5 * (arr.nx - 1) * arr.pitch, -0.5 * (arr.ny - 1) * arr.pitch
    ax = x0 + np.clip(np.round((u - x0) / arr.pitch), 0, arr.nx - 1) * arr.pitch
    ay = y0 + np.clip(np.round((v - y0) / arr.pitch), 0, arr.ny - 1) * arr.pitch
    du, dv = u - ax, v - ay
    r = np.hypot(du, dv)
    r_obj = np.interp(r, r_img, h_obj, right=np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(r > 0, sign * r_obj / np.where(r > 0, r, 1.0), 0.0)
    scale = np.where(np.isfinite(r_obj), scale, np.nan)
    return {"object_xy": np.stack([ax + scale * du, ay + scale * dv], axis=-1)}


def layer_doc(name: str) -> Layer:
    """The documentation of a layer (``object_xy_<channel>`` included)."""
    if name.startswith("object_xy"):
        return OBJECT_LAYER
    return LAYERS[name]


def write_maps(path: Path, maps: dict[str, NDArray[Any]], compression: str = "zstd", **attrs: Any) -> None:
    """Write ``maps`` as one multi-channel float32 EXR (scan lines, ``compression`` one of :data:`MAPS_COMPRESSION`)
    with the format and layer attributes."""
    import OpenEXR

    if compression not in MAPS_COMPRESSION:
        raise ValueError(f"maps compression must be one of {', '.join(MAPS_COMPRESSION)}, got {compression!r}")
    from scopetwin.scenes.io import atomic_path, exr_write_error

    chans: dict[str, NDArray[np.float32]] = {}
    layers = []
    for name, arr in maps.items():
        doc = layer_doc(name)
        a = np.asarray(arr)
        if doc.components:
            if a.ndim != 3 or a.shape[2] != len(doc.components):
                raise FileFormatError(f"map {name!r} needs {len(doc.components)} components, got shape {a.shape}")
            for k, comp in enumerate(doc.components):
                chans[f"{name}.{comp}"] = np.ascontiguousarray(a[..., k], dtype=np.float32)
        else:
            chans[name] = np.ascontiguousarray(a, dtype=np.float32)
        layers.append({"name": name, "components": list(doc.components), "unit": doc.unit, "text": doc.text})
    header: dict[str, Any] = {
        "compression": OpenEXR.ZSTD_COMPRESSION if compression == "zstd" else OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        FORMAT_ATTRIBUTE: f"{MAPS_FORMAT}/{MAPS_VERSION}",
        "scopetwin_maps": json.dumps(layers),
    }
    header.update({k: v if isinstance(v, str | int | float) else json.dumps(v) for k, v in attrs.items()})
    with atomic_path(path) as tmp:
        try:
            OpenEXR.File(header, chans).write(str(tmp))
        except RuntimeError as exc:
            raise exr_write_error(path, exc) from None


def read_maps(path: Path, shape: tuple[int, int] | None = None) -> dict[str, NDArray[Any]]:
    """Read a ``maps.exr``: layer -> (rows, cols) or (rows, cols, k) arrays (flags as bool, ids as int32).

    The file must be a regular file, and the size its header declares must be ``shape`` (rows, cols; the sample's
    image) when given and fit in this machine's memory with every layer, all checked before a pixel is decoded
    (:func:`scopetwin.scenes.safe_read.check_exr_header`).

    Raises
    ------
    FileFormatError
        Not a regular file, a declared size other than ``shape`` or too large, unreadable, or a format this reader
        does not know (the message names the version it needs).
    """
    import OpenEXR

    from scopetwin.scenes.safe_read import check_exr_header, exr_header

    channels = len(exr_header(path, "maps file").get("channels", [])) or 1
    check_exr_header(path, "maps file", shape, floats_per_pixel=FLOATS_PER_MAP_CHANNEL * channels)
    try:
        f = OpenEXR.File(str(path), separate_channels=True)
        channels = f.channels()
        header = dict(f.header())
    except Exception as exc:  # OpenEXR raises bare RuntimeError/ValueError on corrupt files
        raise FileFormatError(f"{path} is not a readable OpenEXR file ({exc})") from None
    check_format(path, header, MAPS_FORMAT, MAPS_VERSION)
    groups: dict[str, dict[str, NDArray[np.float32]]] = {}
    for cname, chan in channels.items():
        layer, _, comp = cname.rpartition(".")
        groups.setdefault(layer or comp, {})[comp if layer else ""] = np.asarray(chan.pixels, dtype=np.float32)
    order = [*[n for n in LAYERS if n in groups], *sorted(n for n in groups if n not in LAYERS)]
    out: dict[str, NDArray[Any]] = {}
    for name in order:
        parts = groups[name]
        if "" in parts:
            arr: NDArray[Any] = parts[""]
        else:
            comps = layer_doc(name).components if (name in LAYERS or name.startswith("object_xy")) else ()
            keys = [c for c in comps if c in parts] or sorted(parts)
            arr = np.stack([parts[c] for c in keys], axis=-1)
        if name in BOOL_LAYERS:
            arr = arr > 0.5
        elif name in INTEGER_LAYERS:
            arr = arr.astype(INTEGER_LAYERS[name])
        out[name] = arr
    return out


def check_format(path: Path | str, header: dict[str, Any], name: str, version: int) -> int:
    """The format version of a file's header (``scopetwin_format`` = ``name/N``; absent: 1); raise when this reader
    cannot read it, naming the version it needs."""
    text = header.get(FORMAT_ATTRIBUTE)
    if text is None:
        return 1
    fname, _, ver = str(text).partition("/")
    if fname != name or not ver.isdigit():
        raise FileFormatError(f"{path}: scopetwin_format {text!r} is not a {name!r} file")
    if int(ver) > version:
        raise FileFormatError(
            f"{path} is {name} format {ver}; this scopetwin reads {name} format {version} and older: "
            "install a newer scopetwin to read it"
        )
    return int(ver)
