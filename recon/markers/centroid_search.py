"""Centroid search of marker identification (thesis §1.5.1; the same search serves the calibration grid, §2.6).

:func:`centroids` estimates the background level and noise from the image (:func:`background_level`), thresholds
it, labels connected components (OpenCV) and takes the grey-value-weighted centre of mass of each spot
(:class:`Spots`). The centroid is the first moment of the *whole* spot: pixels above the threshold define the spot,
and its window is grown by a few pixels so the faint rim below the threshold is weighted too (weights: grey value
minus background). That makes the centroid independent of the threshold and equal, up to pixel sampling, to the
continuous first moment of the spot's irradiance — the quantity that :mod:`scopetwin.recon.bias` predicts from a model.

Coordinates are continuous pixel coordinates (col, row): pixel (r, c) covers [c, c+1) x [r, r+1)
(docs/contract.md, "Camera").
:class:`MarkerError`, raised by every step of :mod:`scopetwin.recon.markers`, is defined here, with the first step.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

import cv2
import numpy as np
from numpy.typing import DTypeLike, NDArray

from scopetwin.scenes.errors import ScopetwinError

Array = NDArray[np.float64]

#: Variance along an axis of a cone spot g = 1 - r/R over the disk of radius R, in units of R^2:
#: (int r^3 cos^2 g dr dphi) / (int r g dr dphi) = (pi R^4 / 20) / (pi R^2 / 3).
CONE_VARIANCE = 0.15


class MarkerError(ScopetwinError, ValueError):
    """An image in which markers cannot be identified; the message says why."""


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
    thesis's images); the noise sigma starts from the scaled median absolute deviation of the samples below
    it (the dark side, which holds no marker light); then level and sigma are the mean and standard deviation
    of the samples within 3.5 sigma, three times. A standard deviation, not a MAD: on an integer
    (ADC) image of ~2 DN dark noise the MAD of integers reads 1 DN, so sigma came out 1.48 DN for a true
    2.2 DN, the 6-sigma threshold sat at 4 sigma and a low exposure filled the image with noise blobs that
    ate into the marker windows.
    """
    sub = image[stride // 2 :: stride, stride // 2 :: stride].ravel().astype(np.float64)
    med = float(np.median(sub))
    low = sub[sub <= med]
    sigma = 1.4826 * float(np.median(med - low)) if low.size else 0.0
    if sigma > 0:
        near = sub[np.abs(sub - med) <= 3.0 * sigma]
        med = float(near.mean()) if near.size else med
    if sigma == 0 and low.size:  # more than half the samples equal: the MAD is 0 even when the rest is noisy
        dev = med - low[low < med]
        sigma = float(np.sqrt(np.mean(dev * dev))) if dev.size else 0.0
    for _ in range(3):
        if not sigma > 0:
            break
        near = sub[np.abs(sub - med) <= 3.5 * sigma]
        if near.size < 2:
            break
        med = float(near.mean())
        sigma = float(near.std() / 0.9938)  # standard deviation of a normal distribution cut at +-3.5 sigma
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


def _drop_fragments(labels: NDArray, n: int, fraction: float) -> tuple[NDArray, int]:
    """Labels without the fragments: components under ``fraction`` of the 90th-percentile area, or under 2 px.

    At a low exposure photon noise breaks isolated pixels off a spot's faint rim. As separate components
    their grown windows took rim pixels from the spot beside them (the window image is a dilation, which
    keeps the larger label), and the spot's centroid moved by up to 1 px (at 2 % of the full
    well). Without their labels those pixels fall in the spot's own window and count for it.
    """
    areas = np.bincount(labels.ravel(), minlength=n)[1:]
    if areas.size == 0:
        return labels, n
    limit = max(2.0, fraction * float(np.percentile(areas, 90)))
    small = areas < limit
    if not small.any() or small.all():
        return labels, n
    lut = np.zeros(n, dtype=np.int32)
    lut[1:][~small] = np.arange(1, int((~small).sum()) + 1, dtype=np.int32)
    return lut[labels], int((~small).sum()) + 1


class _Scratch(threading.local):
    """Per-thread work buffers of the centroid search, reused from frame to frame.

    Fresh large arrays cost page faults on every call (the allocator hands freed memory back to
    the system); with ~20 pixel-list arrays of a few MB per frame that was half of the centroid
    search's time. Each buffer grows to the largest size asked for and is then kept.
    """

    def __init__(self) -> None:
        self.buffers: dict[str, NDArray] = {}

    def get(self, name: str, shape: tuple[int, ...] | int, dtype: DTypeLike) -> NDArray:
        """A C-contiguous array of ``shape`` and ``dtype`` (uninitialised) backed by the named buffer."""
        shape = (shape,) if isinstance(shape, int) else tuple(shape)
        size = int(np.prod(shape))
        buf = self.buffers.get(name)
        if buf is None or buf.dtype != np.dtype(dtype) or buf.size < size:
            buf = self.buffers[name] = np.empty(size + size // 4, dtype=dtype)
        return buf[:size].reshape(shape)


_scratch = _Scratch()


def _spot_threshold(
    top: float, level: float, sigma: float, threshold: float | None, relative_threshold: float, noise_sigmas: float
) -> float:
    """The spot threshold: given, or from the background noise and the peak; a blank image raises."""
    if threshold is None:
        if not top > level + max(noise_sigmas * sigma, 1e-12 * max(abs(level), 1.0)):
            raise MarkerError("image is blank: no pixel stands out of the background")
        threshold = level + max(noise_sigmas * sigma, relative_threshold * (top - level))
    if not top > threshold:
        raise MarkerError(f"image is blank: no pixel exceeds the threshold {threshold:.6g}")
    return threshold


def _label_spots(
    img: NDArray[np.float32], threshold: float, connectivity: int, fragment_fraction: float
) -> tuple[NDArray[np.uint8], tuple[int, int, int, int], NDArray, int]:
    """Threshold mask, bounding box (x, y, w, h) of the spots, and their labels within the box (no fragments)."""
    ny, nx = img.shape
    # OpenCV takes a scalar as the second operand; its stubs list arrays only
    mask = cv2.compare(img, float(threshold), cv2.CMP_GT, dst=_scratch.get("mask", (ny, nx), np.uint8))  # type: ignore[call-overload]
    # all work below happens in the bounding box of the spots, grown by the window margin
    bx, by, bw, bh = cv2.boundingRect(mask)
    if bw == 0 or bh == 0:
        raise MarkerError("image is blank: no spot found")
    n, labels = cv2.connectedComponents(mask[by : by + bh, bx : bx + bw], connectivity=connectivity, ltype=cv2.CV_32S)
    if n <= 1:
        raise MarkerError("image is blank: no spot found")
    labels, n = _drop_fragments(labels, n, fragment_fraction)
    return mask, (bx, by, bw, bh), labels, n


def _default_grow(threshold: float, level: float, top: float, labels: NDArray, n: int) -> int:
    """Window margin reaching the rim of a cone spot of twice the mean area (the reference marker), plus 1.5 px."""
    frac = (threshold - level) / max(top - level, 1e-300)
    r_eq = np.sqrt(2.0 * cv2.countNonZero(labels) / (n - 1) / np.pi)
    return int(np.ceil(frac / max(1.0 - frac, 1e-3) * r_eq + 1.5))


@dataclass
class _Window:
    """The pixels of the spots' windows as flat lists in raster order (views of the scratch buffers)."""

    idx: NDArray[np.intp]
    lab: NDArray[np.intp]
    values: Array
    inside: NDArray[np.bool_]
    rows: NDArray[np.intp]
    x: Array
    w: Array
    flags: NDArray[np.uint8]
    mask_c: NDArray[np.uint8]
    shape: tuple[int, int]
    r0: int


@dataclass
class _Runs:
    """Sums over the runs of :func:`_run_sums`: weight, x moments, pixels above threshold, peak, boundary weight."""

    starts: NDArray[np.intp]
    w: Array
    wx: Array
    wxx: Array
    inside: Array
    peak: Array
    edge: Array


def _window_labels(
    labels: NDArray, n: int, box: tuple[int, int, int, int], corner: tuple[int, int], shape: tuple[int, int], grow: int
) -> NDArray:
    """The label image over the crop at ``corner`` (r0, c0), dilated by ``grow``: each spot's window."""
    bx, by, bw, bh = box
    r0, c0 = corner
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
    return win


def _window_pixels(
    img: NDArray[np.float32],
    mask: NDArray[np.uint8],
    box: tuple[int, int, int, int],
    labels: NDArray,
    n: int,
    grow: int,
    level: float,
) -> _Window:
    """Gather the pixels of every spot's window (the spot grown by ``grow`` px) into flat lists (reused buffers)."""
    ny, nx = img.shape
    bx, by, bw, bh = box
    r0, r1 = max(by - grow, 0), min(by + bh + grow, ny)
    c0, c1 = max(bx - grow, 0), min(bx + bw + grow, nx)
    shape = (r1 - r0, c1 - c0)
    win = _window_labels(labels, n, box, (r0, c0), shape, grow)
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
    return _Window(idx, lab, values, inside, rows, x, w, flags, mask_c, shape, r0)


def _boundary_weights(win: _Window, out: Array) -> Array:
    """``out`` holding the weights of the threshold-boundary pixels (a 4-neighbour below the threshold), else 0."""
    # outside the box: below the threshold
    eroded = cv2.erode(
        win.mask_c,
        cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3)),
        borderValue=0,
        dst=_scratch.get("eroded", win.shape, np.uint8),
    )
    m = win.idx.size
    bnd = np.equal(
        np.take(eroded.ravel(), win.idx, out=win.flags, mode="clip"), 0, out=_scratch.get("bnd", m, np.bool_)
    )
    bnd &= win.inside
    out.fill(0.0)
    np.copyto(out, win.w, where=bnd)
    return out


