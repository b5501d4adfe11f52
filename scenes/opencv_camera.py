"""The thesis's camera in OpenCV's convention: ``K``, ``dist`` (k1, k2, p1, p2, k3), ``R``, ``t``.

OpenCV's pinhole model (``cv2.projectPoints``) maps a world point P to camera coordinates X = R P + t (x right,
y down, z forward), to x' = X/Z, y' = Y/Z, r^2 = x'^2 + y'^2, then
x'' = x' (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x'y' + p2 (r^2 + 2 x'^2) (likewise y''), and to the pixel
(fx x'' + cx, fy y'' + cy), **pixel centres at integer coordinates**.

The thesis's camera (thesis §1.6.2, §2.5.1; :mod:`scopetwin.scenes.camera`, docs/contract.md "Camera") looks along
-N_z with the column growing along T_x and the row against T_y, and the centre of pixel (row, col) at
(col + 0.5, row + 0.5). So, exactly,

* ``R`` has the rows T_x, -T_y, -N_z (right-handed: T_x x (-T_y) = -N_z), ``t = -R r_c`` (mm);
* ``fx = fy = b c0 / pitch``, ``cx = nx/2 - 0.5 - x_cs/pitch``, ``cy = ny/2 - 0.5 + y_cs/pitch``;
* the radial distortion ``r_dist = (c0 + c2 |r|) r`` of §2.5.1 is, in OpenCV's normalised coordinates, the factor
  1 + a r with a = c2 b / c0: a term **linear** in r, which OpenCV's polynomial in r^2 lacks. With c2 = 0 the
  conversion is exact (``dist`` = 0). Otherwise ``dist`` = (k1, k2, 0, 0, k3) and a common scale s of fx, fy are
  fitted by least squares to r (1 + a r) over the ray of every pixel centre of the image, and the size of the
  approximation — the largest and the RMS distance, in pixels, between where the two models put a point over the
  image — is stated with the camera (:attr:`OpenCVCamera.max_error_px`, :attr:`OpenCVCamera.rms_error_px`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array


@dataclass(frozen=True)
class OpenCVCamera:
    """A camera in OpenCV's convention (module docstring); lengths in mm, pixel centres at integers.

    Attributes
    ----------
    K : ndarray, (3, 3)
        Camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], px.
    dist : ndarray, (5,)
        Distortion coefficients in OpenCV's order (k1, k2, p1, p2, k3).
    R : ndarray, (3, 3)
        Rotation world -> camera.
    t : ndarray, (3,)
        Translation world -> camera, mm (X_cam = R P + t).
    image_size : tuple of int
        (width, height) in pixels.
    max_error_px, rms_error_px : float
        Largest and RMS distance (px) over the image's pixel centres between this model and the thesis's camera
        it was made from (0 when the thesis camera has c2 = 0: the conversion is then exact).
    """

    K: Array
    dist: Array
    R: Array
    t: Array
    image_size: tuple[int, int]
    max_error_px: float = 0.0
    rms_error_px: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: ``K``, ``dist``, ``R``, ``t``, ``image_size``, ``max_error_px``, ``rms_error_px``."""
        return {
            "K": self.K.tolist(),
            "dist": self.dist.tolist(),
            "R": self.R.tolist(),
            "t": self.t.tolist(),
            "image_size": list(self.image_size),
            "max_error_px": self.max_error_px,
            "rms_error_px": self.rms_error_px,
        }

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> OpenCVCamera:
        """The inverse of :meth:`as_dict`."""
        w, h = data["image_size"]
        return cls(
            np.asarray(data["K"], dtype=np.float64).reshape(3, 3),
            np.asarray(data["dist"], dtype=np.float64).reshape(5),
            np.asarray(data["R"], dtype=np.float64).reshape(3, 3),
            np.asarray(data["t"], dtype=np.float64).reshape(3),
            (int(w), int(h)),
            float(data.get("max_error_px", 0.0)),
            float(data.get("rms_error_px", 0.0)),
        )

    @property
    def rvec(self) -> Array:
        """``R`` as a rotation vector (axis times angle, rad), the form ``cv2.projectPoints`` takes."""
        from scipy.spatial.transform import Rotation

        return np.asarray(Rotation.from_matrix(self.R).as_rotvec(), dtype=np.float64)

    def project(self, points: ArrayLike) -> Array:
        """World points (..., 3), mm -> pixel coordinates (..., 2) with OpenCV's formula (no cv2 needed)."""
        p = np.asarray(points, dtype=np.float64)
        x = p @ self.R.T + self.t
        xp, yp = x[..., 0] / x[..., 2], x[..., 1] / x[..., 2]
        k1, k2, p1, p2, k3 = self.dist
        r2 = xp * xp + yp * yp
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xpp = xp * radial + 2 * p1 * xp * yp + p2 * (r2 + 2 * xp * xp)
        ypp = yp * radial + p1 * (r2 + 2 * yp * yp) + 2 * p2 * xp * yp
        return np.stack([self.K[0, 0] * xpp + self.K[0, 2], self.K[1, 1] * ypp + self.K[1, 2]], axis=-1)


