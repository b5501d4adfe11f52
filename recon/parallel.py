"""Threads for independent array work of one reconstruction: how many CPUs the process may use, and a map over
them.

NumPy's element-wise kernels release the interpreter lock, so independent whole-image passes (the phase fits of a
fringe sequence's stacks) run side by side in threads without copies or processes. BLAS stays single-threaded where
the reconstruction asks it to (:func:`scopetwin.recon.reconstruct.single_thread_blas`): these threads block while
they wait, they do not spin.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import Generic, TypeVar

T = TypeVar("T")
R = TypeVar("R")


#: This process's share of the CPUs where it is one worker of several (:func:`limit_cpus`); empty: no cap.
_SHARE: list[int] = []


def available_cpus() -> int:
    """The number of CPUs this process may run on (its affinity where the platform reports one), at most its share
    where :func:`limit_cpus` set one."""
    affinity = getattr(os, "sched_getaffinity", None)  # POSIX; elsewhere every CPU counts
    n = len(affinity(0)) if affinity is not None else os.cpu_count() or 1
    return min(n, _SHARE[0]) if _SHARE else n


def limit_cpus(share: int | None) -> None:
    """Cap :func:`available_cpus` for this process at ``share`` (None: no cap). A worker of a multi-process run
    (one per core) sets its share, so that one reconstruction's threads do not compete with the other workers'."""
    if share is not None and share < 1:
        raise ValueError(f"a process's CPU share must be >= 1, got {share}")
    _SHARE[:] = [] if share is None else [int(share)]


def thread_map(fn: Callable[[T], R], items: Sequence[T], max_threads: int | None = None) -> list[R]:
    """``[fn(x) for x in items]``, on up to ``max_threads`` threads (default :func:`available_cpus`), in order.

    One item or one CPU: in this thread, without a pool. An exception of ``fn`` is raised here.
    """
    threads = min(len(items), max_threads or available_cpus())
    if threads <= 1:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(threads) as pool:
        return list(pool.map(fn, items))


class Background(Generic[R]):
    """``fn()`` computed beside the caller: in a thread of its own where the process may use two CPUs (started at
    once), else in the caller's thread when its result is first asked for. Either way :meth:`result` returns its
    value or raises its exception; :meth:`close` waits for the thread (use it as a context manager)."""

    def __init__(self, fn: Callable[[], R]) -> None:
        self._fn = fn
        self._pool = ThreadPoolExecutor(1) if available_cpus() >= 2 else None
        self._job = self._pool.submit(fn) if self._pool is not None else None
        self._value: list[R] = []

    def result(self) -> R:
        """The value of ``fn()`` (computed now where no thread runs it)."""
        if self._job is not None:
            return self._job.result()
        if not self._value:
            self._value.append(self._fn())
        return self._value[0]

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True)

    def __enter__(self) -> Background[R]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
