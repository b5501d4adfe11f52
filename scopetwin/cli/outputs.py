"""Outputs checked before the work, and written last: the command line's side of "nothing half-done".

Each command's parser declares the paths it writes, e.g. ``set_defaults(outputs=[("out", "dir"), ("json",
"file")])``: the attribute, what it must be (``dir`` a folder, ``file`` a file, ``path`` either) and optionally
``"keep"`` for an output that is resumable state rather than a result (a dataset folder, frames of an acquisition:
never rolled back) and ``"positional"`` for a positional argument (named ``OUT`` rather than ``--out``). An
``estimate`` default (a function of the arguments giving ``{attribute: bytes}``) sizes the free-space check.
Before the command runs, :func:`check_outputs` refuses with one line naming the path and the problem, having
created nothing:

* an existing file where a folder is needed, or a folder where a file is needed;
* a path under a file, or where nothing can be created (read-only file system, no permission, ``/proc``);
* less free space than the estimate (at least :data:`MIN_FREE_BYTES` for every output);
* two outputs naming the same path (``--json`` equal to ``--out``);
* ``--json`` in a folder that does not exist (it is not created: a mistyped folder is one line, not a new tree).

``--json -`` writes the result to standard output instead of a file; what the command prints otherwise goes to
standard error then, so that standard output holds the JSON alone (``scopetwin presets --json - | jq``).

:class:`OutputTransaction` then runs the command with its staged commits deferred (:func:`scopetwin.sim.measurement.
deferred_commits`): the ``--json`` result is written to a temporary file beside its destination first, then the
staged folders are moved into place, then the JSON is renamed onto its name. A failure anywhere (``--json`` on a
full disk, a write error) removes what the command created — its staged folders, and the declared outputs that did
not exist before it ran (``keep`` ones excepted) — and ends in one line, exit 2.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import shutil
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from scopetwin.scenes.errors import ScopetwinError

log = logging.getLogger(__name__)

#: Free space every output needs at the least (a JSON file, a report).
MIN_FREE_BYTES = 1 << 20
#: ``--json STDOUT``: the result on standard output.
STDOUT = "-"
Kind = Literal["dir", "file", "path"]


class OutputError(ScopetwinError):
    """An output path that cannot be written (the message names the option, the path and the problem)."""


@dataclass(frozen=True)
class Output:
    """One declared output of a command: the argparse attribute, what it must be, whether it is kept on failure."""

    attr: str
    kind: Kind
    keep: bool = False
    positional: bool = False

    @property
    def option(self) -> str:
        """How the user wrote it: ``--json`` for ``json``, ``OUT`` for a positional ``out``."""
        return self.attr.upper() if self.positional else f"--{self.attr.replace('_', '-')}"


def json_to_stdout(args: argparse.Namespace) -> bool:
    """Whether the command's ``--json`` is :data:`STDOUT` (``-``)."""
    return str(getattr(args, "json", None)) == STDOUT


def declared_outputs(args: argparse.Namespace) -> list[Output]:
    """The outputs a command's parser declared (``outputs`` default); ``--json`` alone when it declared none."""
    spec = getattr(args, "outputs", None)
    if spec is None:
        spec = [("json", "file")] if hasattr(args, "json") else []
    outs = []
    for entry in spec:
        attr, kind, *rest = entry
        outs.append(Output(str(attr), kind, "keep" in rest, "positional" in rest))
    return outs


def human_bytes(n: float) -> str:
    """``12.3 MB``-style size (decimal units)."""
    for unit in ("B", "kB", "MB", "GB", "TB"):
        if abs(n) < 1000 or unit == "TB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} TB"  # pragma: no cover


