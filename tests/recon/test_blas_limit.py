"""The BLAS thread limit of the reconstruction (``single_thread_blas``): one threadpoolctl controller per process."""

from __future__ import annotations

import time

import numpy as np
import scipy.linalg  # noqa: F401  (its BLAS is loaded, as in a reconstruction)
from threadpoolctl import threadpool_info

from scopetwin.recon import reconstruct as rc


def _blas_threads() -> list[int]:
    return [int(lib["num_threads"]) for lib in threadpool_info() if lib["user_api"] == "blas"]


def test_single_thread_blas_limits_every_blas_pool_and_restores_it():
    """Inside the block every loaded BLAS runs one thread; after it, each has its former count again."""
    before = _blas_threads()
    assert before, "no BLAS library loaded"
    with rc.single_thread_blas():
        assert _blas_threads() == [1] * len(before)
        np.linalg.solve(np.eye(3) * 2.0, np.ones(3))
    assert _blas_threads() == before


def test_the_controller_is_made_once_and_a_limit_costs_well_under_a_scan():
    """The limiter reuses the process's controller: entering and leaving the block 50 times costs less than 20 fresh
    scans of the loaded libraries would (a scan ~1.3 ms, a limit from the kept controller ~0.05 ms)."""
    from threadpoolctl import ThreadpoolController

    assert rc._blas_controller() is rc._blas_controller()
    t0 = time.perf_counter()
    for _ in range(20):
        ThreadpoolController()
    scan = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(50):
        with rc.single_thread_blas():
            pass
    assert time.perf_counter() - t0 < scan
