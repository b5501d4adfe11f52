"""The ``scopetwin`` command line (DESIGN.md, "Command line"): it parses arguments and calls library functions.

One module per command group, each with a ``register(subparsers)`` that adds its commands:

=======================  =====================================================================================
:mod:`sim.cli.render`    ``render SETUP``, ``presets``
:mod:`sim.cli.run`       ``run`` (the main job, :mod:`sim.pipeline`)
:mod:`sim.cli.markers`   ``markers IMAGE --pattern SETUP``
:mod:`sim.cli.reconstruct` ``reconstruct IMAGE --setup SETUP --out Z.exr``
:mod:`sim.cli.calibrate` ``calibrate IMAGE``, ``calibrate-setup``
:mod:`sim.cli.optics`    ``optics grin | cmu | scan``
:mod:`sim.cli.rig`       ``rig RIG.toml info | move | position | acquire``
:mod:`sim.cli.dataset`   ``dataset generate | resume | verify``
:mod:`sim.cli.study`     ``study NAME``
=======================  =====================================================================================

Every command function takes the parsed arguments and returns its result as a JSON-ready dict; :func:`main`
writes it to ``--json PATH`` when given. A command whose result decides the exit status (``dataset verify``:
1 when the dataset is incomplete) sets ``exit_code`` (a function of the result) beside ``func`` in its parser's
defaults. Bad input gives one line ``scopetwin: error: ...`` on stderr and exit code 2, and leaves no partial
output behind.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from scenes.errors import ScopetwinError
from scenes.io import write_json_atomic
from sim.cli import calibrate, dataset, markers, optics, reconstruct, render, rig, run, study

EXIT_BAD_INPUT = 2


def build_parser() -> argparse.ArgumentParser:
    """The ``scopetwin`` parser with every command group registered."""
    parser = argparse.ArgumentParser(
        prog="scopetwin",
        description="Physically based testbed: deflectometry, one-shot calibration, the four-channel and GRIN "
        "microscopes, and the instruments that drive them.",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    render.register(sub)
    run.register(sub)
    markers.register(sub)
    reconstruct.register(sub)
    calibrate.register(sub)
    optics.register(sub)
    rig.register(sub)
    dataset.register(sub)
    study.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run one ``scopetwin`` command; returns the exit status (0, 1 from ``exit_code``, 2 bad input, 130)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        result = args.func(args)
        if getattr(args, "json", None):
            write_json_atomic(args.json, result)
    except ScopetwinError as exc:
        print(f"scopetwin: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("scopetwin: interrupted", file=sys.stderr)
        return 130
    exit_code = getattr(args, "exit_code", None)
    return int(exit_code(result)) if exit_code is not None else 0
