"""Marker identification in camera images (seed §1.5 for the deflectometry grid, §2.6 for the calibration grid).

Four steps, as in the seed, each a small function:

1. :func:`centroids` — centroid search (§1.5.1): background level and noise from the image,
   threshold, connected components (OpenCV), grey-value-weighted centre of mass.
2. :func:`filter_spots` — filtering (§1.5.2): area against the median area of the neighbouring
   spots, spots touching the image border or leaving the reflecting region (partially reflected
   markers), and spots with a clipped edge; saturated spots are flagged.
3. :func:`fourier_axes` (deflectometry, §1.5.3) and :func:`reference_axes` (calibration, §2.6.1) —
   the image vectors of one pitch step along the pattern's T_x and T_y.
4. :func:`index_grid` — indexing (§1.5.4): a flood from the reference marker [0, 0] through the
   eight neighbours of each marker, with the neighbour steps re-estimated locally as it proceeds.

:func:`find_markers` runs all four. The centroid is the first moment of the *whole* spot: pixels
above the threshold define the spot, and its window is grown by a few pixels so the faint rim below
the threshold is weighted too (weights: grey value minus background). That makes the centroid
independent of the threshold and equal, up to pixel sampling, to the continuous first moment of the
spot's irradiance — the quantity that :mod:`recon.bias` predicts from a model.

Coordinates are continuous pixel coordinates (col, row): pixel (r, c) covers [c, c+1) x [r, r+1)
(DESIGN.md). Indices (i, j) count pitches along the pattern's own T_x, T_y (DESIGN.md, "Marker indices").
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from scenes.errors import ScopetwinError
from scenes.setup import Setup
from scenes.surface import HeightMap

Array = NDArray[np.float64]

#: Variance along an axis of a cone spot g = 1 - r/R over the disk of radius R, in units of R^2:
#: (int r^3 cos^2 g dr dphi) / (int r g dr dphi) = (pi R^4 / 20) / (pi R^2 / 3).
CONE_VARIANCE = 0.15

#: Neighbour offsets of the flood (§1.5.4): the four axial neighbours first, then the diagonals.
NEIGHBOURS = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [-1, 1], [1, -1], [-1, -1]], dtype=np.int64)


class MarkerError(ScopetwinError, ValueError):
    """An image in which markers cannot be identified; the message says why."""


# ---------------------------------------------------------------------------------------------
# 1. centroid search
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Spots:
    """Bright spots of an image (candidates of §1.5.1).

    Attributes
    ----------
    centroids : ndarray, (n, 2)
        Grey-weighted centres (col, row) in continuous pixel coordinates.
    areas : ndarray, (n,)
        Pixel count above the threshold.
    mass : ndarray, (n,)
        Sum of the grey values above the background over the spot's window.
    peak : ndarray, (n,)
        Largest grey value of each spot (background included).
    cov : ndarray, (n, 2, 2)
        Grey-weighted covariance of the spot (px^2); for a marker's cone profile g = 1 - r/r_m the
        variance along an axis is 0.15 times the squared semi-axis of the spot's rim.
    edge : ndarray, (n,)
        Largest grey value above the background on the spot's threshold boundary, as a fraction of
        its peak above the background. A whole spot fades out there (small); a spot cut off by
        the edge of the reflecting region ends abruptly (large).
    saturated : ndarray of bool, (n,)
        The peak reaches the saturation level.
    background, noise, threshold : float
        Background level, its noise (standard deviation) and the threshold used.
    """

    centroids: Array
    areas: NDArray[np.int64]
    mass: Array
    peak: Array
    cov: Array = field(default_factory=lambda: np.zeros((0, 2, 2)))
    edge: Array = field(default_factory=lambda: np.zeros(0))
    saturated: NDArray[np.bool_] = field(default_factory=lambda: np.zeros(0, dtype=bool))
    background: float = 0.0
    noise: float = 0.0
    threshold: float = 0.0

    def __len__(self) -> int:
        return len(self.areas)

    @property
    def relative_threshold(self) -> Array:
        """Threshold above background as a fraction of each spot's peak above background."""
        return (self.threshold - self.background) / np.maximum(self.peak - self.background, 1e-300)

    def _rim_axes(self) -> tuple[Array, Array, Array]:
        """Semi-axes (minor, major) of the rim ellipses and the major axis's angle (closed-form 2x2 eigen).

        The rim covariance is the spot's less the pixel box (1/12 px^2), over the cone's 0.15.
        """
        c = (self.cov - np.eye(2) / 12.0) / CONE_VARIANCE
        a, b, d = c[:, 0, 0], c[:, 0, 1], c[:, 1, 1]
        mean = 0.5 * (a + d)
        dev = np.sqrt((0.5 * (a - d)) ** 2 + b * b)
        angle = 0.5 * np.arctan2(2.0 * b, a - d)
        return np.sqrt(np.maximum(mean - dev, 0.0)), np.sqrt(np.maximum(mean + dev, 0.0)), angle

    def rim(self, n_points: int = 16, which: NDArray | None = None) -> Array:
        """Points (n, n_points, 2) on each spot's estimated rim ellipse (cone profile, see ``cov``)."""
        sel = slice(None) if which is None else which
        minor, major, angle = (v[sel] for v in self._rim_axes())
        t = np.linspace(0.0, 2.0 * np.pi, n_points, endpoint=False)
        ca, sa = np.cos(angle)[:, None], np.sin(angle)[:, None]
        u = major[:, None] * np.cos(t)[None]
        v = minor[:, None] * np.sin(t)[None]
        return self.centroids[sel][:, None, :] + np.stack([ca * u - sa * v, sa * u + ca * v], axis=-1)

    def minor_radius(self) -> Array:
        """Smallest semi-axis of each spot's estimated rim ellipse, px."""
        return self._rim_axes()[0]

    def major_radius(self) -> Array:
        """Largest semi-axis of each spot's estimated rim ellipse, px."""
        return self._rim_axes()[1]


