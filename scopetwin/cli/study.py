"""``scopetwin study NAME [--out DIR] [--scheduler ADDRESS | --workers N]`` (:mod:`scopetwin.sim.studies`).

Runs an accuracy study (``thesis``, ``noise``, ``angle``, ``surface``) on an embedded Dask LocalCluster
(one process per core, one thread each, 127.0.0.1 only), on an existing cluster, or in this process
(``--workers 0``), and writes ``report.md``, ``results.json`` and PNG plots into ``--out`` when the study ran to its
end (the report is staged and moved into place last; Ctrl-C, SIGTERM and SIGHUP leave nothing). When some of its
tasks failed the report is still written, lists them, and the exit status is 1 (:data:`EXIT_TASKS_FAILED`).
"""

from __future__ import annotations

import argparse
import logging
from typing import Any

from scopetwin.cli.options import add_cluster_options, conventions
from scopetwin.cli.outputs import check_output_path

log = logging.getLogger(__name__)

#: Exit status of a study that ran to its end with failed tasks (its report written, the failures listed).
EXIT_TASKS_FAILED = 1

#: The studies' names, as :data:`scopetwin.sim.studies.runner.STUDIES` registers them, spelt out so that the parser
#: (``--help``) does not import the studies.
STUDY_NAMES = (
    "thesis",
    "noise",
    "angle",
    "surface",
    "inverse",
    "coverage",
    "setup",
    "second-measurement",
    "fringes",
    "fringes-full",
)

#: Plain text for ``--help`` (the module docstring is reST).
DESCRIPTION = (
    "An accuracy study against rendered truth (the study 'thesis' puts the thesis's tables beside ours). It runs on "
    "a local Dask cluster, an existing one (--scheduler) or in this process (--workers 0), and writes report.md, "
    "results.json and PNG plots into --out when it ran to its end. Exit status 1: some tasks failed (the report "
    "lists them and holds the tasks that succeeded)."
)


def cmd_study(args: argparse.Namespace) -> dict[str, Any]:
    """Run the study ``NAME``; returns ``{"study", "report", "results", "seconds", "plots", "notes",
    "failed_tasks"}`` (exit status 1 when ``failed_tasks`` > 0)."""
    from scopetwin.sim.datasets.runner import check_scheduler
    from scopetwin.sim.studies.context import StudyError
    from scopetwin.sim.studies.runner import STUDIES, run_study

    if args.name not in STUDIES:
        raise StudyError(f"unknown study {args.name!r} (known: {', '.join(STUDIES)})")
    if args.workers is not None and args.workers < 0:
        raise StudyError(f"--workers must be >= 0, got {args.workers}")
    if args.scheduler and args.workers is not None:
        raise StudyError("give --scheduler (an existing cluster) or --workers (a local one), not both")
    if args.scheduler:
        check_scheduler(args.scheduler)
    out = args.out or f"study-{args.name}"
    if args.out is None:  # the default folder (a given --out is checked by the command line before this)
        check_output_path(out, "dir", "--out")
    result = run_study(args.name, out, args.scheduler, args.workers, args.threads, not args.quiet)
    print(f"study {args.name}: {result['seconds']:.0f} s -> {result['report']}")
    for n in result["notes"]:
        print(f"  note: {n}")
    if result["failed_tasks"]:
        log.error(
            "study %s: %d task(s) failed; the report lists them (exit status 1)", args.name, result["failed_tasks"]
        )
    return result


def register(subparsers: Any) -> None:
    """Add ``study NAME`` to the ``scopetwin`` parser."""
    p = subparsers.add_parser(
        "study",
        help="an accuracy study against rendered truth; the study 'thesis' puts the thesis's tables beside ours",
        description=DESCRIPTION,
        **conventions("scopetwin study noise --workers 2", "scopetwin study thesis --out tables --workers 0"),
    )
    p.add_argument("name", help=f"one of: {', '.join(STUDY_NAMES)}")
    p.add_argument("--out", help="report folder (default: study-NAME)")
    add_cluster_options(p)
    p.add_argument("--json", metavar="PATH", help="write machine-readable results here")
    p.set_defaults(
        func=cmd_study,
        outputs=[("out", "dir"), ("json", "file")],
        exit_code=lambda result: EXIT_TASKS_FAILED if result["failed_tasks"] else 0,
    )
