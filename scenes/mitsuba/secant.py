"""The ray intersection of :class:`scopetwin.scenes.bicubic.BicubicCells`, compiled: the whole secant iteration of
every ray in one Dr.Jit kernel (LLVM backend) instead of numpy's array passes.

The iteration is the one of thesis §1.6.4 (eq. 1.6) that :func:`scopetwin.scenes.secant.secant_intersection` runs,
with the same start values, stopping rule, steps and cell polynomials, written as the same floating-point operations
in the same order; Dr.Jit emits no fused multiply-adds for them, so the hits agree with the numpy iteration's to the
last bit (measured on a dataset sample's 128,328 pixel rays: every ray parameter, height and slope equal; the tests
check 1e-12 mm). What differs is the cost: each ray runs its loop inside the kernel, with no array pass per step and
no gathers of the rays still iterating (that sample on one thread: 10-12 ms against 85-100 ms).

Where Dr.Jit's LLVM backend is not available, :meth:`BicubicCells.intersect` keeps the numpy iteration
(:func:`available`). Dr.Jit is imported on the first call, never at import; nothing here touches Mitsuba's variant.
One kernel serves every surface of a node grid's size: the surface's scalars (extents, cell count) are opaque, and
every array the kernel reads is copied to :data:`ALIGN`-aligned memory (Dr.Jit compiles for the alignment it finds);
Dr.Jit keeps the kernel on disk between processes.
"""

from __future__ import annotations

import functools
import weakref
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]


class BicubicCells(Protocol):
    """What the kernel reads of a :class:`scopetwin.scenes.bicubic.BicubicCells`."""

    x_left: F64
    y_left: F64
    poly: F64
    n_cx: int
    bounds: tuple[float, float, float, float]


@functools.lru_cache(maxsize=1)
def available() -> bool:
    """Whether Dr.Jit's LLVM backend can run here (a shared LLVM library of version 16 or newer)."""
    from .variant import _llvm_library

    if _llvm_library() is None:
        return False
    try:
        import drjit as dr

        return bool(dr.has_backend(dr.JitBackend.LLVM))
    except Exception:  # an import or backend failure: the numpy iteration serves
        return False


@dataclass(frozen=True)
class _Tables:
    """A :class:`BicubicCells`' knots and cell polynomials as Dr.Jit arrays, and its scalars as opaque values."""

    x_left: Any
    y_left: Any
    poly: Any  # coefficient k of cell c at 16 c + k
    n_cx: Any
    bounds: tuple[Any, Any, Any, Any]


_TABLES: weakref.WeakKeyDictionary[BicubicCells, _Tables] = weakref.WeakKeyDictionary()


def _tables(cells: BicubicCells) -> _Tables:
    """The tables of ``cells``, made once per surface."""
    found = _TABLES.get(cells)
    if found is None:
        import drjit as dr
        from drjit.llvm import Float64, UInt32

        found = _Tables(
            _owned(Float64, cells.x_left),
            _owned(Float64, cells.y_left),
            _owned(Float64, cells.poly.T),
            dr.opaque(UInt32, cells.n_cx),
            tuple(dr.opaque(Float64, float(b)) for b in cells.bounds),  # type: ignore[arg-type]
        )
        _TABLES[cells] = found
    return found


def _cell(dr: Any, left: Any, v: Any) -> Any:
    """The index of the last knot <= v (v clamped to the extents): numpy's ``searchsorted(left, v, "right") - 1``
    clipped to the cells."""
    from drjit.llvm import Float64, Int32

    n = dr.width(left)
    found = dr.binary_search(0, n, lambda i: dr.gather(Float64, left, i) <= v)
    return dr.clip(Int32(found) - 1, 0, n - 1)


def _polynomial(dr: Any, t: _Tables, x: Any, y: Any, grad: bool) -> tuple[Any, Any, Any]:
    """h (and dh/dx, dh/dy) at (x, y) from the cell's polynomial, as :meth:`BicubicCells._polynomial` forms them."""
    from drjit.llvm import Float64, UInt32

    x0, x1, y0, y1 = t.bounds
    xc, yc = dr.minimum(dr.maximum(x, x0), x1), dr.minimum(dr.maximum(y, y0), y1)
    cx, cy = _cell(dr, t.x_left, xc), _cell(dr, t.y_left, yc)
    sx = xc - dr.gather(Float64, t.x_left, UInt32(cx))
    sy = yc - dr.gather(Float64, t.y_left, UInt32(cy))
    base = (UInt32(cy) * t.n_cx + UInt32(cx)) * 16
    a = [dr.gather(Float64, t.poly, base + k) for k in range(16)]
    rows = [((a[4 * p + 3] * sx + a[4 * p + 2]) * sx + a[4 * p + 1]) * sx + a[4 * p] for p in range(4)]
    h = ((rows[3] * sy + rows[2]) * sy + rows[1]) * sy + rows[0]
    if not grad:
        return h, h, h
    drows = [(3.0 * a[4 * p + 3] * sx + 2.0 * a[4 * p + 2]) * sx + a[4 * p + 1] for p in range(4)]
    hx = ((drows[3] * sy + drows[2]) * sy + drows[1]) * sy + drows[0]
    hy = (3.0 * rows[3] * sy + 2.0 * rows[2]) * sy + rows[1]
    hx = dr.select((x >= x0) & (x <= x1), hx, 0.0)  # the constant continuation outside the extents
    hy = dr.select((y >= y0) & (y <= y1), hy, 0.0)
    return h, hx, hy


