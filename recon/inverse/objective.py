"""The loss of the inverse fit and its terms (package docstring)::

    sum_p (I_p - alpha*R_p(c) - beta)^2 / var_p  +  lambda * |D c|^2,   mean_ROI(h) = H

the pixel variances var_p (EMVA 1288, :mod:`scopetwin.scenes.emva1288`), the photometric gain and offset (alpha,
beta) solved in closed form, the weight lambda of the thin-plate prior and the row of the held mean ROI height H
(the frame criterion's start height, thesis §1.4).
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from scopetwin.recon.spline import SplineSurface
from scopetwin.recon.substrate import Substrate2D
from scopetwin.scenes.geometry import Array
from scopetwin.scenes.setup import Setup


def pixel_variance(image: Array, setup: Setup, mode: str = "auto") -> Array:
    """EMVA 1288 variance of each pixel of a camera image in DN, or ones for a noise-free render (irradiance).

    var = K^2 sigma_d^2 + K max(I - black, 0) + 1/12 (shot noise, dark noise, quantisation; the EMVA linear model of
    :mod:`scopetwin.scenes.emva1288`). ``mode`` "auto": the EMVA variance when the image peak exceeds 2 (digital
    numbers).
    """
    img = np.asarray(image, dtype=np.float64)
    use = mode == "emva" or (mode == "auto" and float(np.max(img)) > 2.0)
    if not use:
        return np.ones_like(img)
    s = setup.sensor.sensor()
    k = s.gain_dn_per_e
    return k * k * s.dark_noise_e**2 + k * np.maximum(img - s.black_level_dn, 0.0) + 1.0 / 12.0


def photometric(vals: Array, data: Array, w: Array) -> tuple[float, float]:
    """Gain and offset (alpha, beta) minimising sum w (data - alpha vals - beta)^2."""
    a = np.stack([vals, np.ones_like(vals)], axis=1)
    sw = np.sqrt(w)
    sol, *_ = np.linalg.lstsq(a * sw[:, None], data * sw, rcond=None)
    return float(sol[0]), float(sol[1])


def prior_weight(smoothness: float, info: sp.spmatrix, dtd: sp.spmatrix) -> float:
    """The thin-plate prior's weight lambda: ``smoothness`` relative to the mean diagonals of J^T W J and D^T D."""
    return smoothness * float(info.diagonal().mean()) / max(float(dtd.diagonal().mean()), 1e-300)


def mean_row(surf: SplineSurface, sub: Substrate2D) -> Array:
    """The row m of the mean ROI height the fit holds: m @ c is the mean of ``surf`` over the ROI's grid."""
    xs, ys = sub.roi_grid(max(surf.dx, 0.5))
    return np.asarray(surf.design(xs, ys).mean(axis=0)).ravel()
