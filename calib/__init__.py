"""calib: from camera images to setup parameters — one-shot camera and setup calibration (no Mitsuba).

Modules by the thesis's sections:

* :mod:`scopetwin.calib.oneshot` — one-shot camera calibration (chapter 2): ``linear`` (§2.4, the linear approximation,
  :func:`scopetwin.calib.oneshot.linear_approximation`), ``reprojection`` and ``refinement`` (§2.5, the non-linear
  optimisation and its covariance), ``calibration`` (both), ``bias_correction`` (with the centroid-bias model of
  :mod:`scopetwin.recon.bias`), ``camera_parameters`` (§2.1 a-priori values, §2.3 camera parameters);
* :mod:`scopetwin.calib.setup_calibration` — calibration of the deflectometry setup with a flat mirror (§2.7);
* :mod:`scopetwin.calib.channels` — channel registration of the microscope unit from Siemens-star images (§5.2.2).
"""

if __name__ == "calib":  # the bare folder, from the checkout's root: a second copy of scopetwin.calib
    raise ImportError(
        "calib is part of scopetwin: import scopetwin.calib (install with `make setup` or `pip install -e .`)"
    )