def _run_sums(win: _Window) -> _Runs:
    """Sums along runs: stretches of one label within one image row (the lists are in raster order).

    y is constant along a run, so only the x moments need per-pixel sums.
    """
    lab, rows, w, x = win.lab, win.rows, win.w, win.x
    m = win.idx.size
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
    np.copyto(tmp, win.inside)
    run_in = np.add.reduceat(tmp, runs)
    tmp.fill(-np.inf)
    np.copyto(tmp, win.values, where=win.inside)
    run_peak = np.maximum.reduceat(tmp, runs)
    run_edge = np.maximum.reduceat(_boundary_weights(win, tmp), runs)
    return _Runs(runs, run_w, run_wx, run_wxx, run_in, run_peak, run_edge)


def _spot_sums(
    win: _Window, runs: _Runs, n: int, level: float
) -> tuple[NDArray[np.int64], Array, Array, Array, Array, Array]:
    """Per label, summed over its runs: area, mass, centroid (cx, cy), covariance, peak, relative boundary value."""
    rl = win.lab[runs.starts]
    ry = win.rows[runs.starts] + (win.r0 + 0.5)
    areas = np.bincount(rl, weights=runs.inside, minlength=n).astype(np.int64)
    mass = np.asarray(np.bincount(rl, weights=runs.w, minlength=n), dtype=np.float64)  # weighted: float64
    safe = np.where(mass > 0, mass, 1.0)
    cx = np.bincount(rl, weights=runs.wx, minlength=n) / safe
    cy = np.bincount(rl, weights=runs.w * ry, minlength=n) / safe
    sxx = np.bincount(rl, weights=runs.wxx, minlength=n) / safe - cx * cx
    syy = np.bincount(rl, weights=runs.w * ry * ry, minlength=n) / safe - cy * cy
    sxy = np.bincount(rl, weights=runs.wx * ry, minlength=n) / safe - cx * cy
    cov = np.stack([np.stack([sxx, sxy], -1), np.stack([sxy, syy], -1)], -2)
    peak = np.full(n, -np.inf)
    np.maximum.at(peak, rl, runs.peak)
    edge = np.zeros(n)
    np.maximum.at(edge, rl, runs.edge)
    edge = edge / np.maximum(peak - level, 1e-300)
    return areas, mass, np.stack([cx, cy], axis=-1), cov, peak, edge


