"""The ``scopetwin`` command line (docs/contract.md, "Command line"): it parses arguments and calls library functions.

One module per command group, each with a ``register(subparsers)`` that adds its commands:

================================  ===============================================================
:mod:`scopetwin.cli.render`       ``render SETUP``, ``presets``
:mod:`scopetwin.cli.run`          ``run`` (the main job, :mod:`scopetwin.sim.pipeline`)
:mod:`scopetwin.cli.markers`      ``markers IMAGE --pattern SETUP``
:mod:`scopetwin.cli.reconstruct`  ``reconstruct IMAGE --setup SETUP --out Z.exr``
:mod:`scopetwin.cli.calibrate`    ``calibrate IMAGE``, ``calibrate-setup``
:mod:`scopetwin.cli.optics`       ``optics grin | cmu | scan``
:mod:`scopetwin.cli.rig`          ``rig RIG.toml info | move | position | acquire | mda | serve``
:mod:`scopetwin.cli.emulate`      ``emulate pi-gcs | jena-piezo | fpga-board``
:mod:`scopetwin.cli.dataset`      ``dataset generate | resume | verify``
:mod:`scopetwin.cli.study`        ``study NAME``
================================  ===============================================================

:mod:`scopetwin.cli.outputs` checks and writes the outputs every command declares (below);
:mod:`scopetwin.cli.logs` writes the log on stderr.

Every command function takes the parsed arguments and returns its result as a JSON-ready dict; :func:`main`
writes it to ``--json PATH`` when given (``--json -``: to standard output, :mod:`scopetwin.cli.outputs`). A
command whose result decides the exit status (``dataset verify``: 1 when the dataset is incomplete) sets
``exit_code`` (a function of the result) beside ``func`` in its parser's defaults. Bad input gives one line
``scopetwin: error: ...`` on stderr and exit code 2, and leaves no partial output behind.

Every parser of the tree (commands and their sub-commands) shares the same conventions
(:func:`scopetwin.cli.options.conventions`): ``-v``/``--verbose`` (repeatable) and ``-q``/``--quiet``, before or
after the command words; a help text ending in ``examples:``. :func:`main` sets the ``scopetwin`` logger's level from
them for the command (:mod:`scopetwin.cli.logs`: warnings by default, ``-v`` notes, ``-vv`` debugging, ``-q``
errors only, and no progress bars); the library logs through it and never prints, the commands print their results
on stdout.

Around every command :func:`main` applies two policies:

* **outputs** (:mod:`scopetwin.cli.outputs`): the paths a command declares (``set_defaults(outputs=[("out", "dir"),
  ("json", "file")])``, sized by an optional ``estimate``) are checked before it runs — writable, a folder where a
  folder is needed, enough free space — and ``--json`` is written before the staged results are moved into place;
  a failed write (a full disk) is one line, exit 2, and what the command created is removed;
* **signals** (:mod:`scopetwin.sim.signals`): SIGTERM and SIGHUP raise :class:`~scopetwin.sim.signals.Terminated`, a
  ``KeyboardInterrupt``, so every command cleans up as after Ctrl-C; the command ends with one line
  ``scopetwin: interrupted by SIGTERM`` and exit status 128 + n (130 for Ctrl-C, 143 for SIGTERM, 129 for SIGHUP);
  the program (:func:`console_main`) then ends within :data:`~scopetwin.sim.signals.EXIT_GRACE_S` seconds.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import logging
import sys
import time
from collections.abc import Sequence

from scopetwin._version import __version__
from scopetwin.cli.logs import log_to_stderr
from scopetwin.cli.options import VERBOSE, HelpFormatter, common_options, verbosity
from scopetwin.cli.outputs import OutputTransaction, describe_os_error
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.sim import signals

EXIT_BAD_INPUT = 2

log = logging.getLogger(__name__)

#: Attributes naming the words of a nested command (``dataset generate``, ``optics grin``, ``rig RIG info``).
_COMMAND_WORDS = ("command", "dataset_command", "optics_command", "rig_action")

EXAMPLES = """examples:
  scopetwin presets
  scopetwin render thesis-1.10-deflectometry --out r1 --spp 16
  scopetwin -v reconstruct r1/image.exr --setup thesis-1.10-deflectometry --out r1/heights.exr
  scopetwin COMMAND --help"""


#: The command groups in the order ``scopetwin --help`` lists them, and the group of each top-level command word.
GROUPS = ("render", "run", "markers", "reconstruct", "calibrate", "optics", "rig", "emulate", "dataset", "study")
_GROUP_OF = {"presets": "render", "calibrate-setup": "calibrate", **{g: g for g in GROUPS}}


def _groups_for(argv: Sequence[str] | None) -> tuple[str, ...]:
    """The groups a parser for ``argv`` needs: the command's own where its word is known (the top-level options take
    no values, so the first word is the command), else all of them (help, a misspelt command).

    A command's process then imports its own group only: an emulator or a rig command starts without the
    reconstruction's and the calibration's libraries (``scopetwin emulate`` ~0.3 s instead of ~1.5 s of imports);
    ``--version`` alone needs none. The command modules import their libraries inside the command functions, so
    ``--help``, which registers every group, loads none of them either."""
    if argv is None:
        return GROUPS
    word = next((a for a in argv if not a.startswith("-")), None)
    if word is None and "--version" in argv and not {"-h", "--help"} & set(argv):
        return ()  # --version prints and exits before a command is needed
    return (_GROUP_OF[word],) if word in _GROUP_OF else GROUPS


def build_parser(argv: Sequence[str] | None = None) -> argparse.ArgumentParser:
    """The ``scopetwin`` parser: every command group registered, or (with ``argv``) the one its command needs."""
    parser = argparse.ArgumentParser(
        prog="scopetwin",
        description="Physically based testbed: deflectometry, one-shot calibration, the four-channel and GRIN "
        "microscopes, and the instruments that drive them. -v / -q (before or after the command) set how much "
        "is logged on stderr; results go to stdout.",
        parents=[common_options(top=True)],
        formatter_class=HelpFormatter,
        epilog=EXAMPLES,
    )
    parser.add_argument("--version", action="version", version=f"scopetwin {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for group in _groups_for(argv):
        importlib.import_module(f"scopetwin.cli.{group}").register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run one ``scopetwin`` command; returns the exit status (0; 1 from ``exit_code``; 2 bad input or a failed
    write; 3 a device stopped answering; 128 + n after signal n: 130 Ctrl-C, 143 SIGTERM, 129 SIGHUP)."""
    words = list(sys.argv[1:] if argv is None else argv)
    parser = build_parser(words)
    args, unknown = parser.parse_known_args(words)
    if unknown:  # argparse's error, from the parser of every command (the one built for argv knows its group only)
        parser = build_parser()
        args = parser.parse_args(words)
    level = verbosity(args)
    if level and args.quiet:
        parser.error("-v/--verbose and -q/--quiet exclude each other")
    with log_to_stderr(level, args.quiet):
        return _run(args)