def check_image(image: NDArray) -> NDArray[np.float32]:
    """Validate a camera image and return it as float32 (row, col).

    Raises
    ------
    MarkerError
        Not 2-D, not numeric (bool, complex, object), empty, or NaN / infinite values.
    """
    img = np.asarray(image)
    if img.ndim != 2:
        raise MarkerError(f"image must be 2-D (rows, cols), got shape {img.shape}")
    if img.dtype == np.bool_ or not (np.issubdtype(img.dtype, np.floating) or np.issubdtype(img.dtype, np.integer)):
        raise MarkerError(f"image must have a real numeric dtype (integer or float), got {img.dtype}")
    if min(img.shape) < 8:
        raise MarkerError(f"image is too small for marker identification: {img.shape}")
    out = np.ascontiguousarray(img, dtype=np.float32)
    if not (np.isfinite(out.max()) and np.isfinite(out.min())):  # NaN propagates through min / max
        raise MarkerError("image contains NaN or infinite values")
    return out


def background_level(image: NDArray[np.float32], stride: int = 7) -> tuple[float, float]:
    """Robust background level and noise of an image (for §1.5.1's threshold).

    The level is the median of a strided subsample (markers cover well under half of any of the
    seed's images), refined as the mean of the samples within 3 sigma of it; the noise sigma is the
    scaled median absolute deviation of the samples below the median (the dark side, which holds
    no marker light).
    """
    sub = image[stride // 2 :: stride, stride // 2 :: stride].ravel().astype(np.float64)
    med = float(np.median(sub))
    low = sub[sub <= med]
    sigma = 1.4826 * float(np.median(med - low)) if low.size else 0.0
    if sigma > 0:
        near = sub[np.abs(sub - med) <= 3.0 * sigma]
        med = float(near.mean()) if near.size else med
    return med, sigma


def _saturation_level(image: NDArray, saturation: float | None, top: float | None = None) -> float:
    """Saturation level: given, or the ADC maximum of an integer-valued image (2^k - 1), else +inf.

    ``top`` is the image's maximum where the caller knows it already (float images only).
    """
    if saturation is not None:
        return float(saturation)
    arr = np.asarray(image)
    if np.issubdtype(arr.dtype, np.integer):
        return float(np.iinfo(arr.dtype).max) if arr.max() >= np.iinfo(arr.dtype).max else np.inf
    top = float(arr.max()) if top is None else float(top)
    for bits in (8, 10, 12, 14, 16):
        if top == 2**bits - 1:
            sample = arr.ravel()[::97]
            if np.all(sample == np.round(sample)):
                return top
    return np.inf


class _Scratch(threading.local):
    """Per-thread work buffers of the centroid search, reused from frame to frame.

    Fresh large arrays cost page faults on every call (the allocator hands freed memory back to
    the system); with ~20 pixel-list arrays of a few MB per frame that was half of the centroid
    search's time. Each buffer grows to the largest size asked for and is then kept.
    """

    def __init__(self) -> None:
        self.buffers: dict[str, NDArray] = {}

    def get(self, name: str, shape: tuple[int, ...] | int, dtype: type) -> NDArray:
        """A C-contiguous array of ``shape`` and ``dtype`` (uninitialised) backed by the named buffer."""
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        size = int(np.prod(shape))
        buf = self.buffers.get(name)
        if buf is None or buf.dtype != np.dtype(dtype) or buf.size < size:
            buf = self.buffers[name] = np.empty(size + size // 4, dtype=dtype)
        return buf[:size].reshape(shape)


_scratch = _Scratch()


def centroids(
    image: NDArray,
    threshold: float | None = None,
    background: float | None = None,
    connectivity: int = 8,
    grow: int | None = None,
    saturation: float | None = None,
    relative_threshold: float = 0.08,
    noise_sigmas: float = 6.0,
) -> Spots:
    """Centroid search of seed §1.5.1: connected pixels above a threshold, grey-weighted centre of mass.

    r_s = (1/G) sum_i g_i r_i, G = sum_i g_i (seed §1.5.1), with g_i the grey value minus the
    background. Pixels above ``threshold`` define a spot (OpenCV connected components); the sum runs
    over the spot grown by ``grow`` pixels, so that the spot's faint rim below the threshold counts
    too and the centroid does not depend on the threshold (module docstring).

    Parameters
    ----------
    image : ndarray, (rows, cols)
        Grey values: float images of any scale, or integer images of any bit depth.
    threshold : float, optional
        A pixel belongs to a spot when its value exceeds this. Default:
        ``background + max(noise_sigmas * noise, relative_threshold * (max - background))``.
    background : float, optional
        Level subtracted from the grey values. Default: :func:`background_level`.
    connectivity : {4, 8}
        Pixel neighbourhood of the components.
    grow : int, optional
        Pixels by which each spot's window is grown beyond the threshold boundary. Default: enough to
        reach the rim of a cone-shaped marker spot of the largest area found, plus 1.5 px.
    saturation : float, optional
        Saturation level (default: the ADC maximum of an integer-valued image, else none).

    Raises
    ------
    MarkerError
        Bad image (see :func:`check_image`) or a blank image (no contrast).
    """
    img = check_image(image)
    level, sigma = background_level(img) if background is None else (float(background), 0.0)
    top = float(img.max())
    if threshold is None:
        if not top > level + max(noise_sigmas * sigma, 1e-12 * max(abs(level), 1.0)):
            raise MarkerError("image is blank: no pixel stands out of the background")
        threshold = level + max(noise_sigmas * sigma, relative_threshold * (top - level))
    if not top > threshold:
        raise MarkerError(f"image is blank: no pixel exceeds the threshold {threshold:.6g}")
    ny, nx = img.shape
    mask = cv2.compare(img, float(threshold), cv2.CMP_GT, dst=_scratch.get("mask", (ny, nx), np.uint8))
    # all work below happens in the bounding box of the spots, grown by the window margin
    bx, by, bw, bh = cv2.boundingRect(mask)
    if bw == 0 or bh == 0:
        raise MarkerError("image is blank: no spot found")
    n, labels = cv2.connectedComponents(mask[by : by + bh, bx : bx + bw], connectivity=connectivity, ltype=cv2.CV_32S)
    if n <= 1:
        raise MarkerError("image is blank: no spot found")
    if grow is None:  # reach the rim of a spot twice the mean area (the reference marker)
        frac = (threshold - level) / max(top - level, 1e-300)
        r_eq = np.sqrt(2.0 * cv2.countNonZero(labels) / (n - 1) / np.pi)
        grow = int(np.ceil(frac / max(1.0 - frac, 1e-3) * r_eq + 1.5))
    grow = int(max(grow, 0))
    r0, r1 = max(by - grow, 0), min(by + bh + grow, ny)
    c0, c1 = max(bx - grow, 0), min(bx + bw + grow, nx)
    shape = (r1 - r0, c1 - c0)
    # pixels outside the box are below the threshold: labels and window there are 0, as on the whole image
    lab_img = _scratch.get("labels", shape, np.uint16 if n < 65535 else np.float32)
    lab_img.fill(0)
    lab_img[by - r0 : by - r0 + bh, bx - c0 : bx - c0 + bw] = labels
    win = lab_img
    if grow > 0:
        win = cv2.dilate(
            lab_img,
            cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * grow + 1, 2 * grow + 1)),
            dst=_scratch.get("window", shape, lab_img.dtype),
        )
    # every spot pixel lies in its window: gather the window pixels into flat lists (reused buffers)
    idx = np.flatnonzero(np.not_equal(win, 0, out=_scratch.get("nonzero", shape, np.bool_)))
    m = idx.size
    lab = _scratch.get("lab", m, np.intp)
    np.copyto(lab, np.take(win.ravel(), idx, out=_scratch.get("lab_raw", m, win.dtype), mode="clip"), casting="unsafe")
    crop = _scratch.get("crop", shape, np.float32)
    np.copyto(crop, img[r0:r1, c0:c1])
    values = _scratch.get("values", m, np.float64)
    np.copyto(values, np.take(crop.ravel(), idx, out=_scratch.get("values32", m, np.float32), mode="clip"))
    mask_c = _scratch.get("mask_crop", shape, np.uint8)
    np.copyto(mask_c, mask[r0:r1, c0:c1])
    flags = _scratch.get("flags", m, np.uint8)
    inside = np.not_equal(
        np.take(mask_c.ravel(), idx, out=flags, mode="clip"), 0, out=_scratch.get("inside", m, np.bool_)
    )
    w = np.subtract(values, level, out=_scratch.get("w", m, np.float64))
    rows = np.floor_divide(idx, shape[1], out=_scratch.get("rows", m, np.intp))
    x = np.subtract(
        idx, np.multiply(rows, shape[1], out=_scratch.get("cols", m, np.intp)), out=_scratch.get("x", m, np.float64)
    )
    x += c0 + 0.5
    # sum along runs: stretches of one label within one image row (the lists are in raster order);
    # y is constant along a run, so only the x moments need per-pixel sums
    start = _scratch.get("start", m, np.bool_)
    start[0] = True
    np.not_equal(lab[1:], lab[:-1], out=start[1:])
    start[1:] |= np.not_equal(rows[1:], rows[:-1], out=_scratch.get("row_change", m - 1, np.bool_))
    runs = np.flatnonzero(start)
    tmp = _scratch.get("tmp", m, np.float64)
    tmp2 = _scratch.get("tmp2", m, np.float64)
    run_w = np.add.reduceat(w, runs)
    wx = np.multiply(w, x, out=tmp)
    run_wx = np.add.reduceat(wx, runs)
    run_wxx = np.add.reduceat(np.multiply(wx, x, out=tmp2), runs)
    np.copyto(tmp, inside)
    run_in = np.add.reduceat(tmp, runs)
    tmp.fill(-np.inf)
    np.copyto(tmp, values, where=inside)
    run_peak = np.maximum.reduceat(tmp, runs)
    # threshold boundary: spot pixels with a 4-neighbour below the threshold (outside the box: below)
    eroded = cv2.erode(
        mask_c,
        cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3)),
        borderValue=0,
        dst=_scratch.get("eroded", shape, np.uint8),
    )
    bnd = np.equal(np.take(eroded.ravel(), idx, out=flags, mode="clip"), 0, out=_scratch.get("bnd", m, np.bool_))
    bnd &= inside
    tmp.fill(0.0)
    np.copyto(tmp, w, where=bnd)
    run_edge = np.maximum.reduceat(tmp, runs)
    # per spot: sums over its runs
    rl = lab[runs]
    ry = rows[runs] + (r0 + 0.5)
    areas = np.bincount(rl, weights=run_in, minlength=n).astype(np.int64)
    mass = np.bincount(rl, weights=run_w, minlength=n)
    safe = np.where(mass > 0, mass, 1.0)
    cx = np.bincount(rl, weights=run_wx, minlength=n) / safe
    cy = np.bincount(rl, weights=run_w * ry, minlength=n) / safe
    sxx = np.bincount(rl, weights=run_wxx, minlength=n) / safe - cx * cx
    syy = np.bincount(rl, weights=run_w * ry * ry, minlength=n) / safe - cy * cy
    sxy = np.bincount(rl, weights=run_wx * ry, minlength=n) / safe - cx * cy
    cov = np.stack([np.stack([sxx, sxy], -1), np.stack([sxy, syy], -1)], -2)
    peak = np.full(n, -np.inf)
    np.maximum.at(peak, rl, run_peak)
    edge = np.zeros(n)
    np.maximum.at(edge, rl, run_edge)
    edge = edge / np.maximum(peak - level, 1e-300)
    sat_level = _saturation_level(image, saturation, top if np.asarray(image) is img else None)
    s = slice(1, None)
    ok = mass[s] > 0
    return Spots(
        centroids=np.stack([cx[s], cy[s]], axis=-1)[ok],
        areas=areas[s].astype(np.int64)[ok],
        mass=mass[s][ok],
        peak=peak[s][ok],
        cov=cov[s][ok],
        edge=edge[s][ok],
        saturated=(peak[s] >= sat_level)[ok],
        background=level,
        noise=sigma,
        threshold=float(threshold),
    )


