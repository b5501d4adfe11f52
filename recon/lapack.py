"""Triangular solves, Cholesky factorisations and inverses that run without the interpreter lock, so that threads
run them side by side: SciPy's own BLAS/LAPACK routines (``scipy.linalg.cython_blas``, ``cython_lapack``), called
through ``ctypes``.

SciPy's Python wrappers of these routines (``solve_triangular``, ``lapack.dpotri``, ``blas.dtrsm``) hold the
interpreter lock while they run: two threads each solving half of a posterior's whitening took as long as one solve,
and a Gaussian-process evidence search in a thread stalled the caller's Python work for as long as its inverses ran. A
foreign call through ``ctypes`` releases the lock, and these are the same compiled routines SciPy calls, on the same
memory layout.

:func:`solve_lower` solves in fixed blocks of :data:`BLOCK` right-hand sides, however many threads run them, so its
result does not depend on the thread count. The blocks' results differ from one call on all right-hand sides
(``scipy.linalg.solve_triangular``) by the BLAS kernel's rounding, ~1e-16 relative (measured on a 1100 x 1100 factor,
1054 right-hand sides: at most 2.2e-16 of the largest entry).
"""

from __future__ import annotations

import ctypes
import functools
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.linalg as sla
from numpy.typing import NDArray

from scopetwin.recon.parallel import thread_map

#: Right-hand sides per triangular solve: the unit of work of :func:`solve_lower`'s threads (a 1100 x 1100 factor
#: and 1054 right-hand sides: five blocks, 38 -> 20 ms on two threads against one).
BLOCK = 256


#: The C signatures this module calls SciPy's routines with (SciPy's double type written ``d``): a routine whose
#: exported signature differs (another integer width, say) is not called; SciPy's own wrapper serves instead.
SIGNATURES = {
    "dtrsm": "void (char *, char *, char *, char *, int *, int *, d *, d *, int *, d *, int *)",
    "dpotri": "void (char *, int *, d *, int *, int *)",
    "dpotrf": "void (char *, int *, d *, int *, int *)",
    "dpotrs": "void (char *, int *, int *, d *, int *, d *, int *, int *)",
}


@functools.cache
def _routine(module: str, name: str) -> Any:
    """The C function ``name`` SciPy exports from ``scipy.linalg.<module>`` for ctypes, or None where it is not
    there with the signature of :data:`SIGNATURES` (or this Python cannot read SciPy's capsules)."""
    import importlib
    import re

    try:
        capsule = importlib.import_module(f"scipy.linalg.{module}").__pyx_capi__[name]
        get_name, get_pointer = ctypes.pythonapi.PyCapsule_GetName, ctypes.pythonapi.PyCapsule_GetPointer
        get_name.restype, get_name.argtypes = ctypes.c_char_p, [ctypes.py_object]
        get_pointer.restype, get_pointer.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
        signature = get_name(capsule)
        if re.sub(r"__pyx_t_\w+_d \*", "d *", signature.decode()) != SIGNATURES[name]:
            return None
        address = get_pointer(capsule, signature)
    except (AttributeError, ImportError, KeyError, ValueError):
        return None
    return ctypes.CFUNCTYPE(None, *([ctypes.c_void_p] * (SIGNATURES[name].count(",") + 1)))(address)


def _char(c: str) -> Any:
    return ctypes.byref(ctypes.c_char(c.encode()))


def _int(i: int) -> Any:
    return ctypes.byref(ctypes.c_int(i))


def _lower_factor(low: NDArray[np.float64]) -> tuple[str, str]:
    """BLAS's (uplo, trans) for the lower-triangular ``low`` as stored: Fortran order as it is, C order as the upper
    triangle of its transpose."""
    if low.dtype != np.float64 or low.ndim != 2 or low.shape[0] != low.shape[1]:
        raise ValueError(f"a square float64 factor is needed, got {low.dtype} {low.shape}")
    if low.flags.f_contiguous:
        return "L", "N"
    if low.flags.c_contiguous:
        return "U", "T"
    raise ValueError("the factor must be contiguous")


