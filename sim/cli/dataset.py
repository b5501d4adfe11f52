"""``scopetwin dataset generate | resume | verify`` (docs/contract.md, "Scale"; :mod:`scopetwin.sim.datasets`).

``generate CONFIG.toml --out DIR`` checks the whole config (every sample's setup), the output folder
and the free space for the samples' estimated size before any work, then renders the samples on an
embedded Dask LocalCluster (``--workers N`` processes, one thread each, 127.0.0.1 only), on an existing
cluster (``--scheduler tcp://host:8786``), or in this process (``--workers 0``). One run at a time
holds a dataset folder: a second run on it is refused with one line naming the holder's host and pid.
``resume DIR`` finishes an interrupted set and says what it found and repaired; ``verify DIR``
checks it (exit code 1 when anything is missing, corrupt, duplicated or left over). Ctrl-C, SIGTERM
and SIGHUP stop a run with every finished sample listed in the manifest.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from scopetwin.sim.cli.options import add_cluster_options, conventions
from scopetwin.sim.cli.outputs import check_space, human_bytes
from scopetwin.sim.datasets.config import DatasetError, load_config
from scopetwin.sim.datasets.plan import Plan
from scopetwin.sim.datasets.runner import check_scheduler
from scopetwin.sim.datasets.store import SAMPLE_FILE, SAMPLES, generate, load_plan, parse_indices, sample_name, verify

#: Plain text for ``--help`` (the module docstring is reST).
DESCRIPTION = (
    "Synthetic datasets with exact truth. generate CONFIG.toml --out DIR checks the whole config, the output folder "
    "and the free space before any work, then renders the samples on a local Dask cluster (--workers N), an existing "
    "one (--scheduler tcp://host:8786) or in this process (--workers 0). resume DIR finishes an interrupted dataset "
    "and says what it repaired; verify DIR checks every sample (exit 1 when anything is missing or corrupt). One run "
    "at a time holds a dataset folder."
)


def _common(p: argparse.ArgumentParser) -> None:
    add_cluster_options(p)
    p.add_argument("--json", metavar="PATH", help="write machine-readable results here")


def _check_workers(args: argparse.Namespace) -> None:
    if args.workers is not None and args.workers < 0:
        raise DatasetError(f"--workers must be >= 0, got {args.workers}")
    if args.threads is not None and args.threads <= 0:
        raise DatasetError(f"--threads must be > 0, got {args.threads}")
    if args.scheduler and args.workers is not None:
        raise DatasetError("give --scheduler (an existing cluster) or --workers (a local one), not both")
    if args.scheduler:
        check_scheduler(args.scheduler)


def _check_space(plan: Plan, root: Path, indices: list[int], option: str) -> None:
    """Refuse before any work when the samples still to render would not fit on the file system of ``root``."""
    todo = [i for i in indices if not (root / SAMPLES / sample_name(i) / SAMPLE_FILE).is_file()]
    if todo:
        each = plan.sample_bytes(todo[0])
        check_space(root, len(todo) * each, f"{option} {root} ({len(todo)} sample(s) of about {human_bytes(each)})")


def _report_recovery(state: dict[str, Any], always: bool) -> None:
    """What the run found in the folder and repaired (``resume`` always says it; ``generate`` when it did anything)."""
    repaired = (
        state["relisted"] or state["removed_temporary"] or state["corrupt_removed"] or state["dropped_manifest_lines"]
    )
    if not (always or repaired):
        return
    kept = f", {len(state['kept_temporary'])} kept (a live writer)" if state["kept_temporary"] else ""
    print(
        f"found {state['listed']} sample(s) listed, {len(state['relisted'])} re-listed from disk, "
        f"{len(state['removed_temporary'])} temporary folder(s) removed{kept}, {len(state['corrupt_removed'])} "
        f"corrupt sample(s) removed, {state['dropped_manifest_lines']} manifest line(s) dropped; "
        f"{state['requeued']} sample(s) queued"
    )


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
    _check_space(plan, Path(args.out), indices, "--out")
    result = generate(plan, args.out, args.scheduler, args.workers, args.threads, indices, not args.quiet)
    _report_recovery(result["recovery"], always=False)
    _report(result)
    return result


def cmd_resume(args: argparse.Namespace) -> dict[str, Any]:
    """Finish an interrupted dataset; returns the generation summary."""
    _check_workers(args)
    stored = load_plan(args.dir)
    plan = Plan.build(stored.config)
    _check_space(plan, Path(args.dir), list(range(plan.config.dataset.count)), "DIR")
    result = generate(plan, args.dir, args.scheduler, args.workers, args.threads, None, not args.quiet)
    _report_recovery(result["recovery"], always=True)
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
    if result["in_use_by"]:
        from scopetwin.sim.datasets.lock import describe_holder

        print(f"  the folder is in use: {describe_holder(result['in_use_by'])} is still writing it")
    return json.loads(json.dumps(result))


def register(subparsers: Any) -> None:
    """Add ``dataset generate | resume | verify`` to the ``scopetwin`` parser."""
    top = subparsers.add_parser(
        "dataset",
        help="synthetic datasets with exact truth (local or on a Dask cluster)",
        description=DESCRIPTION,
        **conventions(
            "scopetwin dataset generate examples/datasets/01-deflectometry-small.toml --out ds1 --workers 2",
            "scopetwin dataset verify ds1",
        ),
    )
    sub = top.add_subparsers(dest="dataset_command", required=True)

    h = "render a dataset described by a config TOML"
    p = sub.add_parser(
        "generate",
        help=h,
        description=h,
        **conventions(
            "scopetwin dataset generate examples/datasets/01-deflectometry-small.toml --out ds1 --workers 2",
            "scopetwin dataset generate examples/datasets/03-grin-targets.toml --out grin --indices 0:2 --workers 0 -q",
        ),
    )
    p.add_argument("config", help="dataset config TOML (see examples/datasets/)")
    p.add_argument("--out", required=True, help="dataset folder")
    p.add_argument("--count", type=int, help="override the config's sample count")
    p.add_argument("--indices", metavar="A:B", help="only samples A..B-1")
    _common(p)
    p.set_defaults(func=cmd_generate, outputs=[("out", "dir", "keep"), ("json", "file")])

    h = "finish an interrupted dataset without redoing finished samples"
    p = sub.add_parser(
        "resume",
        help=h,
        description=h,
        **conventions("scopetwin dataset resume ds1", "scopetwin dataset resume ds1 --workers 4 -q"),
    )
    p.add_argument("dir", help="dataset folder")
    _common(p)
    p.set_defaults(func=cmd_resume, outputs=[("dir", "dir", "keep", "positional"), ("json", "file")])

    h = "check every sample against the manifest and its hashes (exit status 1 when anything is wrong)"
    p = sub.add_parser(
        "verify",
        help=h,
        description=h,
        **conventions("scopetwin dataset verify ds1", "scopetwin dataset verify ds1 --json ds1-verify.json"),
    )
    p.add_argument("dir", help="dataset folder")
    p.add_argument("--json", metavar="PATH", help="write {complete, missing, corrupt, duplicates, ...} here")
    p.set_defaults(func=cmd_verify, exit_code=lambda result: 0 if result["ok"] else 1)
