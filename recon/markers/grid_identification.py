"""Grid identification: the image steps of the marker grid's axes (thesis §1.5.3 deflectometry, §2.6.1 calibration).

:func:`fourier_axes` finds the two lattice steps of the deflectometry grid from the Fourier transform of the image
around the reference marker (§1.5.3), and :func:`orient_axes` assigns them to the pattern's +T_x and +T_y with a hint;
:func:`reference_axes` takes the calibration target's axes from the reference marker's neighbours (§2.6.1).
"""

from __future__ import annotations

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from scopetwin.recon.markers.centroid_search import Array, MarkerError


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
    return np.asarray(np.linalg.inv(recip).T, dtype=np.float64)


def orient_axes(steps: Array, hint: Array) -> Array:
    """Assign two unordered, unsigned grid steps to the pattern's +T_x, +T_y (rows of ``hint``).

    Of the eight orderings and sign choices, the one most parallel to the hint (image directions of
    +T_x and +T_y at the reference, e.g. from :func:`expected_axes` or the thesis's "x-axis almost
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
    """Grid axes of the calibration target from the reference marker's neighbours (thesis §2.6.1).

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
