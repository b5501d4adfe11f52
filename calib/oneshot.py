"""One-shot camera calibration from ONE image of a planar marker target (seed chapter 2).

Two steps, as in the seed:

1. :func:`linear_approximation` (§2.4): the affine model u = A x + B y + C,
   v = D x + E y + F fitted by least squares, then principal point, magnification
   (complex square root, eqs. 2.23-2.29, both equations), T_x, T_y, N_z (sign s chosen
   by the coarse N_z estimate), b from the thin-lens equation, g, r_c and the tilt
   angle phi.
2. :func:`refine` (§2.5): the reprojection error of the pinhole model of
   :mod:`scenes.camera` minimised over p = (r_c, r_0, phi) [, b] [, r_cs, c0, c2] with
   :func:`scipy.optimize.least_squares` (Levenberg-Marquardt, analytic Jacobian: the
   per-marker chain rule is written out, the 7-parameter frame map of §2.5.2 is
   differentiated by complex step, which is exact to round-off).

Image distance b (issue item 5): ``lens="thin-lens"`` derives b = g f/(g - f) from the
focal length as the seed does (§2.5.2); ``lens="free"`` estimates b as a parameter (it
is determined only when the target is seen obliquely: a face-on view fixes b/g alone);
``lens="fixed"`` keeps an a-priori b; ``lens="auto"`` is free when the view is oblique
enough and thin-lens otherwise.

All coordinates of the calibration are those of the TARGET (its local frame: markers at
(x, y, 0), seed §2.2). Pixel coordinates are continuous (x_px, y_px) = (column, row)
as in :mod:`scenes.camera`. Lengths in mm, angles in rad.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import least_squares

from scenes.camera import Camera
from scenes.errors import GeometryError, ScopetwinError
from scenes.geometry import Array, Frame

LensMode = Literal["auto", "thin-lens", "free", "fixed"]
LENS_MODES: tuple[str, ...] = ("auto", "thin-lens", "free", "fixed")

#: Smallest marker count accepted (issue 4: "fewer than 6 markers" is an error).
MIN_MARKERS = 6
#: ``lens="auto"`` estimates b freely when the optical axis is tilted at least this much against the target normal.
AUTO_FREE_TILT = np.deg2rad(10.0)
#: Centroid noise assumed when judging whether b is determined, px (the seed's worst case, 1/20 px, §2.8.2).
PRIOR_NOISE_PX = 0.05
#: A free b whose standard deviation at :data:`PRIOR_NOISE_PX` exceeds this (mm) is not determined.
MAX_SIGMA_B = 0.05
_CSTEP = 1e-30


class CalibrationError(ScopetwinError, ValueError):
    """Input from which no trustworthy camera calibration follows; the message says why."""


class CalibrationWarning(UserWarning):
    """A calibration that succeeded but deserves attention (the message says why)."""


@dataclass(frozen=True)
class Prior:
    """The a-priori knowledge of seed §2.1: pixel size, focal length, coarse N_z (plus sensor format).

    Parameters
    ----------
    focal_length : float
        f, mm (thin-lens equation, §2.4.2).
    nx, ny : int
        Pixel counts.
    pitch : float
        Pixel size, mm.
    nz_estimate : array_like, shape (3,)
        Coarse sensor normal in target coordinates (picks the sign s of §2.4.2).
    r_cs, c0, c2 : optional
        Principal-point offset and distortion assumed by the linear step (and kept fixed by
        the refinement unless distortion is refined).
    image_distance : float or None
        A-priori b, mm, for ``lens="fixed"``.
    """

    focal_length: float
    nx: int
    ny: int
    pitch: float
    nz_estimate: tuple[float, float, float] = (0.0, 0.0, 1.0)
    r_cs: tuple[float, float] = (0.0, 0.0)
    c0: float = 1.0
    c2: float = 0.0
    image_distance: float | None = None

    def __post_init__(self) -> None:
        if not self.focal_length > 0:
            raise CalibrationError(f"focal length must be > 0 mm, got {self.focal_length}")
        if not self.pitch > 0:
            raise CalibrationError(f"pixel pitch must be > 0 mm, got {self.pitch}")
        nz = np.asarray(self.nz_estimate, dtype=np.float64)
        if nz.shape != (3,) or not np.all(np.isfinite(nz)) or not np.linalg.norm(nz) > 0:
            raise CalibrationError(f"the N_z estimate must be a non-zero 3-vector, got {self.nz_estimate}")
        object.__setattr__(self, "nz_estimate", tuple(float(v) for v in nz / np.linalg.norm(nz)))
        if self.image_distance is not None and not self.image_distance > 0:
            raise CalibrationError(f"image distance must be > 0 mm, got {self.image_distance}")

    @classmethod
    def from_camera(cls, camera: Camera, focal_length: float, plane: Frame | None = None, **changes) -> Prior:
        """A prior from a (nominal) camera: its format, pitch, distortion, b and N_z in the target frame."""
        plane = plane or Frame.identity()
        kw = dict(
            focal_length=focal_length,
            nx=camera.nx,
            ny=camera.ny,
            pitch=camera.pitch,
            nz_estimate=tuple(plane.vectors_to_local(camera.frame.nz)),
            r_cs=camera.r_cs,
            c0=camera.c0,
            c2=camera.c2,
            image_distance=camera.b,
        )
        kw.update(changes)
        return cls(**kw)

    def sensor_camera(self, b: float = 1.0, frame: Frame | None = None, **changes) -> Camera:
        """A :class:`~scenes.camera.Camera` with this prior's format (pose and b as given)."""
        kw = dict(r_cs=self.r_cs, c0=self.c0, c2=self.c2)
        kw.update(changes)
        return Camera(frame or Frame.identity(), b, self.nx, self.ny, self.pitch, **kw)


