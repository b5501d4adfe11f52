"""Helpers of the calibration benchmarks: deviations, printing, and OpenCV's solvePnP as the peer."""

from __future__ import annotations

import cv2
import numpy as np

from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Frame


def fmt(v, scale: float = 1.0, digits: int = 3) -> str:
    a = np.atleast_1d(np.asarray(v, dtype=np.float64)) * scale
    return "(" + ", ".join(f"{x:.{digits}e}" for x in a) + ")"


def frame_dev(f: Frame, t: Frame) -> dict[str, np.ndarray]:
    return {"r": f.origin - t.origin, "T_x": f.tx - t.tx, "T_y": f.ty - t.ty, "N_z": f.nz - t.nz}


def solvepnp(xy: np.ndarray, px: np.ndarray, camera: Camera, flag: int) -> Frame:
    """Camera pose from OpenCV's solvePnP with the TRUE intrinsics (b/pitch, principal point); target z = 0.

    OpenCV's camera axes are (T_x, -T_y, -N_z) of the thesis camera; continuous pixel coordinates
    are used on both sides, so the principal point is (nx/2 - x_cs/pitch, ny/2 + y_cs/pitch).
    """
    fpx = camera.b / camera.pitch
    cx = 0.5 * camera.nx - camera.r_cs[0] / camera.pitch
    cy = 0.5 * camera.ny + camera.r_cs[1] / camera.pitch
    k = np.array([[fpx, 0.0, cx], [0.0, fpx, cy], [0.0, 0.0, 1.0]])
    obj = np.column_stack([xy, np.zeros(len(xy))]).astype(np.float64)
    ok, rvec, tvec = cv2.solvePnP(obj, np.ascontiguousarray(px, dtype=np.float64), k, None, flags=flag)
    if not ok:
        raise RuntimeError("solvePnP failed")
    if flag == cv2.SOLVEPNP_SQPNP:  # polish as an user of SQPnP would
        rvec, tvec = cv2.solvePnPRefineLM(obj, np.ascontiguousarray(px, dtype=np.float64), k, None, rvec, tvec)
    rot, _ = cv2.Rodrigues(rvec)
    rc = -rot.T @ tvec.ravel()
    return Frame(rc, rot[0], -rot[1], -rot[2])


def pose_error(f: Frame, t: Frame) -> tuple[float, float]:
    """|Δr_c| in mm and the rotation angle between the two frames in rad."""
    r = np.stack([f.tx, f.ty, f.nz]) @ np.stack([t.tx, t.ty, t.nz]).T
    ang = float(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)))
    return float(np.linalg.norm(f.origin - t.origin)), ang
