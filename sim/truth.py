"""Ground truth of a rendered measurement: where each marker centre is imaged, and which markers are whole.

The image of a marker centre is found by tracing it through the real optical
path, not by projecting it: the sensor point whose camera ray, reflected by the
substrate (or mirror), lands exactly on the marker centre (thesis §1.6: camera
ray, secant surface intersection, reflection, pattern plane). It is solved per
marker with a vectorised Newton iteration on the ideal sensor coordinates,
started from the flat-mirror solution.

A marker is *visible* when its centre and every sampled rim point reach the
pattern through the reflecting region (ROI, substrate, mirror) and land inside
the image: the marker is imaged whole.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.analytic import AnalyticScene
from scopetwin.scenes.geometry import Array
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap


@dataclass(frozen=True)
class MarkerTruth:
    """Truth for every marker of a pattern (arrays aligned with ``ij``)."""

    ij: NDArray[np.int64]
    center_px: Array  # (n, 2) continuous pixel coordinates (col, row) of the centre's image
    visible: NDArray[np.bool_]
    converged: NDArray[np.bool_]

    def as_records(self) -> list[dict]:
        """JSON-ready records with the contract's keys (docs/contract.md, "Truth")."""
        out = []
        for (i, j), (col, row), vis, ok in zip(self.ij, self.center_px, self.visible, self.converged, strict=True):
            out.append(
                {
                    "i": int(i),
                    "j": int(j),
                    "center_col": float(col) if ok else None,
                    "center_row": float(row) if ok else None,
                    "visible": bool(vis),
                }
            )
        return out


def _flat_guess(scene: AnalyticScene, points: Array) -> Array:
    """Ideal sensor coordinates of points seen directly (target) or in the plane mirror z = 0."""
    cam = scene.camera
    if scene.setup.scene == "target":
        return cam.project_ideal(points)
    return cam.project_ideal(points * np.array([1.0, 1.0, -1.0]))


def solve_images(
    scene: AnalyticScene, points: Array, tol: float = 1e-11, max_iter: int = 30, step: float = 1e-6
) -> tuple[Array, NDArray[np.bool_], NDArray[np.bool_]]:
    """Ideal sensor points (u, v) whose traced rays land on the given pattern points.

    Parameters
    ----------
    scene : AnalyticScene
        The traced setup.
    points : ndarray, (n, 3)
        Global points on the pattern plane, mm.
    tol : float
        Convergence threshold on the landing error in the pattern plane, mm.
    step : float
        Finite-difference step on the sensor for the 2x2 Jacobian, mm.

    Returns
    -------
    uv : ndarray, (n, 2)
        Ideal sensor coordinates, mm.
    converged : ndarray of bool
        Landing error below ``tol``.
    reaches : ndarray of bool
        The converged ray really reaches the pattern through the reflecting region.
    """
    cam = scene.camera
    target = scene.pattern.frame.to_local(points)[:, :2]
    uv = _flat_guess(scene, points)
    n = len(points)
    converged = np.zeros(n, dtype=bool)
    offsets = np.array([[0.0, 0.0], [step, 0.0], [0.0, step]])

    def land(q: Array) -> tuple[Array, NDArray[np.bool_]]:
        o, d = cam.rays_from_sensor(q)
        return scene.pattern_hits(o, d)

    for _ in range(max_iter):
        active = ~converged & np.all(np.isfinite(uv), axis=1)
        if not active.any():
            break
        q = uv[active]
        trial = (q[:, None, :] + offsets[None]).reshape(-1, 2)
        xy, _ = land(trial)
        xy = xy.reshape(-1, 3, 2)
        resid = xy[:, 0] - target[active]
        jac = np.stack([(xy[:, 1] - xy[:, 0]) / step, (xy[:, 2] - xy[:, 0]) / step], axis=-1)
        err = np.linalg.norm(resid, axis=1)
        idx = np.flatnonzero(active)
        converged[idx[err < tol]] = True
        det = jac[:, 0, 0] * jac[:, 1, 1] - jac[:, 0, 1] * jac[:, 1, 0]
        good = np.isfinite(det) & (np.abs(det) > 0)
        inv = np.empty_like(jac)
        inv[:, 0, 0], inv[:, 1, 1] = jac[:, 1, 1], jac[:, 0, 0]
        inv[:, 0, 1], inv[:, 1, 0] = -jac[:, 0, 1], -jac[:, 1, 0]
        delta = np.einsum("nij,nj->ni", inv, resid) / np.where(good, det, 1.0)[:, None]
        upd = good & (err >= tol)
        uv[idx[upd]] -= delta[upd]
        uv[idx[~good]] = np.nan
    ok_uv = np.where(converged[:, None], uv, 0.0)
    _, reaches = land(ok_uv)
    return uv, converged, converged & reaches


def marker_truth(
    setup: Setup, heights: HeightMap | None = None, rim_points: int = 24, margin_px: float = 0.5
) -> MarkerTruth:
    """Image of every marker centre (continuous pixels) and whether the marker is imaged whole.

    Parameters
    ----------
    setup : Setup
        Any Part I setup ("deflectometry" needs ``heights``).
    heights : HeightMap, optional
        The substrate's true height map.
    rim_points : int
        Rim samples per marker for the visibility test.
    margin_px : float
        A visible marker's rim must stay this far inside the image border, px.
    """
    scene = AnalyticScene(setup, heights)
    cam = scene.camera
    pattern = scene.pattern
    ij = pattern.indices()
    uv, conv, reach = solve_images(scene, pattern.centers(ij))
    center_px = cam.sensor_to_pixel(cam.distort(np.where(conv[:, None], uv, np.nan)))
    rim = pattern.rim_points(rim_points, ij).reshape(-1, 3)
    uv_rim, conv_rim, reach_rim = solve_images(scene, rim)
    rim_px = cam.sensor_to_pixel(cam.distort(np.where(conv_rim[:, None], uv_rim, np.nan)))
    rim_ok = (reach_rim & cam.in_image(rim_px, margin_px)).reshape(len(ij), rim_points).all(axis=1)
    visible = reach & cam.in_image(center_px, margin_px) & rim_ok
    return MarkerTruth(ij, center_px, visible, conv)