def _normalised_radii(camera: Camera, max_points: int) -> NDArray[np.float64]:
    """r' = |(x', y')| (OpenCV's undistorted normalised radius) of the ray of every pixel centre (or a regular
    subset of at most ``max_points``)."""
    step = max(1, int(np.ceil(np.sqrt(camera.nx * camera.ny / max_points))))
    centres = camera.pixel_centers(slice(None, None, step), slice(None, None, step)).reshape(-1, 2)
    uv = camera.undistort(camera.pixel_to_sensor(centres))  # ideal sensor points, mm
    return np.asarray(np.hypot(uv[:, 0], uv[:, 1]) / camera.b, dtype=np.float64)


def opencv_camera(camera: Camera, max_points: int = 1 << 20) -> OpenCVCamera:
    """The thesis camera in OpenCV's convention (module docstring), the distortion fitted where it is not exact.

    Parameters
    ----------
    camera : Camera
        The camera (thesis §1.6.2, §2.5.1). A thin lens does not change the chief ray of a pixel, so it is ignored.
    max_points : int
        Most pixel centres the distortion fit and its error use (a regular subset of a larger image).

    Returns
    -------
    OpenCVCamera
        ``K``, ``dist``, ``R``, ``t``, and the size of the approximation over the image in px (0 when c2 = 0).
    """
    f = camera.frame
    R = np.stack([f.tx, -f.ty, -f.nz])
    t = -R @ f.origin
    focal = camera.b * camera.c0 / camera.pitch  # px
    cx = 0.5 * camera.nx - 0.5 - camera.r_cs[0] / camera.pitch
    cy = 0.5 * camera.ny - 0.5 + camera.r_cs[1] / camera.pitch
    a = camera.c2 * camera.b / camera.c0
    scale, k = 1.0, np.zeros(3)
    max_err = rms_err = 0.0
    if a != 0.0:
        r = _normalised_radii(camera, max_points)
        target = r * (1.0 + a * r)  # the thesis's distorted radius, normalised (times focal: px)
        basis = np.stack([r, r**3, r**5, r**7], axis=-1)
        norm = np.maximum(np.abs(basis).max(axis=0), 1e-300)  # columns of equal size for a well-posed solve
        coef, *_ = np.linalg.lstsq(basis / norm, target, rcond=None)
        coef = coef / norm
        scale = float(coef[0])
        k = coef[1:] / scale
        err = focal * np.abs(basis @ coef - target)  # the radial distance between the two models, px
        max_err, rms_err = float(err.max()), float(np.sqrt(np.mean(err**2)))
    K = np.array([[focal * scale, 0.0, cx], [0.0, focal * scale, cy], [0.0, 0.0, 1.0]])
    dist = np.array([k[0], k[1], 0.0, 0.0, k[2]])
    return OpenCVCamera(K, dist, R, t, (camera.nx, camera.ny), max_err, rms_err)