# -- helpers ----------------------------------------------------------------------------------
def _check_points(xy: ArrayLike, px: ArrayLike, n_params: int = 6) -> tuple[Array, Array]:
    """Validate marker coordinates (n, 2) and their images (n, 2)."""
    xy = np.asarray(xy, dtype=np.float64)
    px = np.asarray(px, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] not in (2, 3):
        raise CalibrationError(f"marker coordinates must have shape (n, 2), got {xy.shape}")
    if xy.shape[1] == 3:
        if np.any(np.abs(xy[:, 2]) > 1e-9):
            raise CalibrationError("marker coordinates must lie in the target plane z = 0")
        xy = xy[:, :2]
    if px.shape != xy.shape:
        raise CalibrationError(f"{len(xy)} marker coordinates but image points of shape {px.shape}")
    if not (np.all(np.isfinite(xy)) and np.all(np.isfinite(px))):
        raise CalibrationError("marker coordinates or image points contain NaN or infinite values")
    need = max(MIN_MARKERS, (n_params + 1) // 2 + 1)
    if len(xy) < need:
        raise CalibrationError(f"{len(xy)} markers are too few for a calibration: at least {need} are needed")
    centred = xy - xy.mean(axis=0)
    ev = np.linalg.eigvalsh(centred.T @ centred)  # squared singular values of the spread, ascending
    if ev[0] <= 1e-18 * max(ev[1], 1e-300):
        raise CalibrationError("the markers are collinear: a calibration needs markers spanning the target plane")
    return xy, px


def _unit(v: Array) -> Array:
    return v / np.linalg.norm(v)


def tilt_phi(frame: Frame) -> float:
    """Tilt angle phi of the sensor (seed §2.4.2, "Tilt Angle"): mean of alpha and beta.

    T_0x = e_y x N_z, T_0y = N_z x T_0x; alpha = atan2(-T_y.T_0x, T_x.T_0x),
    beta = atan2(T_x.T_0y, T_y.T_0y); their mean is taken on the circle.
    """
    t0x = np.cross([0.0, 1.0, 0.0], frame.nz)
    if np.linalg.norm(t0x) < 1e-12:
        raise CalibrationError("the optical axis is parallel to e_y: the tilt angle phi is undefined (seed §2.5.2)")
    t0x = _unit(t0x)
    t0y = np.cross(frame.nz, t0x)
    alpha = np.arctan2(-(frame.ty @ t0x), frame.tx @ t0x)
    beta = np.arctan2(frame.tx @ t0y, frame.ty @ t0y)
    return float(np.arctan2(np.sin(alpha) + np.sin(beta), np.cos(alpha) + np.cos(beta)))


def _fmt(v: ArrayLike) -> str:
    return "(" + ", ".join(f"{x:.4g}" for x in np.asarray(v, dtype=np.float64)) + ")"


def _wrap(angle: float) -> float:
    return float(np.arctan2(np.sin(angle), np.cos(angle)))


def axis_point(frame: Frame) -> tuple[Array, float]:
    """r_0 (x0, y0) where the optical axis meets the target plane z = 0, and g = |r_c - r_0|."""
    nz = frame.nz
    if not nz[2] > 1e-12:
        raise CalibrationError("the optical axis does not meet the target plane in front of the camera")
    g = float(frame.origin[2] / nz[2])
    r0 = frame.origin - g * nz
    return r0[:2].copy(), g


# -- §2.4 linear approximation ------------------------------------------------------------------
@dataclass(frozen=True)
class LinearResult:
    """Result of the linear approximation of seed §2.4 (target coordinates).

    Attributes
    ----------
    coefficients : ndarray (6,)
        A, B, C, D, E, F of eq. 2.19 (sensor mm per target mm, and mm).
    m_x, m_y : float
        Magnification from the two equations m^2 = A^2 + B^2 + P^2 and m^2 = D^2 + E^2 + Q^2.
    m : float
        Their mean.
    sign : int
        The sign s of §2.4.2 chosen by the N_z estimate.
    camera : Camera
        Camera with frame (r_c, T_x, T_y, N_z) and b.
    r_0 : ndarray (2,)
        Axis point in the target plane.
    g, phi : float
        Object distance, mm; tilt angle, rad.
    alternative : Camera
        The same solution with the other sign s (the mirror-ambiguous pose).
    """

    coefficients: Array
    m_x: float
    m_y: float
    m: float
    sign: int
    camera: Camera
    r_0: Array
    g: float
    phi: float
    alternative: Camera

    @property
    def m_disagreement(self) -> float:
        """|m_x - m_y| / m: how far the two magnification equations disagree."""
        return abs(self.m_x - self.m_y) / self.m


def _linear_camera(coef: Array, m: float, s: int, b: float, prior: Prior) -> Camera:
    a, bb, c, d, e, f = coef
    w = np.sqrt(complex((d * d - a * a + e * e - bb * bb), 2.0 * (a * d + bb * e)))
    p, q = w.real, -w.imag
    tx = np.array([a, bb, s * p]) / m
    ty = np.array([d, e, s * q]) / m
    nz = _unit(np.cross(tx, ty))
    tx = _unit(tx - (tx @ nz) * nz)
    ty = np.cross(nz, tx)
    r0 = -np.linalg.solve(np.array([[a, bb], [d, e]]), np.array([c, f]))
    g = b / m
    rc = np.array([r0[0], r0[1], 0.0]) + g * nz
    return prior.sensor_camera(b, Frame(rc, tx, ty, nz))


def linear_approximation(xy: ArrayLike, px: ArrayLike, prior: Prior, b: float | None = None) -> LinearResult:
    """Linear approximation of seed §2.4 from marker coordinates and their image points.

    Parameters
    ----------
    xy : array_like (n, 2)
        Marker centres in target coordinates, mm.
    px : array_like (n, 2)
        Their images, continuous pixel coordinates (col, row).
    prior : Prior
        Pixel pitch, format, focal length, N_z estimate (and the distortion assumed).
    b : float, optional
        Image distance to use instead of the thin-lens b = f (m + 1) of §2.4.2.

    Raises
    ------
    CalibrationError
        Too few or collinear markers, an image that is mirror-inverted or edge-on, an N_z
        estimate pointing away from both possible solutions.
    """
    xy, px = _check_points(xy, px)
    uv = prior.sensor_camera().undistort(prior.sensor_camera().pixel_to_sensor(px))
    design = np.column_stack([xy, np.ones(len(xy))])
    # Least squares of Phi_1, Phi_2 (§2.4.1); lstsq solves the same normal equations M (A,B,C) = V_1 stably.
    sol, _, rank, _ = np.linalg.lstsq(design, uv, rcond=None)
    if rank < 3:
        raise CalibrationError("the markers are collinear: the matrix M of §2.4.1 is singular")
    coef = np.array([sol[0, 0], sol[1, 0], sol[2, 0], sol[0, 1], sol[1, 1], sol[2, 1]])
    a, bb, _, d, e, _ = coef
    w = np.sqrt(complex((d * d - a * a + e * e - bb * bb), 2.0 * (a * d + bb * e)))
    p, q = w.real, -w.imag
    m_x = float(np.sqrt(a * a + bb * bb + p * p))
    m_y = float(np.sqrt(d * d + e * e + q * q))
    m = 0.5 * (m_x + m_y)
    det = a * e - bb * d
    if abs(det) < 1e-6 * m * m:
        raise CalibrationError("the target is seen edge-on: its image is (nearly) a line")
    if det < 0:
        raise CalibrationError(
            "the marker image is mirror-inverted (AE - BD < 0): the marker indices do not match "
            "the target's axes, or a mirrored pattern was not declared as such"
        )
    b_lin = prior.focal_length * (m + 1.0) if b is None else float(b)
    cams = {s: _linear_camera(coef, m, s, b_lin, prior) for s in (1, -1)}
    est = np.asarray(prior.nz_estimate)
    dots = {s: float(c.frame.nz @ est) for s, c in cams.items()}
    if max(dots.values()) <= 0:
        raise CalibrationError(
            f"the N_z estimate {_fmt(est)} points away from the camera: both "
            f"solutions have N_z.N_est <= 0 (the camera must look at the target's front, +z side)"
        )
    s = 1 if dots[1] >= dots[-1] else -1
    cam = cams[s]
    r0, g = axis_point(cam.frame)
    return LinearResult(coef, m_x, m_y, m, s, cam, r0, g, tilt_phi(cam.frame), cams[-s])


# -- §2.5 non-linear refinement ----------------------------------------------------------------
def _frame_batch(q: NDArray, focal_length: float, lens: str, b_fixed: float) -> NDArray:
    """Frame map of seed §2.5.2 for rows q = (x_c, y_c, z_c, x_0, y_0, phi, b); complex-step safe.

    Returns rows (N_z, T_x, T_y, b, g) of length 11.
    """
    rc = q[:, 0:3]
    d = rc - np.stack([q[:, 3], q[:, 4], np.zeros_like(q[:, 3])], axis=1)
    g = np.sqrt(np.sum(d * d, axis=1))
    nz = d / g[:, None]
    h = np.sqrt(nz[:, 2] ** 2 + nz[:, 0] ** 2)
    t0x = np.stack([nz[:, 2], np.zeros_like(h), -nz[:, 0]], axis=1) / h[:, None]
    t0y = np.cross(nz, t0x)
    c, s = np.cos(q[:, 5])[:, None], np.sin(q[:, 5])[:, None]
    tx = c * t0x + s * t0y
    ty = c * t0y - s * t0x
    if lens == "thin-lens":
        b = g * focal_length / (g - focal_length)
    elif lens == "free":
        b = q[:, 6]
    else:
        b = np.full_like(g, b_fixed)
    return np.concatenate([nz, tx, ty, b[:, None], g[:, None]], axis=1)


@dataclass
class _Model:
    """The reprojection model: parameter layout and residual / Jacobian (seed §2.5.3)."""

    xy: Array
    px: Array
    prior: Prior
    lens: str
    distortion: bool
    b_fixed: float
    names: list[str] = field(default_factory=list)
    fixed_dist: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.names = ["x_c", "y_c", "z_c", "x_0", "y_0", "phi"]
        if self.lens == "free":
            self.names.append("b")
        if self.distortion:
            self.names += ["x_cs", "y_cs"]
            if self.lens != "free":
                self.names.append("c0")  # c0 and a free b are exactly degenerate (c0*b is what the image fixes)
            self.names.append("c2")
        self.fixed_dist = {
            "x_cs": self.prior.r_cs[0],
            "y_cs": self.prior.r_cs[1],
            "c0": self.prior.c0,
            "c2": self.prior.c2,
        }
        self.X = np.column_stack([self.xy, np.zeros(len(self.xy))])

    def get(self, p: Array, name: str) -> float:
        return float(p[self.names.index(name)]) if name in self.names else float(self.fixed_dist[name])

    def base(self, p: Array) -> Array:
        q = np.empty(7)
        q[:6] = p[:6]
        q[6] = p[6] if self.lens == "free" else self.b_fixed
        return q

    def frame_and_jac(self, p: Array) -> tuple[Array, Array]:
        """Frame outputs (11,) and their derivatives w.r.t. the 7 base parameters (11, 7), by complex step."""
        q = self.base(p)
        qc = np.tile(q.astype(np.complex128), (8, 1))
        qc[1:, :] += 1j * _CSTEP * np.eye(7)
        out = _frame_batch(qc, self.prior.focal_length, self.lens, self.b_fixed)
        return out[0].real, (out[1:].imag / _CSTEP).T

    def evaluate(self, p: Array, jac: bool) -> tuple[Array, Array | None]:
        fr, dfr = self.frame_and_jac(p)
        nz, tx, ty, b = fr[0:3], fr[3:6], fr[6:9], fr[9]
        rc = p[0:3]
        dvec = self.X - rc
        a = dvec @ tx
        c = dvec @ ty
        dep = -(dvec @ nz)
        # a trial step that puts markers behind the camera gets huge (finite) residuals, so LM rejects it
        dep = np.where(dep > 0, dep, 1e-9 * (1.0 + np.abs(dep)))
        u = b * a / dep
        v = b * c / dep
        rho = np.sqrt(u * u + v * v)
        c0, c2 = self.get(p, "c0"), self.get(p, "c2")
        k = c0 + c2 * rho
        xcs, ycs = self.get(p, "x_cs"), self.get(p, "y_cs")
        pr = self.prior
        x = (k * u - xcs) / pr.pitch + 0.5 * pr.nx
        y = 0.5 * pr.ny - (k * v - ycs) / pr.pitch
        res = np.concatenate([x - self.px[:, 0], y - self.px[:, 1]])
        if not jac:
            return res, None
        # derivatives w.r.t. the 7 base parameters (x_c, y_c, z_c, x_0, y_0, phi, b)
        drc = np.zeros((3, 7))
        drc[:, :3] = np.eye(3)
        da = dvec @ dfr[3:6] - tx @ drc
        dc = dvec @ dfr[6:9] - ty @ drc
        ddep = -(dvec @ dfr[0:3] - nz @ drc)
        db = dfr[9]
        inv = 1.0 / dep
        du = (b * inv)[:, None] * da + (a * inv)[:, None] * db[None, :] - (u * inv)[:, None] * ddep
        dv = (b * inv)[:, None] * dc + (c * inv)[:, None] * db[None, :] - (v * inv)[:, None] * ddep
        safe = np.where(rho > 0, rho, 1.0)
        drho = np.where((rho > 0)[:, None], (u[:, None] * du + v[:, None] * dv) / safe[:, None], 0.0)
        dx_base = (k[:, None] * du + (c2 * u)[:, None] * drho) / pr.pitch
        dy_base = -(k[:, None] * dv + (c2 * v)[:, None] * drho) / pr.pitch
        cols = [0, 1, 2, 3, 4, 5] + ([6] if self.lens == "free" else [])
        jx = [dx_base[:, cols]]
        jy = [dy_base[:, cols]]
        n = len(u)
        for name in self.names[len(cols) :]:
            if name == "x_cs":
                jx.append(np.full((n, 1), -1.0 / pr.pitch))
                jy.append(np.zeros((n, 1)))
            elif name == "y_cs":
                jx.append(np.zeros((n, 1)))
                jy.append(np.full((n, 1), 1.0 / pr.pitch))
            elif name == "c0":
                jx.append((u / pr.pitch)[:, None])
                jy.append((-v / pr.pitch)[:, None])
            elif name == "c2":
                jx.append((rho * u / pr.pitch)[:, None])
                jy.append((-rho * v / pr.pitch)[:, None])
        return res, np.vstack([np.hstack(jx), np.hstack(jy)])

    def camera(self, p: Array) -> Camera:
        fr, _ = self.frame_and_jac(p)
        frame = Frame(p[0:3], fr[3:6], fr[6:9], fr[0:3])
        return self.prior.sensor_camera(
            float(fr[9]),
            frame,
            r_cs=(self.get(p, "x_cs"), self.get(p, "y_cs")),
            c0=self.get(p, "c0"),
            c2=self.get(p, "c2"),
        )

    def start(self, camera: Camera, r0: Array, phi: float) -> Array:
        p = list(camera.center) + [r0[0], r0[1], phi]
        if self.lens == "free":
            p.append(camera.b)
        for name in self.names[len(p) :]:
            p.append(self.fixed_dist[name])
        return np.asarray(p, dtype=np.float64)


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
        Tilt angle, rad; object distance |r_c - r_0|, mm.
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
        """JSON-ready result with the keys of DESIGN.md's ``calibrate`` contract (lengths mm, angles rad)."""
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


def camera_dict(camera: Camera, r0: ArrayLike, phi: float, g: float) -> dict:
    """Camera parameters under the contract's keys (seed Table 2.1 plus phi, r_cs, c0, c2)."""
    f = camera.frame
    return {
        "r_c": f.origin.tolist(),
        "t_x": f.tx.tolist(),
        "t_y": f.ty.tolist(),
        "n_z": f.nz.tolist(),
        "b": camera.b,
        "g": float(g),
        "r_0": [float(v) for v in np.asarray(r0)[:2]],
        "phi": float(phi),
        "r_cs": list(camera.r_cs),
        "c0": camera.c0,
        "c2": camera.c2,
    }


def _solve(model: _Model, p0: Array, max_nfev: int) -> tuple[Array, Array, Array, int, int]:
    def fun(p: Array) -> Array:
        return model.evaluate(p, False)[0]

    def jac(p: Array) -> Array:
        return model.evaluate(p, True)[1]

    out = least_squares(
        fun, p0, jac=jac, method="lm", x_scale="jac", ftol=1e-15, xtol=1e-15, gtol=1e-15, max_nfev=max_nfev
    )
    res, jmat = model.evaluate(out.x, True)
    return out.x, res, jmat, int(out.nfev), int(out.status)


def _covariance(jmat: Array) -> Array:
    """(J^T J)^-1 from the eigen-decomposition of J^T J, column-scaled (pseudo-inverse where rank-deficient)."""
    scale = np.linalg.norm(jmat, axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    js = jmat / scale
    w, v = np.linalg.eigh(js.T @ js)
    tol = w[-1] * 1e-13 * max(jmat.shape)
    inv = np.where(w > tol, 1.0 / np.where(w > tol, w, 1.0), np.inf)
    with np.errstate(invalid="ignore"):
        return ((v * inv) @ v.T) / np.outer(scale, scale)


def _sigmas(model: _Model, p: Array, cov: Array, scale: float) -> dict:
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
    """Non-linear refinement of seed §2.5 by Levenberg-Marquardt (``scipy.optimize.least_squares``).

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
        Also refine r_cs, c2 and (unless b is free) c0 (seed §2.5.1).
    b : float, optional
        The image distance for ``lens="fixed"`` (default: ``prior.image_distance``).
    """
    if lens not in ("thin-lens", "free", "fixed"):
        raise CalibrationError(f"lens mode must be thin-lens, free or fixed here, got {lens!r}")
    b_fixed = float(b if b is not None else (prior.image_distance or 0.0))
    if lens == "fixed" and not b_fixed > 0:
        raise CalibrationError("lens mode 'fixed' needs an a-priori image distance b")
    model = _Model(np.asarray(xy, dtype=np.float64), np.asarray(px, dtype=np.float64), prior, lens, distortion, b_fixed)
    _check_points(model.xy, model.px, len(model.names))
    cam0 = start.camera
    r00, phi0 = np.asarray(start.r_0, dtype=np.float64), float(start.phi)
    p0 = model.start(cam0, r00, phi0)
    if lens == "thin-lens" and not np.linalg.norm(cam0.center - np.append(r00, 0.0)) > prior.focal_length:
        raise CalibrationError("the start camera is closer to the target than the focal length")
    try:
        p, res, jmat, nfev, status = _solve(model, p0, max_nfev)
    except GeometryError as exc:
        raise CalibrationError(f"the refinement failed: {exc}") from None
    if status <= 0:
        raise CalibrationError("the non-linear refinement did not converge (too many evaluations)")
    notes: list[str] = []
    dof = max(len(res) - len(p), 1)
    s2 = float(res @ res) / dof
    cov = _covariance(jmat)
    sig = _sigmas(model, p, cov, np.sqrt(s2))
    sigma_b_prior = None
    if lens == "free":
        sigma_b_prior = float(np.sqrt(cov[6, 6]) * PRIOR_NOISE_PX) if np.isfinite(cov[6, 6]) else float("inf")
    dvec = model.X - p[0:3]
    camera = model.camera(p)
    if np.any(dvec @ camera.frame.nz >= 0):
        raise CalibrationError("the refinement ended with markers behind the camera: the start values are unusable")
    r0 = p[3:5].copy()
    g = float(np.linalg.norm(camera.center - np.append(r0, 0.0)))
    resid = res.reshape(2, -1).T
    start_lin = start.linear if isinstance(start, Calibration) else start
    params = {name: float(v) for name, v in zip(model.names, p, strict=True)}
    return Calibration(
        camera,
        r0,
        _wrap(float(p[5])),
        g,
        start_lin,
        lens,
        distortion,
        params,
        sig,
        sigma_b_prior,
        resid,
        tuple(notes),
        nfev,
    )


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
        How the image distance b is obtained (module docstring).
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
    xy, px = _check_points(xy, px)
    b_lin = (b if b is not None else prior.image_distance) if lens == "fixed" else None
    if lens == "fixed" and b_lin is None:
        raise CalibrationError("lens mode 'fixed' needs an a-priori image distance b")
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

    mode = "thin-lens" if lens == "auto" else lens
    cal = run(lin, mode)
    # the mirror-ambiguous pose (other sign s): keep the N_z estimate's choice unless the data clearly reject it
    alt_nz = lin.alternative.frame.nz
    est = np.asarray(prior.nz_estimate)
    undecided = abs(est @ (lin.camera.frame.nz - alt_nz)) < 1e-3 * np.linalg.norm(lin.camera.frame.nz - alt_nz)
    suspicious = cal.residual_rms_px > 2 * PRIOR_NOISE_PX or undecided
    if suspicious and np.arccos(np.clip(alt_nz @ lin.camera.frame.nz, -1, 1)) > 1e-3:
        try:
            alt = run(_start_of(lin.alternative, lin), mode)
        except CalibrationError:
            alt = None
        if alt is not None and not undecided and np.sum(alt.residual_px**2) < 0.25 * np.sum(cal.residual_px**2):
            notes.append(
                f"the N_z estimate {_fmt(prior.nz_estimate)} picked the mirror-ambiguous "
                f"pose that fits worse (rms {cal.residual_rms_px:.3g} px against "
                f"{alt.residual_rms_px:.3g} px); the better-fitting pose is used"
            )
            cal = alt
        elif alt is not None and undecided and np.sum(alt.residual_px**2) < np.sum(cal.residual_px**2):
            cal = alt
        if undecided:
            notes.append(
                f"the N_z estimate {_fmt(est)} does not tell the two mirror-ambiguous poses "
                "apart; the better-fitting one is used"
            )
    if lens == "free" and not (cal.sigma_b_prior is not None and cal.sigma_b_prior <= MAX_SIGMA_B):
        raise CalibrationError(
            f"the view is too close to face-on (tilt {np.rad2deg(tilt):.2f} deg) to estimate the image distance b: "
            f"its standard deviation at {PRIOR_NOISE_PX} px centroid noise would be {cal.sigma_b_prior:.3g} mm "
            f"(limit {MAX_SIGMA_B} mm); use the thin-lens or fixed mode"
        )
    if lens == "auto" and not distortion and tilt >= AUTO_FREE_TILT:
        cal = _choose_lens(cal, run(cal, "free"))
    if cal.residual_rms_px > residual_warn_px:
        notes.append(
            f"the residual is large ({cal.residual_rms_px:.3g} px rms): check the marker indexing and the "
            "a-priori values"
        )
    for note in notes:
        warnings.warn(note, CalibrationWarning, stacklevel=2)
    return _with_notes(cal, lin, notes)


def _choose_lens(thin: Calibration, free: Calibration, z_limit: float = 3.0) -> Calibration:
    """Thin-lens or free b (issue 4, item 5): free only where the data reject the thin-lens b.

    A free b costs a lot of precision (b and g are strongly correlated), so the seed's thin-lens
    b is kept unless it lies more than ``z_limit`` standard deviations of the free estimate away
    from it, or the free b is not determined (``sigma_b_prior`` above :data:`MAX_SIGMA_B`).
    """
    from dataclasses import replace

    sb = free.sigma["b"]
    determined = free.sigma_b_prior is not None and free.sigma_b_prior <= MAX_SIGMA_B
    z = abs(free.camera.b - thin.camera.b) / sb if sb > 0 else float("inf")
    use_free = determined and z > z_limit
    test = {
        "b_thin_lens": thin.camera.b,
        "b_free": free.camera.b,
        "sigma_b_free": sb,
        "z": z,
        "z_limit": z_limit,
        "chosen": "free" if use_free else "thin-lens",
    }
    return replace(free if use_free else thin, lens_test=test)


def _with_notes(cal: Calibration, lin: LinearResult, notes: list[str]) -> Calibration:
    from dataclasses import replace

    return replace(cal, linear=lin, warnings=tuple(cal.warnings) + tuple(notes))


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
    """Alternate calibration and centroid-bias correction until the parameters stop changing (issue 4, item 3).

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
    return _with_notes(cal, cal.linear, [f"bias correction did not settle within {max_iter} rounds"]), bias, max_iter


# -- centroid bias of a planar target (model for calibrate_bias_corrected) ------------------------
def spot_centroids(
    camera: Camera,
    xy: ArrayLike,
    radii: ArrayLike,
    threshold: float,
    background: float = 0.0,
    radiance: float = 1.0,
    supersample: int = 4,
    chunk: int = 2_000_000,
) -> Array:
    """Predicted centroids of fading round markers on the target plane z = 0 (seed §1.5.1, §1.6.3).

    Each marker (grey value g = 1 - r/r_m, seed §1.6.3) is imaged through ``camera`` (pinhole,
    distortion) into a pixel window; pixels integrate their area (``supersample``^2 stratified
    points, box filter); the centroid is then taken as :func:`recon.markers.centroids` takes it:
    pixels above ``threshold`` weighted by their value minus ``background``, at pixel centres.

    Parameters
    ----------
    camera : Camera
        The camera in target coordinates.
    xy : array_like (n, 2)
        Marker centres, mm.
    radii : array_like (n,)
        Marker radii, mm.
    threshold, background, radiance : float
        Spot threshold and background level of the image, and the radiance of a marker centre.

    Returns
    -------
    ndarray (n, 2)
        Centroids, continuous px (NaN for markers not wholly in front of the camera).
    """
    xy = np.asarray(xy, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    n = len(xy)
    t = np.linspace(0.0, 2.0 * np.pi, 48, endpoint=False)
    rim = np.concatenate(
        [xy[:, None, :] + radii[:, None, None] * np.stack([np.cos(t), np.sin(t)], -1), np.zeros((n, len(t), 1))],
        axis=-1,
    )
    rim_px = camera.project(rim)
    lo = np.floor(np.nanmin(rim_px, axis=1)).astype(int) - 1
    hi = np.ceil(np.nanmax(rim_px, axis=1)).astype(int) + 1
    out = np.full((n, 2), np.nan)
    s = supersample
    sub = (np.arange(s) + 0.5) / s
    off = np.stack(np.meshgrid(sub, sub), -1).reshape(-1, 2)  # (s*s, 2) within a pixel
    order = np.argsort((hi - lo).prod(axis=1))
    start = 0
    while start < n:
        # group markers with windows of one size so that one array holds them
        k = order[start]
        wx, wy = hi[k] - lo[k]
        group = [k]
        total = wx * wy * s * s
        j = start + 1
        while j < n and total < chunk:
            group.append(order[j])
            total += wx * wy * s * s
            j += 1
        start = j
        g_idx = np.asarray(group)
        size = (hi[g_idx] - lo[g_idx]).max(axis=0)
        cols = np.arange(size[0])
        rows = np.arange(size[1])
        cc, rr = np.meshgrid(cols, rows)  # (H, W)
        base = np.stack([cc, rr], -1).reshape(-1, 2).astype(np.float64)  # (P, 2) pixel corners
        pix = lo[g_idx][:, None, None, :] + base[None, :, None, :] + off[None, None, :, :]  # (m, P, S, 2)
        o, d = camera.rays(pix.reshape(-1, 2))
        lam = -o[:, 2] / d[:, 2]
        hit = o[:, :2] + lam[:, None] * d[:, :2]
        hit = hit.reshape(len(g_idx), -1, 2) - xy[g_idx][:, None, :]
        r = np.hypot(hit[..., 0], hit[..., 1]) / radii[g_idx][:, None]
        grey = radiance * np.clip(1.0 - r, 0.0, 1.0)
        grey = np.where((lam > 0).reshape(len(g_idx), -1), grey, 0.0)
        val = grey.reshape(len(g_idx), -1, s * s).mean(axis=2)  # (m, P) pixel values
        w = np.where(val > threshold, val - background, 0.0)
        centres = base + 0.5
        mass = w.sum(axis=1)
        c = (w @ centres) / np.where(mass > 0, mass, np.nan)[:, None]
        out[g_idx] = c + lo[g_idx]
    return out


def spot_bias_model(
    xy: ArrayLike,
    radii: ArrayLike,
    threshold: float = 0.0,
    background: float = 0.0,
    radiance: float = 1.0,
    supersample: int | None = None,
) -> Callable[[Camera], Array]:
    """``predict_bias`` for :func:`calibrate_bias_corrected`: spot centroid minus image of the centre, px.

    The defaults (threshold 0) model the whole-spot first moment of :func:`recon.markers.centroids`.
    ``supersample`` None: enough points per pixel for about 40 samples across a spot radius.
    """
    xy = np.asarray(xy, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    X = np.column_stack([xy, np.zeros(len(xy))])

    def predict(camera: Camera) -> Array:
        s = supersample
        if s is None:
            d = float(np.median(-(X - camera.center) @ camera.frame.nz))
            r_px = float(np.min(radii)) * camera.b / d / camera.pitch
            s = int(np.clip(np.ceil(40.0 / max(r_px, 1e-3)), 2, 8))
        return spot_centroids(camera, xy, radii, threshold, background, radiance, s) - camera.project(X)

    return predict
