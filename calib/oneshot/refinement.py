"""Non-linear refinement of the one-shot calibration and its covariance (thesis §2.5.4).

:func:`refine` minimises the reprojection error of :class:`~scopetwin.calib.oneshot.reprojection.ReprojectionModel` with
:func:`scipy.optimize.least_squares` (Levenberg-Marquardt, analytic Jacobian), starting from the linear
approximation (§2.4) or an earlier :class:`Calibration`; the parameter covariance (J^T J)^-1, scaled by the residual
variance, gives the standard deviations of the parameters and of b, g, T_x, T_y, N_z.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike
from scipy.optimize import least_squares

from scopetwin.calib.oneshot.camera_parameters import (
    PRIOR_NOISE_PX,
    CalibrationError,
    Prior,
    camera_dict,
    check_points,
    wrap_angle,
)
from scopetwin.calib.oneshot.linear import LinearResult
from scopetwin.calib.oneshot.reprojection import ReprojectionModel
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.errors import GeometryError
from scopetwin.scenes.geometry import Array, Frame


@dataclass(frozen=True)
class Calibration:
    """Result of a one-shot calibration (target coordinates).

    Attributes
    ----------
    camera : Camera
        The refined camera (frame, b, r_cs, c0, c2).
    r_0 : ndarray (2,)
        Axis point in the target plane, mm.
    phi, g : float
        Tilt angle, rad; object distance ``|r_c - r_0|``, mm.
    linear : LinearResult
        The §2.4 start values.
    lens : str
        How b was obtained: "thin-lens", "free" or "fixed".
    parameters : dict
        Refined parameter vector by name.
    sigma : dict
        Standard deviations (covariance (J^T J)^-1 scaled by the residual variance) of the
        parameters and of derived quantities (b, g, T_x, T_y, N_z), same units.
    sigma_b_prior : float or None
        Standard deviation of a free b at the a-priori centroid noise :data:`PRIOR_NOISE_PX`, mm.
    residual_px : ndarray (n, 2)
        Model minus measurement, px.
    warnings : tuple of str
        Everything the calibration wants the user to know.
    nfev : int
        Function evaluations of the refinement.
    lens_test : dict or None
        How ``lens="auto"`` chose b (:func:`scopetwin.calib.oneshot.lens_choice.choose_lens`): the candidate, the
        free b, z, and the b uncertainty propagated into ``sigma`` (``sigma_b_kept``).
    """

    camera: Camera
    r_0: Array
    phi: float
    g: float
    linear: LinearResult
    lens: str
    distortion: bool
    parameters: dict
    sigma: dict
    sigma_b_prior: float | None
    residual_px: Array
    warnings: tuple[str, ...]
    nfev: int
    lens_test: dict | None = None

    @property
    def residual_rms_px(self) -> float:
        """RMS of the residual vector lengths, px."""
        return float(np.sqrt(np.mean(np.sum(self.residual_px**2, axis=1))))

    @property
    def residual_max_px(self) -> float:
        """Largest residual vector length, px."""
        return float(np.max(np.linalg.norm(self.residual_px, axis=1)))

    @property
    def residual_pv_px(self) -> float:
        """Peak-to-valley of the residual components (largest max - min of u and v), px."""
        r = self.residual_px
        return float(np.max(r.max(axis=0) - r.min(axis=0)))

    @property
    def focal_length(self) -> float:
        """Thin-lens focal length that b and g imply, f = g b / (g + b), mm."""
        return self.g * self.camera.b / (self.g + self.camera.b)

    @property
    def tilt(self) -> float:
        """Angle between the optical axis and the target normal, rad."""
        return float(np.arccos(np.clip(self.camera.frame.nz[2], -1.0, 1.0)))

    def to_global(self, plane: Frame) -> Camera:
        """The camera in the global frame, given the target's frame (target local -> global)."""
        f = self.camera.frame
        frame = Frame(
            plane.to_global(f.origin),
            plane.vectors_to_global(f.tx),
            plane.vectors_to_global(f.ty),
            plane.vectors_to_global(f.nz),
        )
        return self.camera.with_(frame=frame)

    def as_dict(self, plane: Frame | None = None) -> dict:
        """JSON-ready result with the keys of the ``calibrate`` contract (docs/contract.md) (lengths mm, angles rad)."""
        cam = self.to_global(plane) if plane is not None else self.camera
        pitch_um = self.camera.pitch * 1e3
        return {
            "camera": camera_dict(cam, self.r_0, self.phi, self.g),
            "linear": {
                **camera_dict(self.linear.camera, self.linear.r_0, self.linear.phi, self.linear.g),
                "m_x": self.linear.m_x,
                "m_y": self.linear.m_y,
                "m_disagreement": self.linear.m_disagreement,
                "sign": self.linear.sign,
            },
            "lens": self.lens,
            "distortion": self.distortion,
            "focal_length": self.focal_length,
            "tilt": self.tilt,
            "markers": int(len(self.residual_px)),
            "residual_rms_px": self.residual_rms_px,
            "residual_rms_um": self.residual_rms_px * pitch_um,
            "residual_max_px": self.residual_max_px,
            "residual_max_um": self.residual_max_px * pitch_um,
            "residual_pv_px": self.residual_pv_px,
            "residual_pv_um": self.residual_pv_px * pitch_um,
            "uncertainty": {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in self.sigma.items()},
            "sigma_b_at_prior_noise": self.sigma_b_prior,
            "lens_test": self.lens_test,
            "nfev": self.nfev,
            "warnings": list(self.warnings),
        }


