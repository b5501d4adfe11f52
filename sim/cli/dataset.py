"""``scopetwin dataset generate | resume | verify`` (DESIGN.md "Scale"; :mod:`sim.datasets`).

``generate CONFIG.toml --out DIR`` checks the whole config (every sample's setup) before any
work, then renders the samples on an embedded Dask LocalCluster (``--workers N`` processes, one
thread each, 127.0.0.1 only), on an existing cluster (``--scheduler tcp://host:8786``), or in this
process (``--workers 0``). ``resume DIR`` finishes an interrupted set; ``verify DIR`` checks it
(exit code 1 when anything is missing, corrupt, duplicated or left over).
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from sim.datasets.config import DatasetError, load_config
from sim.datasets.plan import Plan
from sim.datasets.store import generate, load_plan, parse_indices, verify


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scheduler", metavar="ADDRESS", help="existing Dask scheduler, e.g. tcp://host:8786")
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="local worker processes (default: one per core; 0: no Dask, work in this process)",
    )
    p.add_argument("--threads", type=int, metavar="N", help="Dr.Jit threads per worker (default 1 on a local cluster)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument("--json", metavar="PATH", help="write machine-readable results here")


def _check_workers(args: argparse.Namespace) -> None:
    if args.workers is not None and args.workers < 0:
        raise DatasetError(f"--workers must be >= 0, got {args.workers}")
    if args.threads is not None and args.threads <= 0:
        raise DatasetError(f"--threads must be > 0, got {args.threads}")
    if args.scheduler and args.workers is not None:
        raise DatasetError("give --scheduler (an existing cluster) or --workers (a local one), not both")


def _report(result: dict[str, Any]) -> None:
    rate = result["samples_per_minute"]
    print(
        f"{result['written']} sample(s) written, {result['already_done']} already done, of {result['requested']} "
        f"in {result['seconds']:.1f} s" + (f" ({rate:.1f} samples/min)" if rate else "") + f" -> {result['out']}"
    )


def cmd_generate(args: argparse.Namespace) -> dict[str, Any]:
    """Render a dataset described by a config TOML; returns the generation summary."""
    _check_workers(args)
    cfg = load_config(args.config, args.count)
    indices = parse_indices(args.indices, cfg.dataset.count)
    plan = Plan.build(cfg, indices)  # every sample's setup is validated before any work
    result = generate(plan, args.out, args.scheduler, args.workers, args.threads, indices, not args.quiet)
    _report(result)
    return result


def cmd_resume(args: argparse.Namespace) -> dict[str, Any]:
    """Finish an interrupted dataset; returns the generation summary."""
    _check_workers(args)
    stored = load_plan(args.dir)
    plan = Plan.build(stored.config)
    result = generate(plan, args.dir, args.scheduler, args.workers, args.threads, None, not args.quiet)
    _report(result)
    return result


def cmd_verify(args: argparse.Namespace) -> dict[str, Any]:
    """Check a dataset folder; returns the ``dataset verify`` JSON (exit code 1 when ``ok`` is false)."""
    result = verify(args.dir)
    print(
        f"{result['complete']} of {result['count']} samples complete; missing {len(result['missing'])}, corrupt "
        f"{len(result['corrupt'])}, duplicated {len(result['duplicates'])}, unlisted {len(result['unlisted'])}, "
        f"temporary {len(result['temporary'])}"
    )
    for c in result["corrupt"][:10]:
        print(f"  corrupt sample {c['index']}: {c['reason']}")
    return json.loads(json.dumps(result))


def register(subparsers: Any) -> None:
    """Add ``dataset generate | resume | verify`` to the ``scopetwin`` parser."""
    top = subparsers.add_parser(
        "dataset",
        help="synthetic datasets with exact truth (local or on a Dask cluster)",
        description=__doc__.splitlines()[0],
    )
    sub = top.add_subparsers(dest="dataset_command", required=True)

    p = sub.add_parser("generate", help="render a dataset described by a config TOML")
    p.add_argument("config", help="dataset config TOML (see examples/datasets/)")
    p.add_argument("--out", required=True, help="dataset folder")
    p.add_argument("--count", type=int, help="override the config's sample count")
    p.add_argument("--indices", metavar="A:B", help="only samples A..B-1")
    _common(p)
    p.set_defaults(func=cmd_generate)

    p = sub.add_parser("resume", help="finish an interrupted dataset without redoing finished samples")
    p.add_argument("dir", help="dataset folder")
    _common(p)
    p.set_defaults(func=cmd_resume)

    p = sub.add_parser("verify", help="check every sample against the manifest and its hashes")
    p.add_argument("dir", help="dataset folder")
    p.add_argument("--json", metavar="PATH", help="write {complete, missing, corrupt, duplicates, ...} here")
    p.set_defaults(func=cmd_verify, exit_code=lambda result: 0 if result["ok"] else 1)
