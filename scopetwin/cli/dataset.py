"""``scopetwin dataset generate | resume | verify`` (docs/contract.md, "Scale"; :mod:`scopetwin.sim.datasets`).

``generate CONFIG.toml --out DIR`` checks the whole config (every sample's setup), the output folder
and the free space for the samples' estimated size before any work, then renders the samples on an
embedded Dask LocalCluster (``--workers N`` processes, one thread each, 127.0.0.1 only), on an existing
cluster (``--scheduler tcp://host:8786``), or in this process (``--workers 0``). One run at a time
holds a dataset folder: a second run on it is refused with one line naming the holder's host and pid.
``resume DIR`` finishes an interrupted set and says what it found and repaired; ``verify DIR``
checks it (exit code 1 when anything is missing, corrupt, duplicated, left over, or breaks its format's schemas or
holds values that cannot be true). Ctrl-C, SIGTERM and SIGHUP stop a run with every finished sample listed in the
manifest. ``show DIR --out sheet.png`` draws a contact sheet of the samples with their truth; ``export DIR --to zarr |
hdf5 OUT`` stacks every sample into one array store; ``generate --set KEY=VALUE`` overrides a config key.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scopetwin.cli.options import add_cluster_options, conventions
from scopetwin.cli.outputs import check_space, human_bytes

if TYPE_CHECKING:
    from scopetwin.sim.datasets.plan import Plan

#: Plain text for ``--help`` (the module docstring is reST).
DESCRIPTION = (
    "Synthetic datasets with exact truth. generate CONFIG.toml --out DIR checks the whole config, the output folder "
    "and the free space before any work, then renders the samples on a local Dask cluster (--workers N), an existing "
    "one (--scheduler tcp://host:8786) or in this process (--workers 0). resume DIR finishes an interrupted dataset "
    "and says what it repaired; verify DIR checks every sample against the schemas and its values (exit 1 when "
    "anything is missing, corrupt or invalid); show DIR --out sheet.png draws a contact sheet; export DIR --to "
    "zarr|hdf5 OUT stacks every sample into one array store. One run at a time holds a dataset folder."
)


def _common(p: argparse.ArgumentParser) -> None:
    add_cluster_options(p)
    p.add_argument("--json", metavar="PATH", help="write machine-readable results here")


def _check_workers(args: argparse.Namespace) -> None:
    from scopetwin.sim.datasets.config import DatasetError
    from scopetwin.sim.datasets.runner import check_scheduler

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
    from scopetwin.sim.datasets.store import SAMPLE_FILE, SAMPLES, sample_name

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
    from scopetwin.sim.datasets.config import load_config
    from scopetwin.sim.datasets.plan import Plan
    from scopetwin.sim.datasets.store import generate, parse_indices

    _check_workers(args)
    cfg = load_config(args.config, args.count, args.set)
    indices = parse_indices(args.indices, cfg.dataset.count)
    plan = Plan.build(cfg, indices)  # every sample's setup is validated before any work
    _check_space(plan, Path(args.out), indices, "--out")
    result = generate(plan, args.out, args.scheduler, args.workers, args.threads, indices, not args.quiet)
    _report_recovery(result["recovery"], always=False)
    _report(result)
    return result


def cmd_resume(args: argparse.Namespace) -> dict[str, Any]:
    """Finish an interrupted dataset; returns the generation summary."""
    from scopetwin.sim.datasets.plan import Plan
    from scopetwin.sim.datasets.store import generate, load_plan

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
    from scopetwin.sim.datasets.store import verify

    result = verify(args.dir)
    print(
        f"{result['complete']} of {result['count']} samples complete; missing {len(result['missing'])}, corrupt "
        f"{len(result['corrupt'])}, duplicated {len(result['duplicates'])}, unlisted {len(result['unlisted'])}, "
        f"temporary {len(result['temporary'])}, invalid {len(result['invalid'])} (format {result['format']})"
    )
    for c in result["corrupt"][:10]:
        print(f"  corrupt sample {c['index']}: {c['reason']}")
    for c in result["invalid"][:10]:
        print(f"  invalid sample {c['index']}: {'; '.join(c['reasons'][:3])}")
    for e in result["config_errors"][:3]:
        print(f"  dataset.json: {e}")
    if result["in_use_by"]:
        from scopetwin.sim.datasets.lock import describe_holder

        print(f"  the folder is in use: {describe_holder(result['in_use_by'])} is still writing it")
    return json.loads(json.dumps(result))


def _open(folder: str) -> Any:
    from scopetwin.sim.datasets.reader import open_dataset

    return open_dataset(folder)


def _positions(ds: Any, text: str | None, default: int | None = None) -> list[int]:
    """Positions in ``ds`` of the samples whose indices lie in ``A:B`` (all, or the first ``default``, without)."""
    from scopetwin.sim.datasets.store import parse_indices

    if text is None:
        return list(range(len(ds) if default is None else min(default, len(ds))))
    count = int(ds.config.get("config", {}).get("dataset", {}).get("count", len(ds)))
    wanted = set(parse_indices(text, count))
    return [k for k, index in enumerate(ds.indices) if index in wanted]


def cmd_show(args: argparse.Namespace) -> dict[str, Any]:
    """Draw a contact sheet of a dataset's samples with their truth; returns ``{out, samples, columns, rows}``."""
    from scopetwin.sim.datasets.sheet import MAX_TILES, contact_sheet

    ds = _open(args.dir)
    result = contact_sheet(ds, _positions(ds, args.indices, 16 if args.indices is None else MAX_TILES), args.out)
    print(f"{len(result['samples'])} sample(s) drawn -> {result['out']}")
    return result