def console_main() -> int:
    """The ``scopetwin`` program (console script, ``python -m scopetwin``): :func:`main`, and after an interruption
    (status 128 + n) the process ends within :data:`~scopetwin.sim.signals.EXIT_GRACE_S` seconds whatever a
    library left running (:func:`~scopetwin.sim.signals.exit_within`)."""
    status = main()
    if status >= 128:
        signals.exit_within(status)
    _quick_exit()
    return status


def _quick_exit() -> None:
    """Spare the interpreter's exit its garbage collections over every object the command's libraries made.

    The command is done and its outputs are written and closed. The collections Python runs while it unloads the
    modules traverse all live objects (SciPy's alone: ~0.08 s of a ``scopetwin reconstruct``'s ~0.1 s exit);
    :func:`gc.freeze` moves them to the permanent generation, which those collections skip. Exit handlers
    (``atexit``, logging's flush, child processes' clean-up) run as before; only cyclic garbage still unreached now
    is left to the operating system."""
    gc.freeze()


def _run(args: argparse.Namespace) -> int:
    """The command of ``args`` with the policies of :func:`main` around it (logging already set up)."""
    name = " ".join(str(w) for w in (getattr(args, k, None) for k in _COMMAND_WORDS) if w)
    shown = {k: v for k, v in sorted(vars(args).items()) if not (callable(v) or k.startswith(VERBOSE))}
    log.debug("%s: arguments %s", name, shown)
    t0 = time.perf_counter()
    try:
        with signals.terminate_on_signals():
            with OutputTransaction(args) as tx:
                result = args.func(args)
                tx.finish(result)
    except ScopetwinError as exc:
        print(f"scopetwin: error: {exc}", file=sys.stderr)
        return int(getattr(exc, "exit_status", EXIT_BAD_INPUT))  # 3: a device stopped answering (DeviceLost)
    except OSError as exc:  # a write that failed late (a full disk, a folder removed meanwhile), a lost device
        print(f"scopetwin: error: {describe_os_error(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt as exc:  # Ctrl-C, and SIGTERM/SIGHUP as signals.Terminated
        print(f"scopetwin: {signals.describe(exc)}", file=sys.stderr)
        return signals.exit_status(exc)
    exit_code = getattr(args, "exit_code", None)
    status = int(exit_code(result)) if exit_code is not None else 0
    log.info("%s finished in %.2f s (exit status %d)", name, time.perf_counter() - t0, status)
    return status
