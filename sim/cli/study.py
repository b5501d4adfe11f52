"""``scopetwin study NAME [--out DIR] [--scheduler ADDRESS | --workers N]`` (:mod:`sim.studies`).

Runs an accuracy study (``thesis``, ``noise``, ``angle``, ``surface``) on an embedded Dask LocalCluster
(one process per core, one thread each, 127.0.0.1 only), on an existing cluster, or in this process
(``--workers 0``), and writes ``report.md``, ``results.json`` and PNG plots into ``--out``.
"""

from __future__ import annotations

import argparse
from typing import Any

from sim.studies.context import StudyError
from sim.studies.runner import STUDIES, run_study


def cmd_study(args: argparse.Namespace) -> dict[str, Any]:
    """Run the study ``NAME``; returns ``{"study", "report", "results", "seconds", "plots", "notes"}``."""
    if args.name not in STUDIES:
        raise StudyError(f"unknown study {args.name!r} (known: {', '.join(STUDIES)})")
    if args.workers is not None and args.workers < 0:
        raise StudyError(f"--workers must be >= 0, got {args.workers}")
    if args.scheduler and args.workers is not None:
        raise StudyError("give --scheduler (an existing cluster) or --workers (a local one), not both")
    result = run_study(
        args.name, args.out or f"study-{args.name}", args.scheduler, args.workers, args.threads, not args.quiet
    )
    print(f"study {args.name}: {result['seconds']:.0f} s -> {result['report']}")
    for n in result["notes"]:
        print(f"  note: {n}")
    return result


def register(subparsers: Any) -> None:
    """Add ``study NAME`` to the ``scopetwin`` parser."""
    p = subparsers.add_parser(
        "study",
        help="an accuracy study against rendered truth; `thesis` reproduces the seed's tables side by side",
        description=__doc__.splitlines()[0],
    )
    p.add_argument("name", help=f"one of: {', '.join(STUDIES)}")
    p.add_argument("--out", help="report folder (default: study-NAME)")
    p.add_argument("--scheduler", metavar="ADDRESS", help="existing Dask scheduler, e.g. tcp://host:8786")
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="local worker processes (default: one per core; 0: no Dask, work in this process)",
    )
    p.add_argument("--threads", type=int, metavar="N", help="Dr.Jit threads per worker (default 1 on a local cluster)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--json", metavar="PATH", help="write machine-readable results here")
    p.set_defaults(func=cmd_study)
