"""Running a study: the cluster (or this process), the staged report folder, ``report.md`` and ``results.json``.

A study whose tasks partly failed still writes its report (the failures listed under "Problems", the tables from
the tasks that succeeded) and counts the failed tasks (``failed_tasks``): ``scopetwin study`` then exits 1.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from scopetwin.sim.datasets.runner import dask_client, init_worker
from scopetwin.sim.measurement import StagedOutput
from scopetwin.sim.studies import (
    angle,
    coverage,
    fringes,
    inverse,
    noise,
    second_measurement,
    setup_placement,
    surface,
    thesis,
)
from scopetwin.sim.studies.context import StudyContext, StudyError, StudyResult
from scopetwin.sim.studies.tables import jsonable, table_json, table_markdown

#: The studies by name (``scopetwin study NAME``).
STUDIES: dict[str, Callable[[StudyContext], StudyResult]] = {
    "thesis": thesis.thesis,
    "noise": noise.noise,
    "angle": angle.angle,
    "surface": surface.surface,
    "inverse": inverse.inverse,
    "coverage": coverage.coverage,
    "setup": setup_placement.setup_placement,
    "second-measurement": second_measurement.second_measurement,
    "fringes": fringes.fringes,
    "fringes-full": fringes.fringes_full,
}


class _CountingContext(StudyContext):
    """A :class:`StudyContext` that counts the tasks that failed (their exceptions stand in the results)."""

    failed_tasks: int = 0

    def map(self, func: Callable[..., Any], args: Sequence[tuple], desc: str) -> list[Any]:
        results = super().map(func, args, desc)
        self.failed_tasks += sum(1 for r in results if isinstance(r, BaseException))
        return results


# -- running and writing -------------------------------------------------------------------------------------
def report_markdown(name: str, res: StudyResult, seconds: float, where: str, failed_tasks: int = 0) -> str:
    """The ``report.md`` of a study: title, intro, problems (the failed tasks first), every table, the plots."""
    lines = [
        f"# {res.title}",
        "",
        res.intro,
        "",
        f"`scopetwin study {name}`: {seconds:.0f} s on {where}. Figures: {', '.join(res.plots) or 'none'}; "
        "machine-readable: results.json.",
        "",
    ]
    if res.notes or failed_tasks:
        lines += ["## Problems", ""]
        if failed_tasks:
            lines += [f"- {failed_tasks} task(s) failed: the tables hold the tasks that succeeded (exit status 1)"]
        lines += [f"- {n}" for n in res.notes] + [""]
    lines += ["## Tables", ""]
    for t in res.tables:
        lines += [table_markdown(t)]
    for p in res.plots:
        lines += [f"![{p}]({p})", ""]
    return "\n".join(lines)


def run_study(
    name: str,
    out: str | Path,
    scheduler: str | None = None,
    workers: int | None = None,
    threads: int | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Run study ``name`` and write ``report.md``, ``results.json`` and plots into ``out``.

    ``workers`` 0 runs every task in this process; otherwise an embedded LocalCluster (or ``scheduler``). The
    report is written when the study ran to its end, also when some of its tasks failed: the result's
    ``failed_tasks`` counts them (0: every task succeeded). A study that raised, or was interrupted, writes nothing.
    """
    if name not in STUDIES:
        raise StudyError(f"unknown study {name!r} (known: {', '.join(STUDIES)})")
    out = Path(out)
    staged = StagedOutput(out)
    stage = staged.stage
    t0 = time.perf_counter()
    if threads is None and scheduler is None and workers != 0:
        threads = 1
    try:
        ctx_mgr = contextlib.nullcontext(None) if (workers == 0 and not scheduler) else dask_client(scheduler, workers)
        with ctx_mgr as client:
            if client is not None and threads:
                client.run(init_worker, threads)
            where = (
                "this process"
                if client is None
                else (f"Dask at {client.scheduler.address} ({len(client.scheduler_info()['workers'])} workers)")
            )
            ctx = _CountingContext(stage, client, progress, threads)
            res = STUDIES[name](ctx)
        seconds = time.perf_counter() - t0
        failed_tasks = ctx.failed_tasks
        (stage / "report.md").write_text(report_markdown(name, res, seconds, where, failed_tasks))
        summary = {
            "study": name,
            "seconds": seconds,
            "where": where,
            "failed_tasks": failed_tasks,
            "tables": [table_json(t) for t in res.tables],
            "plots": res.plots,
            "notes": res.notes,
            "data": res.summary,
        }
        (stage / "results.json").write_text(json.dumps(jsonable(summary), indent=2) + "\n")
        staged.commit()
    except BaseException:
        staged.discard()
        raise
    return {
        "study": name,
        "report": str(out / "report.md"),
        "results": str(out / "results.json"),
        "seconds": seconds,
        "plots": [str(out / p) for p in res.plots],
        "notes": res.notes,
        "failed_tasks": failed_tasks,
    }
