"""Surface normals from camera and pattern rays, and their conversion to gradients (thesis §1.2, §1.7).

The geometry of one marker (thesis §1.7.1): the camera ray with unit direction
``s_c`` meets the surface at ``r_i``; the marker centre on the pattern is ``r_p``;
the reflected ray runs along ``s_p = (r_p - r_i)/|r_p - r_i|``. The law of
reflection makes the normal the bisector ``N = (s_p - s_c)/|s_p - s_c|``
(eq. 1.1 with s_1 = s_c arriving and s_2 = s_p leaving). The gradient of the
height function follows from ``N = (-h_x, -h_y, 1)/sqrt(1 + h_x^2 + h_y^2)``
(§1.7.2) as ``h_x = -N_x/N_z``, ``h_y = -N_y/N_z`` (§1.7.3, eq. 1.2).

Everything is vectorised over the last axis (shape ``(..., 3)``), float64, mm.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.geometry import Array, Frame, normalize, row_norms


class GradientError(ScopetwinError, ValueError):
    """Rays from which no surface normal can be formed (degenerate geometry)."""


def normals_from_rays(hit_points: ArrayLike, camera_dirs: ArrayLike, pattern_points: ArrayLike) -> Array:
    """Unit surface normals from camera rays and the pattern points they see (thesis §1.7.1).

    Parameters
    ----------
    hit_points : array_like, (..., 3)
        Intersection r_i of each camera ray with the (current) surface, mm.
    camera_dirs : array_like, (..., 3)
        Direction s_c of each camera ray, pointing from the camera toward the surface
        (need not be normalised).
    pattern_points : array_like, (..., 3)
        Global position r_p of the marker centre seen along each ray, mm.

    Returns
    -------
    ndarray, (..., 3)
        N = (s_p - s_c)/|s_p - s_c| with s_p = (r_p - r_i)/|r_p - r_i|.

    Raises
    ------
    GradientError
        A pattern point coincides with its hit point, or the reflected direction equals the
        incoming one (grazing geometry: no normal is defined).
    """
    r_i = np.asarray(hit_points, dtype=np.float64)
    s_c = normalize(camera_dirs)
    to_p = np.asarray(pattern_points, dtype=np.float64) - r_i
    dist = row_norms(to_p, keepdims=True)
    if np.any(dist == 0):
        raise GradientError("a pattern point coincides with its surface point: no reflected ray")
    s_p = to_p / dist
    bis = s_p - s_c
    norm = row_norms(bis, keepdims=True)
    if np.any(norm < 1e-12):
        raise GradientError("reflected and incoming rays are parallel (grazing incidence): no normal defined")
    return bis / norm


def gradients_from_normals(normals: ArrayLike, frame: Frame | None = None) -> tuple[Array, Array]:
    """Height gradients (h_x, h_y) from unit normals: h_x = -N_x/N_z, h_y = -N_y/N_z (thesis §1.7.3).

    Parameters
    ----------
    normals : array_like, (..., 3)
        Surface normals in global coordinates.
    frame : Frame, optional
        The substrate's base plane (thesis §1.6.4); normals are rotated into it first.
        Default: the global frame (the substrate plane by definition, §1.10).

    Raises
    ------
    GradientError
        A normal lies in (or below) the base plane, N_z <= 0: the height function would not be single-valued.
    """
    n = np.asarray(normals, dtype=np.float64)
    if frame is not None:
        n = frame.vectors_to_local(n)
    nz = n[..., 2]
    if np.any(~(nz > 0)):
        raise GradientError("a surface normal points along or below the base plane (N_z <= 0)")
    return -n[..., 0] / nz, -n[..., 1] / nz


def normals_from_gradients(hx: ArrayLike, hy: ArrayLike, frame: Frame | None = None) -> Array:
    """Unit normals N = (-h_x, -h_y, 1)/sqrt(h_x^2 + h_y^2 + 1) (thesis §1.7.2), in global coordinates."""
    gx = np.asarray(hx, dtype=np.float64)
    gy = np.asarray(hy, dtype=np.float64)
    n = normalize(np.stack([-gx, -gy, np.ones_like(gx + gy)], axis=-1))
    return frame.vectors_to_global(n) if frame is not None else n


def marker_gradients(
    hit_points: ArrayLike, camera_dirs: ArrayLike, pattern_points: ArrayLike, frame: Frame | None = None
) -> tuple[Array, Array, Array]:
    """Base-plane position and gradients of each marker observation (thesis §1.7.1 then §1.7.3).

    Returns
    -------
    xy : ndarray, (..., 2)
        Hit points in base-plane coordinates, mm.
    hx, hy : ndarray
        Gradients at those points.
    """
    n = normals_from_rays(hit_points, camera_dirs, pattern_points)
    hx, hy = gradients_from_normals(n, frame)
    p = np.asarray(hit_points, dtype=np.float64)
    local = frame.to_local(p) if frame is not None else p
    return local[..., :2], hx, hy