def cmd_export(args: argparse.Namespace) -> dict[str, Any]:
    """Stack every sample's image and maps into one zarr store or HDF5 file; returns the export summary."""
    from tqdm import tqdm

    from scopetwin.sim.datasets.export import plan_export, write_export

    ds = _open(args.dir)
    plan = plan_export(ds, args.out, args.to, args.only)  # every refusal before the progress bar starts
    with tqdm(total=len(ds), unit="sample", desc="export", disable=args.quiet) as bar:
        result = write_export(plan, progress=bar.update)
    print(f"{result['samples']} sample(s), {len(result['variables'])} variable(s) -> {result['out']} ({args.to})")
    return result


def register(subparsers: Any) -> None:
    """Add ``dataset generate | resume | verify | show | export`` to the ``scopetwin`` parser."""
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
    _register_generate(sub)
    _register_resume_verify(sub)
    _register_show_export(sub)


def _register_generate(sub: Any) -> None:
    """``dataset generate``."""
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
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config key (TOML value, validated as the file is), e.g. --set dataset.spp=4, "
        "--set render.spp=4, --set setup.camera.pixels=[340,256]; repeatable",
    )
    _common(p)
    p.set_defaults(func=cmd_generate, outputs=[("out", "dir", "keep"), ("json", "file")])


def _register_resume_verify(sub: Any) -> None:
    """``dataset resume`` and ``dataset verify``."""
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


def _register_show_export(sub: Any) -> None:
    """``dataset show`` and ``dataset export``."""
    h = "draw a contact sheet of the samples with their truth overlaid (substrate outline, heights, marker ids)"
    p = sub.add_parser(
        "show",
        help=h,
        description=h + "; the first 16 samples without --indices",
        **conventions(
            "scopetwin dataset show ds1 --out sheet.png", "scopetwin dataset show ds1 --indices 0:8 --out s.png"
        ),
    )
    p.add_argument("dir", help="dataset folder")
    p.add_argument("--indices", metavar="A:B", help="the samples with indices A..B-1 (at most 64)")
    p.add_argument("--out", required=True, help="PNG file to write")
    p.add_argument("--json", metavar="PATH", help="write {out, samples, columns, rows} here")
    p.set_defaults(func=cmd_show, outputs=[("out", "file"), ("json", "file")])

    h = "stack every sample's image and per-pixel maps into one zarr store or HDF5 file (named dimensions)"
    p = sub.add_parser(
        "export",
        help=h,
        description=h + "; xarray opens either as one dataset (open_zarr, open_dataset(engine='h5netcdf'))",
        **conventions(
            "scopetwin dataset export ds1 --to zarr ds1.zarr", "scopetwin dataset export ds1 --to hdf5 ds1.h5 -q"
        ),
    )
    p.add_argument("dir", help="dataset folder")
    p.add_argument("--to", required=True, choices=("zarr", "hdf5"), help="the format of OUT")
    p.add_argument("out", help="the zarr store (a folder) or HDF5 file to create")
    p.add_argument("--only", nargs="+", metavar="NAME", help="export only these variables (e.g. image height mask)")
    p.add_argument("--json", metavar="PATH", help="write {out, to, samples, variables} here")
    p.set_defaults(func=cmd_export, outputs=[("out", "path", "positional"), ("json", "file")])
