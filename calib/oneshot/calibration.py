"""One-shot calibration: linear approximation (thesis §2.4) then non-linear refinement (§2.5).

:func:`calibrate` runs :func:`~scopetwin.calib.oneshot.linear.linear_approximation` and
:func:`~scopetwin.calib.oneshot.refinement.refine`, checks the mirror-ambiguous pose (the other sign s of §2.4.2) and
chooses
how the image distance b is obtained (``lens``, see :mod:`scopetwin.calib.oneshot`).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike

from scopetwin.calib.oneshot.camera_parameters import (
    AUTO_FREE_TILT,
    LENS_MODES,
    MAX_SIGMA_B,
    PRIOR_NOISE_PX,
    CalibrationError,
    CalibrationWarning,
    LensMode,
    Prior,
    axis_point,
    check_points,
    format_vector,
    tilt_phi,
)
from scopetwin.calib.oneshot.lens_choice import (
    CONSISTENCY_Z,
    Candidate,
    agreement,
    choose_lens,
    thin_lens_candidate,
)
from scopetwin.calib.oneshot.linear import LinearResult, linear_approximation
from scopetwin.calib.oneshot.refinement import Calibration, refine, with_image_distance_uncertainty
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array


def _start_of(camera: Camera, linear: LinearResult) -> LinearResult:
    """A LinearResult-like start from another linear camera (the alternative sign)."""
    r0, g = axis_point(camera.frame)
    return LinearResult(
        linear.coefficients,
        linear.m_x,
        linear.m_y,
        linear.m,
        -linear.sign,
        camera,
        r0,
        g,
        tilt_phi(camera.frame),
        linear.camera,
    )


def _lens_mode(lens: LensMode, b: float | None, prior: Prior) -> tuple[str, float | None]:
    """The lens mode of the refinement (``"auto"`` resolved) and the a-priori b of the linear approximation."""
    a_priori_b = b if b is not None else prior.image_distance
    # auto: the a-priori b where the prior has one (the camera's stated image distance), else the thin-lens b
    mode = ("fixed" if a_priori_b is not None else "thin-lens") if lens == "auto" else lens
    b_lin = a_priori_b if mode == "fixed" else None
    if mode == "fixed" and b_lin is None:
        raise CalibrationError("lens mode 'fixed' needs an a-priori image distance b")
    return mode, b_lin


def _mirror_pose(
    cal: Calibration,
    lin: LinearResult,
    prior: Prior,
    refit: Callable[[LinearResult], Calibration],
    notes: list[str],
) -> Calibration:
    """The mirror-ambiguous pose (other sign s): keep the N_z estimate's choice unless the data clearly reject it."""
    alt_nz = lin.alternative.frame.nz
    est = np.asarray(prior.nz_estimate)
    undecided = abs(est @ (lin.camera.frame.nz - alt_nz)) < 1e-3 * np.linalg.norm(lin.camera.frame.nz - alt_nz)
    suspicious = cal.residual_rms_px > 2 * PRIOR_NOISE_PX or undecided
    if not (suspicious and np.arccos(np.clip(alt_nz @ lin.camera.frame.nz, -1, 1)) > 1e-3):
        return cal
    try:
        alt = refit(_start_of(lin.alternative, lin))
    except CalibrationError:
        alt = None
    if alt is not None and not undecided and np.sum(alt.residual_px**2) < 0.25 * np.sum(cal.residual_px**2):
        notes.append(
            f"the N_z estimate {format_vector(prior.nz_estimate)} picked the mirror-ambiguous "
            f"pose that fits worse (rms {cal.residual_rms_px:.3g} px against "
            f"{alt.residual_rms_px:.3g} px); the better-fitting pose is used"
        )
        cal = alt
    elif alt is not None and undecided and np.sum(alt.residual_px**2) < np.sum(cal.residual_px**2):
        cal = alt
    if undecided:
        notes.append(
            f"the N_z estimate {format_vector(est)} does not tell the two mirror-ambiguous poses "
            "apart; the better-fitting one is used"
        )
    return cal


def _check_free_b(cal: Calibration, tilt: float) -> None:
    """Raise where a free b is not determined by the view (face-on: its sigma above :data:`MAX_SIGMA_B`)."""
    if not (cal.sigma_b_prior is not None and cal.sigma_b_prior <= MAX_SIGMA_B):
        raise CalibrationError(
            f"the view is too close to face-on (tilt {np.rad2deg(tilt):.2f} deg) to estimate the image distance b: "
            f"its standard deviation at {PRIOR_NOISE_PX} px centroid noise would be {cal.sigma_b_prior:.3g} mm "
            f"(limit {MAX_SIGMA_B} mm); use the thin-lens or fixed mode"
        )