def solve_lower(
    low: NDArray[np.float64], rhs_t: NDArray[np.float64], max_threads: int | None = None
) -> NDArray[np.float64]:
    """X = L^-1 B for a lower-triangular ``low`` (n, n; only its lower triangle is read, so a ``cho_factor`` factor
    with whatever lies above its diagonal will do) and B = ``rhs_t``.T (``rhs_t``: (k, n), its rows the right-hand
    sides); X is (n, k), in Fortran order. On up to ``max_threads`` threads (:func:`thread_map`), block by block."""
    if rhs_t.ndim != 2:
        raise ValueError(f"right-hand sides as the rows of a 2-d array are needed, got shape {rhs_t.shape}")
    return solve_lower_blocks(low, len(rhs_t), lambda start, stop: rhs_t[start:stop], max_threads)


def solve_lower_blocks(
    low: NDArray[np.float64],
    k: int,
    rhs_block: Callable[[int, int], NDArray[np.float64]],
    max_threads: int | None = None,
) -> NDArray[np.float64]:
    """:func:`solve_lower` for k right-hand sides made block by block where they are solved: ``rhs_block(start,
    stop)`` gives rows start:stop of B^T, (stop - start, n) (the threads make them side by side too)."""
    uplo, trans = _lower_factor(low)
    n = low.shape[0]
    out = np.empty((n, k), order="F")
    trsm = _routine("cython_blas", "dtrsm")
    one = ctypes.c_double(1.0)

    def solve(start: int) -> None:
        stop = min(start + BLOCK, k)
        rhs = rhs_block(start, stop)
        if rhs.shape != (stop - start, n):
            raise ValueError(f"right-hand sides of length {n} are needed, got shape {rhs.shape}")
        if trsm is None:  # SciPy's wrapper (it holds the interpreter lock)
            out[:, start:stop] = sla.solve_triangular(low, rhs.T, lower=True, check_finite=False)
            return
        out[:, start:stop] = rhs.T
        block = ctypes.c_void_p(out.ctypes.data + start * n * 8)
        a = ctypes.c_void_p(low.ctypes.data)
        trsm(_char("L"), _char(uplo), _char(trans), _char("N"), _int(n), _int(stop - start), ctypes.byref(one), a,
             _int(n), block, _int(n))  # fmt: skip

    if n and k:
        thread_map(solve, range(0, k, BLOCK), max_threads)
    return out


def lower_inverse(low: NDArray[np.float64]) -> NDArray[np.float64]:
    """K^-1 in the lower triangle of K's lower Cholesky factor ``low`` (Fortran order), in place (LAPACK ``dpotri``;
    what lies above the diagonal is left as it was).

    Raises
    ------
    numpy.linalg.LinAlgError
        ``dpotri`` failed (a zero on the factor's diagonal).
    """
    uplo, _ = _lower_factor(low)
    if uplo != "L":
        raise ValueError("lower_inverse needs the factor in Fortran order")
    potri = _routine("cython_lapack", "dpotri")
    if potri is None:
        inv, failed = sla.lapack.dpotri(low, lower=1, overwrite_c=1)
        if failed != 0:
            raise np.linalg.LinAlgError(f"potri failed ({failed})")
        low[...] = inv
        return low
    info = ctypes.c_int(0)
    n = low.shape[0]
    potri(_char("L"), _int(n), ctypes.c_void_p(low.ctypes.data), _int(n), ctypes.byref(info))
    if info.value != 0:
        raise np.linalg.LinAlgError(f"potri failed ({info.value})")
    return low


