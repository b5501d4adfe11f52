"""``scopetwin run``: the main job on the embedded default (the library is :mod:`scopetwin.sim.pipeline`)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from scopetwin.cli.options import conventions


def cmd_run(args: argparse.Namespace) -> dict[str, Any]:
    """The main job on the embedded default: simulate, render, calibrate, reconstruct, compare.

    Generates a §1.9 surface, renders the two calibration images and the measurement image (noise on)
    with Mitsuba, calibrates the setup, reconstructs with the calibrated and with the ideal setup,
    compares with the truth and writes a report folder (report.md, EXR maps, PNG plots). The folder
    appears only when everything succeeded. ``--setup`` (preset or TOML) and ``--surface`` (height-map EXR) run the
    same job on a user's rig and substrate (:func:`scopetwin.sim.pipeline.run_setups`).
    """
    from scopetwin.sim.measurement import StagedOutput
    from scopetwin.sim.pipeline import run_pipeline

    out = Path(args.out)
    stage = StagedOutput(out)
    try:
        summary = run_pipeline(
            stage.stage, args.spp, args.seed, progress=not args.quiet, setup=args.setup, surface=args.surface
        )
        stage.commit()
    except BaseException:
        stage.discard()
        raise
    print(f"wrote the report to {out / 'report.md'}")
    return {"report": str(out / "report.md"), **summary}


def register(subparsers: Any) -> None:
    """Add ``run`` to the ``scopetwin`` sub-command parsers."""
    help_ = "the main job on the embedded default: simulate, render, calibrate, reconstruct, compare"
    p = subparsers.add_parser(
        "run",
        help=help_,
        description=help_,
        **conventions(
            "scopetwin run",
            "scopetwin run --setup thesis-1.10-deflectometry --spp 16 --seed 2 --out run-seed2 -q",
        ),
    )
    p.set_defaults(func=cmd_run, outputs=[("out", "dir"), ("json", "file")], estimate="run")
    p.add_argument("--json", metavar="PATH", help="write machine-readable results here")
    p.add_argument("--out", default="scopetwin-run", help="report folder (default: scopetwin-run)")
    p.add_argument("--spp", type=int, help="samples per pixel")
    p.add_argument("--seed", type=int, help="random seed")
    p.add_argument(
        "--setup", metavar="SETUP", help="measurement setup: preset name or TOML (default thesis-1.10-deflectometry)"
    )
    p.add_argument("--surface", metavar="Z.exr", help="substrate height map (EXR, channel Z in mm) to measure")