#: A-priori standard deviations of the distortion parameters that one view may not determine:
#: the principal-point offset r_cs (mm; 0.25 mm is ~54 px of the thesis's 4.65 µm pixels) and c0 (which only
#: scales the image, like b). They enter the refinement as pseudo-observations at the prior's values.
DISTORTION_PRIOR_SIGMA = {"x_cs": 0.25, "y_cs": 0.25, "c0": 0.01}


def _undetermined(jmat: Array, model: ReprojectionModel, share: float = 0.5) -> list[str]:
    """Parameters with a pseudo-observation that the data hardly determine (the prior holds >= ``share`` of them).

    The information on parameter k is the k-th diagonal of (J^T J)^-1's inverse; the share of the a-priori
    pseudo-observation in it is w_k^2 times the posterior variance.
    """
    cov = _covariance(jmat)
    out = []
    for k, w in model.prior_weight.items():
        i = model.names.index(k)
        if not np.isfinite(cov[i, i]) or w * w * cov[i, i] >= share:
            out.append(k)
    return out


def _solve(model: ReprojectionModel, p0: Array, max_nfev: int) -> tuple[Array, Array, Array, int, int]:
    def fun(p: Array) -> Array:
        return model.evaluate(p, False)[0]

    def jac(p: Array) -> Array:
        return model.residual_and_jacobian(p)[1]

    out = least_squares(
        fun, p0, jac=jac, method="lm", x_scale="jac", ftol=1e-15, xtol=1e-15, gtol=1e-15, max_nfev=max_nfev
    )
    res, jmat = model.residual_and_jacobian(out.x)
    return out.x, res, jmat, int(out.nfev), int(out.status)