# ---------------------------------------------------------------------------------------------
# 2. filtering
# ---------------------------------------------------------------------------------------------
def local_area_ratio(points: Array, areas: NDArray, reference: NDArray[np.bool_] | None = None, k: int = 8) -> Array:
    """Area of each spot divided by the median area of its ``k`` nearest reference spots (§1.5.2, made local).

    A bowed substrate magnifies spots unevenly and perspective shrinks distant ones, so the seed's
    comparison with the median area is made against the neighbourhood. ``reference`` selects the
    spots that may serve as neighbours (default all): fragments of partially reflected markers at
    the region's edge would otherwise make a whole marker beside them look large.
    """
    n = len(points)
    ref = np.ones(n, dtype=bool) if reference is None else np.asarray(reference, dtype=bool)
    m = int(ref.sum())
    if m < 2:
        return np.ones(n)
    kk = min(k, m - 1)
    rp = points[ref]
    _, nb = cKDTree(rp).query(points, k=kk + 1)
    nb = np.asarray(nb).reshape(n, -1)
    d = np.linalg.norm(rp[nb] - points[:, None, :], axis=-1)
    # drop the spot itself where it is one of the reference spots
    self_hit = d[:, 0] == 0
    nbs = np.where(self_hit[:, None], nb[:, 1:], nb[:, :-1])
    return areas / np.maximum(np.median(areas[ref][nbs], axis=1), 1e-300)


