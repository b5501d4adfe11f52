"""What a study gets (:class:`StudyContext`: where its tasks run) and what it returns (:class:`StudyResult`)."""

from __future__ import annotations

import importlib.util
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.sim.datasets.config import config_from_dict
from scopetwin.sim.datasets.plan import Plan
from scopetwin.sim.datasets.runner import failure_text, run_tasks
from scopetwin.sim.datasets.store import generate
from scopetwin.sim.studies.tables import Table


class StudyError(ScopetwinError, ValueError):
    """A study that cannot run (unknown name, missing capability); the message names it."""


@dataclass
class StudyContext:
    """What a study function gets: the staging folder, the Dask client (or None), progress flag."""

    out: Path
    client: Any | None
    progress: bool = True
    threads: int | None = None

    def map(self, func: Callable[..., Any], args: Sequence[tuple], desc: str) -> list[Any]:
        """Run ``func(*a)`` for each ``a`` (on the cluster); results in order, exceptions in their place.

        The progress bar counts the tasks that succeeded and shows ``failed=N`` beside them.
        """
        from tqdm import tqdm

        results: list[Any] = [None] * len(args)
        failed = 0
        with tqdm(total=len(args), desc=desc, unit="task", disable=not self.progress) as bar:
            tasks = run_tasks(func, args, self.client)
            try:
                for k, res, err in tasks:
                    results[k] = err if err is not None else res
                    if err is None:
                        bar.update(1)
                    else:
                        failed += 1
                        bar.set_postfix(failed=failed)
            finally:
                tasks.close()  # an interruption: cancel the queued tasks now
        return results

    def dataset(self, config: dict[str, Any], name: str) -> Path:
        """Generate a dataset (a config dict as in ``examples/datasets``) under ``out/name`` on the same client.

        The studies read images and truth.json only, so their datasets leave out the per-pixel maps unless the
        config asks for them (``[dataset] maps``).
        """
        config = {**config, "dataset": {"maps": False, **config.get("dataset", {})}}
        plan = Plan.build(config_from_dict(config, f"study dataset {name}"))
        root = self.out / name
        generate(
            plan,
            root,
            threads=self.threads,
            progress=self.progress,
            client=self.client,
            workers=None if self.client is not None else 0,
        )
        return root


@dataclass
class StudyResult:
    """Tables, plots (file names in the output folder), free text and a JSON summary."""

    title: str
    intro: str
    tables: list[Table]
    plots: list[str] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def require(study: str, modules: dict[str, str]) -> None:
    """Raise :class:`StudyError` naming the first missing capability (module -> what it provides)."""
    for module, what in modules.items():
        try:
            found = importlib.util.find_spec(module) is not None
        except ModuleNotFoundError:
            found = False
        if not found:
            raise StudyError(f"study {study!r} needs {what} ({module}), which is not in this installation yet")


def failed(v: Any) -> bool:
    """Whether a task result is an exception (:meth:`StudyContext.map` puts them in place of results)."""
    return isinstance(v, BaseException)


def error_text(v: BaseException) -> str:
    """'Type: message' of a failed task."""
    return failure_text(v)
