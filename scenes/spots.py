"""Spot and aberration metrics shared by the GRIN objectives (thesis ch. 7-8) and the microscope unit (ch. 5).

Both analyses trace a bundle of rays from one object point through a pupil sampled on a square grid clipped to
the unit disk, and read the bundle on an image plane:

* :func:`pupil_disk` -- the pupil sampling (Zemax's "rectangular" grid);
* :func:`rms_radius` -- the RMS spot radius about the centroid of the surviving rays (thesis §8.3, §5.1.2);
* :func:`airy_radius` -- the first dark ring of the diffraction-limited spot, 0.61 lambda / NA (= 1.22 lambda N).

Each analysis keeps its own ray model (GRIN: :mod:`scopetwin.scenes.grin.rkn`; CMU: :mod:`scopetwin.scenes.cmu.trace`)
and its
closed-form refocus (``best_focus``: the mean-square radius of straight rays is quadratic in the image distance);
the two sum the moments in different orders (per axis / per ray), and one shared form would move the recorded
figures in their last digits.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

Array = NDArray[np.float64]


def pupil_disk(n: int) -> tuple[Array, Array]:
    """Square grid of n x n points on [-1, 1]^2 clipped to the unit disk (uniform pupil sampling)."""
    g = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    px, py = np.meshgrid(g, g)
    keep = px * px + py * py <= 1.0
    return px[keep], py[keep]


def rms_radius(x: Array, y: Array) -> float:
    """RMS distance of the spot points (x, y) from their centroid; NaN for an empty spot."""
    if x.size == 0:
        return float("nan")
    return float(np.sqrt(np.mean((x - x.mean()) ** 2 + (y - y.mean()) ** 2)))


def airy_radius(wavelength_nm: float, na: float) -> float:
    """Radius of the Airy disk's first dark ring, 0.61 lambda / NA, mm (``na``: the NA on that side)."""
    return 0.61 * wavelength_nm * 1e-6 / na