@dataclass(frozen=True)
class Filtered:
    """Outcome of :func:`filter_spots`: which candidates are kept, and why the others are not."""

    keep: NDArray[np.bool_]
    reference: int
    ratio: Array
    reasons: dict[str, int]


def find_reference(
    ratio: Array, candidates: NDArray[np.bool_], points: Array, min_ratio: float = 1.45, tie: float = 0.8
) -> int:
    """Index of the reference marker: the spot much larger than its neighbours (§1.5.4, §2.6.1).

    Raises
    ------
    MarkerError
        No spot is ``min_ratio`` times larger than its neighbours, or two candidates are about equally
        large (the second within ``tie`` of the first).
    """
    cand = np.flatnonzero(candidates & (ratio >= min_ratio))
    if cand.size == 0:
        raise MarkerError(f"no reference marker: no spot is at least {min_ratio:g}x larger than its neighbours")
    order = cand[np.argsort(-ratio[cand])]
    if order.size > 1 and ratio[order[1]] >= tie * ratio[order[0]]:
        a, b = points[order[0]], points[order[1]]
        raise MarkerError(
            "two equally large reference marker candidates at "
            f"(col, row) = ({a[0]:.1f}, {a[1]:.1f}) and ({b[0]:.1f}, {b[1]:.1f}) "
            f"(area ratios {ratio[order[0]]:.2f} and {ratio[order[1]]:.2f})"
        )
    return int(order[0])


@dataclass(frozen=True)
class Region:
    """The image of the region where markers are reflected whole: a closed polygon in pixel coordinates.

    For the deflectometry setup it is the image of the substrate's region of interest (seed §1.6.4,
    the gap between the holding-frame regions), for the mirror setup the mirror; a spot whose rim
    crosses its edge belongs to a partially reflected marker (§1.5.2). See :func:`region_for_setup`.
    """

    polygon: Array

    def signed_distance(self, points: Array) -> Array:
        """Distance (px) of points (..., 2) to the polygon's edge, positive inside."""
        p = np.asarray(points, dtype=np.float64)
        shape = p.shape[:-1]
        px = p[..., 0].reshape(-1, 1)
        py = p[..., 1].reshape(-1, 1)
        ax, ay = self.polygon[:, 0], self.polygon[:, 1]
        bx, by = np.roll(ax, -1), np.roll(ay, -1)
        abx, aby = bx - ax, by - ay
        # closest point of each edge (clamped projection), x and y kept apart: (points, edges) arrays
        dx, dy = px - ax, py - ay
        t = np.clip((dx * abx + dy * aby) / np.maximum(abx * abx + aby * aby, 1e-300), 0.0, 1.0)
        dx -= t * abx
        dy -= t * aby
        d = np.sqrt(np.min(dx * dx + dy * dy, axis=1))
        crosses = (ay > py) != (by > py)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = ax + (py - ay) * abx / aby
        inside = (np.count_nonzero(crosses & (px < xc), axis=1) % 2) == 1
        return np.where(inside, d, -d).reshape(shape)


def rim_clearance(
    spots: Spots, shape: tuple[int, int], region: Region | None = None, n_points: int = 24
) -> tuple[Array, Array]:
    """Smallest distance (px) of each spot's estimated rim ellipse to the image border and to the region's edge.

    Returns
    -------
    border, region : ndarray, (n,)
        Clearances; negative where the rim crosses the image border or the region's edge
        (+inf for the region when ``region`` is None).
    """
    rows, cols = shape
    reach = spots.major_radius() + 2.0
    c = spots.centroids
    border = np.minimum(np.minimum(c[:, 0], cols - c[:, 0]), np.minimum(c[:, 1], rows - c[:, 1])) - reach + 2.0
    near = np.flatnonzero(border < 2.0)
    if near.size:
        rim = spots.rim(n_points, near)
        b = np.minimum(np.minimum(rim[..., 0], cols - rim[..., 0]), np.minimum(rim[..., 1], rows - rim[..., 1]))
        border[near] = b.min(axis=1)
    inner = np.full(len(spots), np.inf)
    if region is None or len(spots) == 0:
        return border, inner
    centre = region.signed_distance(c)
    inner = centre - reach + 2.0
    near = np.flatnonzero(centre < reach)
    if near.size:
        inner[near] = region.signed_distance(spots.rim(n_points, near)).min(axis=1)
    return border, inner


