"""One-shot camera calibration from ONE image of a planar marker target (thesis chapter 2).

Two steps, as in the thesis, each in a module named after its section:

1. :mod:`scopetwin.calib.oneshot.linear` — :func:`linear_approximation` (§2.4): the affine model u = A x + B y + C,
   v = D x + E y + F fitted by least squares, then principal point, magnification (complex square root,
   eqs. 2.23-2.29, both equations), T_x, T_y, N_z (sign s chosen by the coarse N_z estimate), b from the thin-lens
   equation, g, r_c and the tilt angle phi.
2. :mod:`scopetwin.calib.oneshot.refinement` — :func:`refine` (§2.5): the reprojection error of the pinhole model of
   :mod:`scopetwin.scenes.camera` (:mod:`scopetwin.calib.oneshot.reprojection`, §2.5.1-2.5.3) minimised over
   p = (r_c, r_0, phi) [, b] [, r_cs, c0, c2] with :func:`scipy.optimize.least_squares` (Levenberg-Marquardt,
   analytic Jacobian: the per-marker chain rule is written out, the 7-parameter frame map of §2.5.2 is
   differentiated by complex step, which is exact to round-off), and the parameter covariance.

:mod:`scopetwin.calib.oneshot.calibration` runs both (:func:`calibrate`);
:mod:`scopetwin.calib.oneshot.bias_correction` alternates
calibration and the centroid-bias correction of :mod:`scopetwin.recon.bias` (:func:`calibrate_bias_corrected` with
:func:`scopetwin.recon.bias.spot_bias_model`);
:mod:`scopetwin.calib.oneshot.camera_parameters` holds the a-priori values (:class:`Prior`, §2.1) and the derived camera
parameters (§2.3). This package's namespace is that public API.

Image distance b: ``lens="thin-lens"`` derives b = g f/(g - f) from the focal length as the thesis does (§2.5.2);
``lens="free"`` estimates b as a parameter (it is determined only when the target is seen obliquely: a face-on view
fixes b/g alone); ``lens="fixed"`` keeps an a-priori b; ``lens="auto"`` holds b at a candidate: the a-priori b
where the prior has one (the image distance the camera's description states, :meth:`Prior.from_camera`) and the
thin-lens relation b = f (m + 1) with the measured magnification agrees with it, else that thin-lens b; it
estimates b freely instead when the view is oblique enough and the data, at their own noise, reject the candidate
(the thin-lens b assumes the target in focus, which costs ~10 µm of r_c along the axis when the
target lies 0.1 mm off the focus plane; a free b scatters by 6-23 µm at realistic sensor noise), and a kept
candidate's uncertainty (the focal length's tolerance, given the data) enters the reported ones
(:mod:`scopetwin.calib.oneshot.lens_choice`).

All coordinates of the calibration are those of the TARGET (its local frame: markers at (x, y, 0), thesis §2.2).
Pixel coordinates are continuous (x_px, y_px) = (column, row) as in :mod:`scopetwin.scenes.camera`. Lengths in mm,
angles in
rad.
"""

from scopetwin.calib.oneshot.bias_correction import calibrate_bias_corrected
from scopetwin.calib.oneshot.calibration import calibrate
from scopetwin.calib.oneshot.camera_parameters import (
    AUTO_FREE_TILT,
    FOCAL_LENGTH_TOLERANCE,
    LENS_MODES,
    MAX_SIGMA_B,
    MIN_MARKERS,
    PRIOR_NOISE_PX,
    CalibrationError,
    CalibrationWarning,
    LensMode,
    Prior,
    axis_point,
    camera_dict,
    tilt_phi,
)
from scopetwin.calib.oneshot.linear import LinearResult, linear_approximation
from scopetwin.calib.oneshot.refinement import Calibration, refine

__all__ = [
    "AUTO_FREE_TILT",
    "FOCAL_LENGTH_TOLERANCE",
    "LENS_MODES",
    "MAX_SIGMA_B",
    "MIN_MARKERS",
    "PRIOR_NOISE_PX",
    "Calibration",
    "CalibrationError",
    "CalibrationWarning",
    "LensMode",
    "LinearResult",
    "Prior",
    "axis_point",
    "calibrate",
    "calibrate_bias_corrected",
    "camera_dict",
    "linear_approximation",
    "refine",
    "tilt_phi",
]
