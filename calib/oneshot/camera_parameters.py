"""What a one-shot calibration starts from and what it reports (thesis §2.1, §2.3; tilt angle and axis point §2.4.2).

:class:`Prior` is the a-priori knowledge of §2.1 (pixel size, focal length, coarse N_z, sensor format); the camera
parameters of §2.3 are derived with :func:`tilt_phi` (the tilt angle phi) and :func:`axis_point` (r_0 and g) and
reported under the contract's keys by :func:`camera_dict`. :func:`check_points` validates marker coordinates and
their images for every step. Errors and warnings of :mod:`scopetwin.calib.oneshot` are defined here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from scopetwin.scenes.camera import Camera
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.geometry import Array, Frame

LensMode = Literal["auto", "thin-lens", "free", "fixed"]
LENS_MODES: tuple[str, ...] = ("auto", "thin-lens", "free", "fixed")

#: Smallest marker count accepted (fewer is an error).
MIN_MARKERS = 6
#: ``lens="auto"`` estimates b freely when the optical axis is tilted at least this much against the target normal.
AUTO_FREE_TILT = np.deg2rad(10.0)
#: Centroid noise assumed when judging whether b is determined, px (the thesis's worst case, 1/20 px, §2.8.2).
PRIOR_NOISE_PX = 0.05
#: A free b whose standard deviation exceeds this (mm) is not determined: in the lens test of ``lens="auto"`` at the
#: centroid noise the residuals show (the data's own precision), for ``lens="free"`` at :data:`PRIOR_NOISE_PX`.
MAX_SIGMA_B = 0.05
#: Default relative standard uncertainty of the a-priori focal length (lens tolerance and focus setting): the
#: thin-lens b = f (m + 1) of thesis §2.4.2 is uncertain by (m + 1) times it.
FOCAL_LENGTH_TOLERANCE = 0.01


class CalibrationError(ScopetwinError, ValueError):
    """Input from which no trustworthy camera calibration follows; the message says why."""


class CalibrationWarning(UserWarning):
    """A calibration that succeeded but deserves attention (the message says why)."""


@dataclass(frozen=True)
class Prior:
    """The a-priori knowledge of thesis §2.1: pixel size, focal length, coarse N_z (plus sensor format).

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
        A-priori b, mm (``lens="fixed"``; the candidate of ``lens="auto"`` where the thin-lens relation agrees).
    focal_length_tolerance : float
        Relative standard uncertainty of ``focal_length`` (default :data:`FOCAL_LENGTH_TOLERANCE`): the
        uncertainty of the thin-lens b of thesis §2.4.2, which ``lens="auto"`` reports where it keeps that b.
    image_distance_sigma : float or None
        Standard uncertainty of ``image_distance``, mm. None (default): ``focal_length_tolerance`` times it (a
        stated b is known no better than the lens data it comes from); 0 declares it exact (a simulated camera's).
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
    focal_length_tolerance: float = FOCAL_LENGTH_TOLERANCE
    image_distance_sigma: float | None = None

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
        if not 0.0 <= self.focal_length_tolerance < 1.0:
            raise CalibrationError(f"focal length tolerance must be in [0, 1), got {self.focal_length_tolerance}")
        s_b = self.image_distance_sigma
        if s_b is not None and not (np.isfinite(s_b) and s_b >= 0):
            raise CalibrationError(f"image distance sigma must be finite and >= 0 mm, got {s_b}")

    @classmethod
    def from_camera(cls, camera: Camera, focal_length: float, plane: Frame | None = None, **changes) -> Prior:
        """A prior from a (nominal) camera: its format, pitch, distortion, b and N_z in the target frame."""
        plane = plane or Frame.identity()
        kw: dict[str, Any] = dict(
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

    def image_distance_uncertainty(self, b: float) -> float:
        """Standard uncertainty of a stated image distance ``b``, mm (``image_distance_sigma``, by default
        ``focal_length_tolerance`` times ``b``)."""
        s_b = self.image_distance_sigma
        return float(s_b) if s_b is not None else self.focal_length_tolerance * float(b)

    def sensor_camera(self, b: float = 1.0, frame: Frame | None = None, **changes) -> Camera:
        """A :class:`~scopetwin.scenes.camera.Camera` with this prior's format (pose and b as given)."""
        kw: dict[str, Any] = dict(r_cs=self.r_cs, c0=self.c0, c2=self.c2)
        kw.update(changes)
        return Camera(frame or Frame.identity(), b, self.nx, self.ny, self.pitch, **kw)


# -- helpers ----------------------------------------------------------------------------------
def check_points(xy: ArrayLike, px: ArrayLike, n_params: int = 6) -> tuple[Array, Array]:
    """Validate marker coordinates (n, 2) and their images (n, 2) for a calibration with ``n_params`` unknowns.

    Parameters
    ----------
    xy : array_like, (n, 2) or (n, 3)
        Marker centres in target coordinates, mm (a third column must be 0: the target plane).
    px : array_like, (n, 2)
        Their images, continuous px.
    n_params : int
        Number of parameters to be determined (each marker gives two equations).

    Returns
    -------
    xy, px : ndarray, (n, 2)
        The validated arrays, float64.

    Raises
    ------
    CalibrationError
        Wrong shapes, non-finite values, too few (fewer than :data:`MIN_MARKERS`) or collinear markers.
    """
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


def unit_vector(v: Array) -> Array:
    """``v`` divided by its length."""
    return v / np.linalg.norm(v)


def tilt_phi(frame: Frame) -> float:
    """Tilt angle phi of the sensor (thesis §2.4.2, "Tilt Angle"): mean of alpha and beta.

    T_0x = e_y x N_z, T_0y = N_z x T_0x; alpha = atan2(-T_y.T_0x, T_x.T_0x),
    beta = atan2(T_x.T_0y, T_y.T_0y); their mean is taken on the circle.
    """
    t0x = np.cross([0.0, 1.0, 0.0], frame.nz)
    if np.linalg.norm(t0x) < 1e-12:
        raise CalibrationError("the optical axis is parallel to e_y: the tilt angle phi is undefined (thesis §2.5.2)")
    t0x = unit_vector(t0x)
    t0y = np.cross(frame.nz, t0x)
    alpha = np.arctan2(-(frame.ty @ t0x), frame.tx @ t0x)
    beta = np.arctan2(frame.tx @ t0y, frame.ty @ t0y)
    return float(np.arctan2(np.sin(alpha) + np.sin(beta), np.cos(alpha) + np.cos(beta)))


def format_vector(v: ArrayLike) -> str:
    """A vector as ``(x, y, ...)`` with four significant digits, for messages."""
    return "(" + ", ".join(f"{x:.4g}" for x in np.asarray(v, dtype=np.float64)) + ")"


def wrap_angle(angle: float) -> float:
    """The angle in (-pi, pi], rad."""
    return float(np.arctan2(np.sin(angle), np.cos(angle)))


def axis_point(frame: Frame) -> tuple[Array, float]:
    """r_0 (x0, y0) where the optical axis meets the target plane z = 0, and ``g = |r_c - r_0|``."""
    nz = frame.nz
    if not nz[2] > 1e-12:
        raise CalibrationError("the optical axis does not meet the target plane in front of the camera")
    g = float(frame.origin[2] / nz[2])
    r0 = frame.origin - g * nz
    return r0[:2].copy(), g


def camera_dict(camera: Camera, r0: ArrayLike, phi: float, g: float) -> dict:
    """Camera parameters under the contract's keys (thesis Table 2.1 plus phi, r_cs, c0, c2)."""
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