def filter_spots(
    spots: Spots,
    shape: tuple[int, int],
    region: Region | None = None,
    area_range: tuple[float, float] = (0.7, 1.4),
    min_area: int = 4,
    edge_slack: float = 1.5,
    border_margin: float = 0.5,
    region_margin: float = 0.5,
    ref_ratio: float = 1.45,
) -> Filtered:
    """Marker filtering of seed §1.5.2 and the reference marker.

    A candidate is kept when

    * its area lies within ``area_range`` times the median area of its neighbours (the reference
      marker, much larger, is found by :func:`find_reference` and kept);
    * its rim ellipse (estimated from the spot's second moments, :meth:`Spots.rim`) stays
      ``border_margin`` px inside the image and ``region_margin`` px inside the region where markers
      are reflected whole (``region``, see :func:`region_for_setup`);
    * its threshold boundary fades out: a cone spot of minor semi-axis R px reaches at most about
      ``t + 1/R`` of its peak on the boundary (t the relative threshold), so a boundary value above
      ``t + edge_slack/R`` marks a spot cut off by the edge of the reflecting region.

    Returns
    -------
    Filtered
        Mask of kept spots, the index of the reference spot, the local area ratios and the number of
        spots rejected for each reason.
    """
    n = len(spots)
    tiny = spots.areas < max(min_area, 0.15 * np.median(spots.areas))
    ratio = np.zeros(n)
    big = ~tiny
    if big.sum() < 3:
        raise MarkerError(f"too few spots to identify a marker grid ({int(big.sum())} found)")
    border, inner = rim_clearance(spots, shape, region)
    at_border = border < border_margin
    outside = ~at_border & (inner < region_margin)
    whole = ~at_border & ~outside
    neighbours = (whole & (spots.areas >= 0.5 * np.median(spots.areas[big])))[big]
    ratio[big] = local_area_ratio(spots.centroids[big], spots.areas[big], neighbours)
    sharp = spots.edge > spots.relative_threshold + edge_slack / np.maximum(spots.minor_radius(), 1.0)
    ref = find_reference(ratio, big & whole & ~sharp, spots.centroids, ref_ratio)
    in_range = (ratio >= area_range[0]) & (ratio <= area_range[1])
    keep = big & whole & in_range & ~sharp
    keep[ref] = True
    reasons = {
        "tiny": int(tiny.sum()),
        "image_border": int((big & at_border).sum()),
        "outside_region": int((big & outside).sum()),
        "area": int((big & whole & ~in_range).sum()) - 1,
        "clipped_edge": int((big & whole & in_range & sharp).sum()),
    }
    return Filtered(keep, ref, ratio, reasons)


# ---------------------------------------------------------------------------------------------
# 3. grid identification
# ---------------------------------------------------------------------------------------------
def nearest_spacing(points: Array) -> float:
    """Median distance of each spot to its nearest neighbour, px."""
    d, _ = cKDTree(points).query(points, k=2)
    return float(np.median(d[:, 1]))


def _peak_subpixel(mag: Array, r: int, c: int, log_mag: Array | None = None) -> tuple[float, float]:
    """Parabolic refinement of a spectral peak (periodic indexing); ``log_mag``: log(mag), if computed already."""
    ny, nx = mag.shape
    lm = np.log(np.maximum(mag, 1e-300)) if log_mag is None else log_mag
    dr = dc = 0.0
    a, b, cc = lm[(r - 1) % ny, c], lm[r, c], lm[(r + 1) % ny, c]
    den = a - 2 * b + cc
    if den < 0:
        dr = 0.5 * (a - cc) / den
    a, cc = lm[r, (c - 1) % nx], lm[r, (c + 1) % nx]
    den = a - 2 * b + cc
    if den < 0:
        dc = 0.5 * (a - cc) / den
    return r + float(np.clip(dr, -0.5, 0.5)), c + float(np.clip(dc, -0.5, 0.5))


def fourier_axes(image: NDArray, center: Array, spacing: float, size: int = 128, periods: float = 8.0) -> Array:
    """Two lattice step vectors of the marker grid from the Fourier transform of the image (§1.5.3).

    A window of about ``periods`` grid periods around ``center`` is resampled to ``size`` x ``size``
    pixels, Hann-windowed and transformed; the two strongest non-collinear spectral peaks are the
    reciprocal lattice vectors b1, b2 (the lowest frequency components), and the real-space steps are
    the rows of inv([b1; b2])^T.

    Returns
    -------
    ndarray, (2, 2)
        Rows: image vectors (d_col, d_row) of two grid steps, unordered and of arbitrary sign
        (:func:`orient_axes` assigns them to the pattern's T_x and T_y).
    """
    img = np.asarray(image, dtype=np.float32)
    ny, nx = img.shape
    half = int(min(max(periods * spacing, 16.0), nx, ny) // 2)
    c0 = int(np.clip(round(center[0]) - half, 0, nx - 2 * half))
    r0 = int(np.clip(round(center[1]) - half, 0, ny - 2 * half))
    crop = img[r0 : r0 + 2 * half, c0 : c0 + 2 * half]
    scale = size / (2.0 * half)
    small = cv2.resize(crop, (size, size), interpolation=cv2.INTER_AREA).astype(np.float64)
    small -= small.mean()
    hann = np.hanning(size)
    spec = np.fft.fft2(small * np.outer(hann, hann))
    mag = np.abs(spec)
    freqs = np.fft.fftfreq(size) * size  # cycles per window, signed
    fr, fc = np.meshgrid(freqs, freqs, indexing="ij")
    rad = np.hypot(fr, fc)
    expected = 2.0 * half / spacing  # cycles per window of the nearest-neighbour period
    mag_sel = np.where(
        (rad >= 0.4 * expected) & (rad <= 2.5 * expected) & ((fc > 0) | ((fc == 0) & (fr > 0))), mag, 0.0
    )
    local_max = mag_sel >= np.maximum.reduce([np.roll(mag_sel, s, axis=a) for a in (0, 1) for s in (-1, 1)])
    cand = np.flatnonzero((local_max & (mag_sel > 0)).ravel())
    if cand.size < 2:
        raise MarkerError("no periodic marker grid found in the image's Fourier transform")
    cand = cand[np.argsort(-mag_sel.ravel()[cand])]
    log_mag = np.log(np.maximum(mag, 1e-300))

    def peak_vector(k: int) -> Array:
        r, c = divmod(int(k), size)
        rr, cc = _peak_subpixel(mag, r, c, log_mag)
        return np.array([cc if cc < size / 2 else cc - size, rr if rr < size / 2 else rr - size])

    b1 = peak_vector(cand[0])
    b2 = None
    for v in map(peak_vector, cand[1:20]):  # refined one at a time, until the second direction is found
        cosang = abs(v @ b1) / (np.linalg.norm(v) * np.linalg.norm(b1))
        if cosang < np.cos(np.radians(30.0)):
            b2 = v
            break
    if b2 is None:
        raise MarkerError("the image's Fourier transform shows only one grid direction")
    recip = np.stack([b1, b2]) / size * scale  # cycles per original pixel, (d_col, d_row) rows
    return np.linalg.inv(recip).T


def orient_axes(steps: Array, hint: Array) -> Array:
    """Assign two unordered, unsigned grid steps to the pattern's +T_x, +T_y (rows of ``hint``).

    Of the eight orderings and sign choices, the one most parallel to the hint (image directions of
    +T_x and +T_y at the reference, e.g. from :func:`expected_axes` or the seed's "x-axis almost
    (1, 0, 0)") is taken.
    """
    h = hint / np.linalg.norm(hint, axis=1, keepdims=True)
    u = steps / np.linalg.norm(steps, axis=1, keepdims=True)
    best, out = -np.inf, steps
    for order in ((0, 1), (1, 0)):
        for sx in (1.0, -1.0):
            for sy in (1.0, -1.0):
                score = sx * (u[order[0]] @ h[0]) + sy * (u[order[1]] @ h[1])
                if score > best:
                    best, out = score, np.stack([sx * steps[order[0]], sy * steps[order[1]]])
    return out


def reference_axes(points: Array, ref: int, mirrored: bool) -> Array:
    """Grid axes of the calibration target from the reference marker's neighbours (seed §2.6.1).

    The closest marker to the reference lies on one axis; the next closest at more than 45° to it
    on the other. Which is T_x follows from right-handedness: the camera is on the +N_z side of the
    pattern, so in pixel coordinates (col, row; row pointing down) a direct view has
    cross(T_x, T_y) < 0 and a view in a mirror cross > 0.

    Returns
    -------
    ndarray, (2, 2)
        Rows: image steps of +T_x and +T_y at the reference.
    """
    d = points - points[ref]
    dist = np.hypot(d[:, 0], d[:, 1])
    dist[ref] = np.inf
    order = np.argsort(dist)
    e1 = d[order[0]]
    e2 = None
    for k in order[1:]:
        if not np.isfinite(dist[k]):
            break
        cosang = (d[k] @ e1) / (dist[k] * dist[order[0]])
        if cosang < np.cos(np.radians(45.0)):
            e2 = d[k]
            break
    if e2 is None:
        raise MarkerError("the reference marker has no second neighbour off its first axis")
    cross = e1[0] * e2[1] - e1[1] * e2[0]
    if (cross < 0) != mirrored:
        return np.stack([e1, e2])
    return np.stack([e2, e1])


# ---------------------------------------------------------------------------------------------
# 4. indexing
# ---------------------------------------------------------------------------------------------
#: Axial neighbour offsets of :func:`_local_basis`: +T_x, -T_x, +T_y, -T_y.
_AXIAL = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]], dtype=np.int64)
_AXIAL_SIGN = np.array([1.0, -1.0, 1.0, -1.0])


