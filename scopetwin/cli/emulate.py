"""``scopetwin emulate pi-gcs|jena-piezo|fpga-board [--model M] [--log FILE] [KEY=VALUE ...]`` (docs/contract.md).

One wire-protocol emulator (:mod:`scopetwin.instrument.emulators`) on a pseudo-terminal in this process, served by
:func:`scopetwin.instrument.emulators.serve.serve`. The first line on stdout is the port path (flushed at once), so a
script can read it and open the port as a serial device — pipython, Micro-Manager, the user's own code, or a rig
TOML with ``port = "/dev/pts/N"``. Unlike an ``emu://`` port, whose emulator lives and dies with one command,
this emulator keeps its state between commands until SIGINT or SIGTERM; it then prints one line (the port, the
number of requests answered, the final state) and exits 0.

``--log FILE`` appends one JSON object per line for every request: ``{"request", "reply", "state"}``, the state
after the request (board: ``"lights_on"``, the channels on, plus ``ttl``; stage: position, servo, referenced;
piezo: position, loop, remote). Device options are ``KEY=VALUE`` pairs, as in ``emu://`` URLs
(``travel_mm=0,150``, ``max_velocity_mm_s=50``, ``axes=1,2``, ``range_um=0,400``), each a finite number in the
range the emulated hardware could have (``range_um=nan,400`` is refused with one line, exit 2); ``fault=NAME
fault_after=N`` makes the device stop answering properly after N requests (``silent``, ``garbage``, ``drop``,
``flood``), to test how a client copes with a device that fails mid-operation.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

from scopetwin.cli.options import conventions
from scopetwin.instrument.emulators import EMULATORS
from scopetwin.instrument.errors import RigError

OPTIONS_HELP = {
    "pi-gcs": "axes=1,2 travel_mm=0,150 max_velocity_mm_s=50 reference_mm=0 stage=M-404.6PD (--model C-863.11)",
    "jena-piezo": "range_um=0,400 voltage_range_v=-20,130 (--model nv40-1 | nv40-3 | 30dv50)",
    "fpga-board": "max_current_index=65535 (no --model)",
    "any": "fault=silent|garbage|drop|flood fault_after=N (stop answering properly after N requests)",
}


def _announce(port: str) -> None:
    print(port, flush=True)


def cmd_emulate(args: argparse.Namespace) -> dict[str, Any]:
    """Serve one emulator until SIGINT/SIGTERM; the port path is the first stdout line."""
    from scopetwin.instrument.emulators.serve import parse_options, serve

    options = parse_options(args.options)
    if args.model is not None:
        if "model" in options:
            raise RigError("give the model once: --model or model=..., not both")
        options["model"] = args.model
    if args.kind == "fpga-board" and "model" in options:
        raise RigError("the fpga-board emulator has one model: drop --model")
    result = serve(args.kind, options, log_path=args.log, announce=_announce)
    summary = {k: v for k, v in result["state"].items() if not isinstance(v, dict | list) or k == "lights_on"}
    print(
        f"emulate: {result['emulator']} on {result['port']} stopped after {result['requests']} request(s); "
        f"state {json.dumps(summary)}",
        flush=True,
    )
    return result


def register(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``emulate KIND [--model M] [--log FILE] [KEY=VALUE ...]`` to an argparse subparsers object."""
    kinds = sorted(EMULATORS)
    options = "; ".join(f"{k}: {v}" for k, v in OPTIONS_HELP.items())
    parser = subparsers.add_parser(
        "emulate",
        help="run one wire-protocol emulator on a pseudo-terminal (first stdout line: the port)",
        description="Run one wire-protocol emulator (PI GCS stage controller, piezosystem jena focus drive, "
        "FPGA light/trigger board) on a pseudo-terminal until SIGINT or SIGTERM. The first stdout line is the "
        'port path: open it as a serial port, or put it in a rig TOML as port = "/dev/pts/N". The emulator '
        "keeps its state between commands (an emu:// port in a rig starts a fresh one for every command).",
        **conventions(
            "scopetwin emulate pi-gcs travel_mm=0,150 max_velocity_mm_s=50 --model C-863.11",
            "scopetwin emulate fpga-board --log board.jsonl",
            note=f"device options (KEY=VALUE) — {options}",
        ),
    )
    parser.add_argument("kind", choices=kinds, help="the wire protocol to emulate")
    parser.add_argument("options", nargs="*", metavar="KEY=VALUE", help="device options, as in emu:// URLs")
    parser.add_argument("--model", help="controller model (pi-gcs: C-863.11 ...; jena-piezo: nv40-1, nv40-3, 30dv50)")
    parser.add_argument("--log", metavar="FILE", help="append one JSON object per request: request, reply, state")
    parser.add_argument("--json", metavar="PATH", help="write the final result here when stopped")
    parser.set_defaults(func=cmd_emulate, outputs=[("log", "file", "keep"), ("json", "file")])
    return parser
