"""Mitsuba shapes of the substrate: heightfield meshes with analytic vertex normals (thesis §1.6.4, §1.4).

The substrate's height map (:class:`scopetwin.scenes.surface.HeightMap`, a bicubic spline) is
tessellated on a regular grid; vertex positions are (x, y, h(x, y)) and vertex normals
are the spline's exact normals (-h_x, -h_y, 1)/|...| (eq. 1.2), so Mitsuba interpolates
exact normals across each triangle. 256 x 512 vertices over the 25.2 x 57 mm substrate
give 0.11 µm position and 0.7 µrad normal error for the §1.10 surfaces (docs/rendering.md).

Only the region of interest reflects (thesis §1.4, Fig. 1.3). The holding-frame regions
roi_length/2 <= |y| <= size_y/2 are separate, black meshes on the same surface: they occlude
exactly the camera rays whose surface hit lies outside the ROI (the mask of
:meth:`scopetwin.scenes.surface.Substrate.points_and_normals`), and, lying on the surface rather than
above it, never block a ray reflected near the ROI boundary.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.mitsuba.variant import mitsuba, resolve
from scopetwin.scenes.surface import HeightMap

#: Vertex counts (x, y) of the mesh over the whole substrate (docs/rendering.md: enough for §1.10).
DEFAULT_VERTICES = (256, 512)

#: A perfect mirror (reflectance 1): Mitsuba's conductor without absorption.
MIRROR_BSDF: dict[str, Any] = {"type": "conductor", "material": "none"}
#: Black: reflects nothing.
BLACK_BSDF: dict[str, Any] = {"type": "diffuse", "reflectance": {"type": "uniform", "value": 0.0}}


def grid_arrays(
    heights: HeightMap, x_range: tuple[float, float], y_range: tuple[float, float], nx: int, ny: int
) -> tuple[NDArray[np.float32], NDArray[np.float32], NDArray[np.uint32]]:
    """Vertex positions, analytic vertex normals and faces of a heightfield grid.

    Parameters
    ----------
    heights : HeightMap
        The surface h(x, y), mm (base-plane = global coordinates).
    x_range, y_range : (float, float)
        Extent of the grid, mm (inclusive; vertices at both ends).
    nx, ny : int
        Vertex counts along x and y (>= 2).

    Returns
    -------
    positions : (nx*ny, 3) float32
        (x, y, h) with vertex k = row*nx + col, row along y.
    normals : (nx*ny, 3) float32
        Unit normals from the spline gradient (thesis eq. 1.2).
    faces : (2*(nx-1)*(ny-1), 3) uint32
        Triangles wound counter-clockwise seen from +z (geometric normal +z).
    """
    if nx < 2 or ny < 2:
        raise SetupError(f"a heightfield mesh needs at least 2 x 2 vertices, got {nx} x {ny}")
    x = np.linspace(x_range[0], x_range[1], nx)
    y = np.linspace(y_range[0], y_range[1], ny)
    xx, yy = np.meshgrid(x, y)
    zz = heights.height(xx, yy)
    normals = heights.normals(xx, yy)
    positions = np.stack([xx, yy, zz], axis=-1).reshape(-1, 3)
    col, row = np.meshgrid(np.arange(nx - 1), np.arange(ny - 1))
    v00 = (row * nx + col).ravel()
    v10 = v00 + 1
    v01 = v00 + nx
    v11 = v01 + 1
    faces = np.concatenate([np.stack([v00, v10, v11], axis=-1), np.stack([v00, v11, v01], axis=-1)])
    return positions.astype(np.float32), normals.reshape(-1, 3).astype(np.float32), faces.astype(np.uint32)


def heightfield_mesh(
    heights: HeightMap,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    nx: int,
    ny: int,
    name: str = "heightfield",
    bsdf: dict[str, Any] | None = None,
    variant: str | None = None,
) -> Any:
    """A ``mitsuba.Mesh`` of the surface over a rectangle, with analytic vertex normals.

    ``bsdf`` is a scene-dictionary BSDF (default: a perfect mirror, :data:`MIRROR_BSDF`); ``variant`` the
    Mitsuba variant (default ``choose("mono")``).
    """
    mi = mitsuba(resolve(variant, "mono"))
    positions, normals, faces = grid_arrays(heights, x_range, y_range, nx, ny)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf if bsdf is not None else MIRROR_BSDF)
    mesh = mi.Mesh(name, len(positions), len(faces), props=props, has_vertex_normals=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(positions.ravel())
    params["vertex_normals"] = mi.Float(normals.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    return mesh


def substrate_shapes(
    heights: HeightMap,
    size: tuple[float, float],
    roi_length: float,
    vertices: tuple[int, int] = DEFAULT_VERTICES,
    variant: str | None = None,
) -> dict[str, Any]:
    """Scene-dictionary entries of the substrate: the mirroring ROI and the black frame regions.

    Parameters
    ----------
    heights : HeightMap
        The substrate surface (global = base-plane coordinates, §1.10).
    size : (float, float)
        Substrate extent (x, y), mm, centred on the origin.
    roi_length : float
        Length of the region of interest along y, mm; |y| >= roi_length/2 is holding frame.
    vertices : (int, int)
        Vertex counts (x, y) the whole substrate would have; every part keeps this spacing.
    variant : str, optional
        Mitsuba variant (default ``choose("mono")``).

    Returns
    -------
    dict
        ``substrate_roi`` (mirror) and, when the ROI is shorter than the substrate,
        ``frame_low`` / ``frame_high`` (black), each a ``mitsuba.Mesh``.
    """
    if not isinstance(heights, HeightMap):
        raise SetupError(f"the substrate's heights must be a scenes.surface.HeightMap, got {type(heights).__name__}")
    variant = resolve(variant, "mono")
    sx, sy = (float(s) for s in size)
    nx, ny = vertices
    dy = sy / (ny - 1)
    half_roi = 0.5 * float(roi_length)
    xr = (-0.5 * sx, 0.5 * sx)
    n_roi = max(2, math.ceil(2 * half_roi / dy) + 1)
    out = {
        "substrate_roi": heightfield_mesh(
            heights, xr, (-half_roi, half_roi), nx, n_roi, "substrate_roi", variant=variant
        )
    }
    strip = 0.5 * sy - half_roi
    if strip > 1e-9:
        n_strip = max(2, math.ceil(strip / dy) + 1)
        out["frame_low"] = heightfield_mesh(
            heights, xr, (-0.5 * sy, -half_roi), nx, n_strip, "frame_low", BLACK_BSDF, variant
        )
        out["frame_high"] = heightfield_mesh(
            heights, xr, (half_roi, 0.5 * sy), nx, n_strip, "frame_high", BLACK_BSDF, variant
        )
    return out