def _local_basis(pts: Array, table: NDArray, off: int, ij: NDArray, fallback: Array) -> Array:
    """Local steps of the markers at indices ``ij`` from their indexed axial neighbours.

    a_x is the mean of p[i+1, j] - p[i, j] and p[i, j] - p[i-1, j] where those exist (a_y likewise);
    where neither exists the fallback step is kept. ``table`` must extend at least one index beyond
    every ``ij`` (:func:`index_grid` keeps it so).
    """
    p = pts[table[ij[:, 0] + off, ij[:, 1] + off]]
    nb = ij[:, None, :] + _AXIAL + off  # (m, 4, 2)
    sid = table[nb[..., 0], nb[..., 1]]
    has = sid >= 0
    steps = (pts[sid] - p[:, None, :]) * (_AXIAL_SIGN[:, None] * has[..., None])  # zero where missing
    acc = steps[:, 0::2] + steps[:, 1::2]  # (m, 2 axes, 2)
    cnt = has[:, 0::2].astype(np.float64) + has[:, 1::2]
    got = cnt > 0
    return np.where(got[..., None], acc / np.where(got, cnt, 1.0)[..., None], fallback)


def _grow_table(table: NDArray, off: int) -> tuple[NDArray, int]:
    """The index table with its offset doubled (same entries, more room around them)."""
    new_off = 2 * off
    size = 2 * new_off + 1
    out = np.full((size, size), -1, dtype=table.dtype)
    out[off : off + table.shape[0], off : off + table.shape[1]] = table
    return out, new_off