def _nearest_existing(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and not p.is_symlink():
        if p.parent == p:
            break
        p = p.parent
    return p


def _probe_writable(folder: Path) -> str | None:
    """None when a file can be created in ``folder`` (tried, then removed); else the reason."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=".scopetwin-probe-", dir=folder)
    except OSError as exc:
        return exc.strerror or str(exc)
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(tmp)
    return None


def check_output_path(path: str | Path, kind: Kind, option: str, need_bytes: int = MIN_FREE_BYTES) -> Path:
    """Refuse an output path that cannot be written as ``kind``, before anything is created; returns it.

    Raises
    ------
    OutputError
        One line: ``OPTION PATH: the problem``.
    """
    text = str(path)
    where = f"{option} {text}"
    if not text:
        raise OutputError(f"{option}: the path is empty")
    p = Path(text)
    if p.exists():
        if kind == "dir" and not p.is_dir():
            raise OutputError(f"{where}: is an existing file, not a folder")
        if kind == "file" and p.is_dir():
            raise OutputError(f"{where}: is an existing folder, not a file")
    elif kind == "file" and text.endswith(os.sep):
        raise OutputError(f"{where}: names a folder, but a file is needed")
    if p.exists():  # a folder being filled is written in; a file is replaced from beside it
        probe = p if (p.is_dir() and kind != "file") else p.absolute().parent
    else:
        probe = _nearest_existing(p)
        if not probe.is_dir():
            raise OutputError(f"{where}: cannot be created, {probe} is a file, not a folder")
    reason = _probe_writable(probe)
    if reason is not None:
        raise OutputError(f"{where}: cannot write in {probe} ({reason})")
    check_space(probe, need_bytes, where)
    return p


def check_space(path: str | Path, need_bytes: int, what: str) -> None:
    """Refuse when the file system of ``path`` has less free space than ``need_bytes``.

    Raises
    ------
    OutputError
        ``WHAT: not enough free space on PATH: about N needed, M free``.
    """
    base = _nearest_existing(Path(path))
    try:
        free = shutil.disk_usage(base).free
    except OSError:
        return  # no figure for this file system: the write itself will tell
    if free < need_bytes:
        raise OutputError(
            f"{what}: not enough free space in {base}: about {human_bytes(need_bytes)} needed, {human_bytes(free)} free"
        )


def check_outputs(args: argparse.Namespace) -> list[tuple[Output, Path, bool]]:
    """Check every declared output of a command before it runs; returns (output, path, existed before) each.

    The command's ``estimate`` default (``args -> {attribute: bytes}``, or the name of one in :data:`ESTIMATES`),
    when given, sizes the free-space check; an estimate that cannot be made (bad input the command itself reports)
    falls back to the minimum.
    """
    estimate = getattr(args, "estimate", None)
    if isinstance(estimate, str):
        estimate = ESTIMATES[estimate]
    sizes: dict[str, int] = {}
    if estimate is not None:
        with contextlib.suppress(ScopetwinError, OSError, ValueError):
            sizes = dict(estimate(args))
    checked = []
    named: dict[str, Output] = {}
    for out in declared_outputs(args):
        value = getattr(args, out.attr, None)
        if value is None or (out.attr == "json" and str(value) == STDOUT):
            continue
        same = named.setdefault(os.path.realpath(os.path.abspath(str(value))), out) if str(value) else out
        if same is not out:  # e.g. --json equal to --out: refused before any work, not found after it
            raise OutputError(f"{same.option} and {out.option} both name {value}: give each output its own path")
        need = max(MIN_FREE_BYTES, int(sizes.get(out.attr, 0)))
        path = check_output_path(value, out.kind, out.option, need)
        if out.attr == "json" and not path.absolute().parent.is_dir():
            raise OutputError(f"{out.option} {value}: the folder {path.absolute().parent} does not exist")
        log.debug("%s %s: writable, %s free space needed", out.option, path, human_bytes(need))
        checked.append((out, path, path.exists() or path.is_symlink()))
    return checked


def describe_os_error(exc: OSError) -> str:
    """One line for a failed system call: ``PATH: No space left on device`` (the path when the error names one)."""
    reason = exc.strerror or str(exc) or type(exc).__name__
    return f"{exc.filename}: {reason}" if exc.filename is not None else reason


def _remove_created(path: Path, base: Path | None) -> None:
    """Remove ``path`` (created by the failed command) and the empty folders above it, up to ``base``."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists() or path.is_symlink():
        with contextlib.suppress(OSError):
            path.unlink()
    if base is None:
        return
    p = path.absolute().parent
    while p != base and base in p.parents:
        try:
            p.rmdir()
        except OSError:
            break
        p = p.parent


class OutputTransaction:
    """Run a command with its outputs checked first and its result written last (see the module text).

    Use as ``with OutputTransaction(args) as tx: result = args.func(args); tx.finish(result)``.
    """

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.outputs = check_outputs(args)
        self._bases = {out.attr: _nearest_existing(path) for out, path, existed in self.outputs if not existed}
        self._stack = contextlib.ExitStack()
        self._pending: list[Any] = []
        self._done = False
        self._stdout: Any = sys.stdout

    def __enter__(self) -> OutputTransaction:
        from scopetwin.sim.measurement import deferred_commits

        self._stdout = sys.stdout
        if json_to_stdout(self.args):  # standard output holds the JSON alone: the command's own lines go to stderr
            self._stack.enter_context(contextlib.redirect_stdout(sys.stderr))
        self._pending = self._stack.enter_context(deferred_commits())
        return self

    def finish(self, result: Any) -> None:
        """Write ``--json`` to a temporary file, move the deferred staged folders into place, rename the JSON (``--json
        -``: print it once the folders are in place)."""
        from scopetwin.scenes.io import atomic_path
        from scopetwin.sim.signals import deferred_signals

        json_path = getattr(self.args, "json", None)
        text = None
        if json_path:
            try:
                text = json.dumps(result, indent=2) + "\n"
            except TypeError as exc:  # a command returned something JSON cannot hold: a bug, said plainly
                raise OutputError(f"--json {json_path}: the result is not JSON ({exc})") from None
        with deferred_signals():  # a signal now waits until the result is in place
            with contextlib.ExitStack() as stack:
                if text is not None and not json_to_stdout(self.args):
                    stack.enter_context(atomic_path(str(json_path))).write_text(text)
                    log.info("wrote the result to --json %s", json_path)
                for stage in list(self._pending):
                    stage.commit_now()
                    self._pending.remove(stage)
            if text is not None and json_to_stdout(self.args):  # once the results are in place
                self._stdout.write(text)
                self._stdout.flush()
            self._done = True

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: Any) -> None:
        self._stack.close()  # discards staged folders still pending
        if exc_type is not None and not self._done:
            self.rollback()

    def rollback(self) -> None:
        """Remove the declared outputs (not ``keep``) that the command created before it failed."""
        for out, path, existed in self.outputs:
            if not (existed or out.keep):
                log.info("the command failed: removing %s %s", out.option, path)
                _remove_created(path, self._bases.get(out.attr))


