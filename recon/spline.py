"""The inverse fit's surface: a uniform cubic B-spline over the substrate's base plane.

Fine enough for 3 mm correlation lengths; its values and slopes at any point are 16 coefficients times the basis
(:meth:`SplineSurface.basis_rows`), so the inverse fit's Jacobian is sparse. :meth:`SplineSurface.span` writes the
centroid method's shifted basis (§1.8) as B-splines, so that the inverse fit can be held to its span.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray

from scopetwin.recon.shifted_basis import ShiftedBasis
from scopetwin.recon.substrate import Substrate2D
from scopetwin.scenes.bspline import cubic_bspline_second, cubic_bspline_weights
from scopetwin.scenes.geometry import Array
from scopetwin.scenes.surface import HeightMap


@dataclass(frozen=True)
class SplineSurface:
    """h(x, y) = sum c_mk B((x - x_k)/dx) B((y - y_m)/dy): a uniform cubic B-spline over the base plane.

    Coefficient (row m, column k) sits at (x0 + k*dx, y0 + m*dy)
    (the renderer's :class:`scopetwin.scenes.mitsuba.deflectometry_ad.SplineGrid` describes the same grid).
    """

    x0: float
    y0: float
    dx: float
    dy: float
    coef: Array

    @classmethod
    def covering(cls, sub: Substrate2D, spacing: float, value: float = 0.0) -> SplineSurface:
        """A spline of knot spacing ``spacing`` (mm) whose domain covers the substrate with half a cell to spare."""
        nx = int(np.ceil(sub.size_x / spacing)) + 4
        ny = int(np.ceil(sub.size_y / spacing)) + 4
        x0 = -0.5 * (nx - 1) * spacing
        y0 = -0.5 * (ny - 1) * spacing
        return cls(x0, y0, spacing, spacing, np.full((ny, nx), float(value)))

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.coef.shape[0]), int(self.coef.shape[1]))

    def with_coef(self, coef: Array) -> SplineSurface:
        return replace(self, coef=np.asarray(coef, dtype=np.float64).reshape(self.shape))

    def basis_rows(self, x: Array, y: Array) -> tuple[NDArray[np.int64], Array, Array, Array]:
        """For each point: the 16 coefficient indices (flattened) and the basis values and x/y derivatives there."""
        idx, w, wx, wy, _ = self._rows(x, y, False)
        return idx, w, wx, wy

    def basis_rows_second(
        self, x: Array, y: Array
    ) -> tuple[NDArray[np.int64], Array, Array, Array, tuple[Array, Array, Array]]:
        """:meth:`basis_rows` and the second derivatives (xx, xy, yy) of the basis."""
        idx, w, wx, wy, second = self._rows(x, y, True)
        assert second is not None
        return idx, w, wx, wy, second

    def axis_weights(
        self, x: Array, y: Array
    ) -> tuple[NDArray[np.int64], tuple[Array, Array, Array], tuple[Array, Array, Array]]:
        """For each point: the 16 coefficient indices (flattened; entry 4 m + k is coefficient row j - 1 + m, column
        i - 1 + k) and, along x and along y, the four cubic B-spline weights with their first and second derivatives
        by x (by y), each (n, 4). The basis is their tensor product: value ``outer(wy, wx)``, d/dx
        ``outer(wy, dwx)``, d2/dxdy ``outer(dwy, dwx)``, and so on."""
        ny, nx = self.shape
        u = (np.asarray(x, dtype=np.float64).ravel() - self.x0) / self.dx
        v = (np.asarray(y, dtype=np.float64).ravel() - self.y0) / self.dy
        i = np.clip(np.floor(u).astype(np.int64), 1, nx - 3)
        j = np.clip(np.floor(v).astype(np.int64), 1, ny - 3)
        tu, tv = u - i, v - j
        n, r4 = len(u), np.arange(4)
        idx = ((((j - 1)[:, None] + r4) * nx)[:, :, None] + ((i - 1)[:, None] + r4)[:, None, :]).reshape(n, 16)

        def axis(t: Array, step: float) -> tuple[Array, Array, Array]:
            w = np.stack(cubic_bspline_weights(t), axis=-1)  # (n, 8): the weights, then their derivatives by t
            second = np.stack(cubic_bspline_second(t), axis=-1)  # d^2 w / dt^2
            return w[:, :4], w[:, 4:] / step, second / step**2

        return idx, axis(tu, self.dx), axis(tv, self.dy)

    def _rows(
        self, x: Array, y: Array, second: bool
    ) -> tuple[NDArray[np.int64], Array, Array, Array, tuple[Array, Array, Array] | None]:
        idx, (wu, du, su), (wv, dv, sv) = self.axis_weights(x, y)
        w, wx, wy = _outer(wv, wu), _outer(wv, du), _outer(dv, wu)
        if not second:
            return idx, w, wx, wy, None
        return idx, w, wx, wy, (_outer(wv, su), _outer(dv, du), _outer(sv, wu))

    def design(self, x: Array, y: Array) -> sp.csr_matrix:
        """Sparse matrix of basis values: (design @ coef.ravel()) = h(x, y)."""
        idx, w, _, _ = self.basis_rows(x, y)
        n = idx.shape[0]
        return sp.csr_matrix((w.ravel(), (np.repeat(np.arange(n), 16), idx.ravel())), shape=(n, self.coef.size))

    def height(self, x: Any, y: Any) -> Array:
        """h(x, y), mm (any array shape; the points' shape broadcast).

        The tensor product summed one spline axis at a time (four rows of four coefficients gathered per point), the
        weights of :meth:`basis_rows` without forming its (n, 16) index and derivative arrays: the same values, about
        five times faster on the 10^5-10^6 points of a fringe measurement's secant steps.
        """
        xa, ya = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        ny, nx = self.shape
        u = (xa.ravel() - self.x0) / self.dx
        v = (ya.ravel() - self.y0) / self.dy
        i = np.clip(np.floor(u).astype(np.intp), 1, nx - 3)
        j = np.clip(np.floor(v).astype(np.intp), 1, ny - 3)
        wu = cubic_bspline_weights(u - i)[:4]
        wv = cubic_bspline_weights(v - j)[:4]
        flat = self.coef.ravel()
        base = (j - 1) * nx + (i - 1)
        out = np.zeros(u.shape)
        for m in range(4):
            row = base + m * nx
            out += wv[m] * (wu[0] * flat[row] + wu[1] * flat[row + 1] + wu[2] * flat[row + 2] + wu[3] * flat[row + 3])
        return out.reshape(xa.shape)

    def gradient(self, x: Any, y: Any) -> tuple[Array, Array]:
        """(dh/dx, dh/dy)."""
        xa = np.asarray(x, dtype=np.float64)
        idx, _, wx, wy = self.basis_rows(xa, np.asarray(y, dtype=np.float64))
        c = self.coef.ravel()[idx]
        return np.sum(wx * c, axis=1).reshape(xa.shape), np.sum(wy * c, axis=1).reshape(xa.shape)

    def heightmap(self, sub: Substrate2D, nx: int = 128, ny: int = 288) -> HeightMap:
        """The surface on the contract's node grid over the substrate (docs/contract.md, "Height maps")."""
        xs = np.linspace(*sub.x_range, nx)
        ys = np.linspace(*sub.y_range, ny)
        xx, yy = np.meshgrid(xs, ys)
        return HeightMap(self.height(xx, yy), sub.x_range[0], sub.x_range[1], sub.y_range[0], sub.y_range[1])

    def smoothness(self) -> sp.csr_matrix:
        """D: second differences (xx, yy, sqrt(2) xy) of the coefficient grid per mm^2 (thin-plate ``|D c|^2``)."""
        ny, nx = self.shape

        def second(n: int, h: float) -> sp.csr_matrix:
            return sp.diags([1.0, -2.0, 1.0], [0, 1, 2], shape=(n - 2, n)) / (h * h)

        def first(n: int, h: float) -> sp.csr_matrix:
            return sp.diags([-1.0, 1.0], [0, 1], shape=(n - 1, n)) / h

        ix, iy = sp.identity(nx), sp.identity(ny)
        dxx = sp.kron(iy, second(nx, self.dx))
        dyy = sp.kron(second(ny, self.dy), ix)
        dxy = sp.kron(first(ny, self.dy), first(nx, self.dx)) * np.sqrt(2.0)
        # scaled by the cell area so that |D c|^2 approximates the integral of the curvature energy
        return sp.vstack([dxx, dyy, dxy]).tocsr() * np.sqrt(self.dx * self.dy)

    @classmethod
    def fit(cls, func: Any, sub: Substrate2D, spacing: float, step: float | None = None) -> SplineSurface:
        """Least-squares B-spline approximation of ``func(x, y)`` over the substrate (a light thin-plate damping)."""
        s, project = cls._projector(sub, spacing, step)
        return s.with_coef(project(func))

    @classmethod
    def span(cls, basis: ShiftedBasis, sub: Substrate2D, spacing: float) -> Array:
        """Spline coefficients of every term of a shifted basis and of a constant: the columns of P, (n, k + 1).

        The surfaces c = P a are those of the basis (plus an offset), as B-splines of knot spacing ``spacing``.
        """
        cols = cls.fit_columns(lambda x, y: basis.values(x.ravel(), y.ravel()), sub, spacing)
        return np.column_stack([cols, np.ones(cols.shape[0])])

    @classmethod
    def fit_columns(cls, func: Any, sub: Substrate2D, spacing: float) -> Array:
        """:meth:`fit` of many functions at once: ``func(x, y)`` gives (points, k) values; returns (n, k)."""
        s, project = cls._projector(sub, spacing, None)
        return np.asarray(project(func), dtype=np.float64).reshape(s.coef.size, -1)

    @classmethod
    def _projector(cls, sub: Substrate2D, spacing: float, step: float | None) -> tuple[SplineSurface, Any]:
        """The spline covering ``sub`` and a function taking func(x, y) (one or more columns) to its coefficients."""
        s = cls.covering(sub, spacing)
        step = step or spacing / 3.0
        # samples on the substrate only (beyond it the thin-plate damping continues the surface smoothly)
        xs = np.linspace(*sub.x_range, int(np.ceil(sub.size_x / step)) + 1)
        ys = np.linspace(*sub.y_range, int(np.ceil(sub.size_y / step)) + 1)
        xx, yy = np.meshgrid(xs, ys)
        a = s.design(xx, yy)
        d = s.smoothness()
        ata = a.T @ a
        lu = spla.splu((ata + 1e-8 * ata.diagonal().mean() * (d.T @ d)).tocsc())

        def project(func: Any) -> Array:
            z = np.asarray(func(xx, yy), dtype=np.float64).reshape(xx.size, -1)
            out = np.asarray(lu.solve(np.asarray(a.T @ z)), dtype=np.float64)
            return out[:, 0] if out.shape[1] == 1 else out

        return s, project


def _outer(a: Array, b: Array) -> Array:
    """Row-wise outer products of (n, 4) arrays, flattened to (n, 16) (entry 4 m + k: a[:, m] b[:, k])."""
    return (a[:, :, None] * b[:, None, :]).reshape(len(a), 16)
