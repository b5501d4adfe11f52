"""How ``lens="auto"`` obtains the image distance b: a candidate, the data's test of it, its uncertainty.

One view of a plane fixes b only through perspective, and b and g are strongly correlated, so a free b costs a lot
of precision (for the thesis's §2.8.1 angular view sigma_b = 0.7-2.8 µm at 0.004-0.013 px centroid noise, which is
6-23 µm of r_c along the viewing axis). ``lens="auto"`` therefore holds b at a candidate unless the data reject it:

1. The candidate (:func:`thin_lens_candidate`, :func:`stated_candidate`): the thin-lens b = f (m + 1) of thesis
   §2.4.2 with the magnification m = b/g the image measures, uncertain by (m + 1) times the focal length's
   tolerance (:attr:`~scopetwin.calib.oneshot.camera_parameters.Prior.focal_length_tolerance`) and f times the
   magnification's standard deviation. An a-priori b (the camera's stated image distance) is the candidate instead
   where it agrees with that thin-lens b within :data:`CONSISTENCY_Z` combined standard deviations; a preset's b
   for a view at another distance does not (a target seen from 242 mm with the 233 mm preset's
   b = 28 mm put the camera centre 1.0 mm off).
2. The test (:func:`choose_lens`): for a view tilted by at least ``AUTO_FREE_TILT``, b is also estimated freely;
   its standard deviation at the centroid noise the residuals show (the data's own precision) decides whether the
   data determine b (below ``MAX_SIGMA_B``) and how many of its standard deviations the candidate lies away (z).
   Where the data determine b and z exceeds :data:`LENS_TEST_Z`, the free b is used.
3. The uncertainty (:func:`kept_sigma`): where the candidate is kept, its own uncertainty given the data (the
   inverse-variance combination of candidate and free b: the kept b's distance from it and its standard deviation
   in quadrature; the candidate's own where no free b was estimated) is propagated into every reported standard
   deviation (:func:`~scopetwin.calib.oneshot.refinement.with_image_distance_uncertainty`), so that the reported
   u of the camera centre covers a wrong candidate.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from scopetwin.calib.oneshot.camera_parameters import MAX_SIGMA_B, Prior
from scopetwin.calib.oneshot.refinement import Calibration

#: A stated b further than this many combined standard deviations from the thin-lens b is not the candidate.
CONSISTENCY_Z = 3.0
#: The candidate gives way to a free b that the data determine and that lies more than this many of its own
#: standard deviations away. 5, not 3: on rendered noisy views the free b's reported sigma is ~1.6 times too
#: small (the centroid errors are not independent), and a 3-sigma test switched one draw in eight to a free b
#: 6 µm off (52 µm of r_c) although the a-priori b was exact.
LENS_TEST_Z = 5.0


@dataclass(frozen=True)
class Candidate:
    """An image distance held by the refinement: where it comes from, its value and standard uncertainty, mm."""

    kind: str
    b: float
    sigma: float


def measured_magnification(cal: Calibration, focal_length: float) -> tuple[float, float]:
    """The magnification m = b/g (thesis §2.4.1) of a fit with b held, and its standard deviation (first order).

    The image fixes the ratio b/g whatever b is held at: a wrong b moves g along with it.
    """
    m = cal.camera.b / cal.g
    dm_dg = m / (cal.g - focal_length) if cal.lens == "thin-lens" else m / cal.g  # thin-lens: m = f/(g - f)
    return m, float(dm_dg * cal.sigma["g"])


def thin_lens_candidate(cal: Calibration, prior: Prior) -> Candidate:
    """The thin-lens b = f (m + 1) of thesis §2.4.2 with the measured magnification, and its uncertainty."""
    f = prior.focal_length
    m, sigma_m = measured_magnification(cal, f)
    sigma = float(np.hypot((m + 1.0) * prior.focal_length_tolerance * f, f * sigma_m))
    return Candidate("thin-lens", f * (m + 1.0), sigma)


def agreement(stated: Candidate, thin: Candidate) -> float:
    """How many combined standard deviations a stated b lies from the thin-lens b (inf where both are exact)."""
    d = abs(stated.b - thin.b)
    s = float(np.hypot(stated.sigma, thin.sigma))
    if s > 0:
        return d / s
    return 0.0 if d <= 1e-12 * thin.b else float("inf")


def kept_sigma(cand: Candidate, b_free: float | None, sigma_free: float | None) -> float:
    """Standard uncertainty of the candidate's b given the data.

    The candidate (b_c, s_c) and the free b (b_f, s_f) combined by inverse variance give b_comb with
    s_comb = (1/s_c^2 + 1/s_f^2)^-1/2; the kept b_c is off it by |b_c - b_comb|, so its uncertainty is that and
    s_comb in quadrature (<= s_c; about |b_c - b_f| and s_f in quadrature where the data know b far better than
    the candidate). An exact candidate (s_c = 0) stays exact; without a free b it is s_c.
    """
    if cand.sigma == 0:
        return 0.0
    if b_free is None or sigma_free is None or not (np.isfinite(sigma_free) and sigma_free > 0):
        return cand.sigma
    w = 1.0 / cand.sigma**2 + 1.0 / sigma_free**2
    b_comb = (cand.b / cand.sigma**2 + b_free / sigma_free**2) / w
    return float(np.hypot(cand.b - b_comb, 1.0 / np.sqrt(w)))


def choose_lens(
    kept: Calibration, free: Calibration | None, cand: Candidate, z_limit: float = LENS_TEST_Z
) -> tuple[Calibration, dict[str, Any]]:
    """The candidate's fit ``kept`` or the free fit, and the test's record (module docstring, step 2).

    ``free`` is None where no free b was estimated (a view closer to face-on than ``AUTO_FREE_TILT``, or a free
    fit that failed): the candidate is kept. The record's ``sigma_b_kept`` is :func:`kept_sigma`, the uncertainty
    the caller propagates where the candidate is kept.
    """
    test: dict[str, Any] = {
        "candidate": cand.kind,
        "b_candidate": cand.b,
        "sigma_b_candidate": cand.sigma,
        "b_free": None,
        "sigma_b_free": None,
        "z": None,
        "z_limit": z_limit,
        "determined": False,
    }
    if free is None:
        test.update(sigma_b_kept=cand.sigma, chosen=kept.lens)
        return kept, test
    sb = float(free.sigma["b"])  # at the residuals' own noise (the covariance is scaled by it)
    d = abs(free.camera.b - cand.b)
    z = d / sb if sb > 0 else (0.0 if d == 0 else float("inf"))
    determined = bool(np.isfinite(sb) and sb <= MAX_SIGMA_B)
    use_free = determined and z > z_limit
    test.update(
        b_free=free.camera.b,
        sigma_b_free=sb,
        sigma_b_at_prior_noise=free.sigma_b_prior,
        residual_rms_px_free=free.residual_rms_px,
        z=z,
        determined=determined,
        sigma_b_kept=0.0 if use_free else kept_sigma(cand, free.camera.b, sb),
        chosen="free" if use_free else kept.lens,
    )
    return (free if use_free else kept), test
