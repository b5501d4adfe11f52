"""Where tasks run: in this process or on Dask distributed (an embedded LocalCluster or an existing scheduler).

Shared by the datasets and the studies (DESIGN.md "Scale"). :func:`run_tasks` yields each task's result or error
as it finishes, so one failed task does not lose the others' results; :func:`init_worker` sets a worker process's
Dr.Jit thread count once.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from scenes.errors import ScopetwinError
from sim.datasets.config import DatasetError

#: What :func:`init_worker` set in this process (so a second call with the same count does nothing).
_WORKER_STATE: dict[str, Any] = {}


def init_worker(threads: int | None) -> None:
    """Once per worker process: Dr.Jit's thread count (one per worker on a local cluster); None/0 leaves it."""
    if threads and _WORKER_STATE.get("threads") != threads:
        from scenes.mitsuba.variant import set_thread_count

        set_thread_count(int(threads))
        _WORKER_STATE["threads"] = threads


def default_workers() -> int:
    """One worker per core this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None) -> Iterator[Any]:
    """A Dask client: on ``scheduler`` (an existing cluster, unchanged) or on an embedded LocalCluster.

    The local cluster has ``workers`` worker processes (default: one per core) with one thread each,
    started with ``spawn`` (Mitsuba's plugin registry is per thread and does not survive ``fork``),
    and listens on 127.0.0.1 only, without a dashboard.
    """
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError as exc:
        raise DatasetError(
            f"Dask distributed is not installed ({exc}); install dask[distributed] or use "
            "--workers 0 to work in this process"
        ) from None
    if scheduler:
        try:
            client = Client(scheduler, timeout="30s")
        except (OSError, TimeoutError) as exc:
            raise DatasetError(f"cannot connect to the Dask scheduler {scheduler}: {exc}") from None
        try:
            yield client
        finally:
            client.close()
        return
    with dask.config.set(
        {
            "distributed.worker.multiprocessing-method": "spawn",
            "distributed.scheduler.allowed-failures": 5,
            "distributed.worker.memory.terminate": False,
        }
    ):
        cluster = LocalCluster(
            n_workers=workers or default_workers(),
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            silence_logs=logging.ERROR,
        )
        client = Client(cluster)
        try:
            yield client
        finally:
            client.close()
            cluster.close()


class TaskFailure(ScopetwinError):
    """A task raised on a worker; the message is the original exception's type and message."""


def _guarded(func: Callable[..., Any], *args: Any) -> tuple[bool, Any]:
    """Run a task and hand its exception back as a value (no worker-log traceback, always unpicklable-safe)."""
    try:
        return True, func(*args)
    except Exception as exc:  # noqa: BLE001 - handed to the client
        return False, f"{type(exc).__name__}: {exc}"


def failure_text(err: BaseException) -> str:
    """'Type: message' of a task's error."""
    return str(err) if isinstance(err, TaskFailure) else f"{type(err).__name__}: {err}"


def run_tasks(
    func: Callable[..., Any], args: Sequence[tuple], client: Any | None, keys: Sequence[str] | None = None
) -> Iterator[tuple[int, Any, BaseException | None]]:
    """Run ``func(*a)`` for every ``a`` in ``args``; yield (position, result, error) as each finishes.

    ``client`` None runs in this process, in order. Errors are yielded, not raised, so one bad
    task does not lose the others' results.
    """
    if client is None:
        for k, a in enumerate(args):
            try:
                yield k, func(*a), None
            except Exception as exc:  # noqa: BLE001 - handed to the caller
                yield k, None, exc
        return
    from distributed import as_completed

    futures = [
        client.submit(_guarded, func, *a, key=None if keys is None else keys[k], pure=False) for k, a in enumerate(args)
    ]
    position = {f.key: k for k, f in enumerate(futures)}
    try:
        for fut in as_completed(futures):
            k = position[fut.key]
            try:
                ok, value = fut.result()
            except Exception as exc:  # noqa: BLE001 - e.g. KilledWorker after repeated worker deaths
                yield k, None, exc
                continue
            yield (k, value, None) if ok else (k, None, TaskFailure(value))
            fut.release()
    finally:
        for f in futures:
            f.cancel()