def factor_solve(low: NDArray[np.float64], rhs: NDArray[np.float64]) -> NDArray[np.float64]:
    """x with L L^T x = rhs for the Fortran-order lower Cholesky factor ``low`` (:func:`cholesky_lower`; LAPACK
    ``dpotrs``, what ``scipy.linalg.cho_solve`` calls, without its checks and without the interpreter lock). ``rhs``:
    (n,) or (n, k)."""
    uplo, _ = _lower_factor(low)
    if uplo != "L":
        raise ValueError("factor_solve needs the factor in Fortran order")
    n = low.shape[0]
    x = np.array(rhs, dtype=np.float64, order="F", copy=True)
    if x.shape[0] != n:
        raise ValueError(f"right-hand sides of length {n} are needed, got shape {x.shape}")
    potrs = _routine("cython_lapack", "dpotrs")
    if potrs is None:
        return np.asarray(sla.cho_solve((low, True), x, check_finite=False))
    info = ctypes.c_int(0)
    k = 1 if x.ndim == 1 else x.shape[1]
    potrs(_char("L"), _int(n), _int(k), ctypes.c_void_p(low.ctypes.data), _int(n), ctypes.c_void_p(x.ctypes.data),
          _int(n), ctypes.byref(info))  # fmt: skip
    return x


def _factor_in_place(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """The lower Cholesky factor of the symmetric positive definite, contiguous ``a`` in its own memory (LAPACK
    ``dpotrf``; a C-order ``a`` read in Fortran order is the same symmetric matrix), as the Fortran-order view whose
    lower triangle holds it; what lies above the diagonal is left as it was.

    Raises
    ------
    numpy.linalg.LinAlgError
        ``a`` is not positive definite.
    """
    if (
        a.dtype != np.float64
        or a.ndim != 2
        or a.shape[0] != a.shape[1]
        or not (a.flags.c_contiguous or a.flags.f_contiguous)
    ):
        raise ValueError(f"a contiguous square float64 matrix is needed, got {a.dtype} {a.shape}")
    f = a if a.flags.f_contiguous else a.T
    potrf = _routine("cython_lapack", "dpotrf")
    if potrf is None:  # SciPy's wrapper (it holds the interpreter lock)
        factor, failed = sla.lapack.dpotrf(f, lower=1, clean=0, overwrite_a=1)
        info = int(failed)
        if info == 0:
            f[...] = factor
    else:
        status = ctypes.c_int(0)
        potrf(_char("L"), _int(f.shape[0]), ctypes.c_void_p(f.ctypes.data), _int(f.shape[0]), ctypes.byref(status))
        info = status.value
    if info != 0:
        raise np.linalg.LinAlgError(f"the matrix is not positive definite (potrf: {info})")
    return f


def cholesky_solve(m: NDArray[np.float64], rhs: NDArray[np.float64]) -> NDArray[np.float64]:
    """x with M x = rhs for a symmetric positive definite, contiguous ``m`` (n, n), which is overwritten by its
    Cholesky factor (:func:`_factor_in_place`, then :func:`factor_solve`). ``rhs``: (n,) or (n, k).

    Raises
    ------
    numpy.linalg.LinAlgError
        ``m`` is not positive definite.
    """
    return factor_solve(_factor_in_place(m), rhs)


@functools.lru_cache(maxsize=4)
def _lower_mask(n: int) -> NDArray[np.float64]:
    """1 on and below the diagonal of an (n, n) Fortran-order matrix, 0 above, as the C-order array of its memory."""
    return np.ascontiguousarray(np.tril(np.ones((n, n))).T)


def cholesky_lower(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """The lower Cholesky factor of the symmetric positive definite, C-contiguous ``a``, in place
    (:func:`_factor_in_place`), returned as a Fortran-order view of that memory with zeros above the diagonal (what
    :func:`lower_inverse` takes).

    Raises
    ------
    numpy.linalg.LinAlgError
        ``a`` is not positive definite.
    """
    if not a.flags.c_contiguous:
        raise ValueError("cholesky_lower needs a C-contiguous matrix")
    factor = _factor_in_place(a)
    a *= _lower_mask(a.shape[0])
    return factor