def calibrate(
    xy: ArrayLike,
    px: ArrayLike,
    prior: Prior,
    lens: LensMode = "auto",
    distortion: bool = False,
    b: float | None = None,
    residual_warn_px: float = 1.0,
) -> Calibration:
    """One-shot calibration: linear approximation (§2.4) then non-linear refinement (§2.5).

    Parameters
    ----------
    xy : array_like (n, 2)
        Marker centres in target coordinates, mm (thesis §2.2).
    px : array_like (n, 2)
        Their images, continuous pixel coordinates (col, row).
    prior : Prior
        A-priori values (thesis §2.1).
    lens : {"auto", "thin-lens", "free", "fixed"}
        How the image distance b is obtained (module docstring). ``"auto"``: the a-priori b (``b``, else
        ``prior.image_distance``) where the thin-lens relation with the measured magnification agrees with it
        (thesis §2.4.2), else the thin-lens b; for an oblique view a free b where the data reject that; the
        uncertainty of a kept b enters the reported ones (:mod:`scopetwin.calib.oneshot.lens_choice`).
    distortion : bool
        Refine r_cs, c0, c2 too (thesis §2.5.1, §2.8.5).
    b : float, optional
        A-priori b for ``lens="fixed"``.
    residual_warn_px : float
        A final RMS residual above this adds a warning (wrong indexing, outliers).

    Raises
    ------
    CalibrationError
        Degenerate or hopeless input: too few or collinear markers, an edge-on or mirror-inverted
        view, an N_z estimate pointing the wrong way, a free b from a (nearly) face-on view.
    """
    if lens not in LENS_MODES:
        raise CalibrationError(f"lens mode must be one of {', '.join(LENS_MODES)}, got {lens!r}")
    xy, px = check_points(xy, px)
    mode, b_lin = _lens_mode(lens, b, prior)
    lin = linear_approximation(xy, px, prior, b_lin)
    tilt = float(np.arccos(np.clip(lin.camera.frame.nz[2], -1, 1)))
    notes: list[str] = []
    if lin.m_disagreement > 0.05:
        notes.append(
            f"the two magnification equations of §2.4.2 disagree by {100 * lin.m_disagreement:.1f} %: "
            "the linear start is poor"
        )

    def run(start: LinearResult | Calibration, how: str) -> Calibration:
        return refine(xy, px, prior, start, how, distortion, b)

    cal = _mirror_pose(run(lin, mode), lin, prior, lambda start: run(start, mode), notes)
    if lens == "free":
        _check_free_b(cal, tilt)
    if lens == "auto" and not distortion:
        cal = _auto_lens(cal, run, xy, px, prior, tilt, notes)
    if cal.residual_rms_px > residual_warn_px:
        notes.append(
            f"the residual is large ({cal.residual_rms_px:.3g} px rms): check the marker indexing and the "
            "a-priori values"
        )
    for note in notes:
        warnings.warn(note, CalibrationWarning, stacklevel=2)
    return with_notes(cal, lin, notes)


def _auto_lens(
    cal: Calibration,
    run: Callable[[LinearResult | Calibration, str], Calibration],
    xy: Array,
    px: Array,
    prior: Prior,
    tilt: float,
    notes: list[str],
) -> Calibration:
    """``lens="auto"`` without distortion: the candidate b, the data's test of it, its uncertainty.

    The candidate is the thin-lens b of thesis §2.4.2 with the measured magnification, or the a-priori b of ``cal``
    (a fixed-b fit) where it agrees with that; a view tilted by at least :data:`AUTO_FREE_TILT` also gets a free
    b, which replaces the candidate where the data reject it; a kept candidate's uncertainty given the data is
    propagated into the reported standard deviations (:mod:`scopetwin.calib.oneshot.lens_choice`).
    """
    cand = thin_lens_candidate(cal, prior)
    if cal.lens == "fixed":
        stated = Candidate("a-priori", cal.camera.b, prior.image_distance_uncertainty(cal.camera.b))
        z = agreement(stated, cand)
        if z <= CONSISTENCY_Z:
            cand = stated
        else:
            m = cand.b / prior.focal_length - 1.0
            notes.append(
                f"the a-priori image distance b = {stated.b:.5g} mm disagrees with the thin-lens b = f (m + 1) = "
                f"{cand.b:.5g} +- {cand.sigma:.2g} mm of the measured magnification m = {m:.5g} and f = "
                f"{prior.focal_length:.5g} mm (thesis §2.4.2; {z:.3g} standard deviations): the thin-lens b is the "
                "candidate instead"
            )
            cal = run(cal, "thin-lens")
            cand = thin_lens_candidate(cal, prior)
    free = None
    if tilt >= AUTO_FREE_TILT:
        try:
            free = run(cal, "free")
        except CalibrationError:
            free = None
    chosen, test = choose_lens(cal, free, cand)
    if chosen is cal:
        chosen = with_image_distance_uncertainty(cal, xy, px, prior, test["sigma_b_kept"])
    return replace(chosen, lens_test=test)


def with_notes(cal: Calibration, lin: LinearResult, notes: list[str]) -> Calibration:
    """``cal`` with the linear start ``lin`` and the warnings ``notes`` added to its own."""
    return replace(cal, linear=lin, warnings=tuple(cal.warnings) + tuple(notes))