def index_grid(points: Array, ref: int, axes: Array, tol: float = 0.3, check: float = 0.25) -> NDArray[np.int64]:
    """Index spots relative to the reference marker by a flood over the eight neighbours (seed §1.5.4).

    From each indexed marker the positions of its eight neighbours are predicted with the *local*
    grid steps (a_x, a_y), re-estimated at every marker from its already indexed axial neighbours, so
    the flood follows a grid distorted by a bowed substrate or by perspective. The seed's search
    within r_s = sqrt((1.5 p_x)^2 + (1.5 p_y)^2) and its eight angle classes "with the tilt" become
    the eight predicted positions; as in the seed, the closest candidate of each class is kept, and
    only if it lies within ``tol`` times the shorter local step of the prediction. Claims on one spot
    from several markers go to the closest prediction. The whole frontier is processed at once.

    A final check drops a marker whose position departs from the mean of its two opposite
    neighbours (along either axis) by more than ``check`` times the local step: a spurious blob that
    slipped in where a marker is missing.

    Parameters
    ----------
    points : ndarray, (n, 2)
        Spot centroids (col, row).
    ref : int
        Row of the reference marker in ``points``; it gets index (0, 0).
    axes : ndarray, (2, 2)
        Rows: image steps of +T_x and +T_y at the reference.

    Returns
    -------
    ndarray, (n, 2), int
        (i, j) of each spot; unreached spots get the sentinel ``-2**31``.
    """
    n = len(points)
    none = np.iinfo(np.int32).min
    ij = np.full((n, 2), none, dtype=np.int64)
    if n == 0:
        return ij
    pts = np.asarray(points, dtype=np.float64)
    tree = cKDTree(pts)
    # table of spot rows by index (i + off, j + off); it grows as the flood spreads, always keeping
    # two indices of room beyond every assigned marker (neighbour look-ups go one step further)
    off = 16
    table = np.full((2 * off + 1, 2 * off + 1), -1, dtype=np.int64)
    basis = np.zeros((n, 2, 2))
    assigned = np.zeros(n, dtype=bool)
    ij[ref] = 0
    table[off, off] = ref
    basis[ref] = axes
    assigned[ref] = True
    frontier = np.array([ref])
    offs = NEIGHBOURS.astype(np.float64)
    while frontier.size:
        b = basis[frontier]  # (m, 2, 2) rows a_x, a_y
        pred = pts[frontier][:, None, :] + (
            offs[None, :, 0, None] * b[:, None, 0] + offs[None, :, 1, None] * b[:, None, 1]
        )
        tij = ij[frontier][:, None, :] + NEIGHBOURS[None]
        free = table[tij[..., 0] + off, tij[..., 1] + off] < 0
        step = np.minimum(np.linalg.norm(b[:, 0], axis=1), np.linalg.norm(b[:, 1], axis=1))
        # only predictions of indices still free need a search
        dist = np.full(free.shape, np.inf)
        sid = np.zeros(free.shape, dtype=np.intp)
        dist[free], sid[free] = tree.query(pred[free])
        ok = free & (dist < tol * step[:, None]) & ~assigned[sid]
        par, k = np.nonzero(ok)
        if par.size == 0:
            break
        d, s, t = dist[par, k], sid[par, k], tij[par, k]
        order = np.argsort(d, kind="stable")
        par, k, s, t = par[order], k[order], s[order], t[order]
        _, first_s = np.unique(s, return_index=True)
        keep = np.zeros(len(s), dtype=bool)
        keep[first_s] = True
        key = (t[:, 0] + off) * (2 * off + 1) + (t[:, 1] + off)  # >= 0: never equal to the sentinels below
        _, first_t = np.unique(np.where(keep, key, -1 - np.arange(len(key))), return_index=True)
        keep2 = np.zeros(len(s), dtype=bool)
        keep2[first_t] = True
        keep &= keep2
        par, k, s, t = par[keep], k[keep], s[keep], t[keep]
        while np.abs(t).max() > off - 2:
            table, off = _grow_table(table, off)
        ij[s] = t
        table[t[:, 0] + off, t[:, 1] + off] = s
        assigned[s] = True
        parent = frontier[par]
        fb = basis[parent].copy()
        # keep the parent's steps, corrected by what the step to this marker showed
        resid = pts[s] - pts[parent] - (offs[k, 0, None] * fb[:, 0] + offs[k, 1, None] * fb[:, 1])
        nz = NEIGHBOURS[k] != 0
        share = nz / np.maximum(nz.sum(axis=1, keepdims=True), 1)
        fb += (share * np.sign(NEIGHBOURS[k]))[:, :, None] * resid[:, None, :]
        basis[s] = _local_basis(pts, table, off, t, fb)
        frontier = s
    # consistency check against opposite neighbours
    idx = np.flatnonzero(assigned)
    tt = ij[idx]
    bad = np.zeros(len(idx), dtype=bool)
    size = table.shape[0]
    for axis in (0, 1):
        lo, hi = tt.copy(), tt.copy()
        lo[:, axis] -= 1
        hi[:, axis] += 1
        inside = np.all((lo + off >= 0) & (hi + off < size), axis=1)
        a = np.full(len(idx), -1)
        c = np.full(len(idx), -1)
        a[inside] = table[lo[inside, 0] + off, lo[inside, 1] + off]
        c[inside] = table[hi[inside, 0] + off, hi[inside, 1] + off]
        both = (a >= 0) & (c >= 0)
        mid = 0.5 * (pts[a[both]] + pts[c[both]])
        dev = np.linalg.norm(pts[idx[both]] - mid, axis=1)
        loc = 0.5 * np.linalg.norm(pts[c[both]] - pts[a[both]], axis=1)
        bad[np.flatnonzero(both)[dev > check * loc]] = True
    bad &= idx != ref
    ij[idx[bad]] = none
    return ij


# ---------------------------------------------------------------------------------------------
# all four steps
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Markers:
    """Identified markers of one image.

    Attributes
    ----------
    ij : ndarray, (n, 2), int
        Marker indices on the pattern (DESIGN.md), reference (0, 0).
    centroids : ndarray, (n, 2)
        Raw grey-weighted centroids (col, row), continuous pixel coordinates.
    areas : ndarray, (n,)
        Pixel counts above the threshold.
    peak : ndarray, (n,)
        Peak grey values.
    saturated : ndarray of bool, (n,)
        Peak at the saturation level (the centroid may be biased).
    axes : ndarray, (2, 2)
        Image steps of +T_x, +T_y at the reference marker.
    rejected : int
        Candidate spots not reported (filtered out or not reached by the indexing).
    reasons : dict
        Number of rejected candidates per reason.
    spots : Spots
        All candidates of the centroid search.
    """

    ij: NDArray[np.int64]
    centroids: Array
    areas: NDArray[np.int64]
    peak: Array
    saturated: NDArray[np.bool_]
    axes: Array
    rejected: int
    reasons: dict[str, int]
    spots: Spots

    def __len__(self) -> int:
        return len(self.ij)

    def as_json(self) -> dict:
        """The ``markers`` JSON of DESIGN.md: ``{"markers": [{i, j, col, row, area}], "rejected": n}``."""
        recs = [
            {"i": int(i), "j": int(j), "col": float(c), "row": float(r), "area": int(a), "saturated": bool(s)}
            for (i, j), (c, r), a, s in zip(self.ij, self.centroids, self.areas, self.saturated, strict=True)
        ]
        return {
            "markers": recs,
            "rejected": int(self.rejected),
            "saturated": int(self.saturated.sum()),
            "reasons": dict(self.reasons),
        }


