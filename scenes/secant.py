"""The secant iteration of thesis §1.6.4 (eq. 1.6): where rays meet a surface z = h(x, y), vectorised over the rays.

The one iteration of the project: the substrate's height maps (:mod:`scopetwin.scenes.surface`, on the spline's
cells of :mod:`scopetwin.scenes.bicubic`) and the reconstruction's fitted surfaces (:mod:`scopetwin.recon.substrate`)
feed it their heights.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scopetwin.scenes.geometry import Array

#: A surface given by a function: heights h(x, y), mm, of local base-plane points (vectorised).
HeightFunction = Callable[[Array, Array], Array]


class HeightModel(Protocol):
    """A surface given by a model with a ``height`` method (:class:`HeightMap`, a fitted basis surface, ...)."""

    def height(self, x: Array, y: Array) -> Array:
        """h(x, y), mm, of local base-plane points."""
        ...


def secant_intersection(
    surface: HeightModel | HeightFunction,
    origins: ArrayLike,
    directions: ArrayLike,
    lam0: ArrayLike,
    lam1: ArrayLike | None = None,
    tol: float = 1e-10,
    max_iter: int = 60,
    residual: Callable[..., Array] | None = None,
) -> tuple[Array, NDArray[np.bool_]]:
    """Ray parameters where rays meet the surface z = h(x, y), by the secant iteration (thesis §1.6.4, eq. 1.6).

    The root of f(lambda) = h(x(lambda), y(lambda)) - z(lambda) along each ray is searched by
    lambda_{k+1} = (lambda_{k-1} f_k - lambda_k f_{k-1}) / (f_k - f_{k-1}), vectorised over the rays;
    a ray stops when ``|f|`` < ``tol`` (its value is kept), or when a step is undefined (f_k = f_{k-1}) or
    not finite. Only the rays still iterating are evaluated.

    Parameters
    ----------
    surface : HeightModel or callable
        The surface: an object with ``height(x, y)`` (a :class:`HeightMap`, a fitted height model) or a
        function ``h(x, y)``, in the base-plane coordinates of ``origins`` and ``directions``.
    origins, directions : array_like, (n, 3)
        Rays in the surface's base-plane (local) coordinates.
    lam0 : array_like, (n,)
        First start value of the ray parameter (NaN or inf: the ray is not traced).
    lam1 : array_like, (n,), optional
        Second start value. None: the intersection with the plane z = h at the first start point,
        lambda_1 = lambda_0 + f(lambda_0) / d_z (one Newton step with the slope of a flat surface).
    tol : float
        Convergence threshold on ``|f|``, mm.
    max_iter : int
        Largest number of secant steps.
    residual : callable, optional
        ``residual(lam, idx)`` -> f at ``lam`` for the rays ``idx`` (all rays where None), in place of the one formed
        from ``surface.height``: for an evaluator that keeps per-ray state between steps (the dataset maps' cell
        cache, :meth:`scopetwin.scenes.bicubic.BicubicCells.intersect`). The iteration is this one either way.

    Returns
    -------
    lam : ndarray, (n,)
        Last iterate of each ray (the hit where ``converged``).
    converged : ndarray of bool, (n,)
        Where ``|f(lam)|`` < ``tol`` was reached. Whether the hit is in front of the camera (lam > 0) or on
        the substrate is for the caller to decide.
    """
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    n = len(o)
    f = residual if residual is not None else _height_residual(surface, o, d)
    lam_prev = np.array(lam0, dtype=np.float64).reshape(n)
    f_prev = f(np.where(np.isfinite(lam_prev), lam_prev, 0.0))
    if lam1 is None:
        with np.errstate(divide="ignore", invalid="ignore"):
            lam_cur = lam_prev + f_prev / d[:, 2]
    else:
        lam_cur = np.array(lam1, dtype=np.float64).reshape(n)
    active = np.isfinite(lam_cur)
    f_cur = f(np.where(active, lam_cur, 0.0))
    converged = np.zeros(n, dtype=bool)
    for _ in range(max_iter):
        done = active & (np.abs(f_cur) < tol)
        converged |= done
        active &= ~done
        if not active.any():
            break
        _secant_step(f, lam_prev, f_prev, lam_cur, f_cur, active)
    converged |= active & (np.abs(f_cur) < tol)
    return lam_cur, converged


def _height_residual(surface: HeightModel | HeightFunction, o: Array, d: Array) -> Callable[..., Array]:
    """f(lam, idx) = h(x, y) - z at the points o + lam d of the rays ``idx`` (all rays where None)."""
    height = surface.height if hasattr(surface, "height") else surface

    def from_height(lam: Array, idx: NDArray[np.intp] | None = None) -> Array:
        oo, dd = (o, d) if idx is None else (o[idx], d[idx])
        p = oo + lam[:, None] * dd
        return np.asarray(height(p[:, 0], p[:, 1]), dtype=np.float64) - p[:, 2]

    return from_height


def _secant_step(
    f: Callable[..., Array], lam_prev: Array, f_prev: Array, lam_cur: Array, f_cur: Array, active: NDArray[np.bool_]
) -> None:
    """One secant step (eq. 1.6) of the ``active`` rays, in place; a ray whose step is undefined stops."""
    a = np.flatnonzero(active)
    den = f_cur[a] - f_prev[a]
    ok = den != 0
    with np.errstate(invalid="ignore", over="ignore"):
        new = np.where(ok, (lam_prev[a] * f_cur[a] - lam_cur[a] * f_prev[a]) / np.where(ok, den, 1.0), np.nan)
    lam_prev[a], f_prev[a] = lam_cur[a], f_cur[a]
    lam_cur[a] = new
    good = np.isfinite(new)
    active[a[~good]] = False
    ag = a[good]
    f_cur[ag] = f(lam_cur[ag], ag)