# -- size estimates of the commands (``set_defaults(estimate=...)``) ----------------------------------------
def _image_bytes(nx: int, ny: int, images: int = 1) -> int:
    return int(nx) * int(ny) * images * (4 + 1)  # float32 EXR + 8-bit preview


def estimate_render(args: argparse.Namespace) -> dict[str, int]:
    """``render``: the image (float32) and its preview, the surface height map, the truth JSON (each twice with a
    second pattern position); for a fringe setup one image per frame."""
    from scopetwin.scenes.setup import load_setup

    setup = load_setup(args.setup)
    cam = setup.camera_model
    nodes = 0 if setup.substrate is None else setup.substrate.surface.grid[0] * setup.substrate.surface.grid[1]
    times = 2 if getattr(args, "pattern_shift", None) is not None or setup.pattern_stage is not None else 1
    if setup.fringe_sequence is not None:  # one float32 EXR per frame, one surface, fringes.json (per position)
        return {"out": times * (len(setup.fringe_sequence) * 4 * cam.nx * cam.ny + 4 * nodes + (256 << 10))}
    return {"out": times * (_image_bytes(cam.nx, cam.ny) + 4 * nodes + (256 << 10))}


def estimate_run(args: argparse.Namespace) -> dict[str, int]:
    """``run``: three images of the §1.10 setup, height and error maps, plots (16 MB for those)."""
    from scopetwin.scenes.setup import load_setup
    from scopetwin.sim.pipeline import MEASUREMENT

    setup = load_setup(getattr(args, "setup", None) or MEASUREMENT)
    cam = setup.camera_model
    return {"out": _image_bytes(cam.nx, cam.ny, 3) + (16 << 20)}


#: The estimates a parser can name (``set_defaults(estimate="render")``).
ESTIMATES: dict[str, Callable[[argparse.Namespace], dict[str, int]]] = {"render": estimate_render, "run": estimate_run}