def _covariance(jmat: Array) -> Array:
    """(J^T J)^-1 from the SVD of the column-scaled J (infinite along directions J does not determine).

    The singular values of J itself (not the eigenvalues of J^T J) resolve weakly determined directions down to
    ~1e-13 of the strongest, such as the principal point held only by its a-priori pseudo-observation.
    """
    scale = np.linalg.norm(jmat, axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    js = jmat / scale
    _, sv, vt = np.linalg.svd(js, full_matrices=False)
    v = vt.T
    w = sv * sv
    tol = (sv[0] * 1e-13 * max(jmat.shape) ** 0.5) ** 2
    inv = np.where(w > tol, 1.0 / np.where(w > tol, w, 1.0), np.inf)
    with np.errstate(invalid="ignore"):
        return ((v * inv) @ v.T) / np.outer(scale, scale)


def _sigmas(model: ReprojectionModel, p: Array, cov: Array, scale: float) -> dict:
    """Standard deviations of the parameters and of b, g, T_x, T_y, N_z (first-order propagation)."""
    sd = np.sqrt(np.clip(np.diag(cov), 0, None)) * scale
    sig: dict = {name: float(v) for name, v in zip(model.names, sd, strict=True)}
    sig["r_c"] = sd[0:3]
    sig["r_0"] = sd[3:5]
    _, dfr = model.frame_and_jac(p)
    ncols = 7 if model.lens == "free" else 6
    jf = dfr[:, :ncols]
    cf = cov[:ncols, :ncols]
    with np.errstate(invalid="ignore"):
        var = np.einsum("ij,jk,ik->i", jf, cf, jf)
    vs = np.sqrt(np.clip(np.nan_to_num(var, nan=np.inf), 0, None)) * scale
    sig["n_z"], sig["t_x"], sig["t_y"] = vs[0:3], vs[3:6], vs[6:9]
    sig["b"], sig["g"] = float(vs[9]), float(vs[10])
    return sig


def _b_of(lens: str, b: float | None, prior: Prior) -> float:
    """The image distance held fixed (0 where none is known); an unknown lens mode or a fixed one without b raise."""
    if lens not in ("thin-lens", "free", "fixed"):
        raise CalibrationError(f"lens mode must be thin-lens, free or fixed here, got {lens!r}")
    b_fixed = float(b if b is not None else (prior.image_distance or 0.0))
    if lens == "fixed" and not b_fixed > 0:
        raise CalibrationError("lens mode 'fixed' needs an a-priori image distance b")
    return b_fixed


@dataclass(frozen=True)
class _Problem:
    """The data and settings of one refinement (arguments of :class:`ReprojectionModel`)."""

    xy: Array
    px: Array
    prior: Prior
    lens: str
    distortion: bool
    b_fixed: float

    def weighted(self, noise_px: float) -> ReprojectionModel:
        """The model with the a-priori distortion (if refined) as pseudo-observations weighed at ``noise_px``."""
        weights = {k: noise_px / v for k, v in DISTORTION_PRIOR_SIGMA.items()} if self.distortion else {}
        return ReprojectionModel(
            self.xy, self.px, self.prior, self.lens, self.distortion, self.b_fixed, prior_weight=weights
        )

    def free(self) -> ReprojectionModel:
        """The model without pseudo-observations."""
        return ReprojectionModel(self.xy, self.px, self.prior, self.lens, self.distortion, self.b_fixed)


def _first_fit(
    model: ReprojectionModel, start: LinearResult | Calibration, max_nfev: int
) -> tuple[Array, Array, Array, int]:
    """Parameters, residuals, Jacobian and evaluations of the refinement from the start values (checked)."""
    check_points(model.xy, model.px, len(model.names))
    cam0 = start.camera
    r00, phi0 = np.asarray(start.r_0, dtype=np.float64), float(start.phi)
    p0 = model.start(cam0, r00, phi0)
    if model.lens == "thin-lens" and not np.linalg.norm(cam0.center - np.append(r00, 0.0)) > model.prior.focal_length:
        raise CalibrationError("the start camera is closer to the target than the focal length")
    try:
        p, res, jmat, nfev, status = _solve(model, p0, max_nfev)
    except GeometryError as exc:
        raise CalibrationError(f"the refinement failed: {exc}") from None
    if status <= 0:
        raise CalibrationError("the non-linear refinement did not converge (too many evaluations)")
    return p, res, jmat, nfev


def _refit_distortion(
    prob: _Problem, p: Array, nfev: int, s2: float, max_nfev: int, notes: list[str]
) -> tuple[ReprojectionModel, Array, Array, Array, int, float]:
    """The distortion refit's model, parameters, residuals, Jacobian, evaluations and residual variance.

    First the a-priori r_cs, c0 weighed at the a-priori centroid noise (a well-posed problem that converges
    quickly); then at the noise the residuals show: where the data determine every parameter, once more from
    there without them (they then pull nothing); where they do not, the first estimate is kept, and the
    covariance carries the a-priori standard deviation (DISTORTION_PRIOR_SIGMA) in those directions (a note).
    """
    n_data = 2 * len(prob.xy)
    model = prob.weighted(max(float(np.sqrt(s2)), 1e-9))
    res, jmat = model.residual_and_jacobian(p)
    undetermined = _undetermined(jmat, model)
    if undetermined:
        notes.append(
            f"this view hardly determines {', '.join(undetermined)} (no distortion shows where the optical "
            "axis is): kept near the a-priori values, within their a-priori uncertainty"
        )
        return model, p, res, jmat, nfev, s2
    # the data determine every parameter: solve once more without the a-priori pseudo-observations, so
    # that they pull nothing (exact data are then recovered to round-off)
    free_model = prob.free()
    try:
        p2, res2, jmat2, nfev2, status2 = _solve(free_model, p, max_nfev)
    except GeometryError:
        status2 = 0
    if status2 > 0:
        dof = max(n_data - len(p2), 1)
        return free_model, p2, res2, jmat2, nfev + nfev2, float(res2[:n_data] @ res2[:n_data]) / dof
    return model, p, res, jmat, nfev, s2


def _calibration(
    model: ReprojectionModel,
    p: Array,
    res: Array,
    jmat: Array,
    s2: float,
    start: LinearResult | Calibration,
    notes: list[str],
    nfev: int,
) -> Calibration:
    """The :class:`Calibration` of the refined parameters ``p``, with their covariance scaled by ``s2``."""
    n_data = 2 * len(model.xy)
    cov = _covariance(jmat)
    sig = _sigmas(model, p, cov, np.sqrt(s2))
    sigma_b_prior = None
    if model.lens == "free":
        sigma_b_prior = float(np.sqrt(cov[6, 6]) * PRIOR_NOISE_PX) if np.isfinite(cov[6, 6]) else float("inf")
    dvec = model.X - p[0:3]
    camera = model.camera(p)
    if np.any(dvec @ camera.frame.nz >= 0):
        raise CalibrationError("the refinement ended with markers behind the camera: the start values are unusable")
    r0 = p[3:5].copy()
    g = float(np.linalg.norm(camera.center - np.append(r0, 0.0)))
    resid = res[:n_data].reshape(2, -1).T
    start_lin = start.linear if isinstance(start, Calibration) else start
    params = {name: float(v) for name, v in zip(model.names, p, strict=True)}
    return Calibration(
        camera,
        r0,
        wrap_angle(float(p[5])),
        g,
        start_lin,
        model.lens,
        model.distortion,
        params,
        sig,
        sigma_b_prior,
        resid,
        tuple(notes),
        nfev,
    )


def refine(
    xy: ArrayLike,
    px: ArrayLike,
    prior: Prior,
    start: LinearResult | Calibration,
    lens: str = "thin-lens",
    distortion: bool = False,
    b: float | None = None,
    max_nfev: int = 200,
) -> Calibration:
    """Non-linear refinement of thesis §2.5 by Levenberg-Marquardt (``scipy.optimize.least_squares``).

    Parameters
    ----------
    xy, px : array_like (n, 2)
        Marker coordinates (target frame, mm) and their images (continuous px).
    prior : Prior
        A-priori values (focal length, format, fixed distortion).
    start : LinearResult or Calibration
        Start values (camera, r_0, phi).
    lens : {"thin-lens", "free", "fixed"}
        How b is obtained (module docstring).
    distortion : bool
        Also refine r_cs, c2 and (unless b is free) c0 (thesis §2.5.1).
    b : float, optional
        The image distance for ``lens="fixed"`` (default: ``prior.image_distance``).
    """
    b_fixed = _b_of(lens, b, prior)
    prob = _Problem(
        np.asarray(xy, dtype=np.float64), np.asarray(px, dtype=np.float64), prior, lens, distortion, b_fixed
    )
    model = prob.weighted(PRIOR_NOISE_PX)
    p, res, jmat, nfev = _first_fit(model, start, max_nfev)
    n_data = 2 * len(model.xy)
    notes: list[str] = []
    dof = max(n_data - len(p) + len(model.prior_weight), 1)
    s2 = float(res[:n_data] @ res[:n_data]) / dof
    if distortion:
        model, p, res, jmat, nfev, s2 = _refit_distortion(prob, p, nfev, s2, max_nfev, notes)
    return _calibration(model, p, res, jmat, s2, start, notes, nfev)


def with_image_distance_uncertainty(
    cal: Calibration, xy: ArrayLike, px: ArrayLike, prior: Prior, sigma_b: float
) -> Calibration:
    """``cal`` (b held: fixed or thin-lens, no distortion) with a standard uncertainty ``sigma_b`` of its b added.

    A b taken from outside the data (an a-priori or thin-lens b, thesis §2.4.2) is uncertain
    itself, and a shift db of it moves the whole pose: at the optimum, dp/db = -(J_p^T J_p)^-1 J_p^T J_b (J_p the
    held-b Jacobian, J_b the column of a free b; for the thin-lens b the relation b = g f/(g - f) moves with
    the pose). The reported standard deviations of the parameters and of N_z, T_x, T_y, b, g get |d/db| sigma_b
    added in quadrature (first order; zero ``sigma_b`` returns ``cal`` unchanged).
    """
    if not sigma_b > 0:
        return cal
    if cal.lens not in ("fixed", "thin-lens") or cal.distortion:
        raise CalibrationError(f"an image-distance uncertainty applies to a held b without distortion, not {cal.lens}")
    xy, px = np.asarray(xy, dtype=np.float64), np.asarray(px, dtype=np.float64)
    held = ReprojectionModel(xy, px, prior, cal.lens, False, cal.camera.b)
    p = np.array([cal.parameters[name] for name in held.names])
    free = ReprojectionModel(xy, px, prior, "free", False, 0.0)
    q = np.append(p, cal.camera.b)
    jb = free.residual_and_jacobian(q)[1][:, 6]
    dp = -np.linalg.lstsq(held.residual_and_jacobian(p)[1], jb, rcond=None)[0]
    dq = np.append(dp, 1.0 + held.frame_and_jac(p)[1][9, :6] @ dp)
    dfr = free.frame_and_jac(q)[1] @ dq  # N_z, T_x, T_y, b, g per unit db
    sig = dict(cal.sigma)
    for i, name in enumerate(held.names):
        sig[name] = float(np.hypot(sig[name], dp[i] * sigma_b))
    for key, d in (("r_c", dp[0:3]), ("r_0", dp[3:5]), ("n_z", dfr[0:3]), ("t_x", dfr[3:6]), ("t_y", dfr[6:9])):
        sig[key] = np.hypot(np.asarray(sig[key], dtype=np.float64), d * sigma_b)
    sig["b"], sig["g"] = float(np.hypot(sig["b"], dfr[9] * sigma_b)), float(np.hypot(sig["g"], dfr[10] * sigma_b))
    return replace(cal, sigma=sig)
