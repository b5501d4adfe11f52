"""Bias-corrected one-shot calibration: calibrate, predict the centroid bias, correct, calibrate again (§2.8.2).

:func:`calibrate_bias_corrected` alternates :func:`~scopetwin.calib.oneshot.calibration.calibrate` and a centroid-bias
prediction until the parameters stop changing. The prediction is the centroid-bias model of :mod:`scopetwin.recon.bias`:
:func:`scopetwin.recon.bias.spot_bias_model` for a planar target (the spot centroid as the pixels see it,
thesis §1.5.1).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike

from scopetwin.calib.oneshot.calibration import calibrate, with_notes
from scopetwin.calib.oneshot.camera_parameters import (
    CalibrationError,
    CalibrationWarning,
    LensMode,
    Prior,
)
from scopetwin.calib.oneshot.refinement import Calibration
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array


def calibrate_bias_corrected(
    xy: ArrayLike,
    centroids_px: ArrayLike,
    prior: Prior,
    predict_bias: Callable[[Camera], Array],
    lens: LensMode = "auto",
    distortion: bool = False,
    b: float | None = None,
    tol_px: float = 1e-5,
    max_iter: int = 10,
) -> tuple[Calibration, Array, int]:
    """Alternate calibration and centroid-bias correction until the parameters stop changing.

    Parameters
    ----------
    xy : array_like (n, 2)
        Marker centres in target coordinates, mm.
    centroids_px : array_like (n, 2)
        Measured (biased) centroids, continuous px.
    predict_bias : callable
        ``predict_bias(camera) -> (n, 2)``: centroid minus image of the marker centre that the
        current camera predicts for each marker, px.
    tol_px : float
        Stop when the predicted marker images move less than this between two rounds, px.

    Returns
    -------
    calibration, bias_px, rounds
        The final calibration, the last bias estimate and the number of correction rounds.
    """
    c = np.asarray(centroids_px, dtype=np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)
        return _bias_loop(xy, c, prior, predict_bias, lens, distortion, b, tol_px, max_iter)


def _bias_loop(
    xy: ArrayLike,
    c: Array,
    prior: Prior,
    predict_bias: Callable[[Camera], Array],
    lens: LensMode,
    distortion: bool,
    b: float | None,
    tol_px: float,
    max_iter: int,
) -> tuple[Calibration, Array, int]:
    cal = calibrate(xy, c, prior, lens, distortion, b)
    X = np.column_stack([np.asarray(xy, dtype=np.float64)[:, :2], np.zeros(len(c))])
    bias = np.zeros_like(c)
    for rounds in range(1, max_iter + 1):
        bias = np.asarray(predict_bias(cal.camera), dtype=np.float64)
        if bias.shape != c.shape or not np.all(np.isfinite(bias)):
            raise CalibrationError("the centroid-bias model returned an unusable correction")
        new = calibrate(xy, c - bias, prior, lens, distortion, b)
        move = float(np.max(np.abs(new.camera.project(X) - cal.camera.project(X))))
        cal = new
        if move < tol_px:
            return cal, bias, rounds
    return with_notes(cal, cal.linear, [f"bias correction did not settle within {max_iter} rounds"]), bias, max_iter
