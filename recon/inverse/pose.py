"""The setup's refinement (``refine_setup``): 12 rigid-motion parameters of camera and pattern among the unknowns,
held near the calibration by a Gaussian prior of the given standard deviations (thesis §2.7) and within a box of
``pose_box`` of them."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array, Frame
from scopetwin.scenes.pattern import MarkerPattern


def _pose_update(camera: Camera, pattern: MarkerPattern, p: Array) -> tuple[Camera, MarkerPattern]:
    """Apply a rigid-motion step (camera shift, rotation vector; pattern shift, rotation vector) exactly."""
    from scipy.spatial.transform import Rotation

    def moved(frame: Frame, shift: Array, rot: Array) -> Frame:
        r = Rotation.from_rotvec(rot).as_matrix()
        return Frame(frame.origin + shift, r @ frame.tx, r @ frame.ty, r @ frame.nz)

    cam = camera.with_(frame=moved(camera.frame, p[0:3], p[3:6]))
    pf = moved(pattern.frame, p[6:9], p[9:12])
    return cam, replace(pattern, frame=pf)


def _box_fraction(pose: Array, step: Array, bound: Array) -> float:
    """Largest f in [0, 1] with |pose + f step| <= bound componentwise (pose itself inside the box)."""
    out = np.abs(step) > 0
    room = np.where(step > 0, bound - pose, bound + pose)
    with np.errstate(divide="ignore", invalid="ignore"):
        limits = np.where(out, np.maximum(room, 0.0) / np.abs(step), np.inf)
    return float(min(1.0, np.min(limits)))


@dataclass
class _PoseBlocks:
    """The pose's blocks of one step's normal equations: prior sigmas (12), A_pp, A_pc (pose x coefficients), g_p."""

    sig: Array
    a_pp: Array
    a_pc: sp.csr_matrix
    g_p: Array


def _pose_blocks(
    jp: Array,
    wgt: Array,
    ja: sp.csr_matrix,
    r: Array,
    pose_sigma: tuple[float, float, float, float],
    pose: Array,
    span: Array | None,
) -> _PoseBlocks:
    """The 12 pose parameters' blocks of the normal equations, their Gaussian prior about the setup included.

    ``jp``: the pose Jacobian of the usable pixels scaled by the photometric gain, ``ja`` the coefficients' one,
    ``r`` the residuals, ``pose`` the motions so far; ``span``: the coefficients' span where the fit keeps to one.
    """
    sig = np.repeat(np.asarray(pose_sigma, dtype=np.float64), 3)  # (shift, rotation) x 3 per device
    prior = 1.0 / np.maximum(sig, 1e-12) ** 2
    jpw = jp.T * wgt[None, :]
    a_pp = jpw @ jp + np.diag(prior)
    a_pc = sp.csr_matrix(jpw @ ja if span is None else (jpw @ ja) @ span)
    g_p = jpw @ r - prior * pose
    return _PoseBlocks(sig, a_pp, a_pc, g_p)