#: Bytes a kernel's array is aligned to: Dr.Jit compiles its vector loads for the alignment it finds (128 bytes: 16
#: doubles), so memory aligned differently from call to call would name (and compile) a new kernel each time.
ALIGN = 128


def _owned(kind: Any, values: F64) -> Any:
    """A Dr.Jit array over a copy of ``values`` (any shape, read in C order) aligned to :data:`ALIGN` bytes."""
    values = np.asarray(values, dtype=np.float64)
    buf = np.empty(values.size + ALIGN // 8, dtype=np.float64)
    start = (-buf.ctypes.data % ALIGN) // 8
    aligned = buf[start : start + values.size]
    np.copyto(aligned.reshape(values.shape), values)  # one copy, whatever the strides
    return kind(aligned)


def intersect(
    cells: BicubicCells, o: F64, d: F64, lam0: F64, lam1: F64 | None, tol: float, max_iter: int
) -> tuple[F64, NDArray[np.bool_], F64, F64, F64]:
    """:meth:`BicubicCells.intersect` of rays ``o``, ``d`` ((n, 3), local) from ``lam0`` (and ``lam1``; None: the flat
    Newton step from ``lam0``), compiled (module docstring). Returns lam (NaN where not converged), the mask, h, hx,
    hy (NaN where not converged)."""
    import drjit as dr
    from drjit.llvm import Float64

    rays = tuple(_owned(Float64, a[:, k]) for a in (o, d) for k in range(3))
    start = _owned(Float64, lam0)
    second = start if lam1 is None else _owned(Float64, lam1)
    out = _trace(_tables(cells), rays, start, second, lam1 is None, tol, max_iter)
    dr.eval(*out)  # one kernel for all five
    converged = out[1].numpy().astype(bool)
    lam, h, hx, hy = (np.where(converged, v.numpy(), np.nan) for v in (out[0], *out[2:]))
    return lam, converged, h, hx, hy


def _trace(
    t: _Tables, rays: tuple[Any, ...], lam0: Any, lam1: Any, newton: bool, tol: float, max_iter: int
) -> tuple[Any, ...]:
    """The secant iteration of every ray in one kernel: lam, converged, h, hx, hy (Dr.Jit arrays). ``newton``: the
    second start is the flat Newton step from ``lam0`` (``lam1`` is not read)."""
    import drjit as dr
    from drjit.llvm import Bool, UInt32

    ox, oy, oz, dx, dy, dz = rays

    def residual(lam: Any) -> Any:
        return _polynomial(dr, t, ox + lam * dx, oy + lam * dy, False)[0] - (oz + lam * dz)

    f_prev = residual(dr.select(dr.isfinite(lam0), lam0, 0.0))
    lam_cur = lam0 + f_prev / dz if newton else lam1
    going = Bool(dr.isfinite(lam_cur))
    f_cur = residual(dr.select(going, lam_cur, 0.0))

    def more(lp: Any, fp: Any, lc: Any, fc: Any, k: Any, on: Any) -> Any:
        return on & (dr.abs(fc) >= tol) & (k < max_iter)

    def step(lp: Any, fp: Any, lc: Any, fc: Any, k: Any, on: Any) -> tuple[Any, ...]:
        den = fc - fp
        new = (lp * fc - lc * fp) / den
        good = (den != 0) & dr.isfinite(new)  # else the ray stops where it is, not converged
        fn = residual(dr.select(good, new, lc))
        return (
            dr.select(good, lc, lp),
            dr.select(good, fc, fp),
            dr.select(good, new, lc),
            dr.select(good, fn, fc),
            k + 1,
            Bool(good),
        )

    state = (lam0, f_prev, lam_cur, f_cur, UInt32(0), going)
    _, _, lam_cur, f_cur, _, _ = dr.while_loop(state, more, step)
    done = (dr.abs(f_cur) < tol) & dr.isfinite(lam_cur)  # a ray never started is not converged
    h, hx, hy = _polynomial(dr, t, ox + lam_cur * dx, oy + lam_cur * dy, True)
    return lam_cur, done, h, hx, hy
