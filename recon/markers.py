"""Marker identification in camera images (seed §1.5, §2.6).

So far: the centroid search of §1.5.1 (threshold, connected components,
grey-value-weighted centre of mass). Filtering, grid identification and
indexing build on it.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from scenes.errors import ScopetwinError


class MarkerError(ScopetwinError, ValueError):
    """An image in which markers cannot be identified; the message says why."""


@dataclass(frozen=True)
class Spots:
    """Bright spots of an image.

    Attributes
    ----------
    centroids : ndarray, (n, 2)
        Grey-weighted centres (col, row) in continuous pixel coordinates
        (pixel (r, c) covers [c, c+1) x [r, r+1), DESIGN.md).
    areas : ndarray, (n,)
        Pixel count of each spot.
    mass : ndarray, (n,)
        Sum of the grey values (above the background) of each spot.
    peak : ndarray, (n,)
        Largest grey value of each spot.
    """

    centroids: NDArray[np.float64]
    areas: NDArray[np.int64]
    mass: NDArray[np.float64]
    peak: NDArray[np.float64]


def _check_image(image: NDArray) -> NDArray[np.float64]:
    img = np.asarray(image)
    if img.ndim != 2:
        raise MarkerError(f"image must be 2-D (rows, cols), got shape {img.shape}")
    if not (np.issubdtype(img.dtype, np.floating) or np.issubdtype(img.dtype, np.integer)):
        raise MarkerError(f"image must be numeric, got dtype {img.dtype}")
    img = img.astype(np.float64)
    if not np.all(np.isfinite(img)):
        raise MarkerError("image contains NaN or infinite values")
    return img


def centroids(image: NDArray, threshold: float, background: float = 0.0, connectivity: int = 8) -> Spots:
    """Centroid search of seed §1.5.1: connected pixels above ``threshold``, grey-weighted centre of mass.

    r_s = (1/G) sum_i g_i r_i with G = sum_i g_i over the N pixels of a spot; the weights
    are the grey values minus ``background``. Connected components are found with OpenCV.

    Parameters
    ----------
    image : ndarray, (rows, cols)
        Grey values (any numeric dtype).
    threshold : float
        A pixel belongs to a spot when its value exceeds this.
    background : float
        Level subtracted from the grey values before weighting.
    connectivity : {4, 8}
        Pixel neighbourhood.
    """
    img = _check_image(image)
    mask = (img > threshold).astype(np.uint8)
    n, labels = cv2.connectedComponents(mask, connectivity=connectivity, ltype=cv2.CV_32S)
    if n <= 1:
        empty = np.zeros((0, 2))
        return Spots(empty, np.zeros(0, dtype=np.int64), np.zeros(0), np.zeros(0))
    lab = labels.ravel()
    sel = lab > 0
    lab = lab[sel]
    w = (img.ravel() - background)[sel]
    rows, cols = np.divmod(np.flatnonzero(sel), img.shape[1])
    mass = np.bincount(lab, weights=w, minlength=n)[1:]
    cx = np.bincount(lab, weights=w * (cols + 0.5), minlength=n)[1:] / mass
    cy = np.bincount(lab, weights=w * (rows + 0.5), minlength=n)[1:] / mass
    areas = np.bincount(lab, minlength=n)[1:]
    peak = np.full(n, -np.inf)
    np.maximum.at(peak, lab, img.ravel()[sel])
    return Spots(np.stack([cx, cy], axis=-1), areas.astype(np.int64), mass, peak[1:])
