"""One-shot calibration from a camera image of a target (thesis ch. 2): markers found and indexed (§2.6), their
centroid bias corrected (§2.8.2), the linear approximation and the refinement (§2.4-§2.5).

The one path from an image to a :class:`~scopetwin.calib.oneshot.refinement.Calibration`: ``scopetwin calibrate``
and :func:`scopetwin.calibrate` both call :func:`calibrate_image`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.calib.oneshot.bias_correction import calibrate_bias_corrected
from scopetwin.calib.oneshot.calibration import calibrate
from scopetwin.calib.oneshot.camera_parameters import CalibrationError, LensMode, Prior
from scopetwin.calib.oneshot.refinement import Calibration
from scopetwin.scenes.setup import Setup

#: Fewest indexed markers a one-shot calibration is attempted with (the linear approximation of §2.4 needs six).
MIN_MARKERS = 6


def target_prior(setup: Setup, focal_length: float | None = None, **changes: Any) -> Prior:
    """The a-priori camera values of a ``target`` scene (thesis §2.1): format, pitch, focal length, N_z in the
    target's coordinates; ``changes`` override fields (``pitch``, ``nz_estimate``, ``image_distance``)."""
    f = focal_length if focal_length is not None else setup.camera.focal_length
    return Prior.from_camera(setup.camera_model, f, plane=setup.marker_pattern.frame, **changes)


def calibrate_image(
    image: NDArray[Any],
    setup: Setup,
    *,
    prior: Prior | None = None,
    focal_length: float | None = None,
    lens: LensMode = "auto",
    distortion: bool = False,
    image_distance: float | None = None,
    bias_correction: bool = True,
    name: str = "the image",
) -> tuple[Calibration, Any]:
    """Calibrate the camera from one image of the target of ``setup`` (thesis §2.4-§2.5, bias-corrected §2.8.2).

    Parameters
    ----------
    image : ndarray, (rows, cols)
        The camera image of the target.
    setup : Setup
        A ``target`` scene: the target's markers and pose; its camera gives the a-priori values.
    prior : Prior, optional
        A-priori values (default: :func:`target_prior` of the setup with ``focal_length``).
    focal_length : float, optional
        A-priori focal length, mm (default: the setup camera's).
    lens, distortion, image_distance
        As in :func:`scopetwin.calib.oneshot.calibration.calibrate` (``image_distance``: its ``b``).
    bias_correction : bool
        Correct the markers' centroid bias (default).
    name : str
        How error messages name the image (e.g. its path).

    Returns
    -------
    calibration : Calibration
        The calibrated camera with residuals and uncertainties.
    markers : Markers
        The indexed markers it rests on.

    Raises
    ------
    CalibrationError
        A setup that is not a target scene, an image whose format is not the camera's, fewer than
        :data:`MIN_MARKERS` markers, or a calibration that fails.
    """
    from scopetwin.recon.bias import spot_bias_model
    from scopetwin.recon.markers import find_markers_for

    if setup.scene != "target":
        raise CalibrationError(f"setup {setup.name} is a {setup.scene} scene, not a calibration target")
    prior = prior if prior is not None else target_prior(setup, focal_length)
    if np.shape(image) != (prior.ny, prior.nx):
        shape = np.shape(image)
        raise CalibrationError(
            f"{name} has {shape[1]} x {shape[0]} pixels but the setup's camera has {prior.nx} x {prior.ny}"
        )
    found = find_markers_for(image, setup)
    if len(found) < MIN_MARKERS:
        raise CalibrationError(f"{name}: only {len(found)} markers were found and indexed")
    pattern = setup.marker_pattern
    xy = pattern.centers_local(found.ij)
    kw: dict[str, Any] = {"lens": lens, "distortion": distortion, "b": image_distance}
    if not bias_correction:
        return calibrate(xy, found.centroids, prior, **kw), found
    bias = spot_bias_model(xy, pattern.radii(found.ij))
    return calibrate_bias_corrected(xy, found.centroids, prior, bias, **kw)[0], found


__all__ = ["MIN_MARKERS", "calibrate_image", "target_prior"]
