"""One-shot calibration: linear approximation (seed §2.4) then non-linear refinement (§2.5).

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
from scopetwin.calib.oneshot.linear import LinearResult, linear_approximation
from scopetwin.calib.oneshot.refinement import Calibration, refine
from scopetwin.scenes.camera import Camera


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
        Marker centres in target coordinates, mm (seed §2.2).
    px : array_like (n, 2)
        Their images, continuous pixel coordinates (col, row).
    prior : Prior
        A-priori values (seed §2.1).
    lens : {"auto", "thin-lens", "free", "fixed"}
        How the image distance b is obtained (module docstring). ``"auto"``: the a-priori b (``b``, else
        ``prior.image_distance``), else the thin-lens b; for an oblique view a free b where the data reject it.
    distortion : bool
        Refine r_cs, c0, c2 too (seed §2.5.1, §2.8.5).
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
    if lens == "auto" and not distortion and tilt >= AUTO_FREE_TILT:
        cal = _choose_lens(cal, run(cal, "free"))
    if cal.residual_rms_px > residual_warn_px:
        notes.append(
            f"the residual is large ({cal.residual_rms_px:.3g} px rms): check the marker indexing and the "
            "a-priori values"
        )
    for note in notes:
        warnings.warn(note, CalibrationWarning, stacklevel=2)
    return with_notes(cal, lin, notes)


def _choose_lens(kept: Calibration, free: Calibration, z_limit: float = 5.0) -> Calibration:
    """The a-priori (or thin-lens) b, or a free b (issue 4 item 5, issue 14 item 4): free only where the data reject it.

    A free b costs a lot of precision: b and g are strongly correlated, and one view of a plane fixes b only
    through perspective (for the seed's §2.8.1 angular view sigma_b = 0.7-2.8 µm at 0.004-0.013 px centroid
    noise, which is 6-23 µm of r_c along the viewing axis). So the b of ``kept`` (the a-priori image
    distance, or the seed's thin-lens b when the prior has none) is kept unless it lies more than ``z_limit``
    standard deviations of the free estimate away from it, or the free b is not determined (``sigma_b_prior``
    above :data:`MAX_SIGMA_B`). The thin-lens b assumes the target in focus: for the seed's b = 28 mm, f = 25 mm
    camera 233.24 mm from the target (focused at 233.33 mm) it is 1.23 µm long, 10 µm of r_c along the axis.
    The limit is 5, not 3: on rendered noisy views the free b's reported sigma is ~1.6 times too small (the
    centroid errors are not independent), and a 3-sigma test switched one draw in eight to a free b 6 µm off
    (52 µm of r_c) although the a-priori b was exact.
    """
    sb = free.sigma["b"]
    determined = free.sigma_b_prior is not None and free.sigma_b_prior <= MAX_SIGMA_B
    z = abs(free.camera.b - kept.camera.b) / sb if sb > 0 else float("inf")
    use_free = determined and z > z_limit
    test: dict[str, float | str] = {
        "candidate": "thin-lens" if kept.lens == "thin-lens" else "a-priori",
        "b_candidate": kept.camera.b,
        "b_free": free.camera.b,
        "sigma_b_free": sb,
        "z": z,
        "z_limit": z_limit,
        "chosen": "free" if use_free else kept.lens,
    }
    return replace(free if use_free else kept, lens_test=test)


def with_notes(cal: Calibration, lin: LinearResult, notes: list[str]) -> Calibration:
    """``cal`` with the linear start ``lin`` and the warnings ``notes`` added to its own."""
    return replace(cal, linear=lin, warnings=tuple(cal.warnings) + tuple(notes))
