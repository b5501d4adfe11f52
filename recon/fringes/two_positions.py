"""The absolute height per pixel from two display positions (thesis §1.3: resolving the height-normal ambiguity).

With the display moved along its normal N_z by a known distance (as :func:`scopetwin.scenes.pattern_stage.
shift_pattern` moves the marker pattern), a pixel sees a display point P_1 in the first position and P_2 in the
second. Both lie on the same reflected ray (the surface point and its normal do not change), so the line P_1 P_2 is
the reflected ray and its closest approach to the pixel's camera ray is the surface point: the absolute height with
no frame criterion. The display points' noise is carried into the height by the Jacobian of this construction
(central differences in the four display coordinates).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scopetwin.recon.fringes.phase import DisplayCoordinates, FringeDecodingError
from scopetwin.recon.fringes.slopes import JACOBIAN_STEP_MM, PixelRays, display_points
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array, Frame


@dataclass(frozen=True)
class DirectPoints:
    """Surface points triangulated per pixel from two display positions.

    Attributes
    ----------
    index : ndarray of int
        Flat pixel index.
    xy : ndarray, (n, 2)
        Base-plane point, mm.
    z : ndarray, (n,)
        Height above the base plane, mm.
    z_std : ndarray, (n,)
        Its standard uncertainty, mm.
    """

    index: NDArray[np.intp]
    xy: Array
    z: Array
    z_std: Array


def moved_frame(frame: Frame, shift_mm: float) -> Frame:
    """The display's frame moved by ``shift_mm`` along its normal N_z (the second position)."""
    return Frame(frame.origin + float(shift_mm) * frame.nz, frame.tx, frame.ty, frame.nz)


def _closest_on_camera_ray(o: Array, d: Array, p1: Array, p2: Array) -> tuple[Array, NDArray[np.bool_]]:
    """Points of the camera rays o + lam d closest to the lines p1 + t (p2 - p1); whether the lines are not parallel."""
    e = p2 - p1
    w = o - p1
    a = np.einsum("ij,ij->i", d, d)
    b = np.einsum("ij,ij->i", d, e)
    c = np.einsum("ij,ij->i", e, e)
    dd = np.einsum("ij,ij->i", d, w)
    ee = np.einsum("ij,ij->i", e, w)
    den = a * c - b * b
    ok = den > 1e-12 * a * c
    lam = np.where(ok, (b * ee - c * dd) / np.where(ok, den, 1.0), np.nan)
    return o + lam[:, None] * d, ok & (lam > 0)


def two_position_points(
    camera: Camera,
    frame_1: Frame,
    shift_mm: float,
    first: DisplayCoordinates,
    second: DisplayCoordinates,
    base: Frame | None = None,
) -> DirectPoints:
    """The surface point seen by every pixel decoded in both display positions (module docstring).

    Parameters
    ----------
    camera : Camera
        The camera.
    frame_1 : Frame
        The display's frame in the first position.
    shift_mm : float
        How far the display moved along its N_z for the second, mm.
    first, second : DisplayCoordinates
        The decoded display points of the two positions (the same image shape).
    base : Frame, optional
        The substrate's base plane (default: the global frame).

    Raises
    ------
    FringeDecodingError
        The two maps differ in shape, the shift is zero or not finite, or no pixel is valid in both.
    """
    if first.shape != second.shape or first.block != second.block:
        raise FringeDecodingError(f"the two positions' maps differ in shape: {first.shape} and {second.shape}")
    if not np.isfinite(shift_mm) or shift_mm == 0:
        raise FringeDecodingError(f"the display shift must be a finite, non-zero distance, got {shift_mm!r} mm")
    both = first.valid & second.valid
    if not both.any():
        raise FringeDecodingError("no pixel is decoded in both display positions")
    rays = PixelRays.of(camera, both, first.block)
    frame_2 = moved_frame(frame_1, shift_mm)
    k = rays.index
    vals = [a.ravel()[k] for a in (first.u, first.v, second.u, second.v)]
    stds = [a.ravel()[k] for a in (first.u_std, first.v_std, second.u_std, second.v_std)]
    n, e = len(k), JACOBIAN_STEP_MM
    # the point and its 8 displaced copies: (9 n) rays at once
    steps = np.zeros((9, 4))
    for j in range(4):
        steps[1 + 2 * j, j], steps[2 + 2 * j, j] = e, -e
    coords = [(vals[j][None, :] + steps[:, j : j + 1]).ravel() for j in range(4)]
    p1 = display_points(frame_1, coords[0], coords[1])
    p2 = display_points(frame_2, coords[2], coords[3])
    pts, ok = _closest_on_camera_ray(np.tile(rays.origins, (9, 1)), np.tile(rays.dirs, (9, 1)), p1, p2)
    local = (base.to_local(pts) if base is not None else pts).reshape(9, n, 3)
    good = np.asarray(ok.reshape(9, n).all(axis=0), dtype=bool)
    z = local[0, :, 2]
    var = np.zeros(n)
    for j in range(4):
        dz = (local[1 + 2 * j, :, 2] - local[2 + 2 * j, :, 2]) / (2 * e)
        var += (dz * stds[j]) ** 2
    return DirectPoints(k[good], local[0, good, :2], z[good], np.sqrt(var[good]))
