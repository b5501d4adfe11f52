"""Inverse rendering: the substrate's surface fitted to the whole image through a differentiable render.

The centroid method (:mod:`scopetwin.recon.reconstruct`, thesis §1.4-§1.8) needs every marker's image to be a compact
spot whose centroid follows the image of its centre. Here instead the image itself is the data: the surface (a
uniform cubic B-spline over the base plane, fine enough for 3 mm correlation lengths) is fitted so that a render
of the measurement — the thesis's ray model of §1.6 written in Dr.Jit
(:mod:`scopetwin.scenes.mitsuba.deflectometry_ad`) — matches the camera image pixel by pixel, partial markers included.

Loss (Gauss-Newton / Levenberg-Marquardt on the coefficients c)::

    sum_p (I_p - alpha*R_p(c) - beta)^2 / var_p  +  lambda * |D c|^2,   mean_ROI(h) = H

* ``var_p``: the EMVA 1288 variance of pixel p (:mod:`scopetwin.scenes.emva1288`: K^2 sigma_d^2 + K (I - black) +
  1/12 in DN) for camera images; a constant for noise-free renders;
* ``alpha, beta``: the photometric gain and offset (exposure, black level), solved in closed form each step;
* ``D``: second differences of the coefficient grid (a discrete thin-plate energy): the smoothness prior, which
  also carries the surface into the frame regions, where there are no data;
* the Jacobian dR/dc is sparse (16 coefficients per ray) and exact: per ray, the render returns the derivative
  with respect to a local height/slope perturbation (closed form, in the trace's kernel), combined with the
  B-spline basis (:mod:`~scopetwin.recon.inverse.render`);
* coarse to fine from a plane start: first on binned images (b x b pixels each, rendered as one super-pixel: the
  image blurred and decimated, which widens the basin), then on the full-resolution image; from the centroid
  method's surface (already inside the basin) the full-resolution image directly.

From a converged centroid start the coefficients are held to the span of the centroid method's shifted basis
(``surface="start-basis"``: c = P a, P the basis functions as B-splines, :meth:`SplineSurface.span`; its scale was
chosen from the data by :func:`scopetwin.recon.scale.select_sigma`): the prior the centroid method found for this
surface, fitted now to every pixel instead of to the markers' centroids. The free spline (every coefficient,
thin-plate prior) is used from a plane start and where the height is searched.

The absolute height is decided by the frame criterion (thesis §1.4, eqs. 1.3-1.4,
:mod:`scopetwin.recon.frame_criterion`): the fit is constrained to a mean ROI height H; from a centroid start H is
the centroid method's (found by the frame criterion on its Gaussian-process surface, the better extrapolation into
the frame regions), and with ``absolute="frame"`` or from a plane H is searched (secant) until the fitted surface's
maxima over the two frame regions lie on the holding frame (the one bracketed secant of both methods,
:func:`scopetwin.recon.frame_criterion.next_start_height`). ``refine_setup`` adds 12 rigid-motion parameters of
camera and pattern to the unknowns, held near the calibration by a Gaussian prior of the given standard deviations.

This is the one reconstruction package that renders: it imports the renderer (:mod:`scopetwin.scenes.mitsuba`)
lazily, inside the functions of :mod:`~scopetwin.recon.inverse.render` (``tests/architecture/test_layers.py`` names
the package), because a differentiable render of the measurement is the method. On a real rig the image comes from a
camera as for every other recon module.

The package's modules, one concept each:

* :mod:`~scopetwin.recon.inverse.config`: :class:`InverseConfig`, :func:`pose_sigma_for`;
* :mod:`~scopetwin.recon.inverse.result`: :class:`InverseResult`, :class:`InverseStep`;
* :mod:`~scopetwin.recon.inverse.render`: the forward model of one resolution level and its Jacobian;
* :mod:`~scopetwin.recon.inverse.objective`: the loss's terms (pixel variances, photometric gain and offset,
  prior weight, the held mean-height row);
* :mod:`~scopetwin.recon.inverse.pose`: the camera's and pattern's rigid motions of ``refine_setup``;
* :mod:`~scopetwin.recon.inverse.measurement`: the image, its window and the state the fit carries;
* :mod:`~scopetwin.recon.inverse.gauss_newton`: the Gauss-Newton / Levenberg-Marquardt steps of one level;
* :mod:`~scopetwin.recon.inverse.uncertainty`: the shape uncertainty and the bounds of the pixel data;
* :mod:`~scopetwin.recon.inverse.reconstructor`: :class:`InverseReconstructor` (coarse to fine, the start-height
  search) and :func:`reconstruct_inverse`.
"""

# The names of the package (``__all__``); beside them, as ``name as name``: the fitted surface's type, and the pose
# and binning helpers that the tests and benchmarks check on their own.
from scopetwin.recon.inverse.config import InverseConfig, pose_sigma_for
from scopetwin.recon.inverse.objective import pixel_variance
from scopetwin.recon.inverse.pose import _box_fraction as _box_fraction
from scopetwin.recon.inverse.pose import _pose_update as _pose_update
from scopetwin.recon.inverse.reconstructor import InverseReconstructor, reconstruct_inverse
from scopetwin.recon.inverse.render import _binned_camera as _binned_camera
from scopetwin.recon.inverse.render import bin_image, spline_grid
from scopetwin.recon.inverse.result import InverseResult, InverseStep
from scopetwin.recon.inverse.uncertainty import without_plane
from scopetwin.recon.spline import SplineSurface as SplineSurface

__all__ = [  # in the order of the reference documentation: the configuration and result, the pieces, the fit
    "InverseConfig",
    "InverseStep",
    "InverseResult",
    "bin_image",
    "pixel_variance",
    "spline_grid",
    "without_plane",
    "InverseReconstructor",
    "pose_sigma_for",
    "reconstruct_inverse",
]