def centroids(
    image: NDArray,
    threshold: float | None = None,
    background: float | None = None,
    connectivity: int = 8,
    grow: int | None = None,
    saturation: float | None = None,
    relative_threshold: float = 0.08,
    noise_sigmas: float = 6.0,
    fragment_fraction: float = 0.03,
) -> Spots:
    """Centroid search of thesis §1.5.1: connected pixels above a threshold, grey-weighted centre of mass.

    r_s = (1/G) sum_i g_i r_i, G = sum_i g_i (thesis §1.5.1), with g_i the grey value minus the
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
    fragment_fraction : float
        Components smaller than this fraction of the 90th-percentile area (and than 2 px) are fragments,
        not spots (:func:`_drop_fragments`).

    Raises
    ------
    MarkerError
        Bad image (see :func:`check_image`) or a blank image (no contrast).
    """
    img = check_image(image)
    level, sigma = background_level(img) if background is None else (float(background), 0.0)
    top = float(img.max())
    threshold = _spot_threshold(top, level, sigma, threshold, relative_threshold, noise_sigmas)
    mask, box, labels, n = _label_spots(img, threshold, connectivity, fragment_fraction)
    if grow is None:  # reach the rim of a spot twice the mean area (the reference marker)
        grow = _default_grow(threshold, level, top, labels, n)
    win = _window_pixels(img, mask, box, labels, n, int(max(grow, 0)), level)
    areas, mass, cen, cov, peak, edge = _spot_sums(win, _run_sums(win), n, level)
    sat_level = _saturation_level(image, saturation, top if np.asarray(image) is img else None)
    s = slice(1, None)
    ok = mass[s] > 0
    return Spots(
        centroids=cen[s][ok],
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
