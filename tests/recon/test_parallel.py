"""recon.parallel: the thread map keeps the order, raises its function's errors, and runs here without a pool."""

from __future__ import annotations

import threading

import pytest

from scopetwin.recon.parallel import available_cpus, thread_map


def test_thread_map_keeps_the_order_of_its_items() -> None:
    assert thread_map(lambda x: x * x, list(range(20)), max_threads=3) == [x * x for x in range(20)]
    assert available_cpus() >= 1


def test_thread_map_raises_the_error_of_its_function() -> None:
    def bad(x: int) -> int:
        if x == 3:
            raise ValueError("three")
        return x

    with pytest.raises(ValueError, match="three"):
        thread_map(bad, [1, 2, 3, 4], max_threads=2)


def test_one_thread_or_one_item_runs_in_the_calling_thread() -> None:
    here = threading.get_ident()
    assert thread_map(lambda _: threading.get_ident(), [0, 1], max_threads=1) == [here, here]
    assert thread_map(lambda _: threading.get_ident(), [0]) == [here]


@pytest.mark.parametrize("cpus", [1, 2])
def test_background_gives_its_value_or_its_error_on_one_cpu_or_two(monkeypatch, cpus: int) -> None:
    from scopetwin.recon import parallel

    monkeypatch.setattr(parallel, "available_cpus", lambda: cpus)
    runs: list[int] = []

    def work() -> int:
        runs.append(threading.get_ident())
        return 42

    with parallel.Background(work) as job:
        if cpus == 1:
            assert runs == []  # on one CPU nothing runs until the result is asked for
        assert job.result() == 42 and job.result() == 42
    assert len(runs) == 1 and (runs[0] == threading.get_ident()) == (cpus == 1)

    def fail() -> int:
        raise ValueError("no data")

    with parallel.Background(fail) as bad, pytest.raises(ValueError, match="no data"):
        bad.result()


def test_a_workers_share_caps_the_cpus_its_threads_use() -> None:
    """A worker of a multi-process run caps this process's CPUs at its share (limit_cpus): thread_map then runs in
    the calling thread; no cap again gives the affinity's count; a share below one is refused."""
    from scopetwin.recon.parallel import limit_cpus

    full = available_cpus()
    here = threading.get_ident()
    try:
        limit_cpus(1)
        assert available_cpus() == 1
        assert thread_map(lambda _: threading.get_ident(), [0, 1, 2]) == [here] * 3
        limit_cpus(full + 5)
        assert available_cpus() == full
        with pytest.raises(ValueError, match="share"):
            limit_cpus(0)
    finally:
        limit_cpus(None)
    assert available_cpus() == full
