"""The linear approximation of the one-shot calibration (thesis §2.4).

:func:`linear_approximation`: the affine model u = A x + B y + C, v = D x + E y + F fitted by least squares
(§2.4.1), then principal point, magnification (complex square root, eqs. 2.23-2.29, both equations), T_x, T_y, N_z
(sign s chosen by the coarse N_z estimate), b from the thin-lens equation, g, r_c and the tilt angle phi (§2.4.2).
The result (:class:`LinearResult`) is the start of the non-linear refinement
(:mod:`scopetwin.calib.oneshot.refinement`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from scopetwin.calib.oneshot.camera_parameters import (
    CalibrationError,
    Prior,
    axis_point,
    check_points,
    format_vector,
    tilt_phi,
    unit_vector,
)
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array, Frame


@dataclass(frozen=True)
class LinearResult:
    """Result of the linear approximation of thesis §2.4 (target coordinates).

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
        """``|m_x - m_y| / m``: how far the two magnification equations disagree."""
        return abs(self.m_x - self.m_y) / self.m


def _linear_camera(coef: Array, m: float, s: int, b: float, prior: Prior) -> Camera:
    a, bb, c, d, e, f = coef
    w = np.sqrt(complex((d * d - a * a + e * e - bb * bb), 2.0 * (a * d + bb * e)))
    p, q = w.real, -w.imag
    tx = np.array([a, bb, s * p]) / m
    ty = np.array([d, e, s * q]) / m
    nz = unit_vector(np.cross(tx, ty))
    tx = unit_vector(tx - (tx @ nz) * nz)
    ty = np.cross(nz, tx)
    r0 = -np.linalg.solve(np.array([[a, bb], [d, e]]), np.array([c, f]))
    g = b / m
    rc = np.array([r0[0], r0[1], 0.0]) + g * nz
    return prior.sensor_camera(b, Frame(rc, tx, ty, nz))


def linear_approximation(xy: ArrayLike, px: ArrayLike, prior: Prior, b: float | None = None) -> LinearResult:
    """Linear approximation of thesis §2.4 from marker coordinates and their image points.

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
    xy, px = check_points(xy, px)
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
            f"the N_z estimate {format_vector(est)} points away from the camera: both "
            f"solutions have N_z.N_est <= 0 (the camera must look at the target's front, +z side)"
        )
    s = 1 if dots[1] >= dots[-1] else -1
    cam = cams[s]
    r0, g = axis_point(cam.frame)
    return LinearResult(coef, m_x, m_y, m, s, cam, r0, g, tilt_phi(cam.frame), cams[-s])
