"""scopetwin.sim.datasets.runner.run_tasks on a real (in-process) Dask cluster: results as they finish, errors as
values, and a caller that stops early gives up the queued tasks without waiting on the scheduler."""

from __future__ import annotations

import time

import pytest

from scopetwin.sim.datasets import runner

distributed = pytest.importorskip("distributed")


def _square_slowly(x: int) -> int:
    time.sleep(0.2)
    if x == 3:
        raise ValueError("three")
    return x * x


@pytest.fixture
def client():
    with distributed.Client(processes=False, n_workers=1, threads_per_worker=1, dashboard_address=None) as c:
        yield c


def _scheduler_keys(client) -> set[str]:
    return set(client.run_on_scheduler(lambda dask_scheduler: [str(k) for k in dask_scheduler.tasks]))


def test_every_result_and_error_comes_back_once(client):
    keys = [f"square-{k}" for k in range(5)]
    got = {k: (v, e) for k, v, e in runner.run_tasks(_square_slowly, [(k,) for k in range(5)], client, keys)}
    assert sorted(got) == list(range(5))
    assert [got[k][0] for k in (0, 1, 2, 4)] == [0, 1, 4, 16]
    assert isinstance(got[3][1], runner.TaskFailure) and str(got[3][1]) == "ValueError: three"


def test_stopping_early_gives_up_the_queued_tasks_and_hands_over_the_finished_ones(client):
    """The caller takes one result and stops: the tasks not yet run are gone from the scheduler within seconds, and
    a task that finished but was not yet taken reaches ``on_abandon``."""
    keys = [f"stop-{k}" for k in range(8)]
    abandoned: list[tuple[int, int]] = []
    tasks = runner.run_tasks(
        _square_slowly, [(k,) for k in range(8)], client, keys, on_abandon=lambda k, v: abandoned.append((k, v))
    )
    first = next(tasks)
    time.sleep(1.0)  # the next task (0.2 s) finishes meanwhile
    t0 = time.monotonic()
    tasks.close()
    assert time.monotonic() - t0 < 5
    assert first[0] == 0 and first[2] is None
    assert abandoned and all(v == k * k for k, v in abandoned) and {k for k, _ in abandoned} <= set(range(1, 8))
    deadline = time.monotonic() + 10
    while _scheduler_keys(client) & set(keys) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _scheduler_keys(client) & set(keys)


def test_a_plan_run_into_two_folders_has_two_sets_of_task_keys(tmp_path):
    """On a shared scheduler one key is one task: the same plan into another folder must not share its keys (it would
    be handed the first folder's samples); the same folder again (a resume) gets the same keys."""
    from scopetwin.sim.datasets.store import task_keys

    plan = {"dataset": {"count": 3, "seed": 1}}
    a, b = tmp_path / "a", tmp_path / "b"
    keys_a, keys_b = task_keys(plan, a, range(3)), task_keys(plan, b, range(3))
    assert len(set(keys_a)) == 3 and not set(keys_a) & set(keys_b)
    assert task_keys(plan, a, [2]) == keys_a[2:] and task_keys(plan, tmp_path / "x" / ".." / "a", [0]) == keys_a[:1]