def find_markers(
    image: NDArray,
    layout: str = "deflectometry",
    *,
    hint: Array | None = None,
    mirrored: bool | None = None,
    region: Region | None = None,
    index_range: tuple[tuple[int, int], tuple[int, int]] | None = None,
    threshold: float | None = None,
    saturation: float | None = None,
    area_range: tuple[float, float] = (0.7, 1.4),
    region_margin: float = 0.5,
) -> Markers:
    """Find, filter and index the markers of an image (seed §1.5 and §2.6).

    Parameters
    ----------
    image : ndarray, (rows, cols)
        Camera image (float of any scale, or integer of any bit depth).
    layout : {"deflectometry", "calibration"}
        Deflectometry grid (reference in the centre, axes from the Fourier transform, §1.5.3) or
        calibration target (reference at the -x/-y corner, axes from its neighbours, §2.6.1).
    hint : ndarray, (2, 2), optional
        Approximate image directions of the pattern's +T_x and +T_y (rows), e.g. from
        :func:`expected_axes`. Default (seed §1.5.3): T_x along +col, T_y along -row in a direct view
        and along +row in a mirror view.
    mirrored : bool, optional
        The pattern is seen in a mirror (deflectometry); default: ``layout == "deflectometry"``.
        Decides the calibration grid's x/y assignment by right-handedness.
    region : Region, optional
        Image of the region where markers are reflected whole (:func:`region_for_setup`); spots whose
        rim leaves it by more than ``region_margin`` px are rejected as partially reflected.
    index_range : ((i_min, i_max), (j_min, j_max)), optional
        Indices that exist on the pattern; markers indexed outside are rejected.
    threshold, saturation : float, optional
        See :func:`centroids`.
    area_range : (float, float)
        Accepted area relative to the neighbours' median (§1.5.2).

    Raises
    ------
    MarkerError
        Bad or blank image, no reference marker, two equally large reference candidates, no grid.
    """
    if layout not in ("deflectometry", "calibration"):
        raise MarkerError(f"layout must be 'deflectometry' or 'calibration', got {layout!r}")
    mirrored = (layout == "deflectometry") if mirrored is None else bool(mirrored)
    spots = centroids(image, threshold=threshold, saturation=saturation)
    filt = filter_spots(spots, np.shape(image), region=region, area_range=area_range, region_margin=region_margin)
    keep = np.flatnonzero(filt.keep)
    if len(keep) < 3:
        raise MarkerError(f"too few markers left after filtering ({len(keep)})")
    pts = spots.centroids[keep]
    ref = int(np.flatnonzero(keep == filt.reference)[0])
    if layout == "calibration":
        axes = reference_axes(pts, ref, mirrored)
    else:
        h = hint if hint is not None else np.array([[1.0, 0.0], [0.0, 1.0 if mirrored else -1.0]])
        steps = fourier_axes(image, pts[ref], nearest_spacing(pts))
        axes = orient_axes(steps, np.asarray(h, dtype=np.float64))
    ij = index_grid(pts, ref, axes)
    found = ij[:, 0] != np.iinfo(np.int32).min
    reasons = dict(filt.reasons)
    reasons["not_indexed"] = int((~found).sum())
    if index_range is not None:
        (i0, i1), (j0, j1) = index_range
        inside = (ij[:, 0] >= i0) & (ij[:, 0] <= i1) & (ij[:, 1] >= j0) & (ij[:, 1] <= j1)
        reasons["index_range"] = int((found & ~inside).sum())
        found &= inside
    sel = keep[found]
    return Markers(
        ij=ij[found],
        centroids=spots.centroids[sel],
        areas=spots.areas[sel],
        peak=spots.peak[sel],
        saturated=spots.saturated[sel],
        axes=axes,
        rejected=len(spots) - len(sel),
        reasons=reasons,
        spots=spots,
    )


# ---------------------------------------------------------------------------------------------
# what a setup tells about its image (nominal geometry: a flat substrate or mirror in z = 0)
# ---------------------------------------------------------------------------------------------
def _seen_points(setup: Setup, points: Array) -> Array:
    """Pixel coordinates of pattern points seen directly (target) or in the plane mirror z = 0."""
    cam = setup.camera_model
    if setup.scene == "target":
        return cam.project(points)
    return cam.project(points * np.array([1.0, 1.0, -1.0]))


def expected_axes(setup: Setup) -> Array:
    """Image steps of the pattern's +T_x and +T_y at the reference marker, from the nominal setup.

    The reflecting element is taken as the flat plane z = 0 (the substrate's base plane, §1.10), so
    this is the seed's coarse axis estimate made exact for an unbent substrate.
    """
    pat = setup.marker_pattern
    px = _seen_points(setup, pat.centers(np.array([[0, 0], [1, 0], [0, 1]])))
    return np.stack([px[1] - px[0], px[2] - px[0]])


def region_for_setup(setup: Setup, heights: HeightMap | None = None, per_side: int = 8) -> Region | None:
    """Image of the region where markers are reflected whole.

    Deflectometry: the substrate's region of interest (|x| <= size_x/2, |y| < roi_length/2, §1.6.4);
    mirror: the mirror; calibration target: None (the markers lie on the target itself). The outline
    lies on the surface: points (x, y, h(x, y)) with ``heights`` (a current surface estimate or the
    truth), else on the flat base plane z = 0, where the seed's 40 µm bow moves the outline's image by
    up to ~0.7 px. Each side is sampled with ``per_side`` points so lens distortion bends it correctly.
    """
    if setup.scene == "target":
        return None
    if setup.scene == "deflectometry":
        assert setup.substrate is not None
        hx, hy = 0.5 * setup.substrate.size[0], 0.5 * setup.substrate.roi_length
    else:
        assert setup.mirror is not None
        hx, hy = 0.5 * setup.mirror.size[0], 0.5 * setup.mirror.size[1]
    t = np.linspace(0.0, 1.0, per_side, endpoint=False)
    corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    sides = [corners[k] + t[:, None] * (corners[(k + 1) % 4] - corners[k]) for k in range(4)]
    outline = np.concatenate(sides)
    z = (
        np.zeros(len(outline))
        if heights is None or setup.scene != "deflectometry"
        else heights.height(outline[:, 0], outline[:, 1])
    )
    pts = np.concatenate([outline, z[:, None]], axis=1)
    px = setup.camera_model.project(pts)
    if not np.all(np.isfinite(px)):
        raise MarkerError("the reflecting region is not in front of the camera")
    return Region(px)


def index_range(setup: Setup) -> tuple[tuple[int, int], tuple[int, int]]:
    """Smallest and largest marker index along T_x and T_y of a setup's pattern."""
    ij = setup.marker_pattern.indices()
    return (int(ij[:, 0].min()), int(ij[:, 0].max())), (int(ij[:, 1].min()), int(ij[:, 1].max()))


def find_markers_for(image: NDArray, setup: Setup, heights: HeightMap | None = None, **kwargs) -> Markers:
    """:func:`find_markers` with layout, axis hint, view, region and index range from a setup.

    ``heights`` (a surface estimate) places the region's outline on the bent surface
    (:func:`region_for_setup`); keyword arguments override any option.
    """
    opts = dict(
        layout=setup.marker_pattern.layout,
        hint=expected_axes(setup),
        mirrored=setup.scene != "target",
        region=region_for_setup(setup, heights),
        index_range=index_range(setup),
    )
    opts.update(kwargs)
    return find_markers(image, **opts)
