"""Bad inputs and faults, one row each — what the command does with them.

Every row builds its inputs in a fresh folder, runs one ``scopetwin`` command and checks:

* the **exit code**: 2 for bad input, 3 for a device that stopped answering (docs/contract.md, "Command line");
* **one line** on stderr, ``scopetwin: error: ...``, saying what the row expects (the device and its state, the file
  and the limit), nothing on stdout that a library printed (OpenEXR's ``Warning:``), **no traceback**;
* **nothing left behind**: no path the command created, except what the row keeps (the frames an acquisition took
  before its light board went silent, listed in its manifest), no ``.part`` or staging file;
* a **bounded time**: each row within its budget (inputs that could hang — a FIFO, ``/dev/zero`` — run in their own
  process with a timeout).

The classes: inputs that hang, recurse or exhaust (FIFOs, devices, folders, oversized, not UTF-8, nested 3000 deep in
arrays, tables or dotted keys, as setups, their ``base``, rigs, dataset configs and ``--set`` values, MDA sequences,
images and height maps); numbers out of their physical range (setups, rigs, emulator options); one clear line before
any work (a truncated EXR, an MDA file pydantic rejects, a relative ``base``, ``--json`` equal to ``--out``); devices
that stop answering (silent, garbage, a flood, a dropped line) mid-move, mid-acquisition and mid-MDA, and emulators
killed in their own processes. The last test prints ``tried N / held M``.
"""

from __future__ import annotations

import contextlib
import json
import os
import subprocess
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from scopetwin.cli import main
from scopetwin.scenes.io import write_heightmap, write_image
from scopetwin.scenes.surface import HeightMap
from tests.instrument.cli_processes import ROOT, emulator, scopetwin

RIGS = ROOT / "rigs"
EMULATED = (RIGS / "emulated-hardware.toml").read_text()
BOARD = '"emu://fpga-board"'
STAGE_X = '"emu://pi-gcs?travel_mm=0,150&max_velocity_mm_s=50"'
FOCUS = '"emu://jena-piezo?model=nv40-1"'
DEEP = 3000
#: Rows tried and held, by id (the last test prints the tally).
RESULTS: dict[str, bool] = {}


@dataclass
class Run:
    """What a row runs: the arguments, and for a row in its own process what happens while it runs."""

    argv: list[str]
    process: bool = False
    during: Callable[[subprocess.Popen], None] | None = None
    cwd: Path | None = None


@dataclass
class Row:
    """One bad input or fault: how to make it, and what the command must do with it."""

    id: str
    make: Callable[[Path, contextlib.ExitStack], Run]
    code: int
    says: list[str]
    keep: Callable[[Path, str], None] | None = None  # checks what the command keeps (frames) and may leave
    budget_s: float = 30.0
    slow: bool = False
    stdout_may: bool = False  # the command prints its result (an MDA's progress is off with -q)
    refuses: list[str] = field(default_factory=list)  # texts the line must not contain (a URL, a second line)


# -- inputs ---------------------------------------------------------------------------------------------------------
def _fifo(d: Path, name: str) -> Path:
    path = d / name
    os.mkfifo(path)
    return path


def _write(d: Path, name: str, text: str) -> Path:
    path = d / name
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path


def _setup(d: Path, body: str, base: str = "thesis-1.10-deflectometry") -> Path:
    return _write(d, "setup.toml", f'base = "{base}"\n{body}\n')


def _deep_array() -> str:
    return "[" * DEEP + "]" * DEEP


def _render(path: Path | str, d: Path, *more: str) -> Run:
    return Run(["render", str(path), "--out", str(d / "out"), *more])


def _rig(d: Path, text: str, name: str = "rig.toml") -> Path:
    return _write(d, name, text)


def _stage_rig(d: Path, body: str) -> Path:
    head = '[devices.x]\nkind = "stage"\ndriver = "sim"\ntravel_mm = [0.0, 150.0]\nmax_velocity_mm_s = 50.0\n'
    return _rig(d, head + body + "\n")


def _faulty(port: str, fault: str, after: int) -> str:
    """``port`` (a quoted emu:// URL) whose emulator answers ``after`` requests, then fails with ``fault``."""
    url = port.strip('"')
    sep = "&" if "?" in url else "?"
    return f'"{url}{sep}fault={fault}&fault_after={after}"'


def _emulated(d: Path, replace: dict[str, str]) -> Path:
    text = EMULATED
    for old, new in replace.items():
        assert old in text
        text = text.replace(old, new)
    return _rig(d, text)


def _image(d: Path) -> Path:
    path = d / "image.exr"
    write_image(path, np.full((102, 136), 0.5, np.float32))
    return path


def _truncated(path: Path) -> Path:
    data = path.read_bytes()
    cut = path.with_name("cut-" + path.name)
    cut.write_bytes(data[: len(data) // 2])
    path.unlink()
    return cut


def _dataset(d: Path, extra: str = "") -> Path:
    return _write(
        d,
        "dataset.toml",
        '[dataset]\nkind = "deflectometry"\nsetup = "thesis-1.10-deflectometry"\ncount = 2\nmaster_seed = 1\n'
        f"spp = 1\n{extra}\n",
    )


SEQUENCE = {"channels": [{"config": "halogen", "group": "Channel", "exposure": 10.0}]}


def _sequence(d: Path, data: dict | None = None, name: str = "seq.json", text: str | None = None) -> Path:
    return _write(d, name, text if text is not None else json.dumps(data or SEQUENCE))


def _mda(rig: Path, seq: Path, d: Path) -> Run:
    return Run(["rig", str(rig), "mda", str(seq), "--out", str(d / "stack.ome.tif"), "-q"])


# -- what a row may leave -------------------------------------------------------------------------------------------
def _frames_kept(d: Path, line: str) -> None:
    """The frames taken before the fault: on disk, each listed in the manifest, the manifest says how it ended."""
    out = d / "frames"
    manifest = json.loads((out / "manifest.json").read_text())
    on_disk = sorted(p.name for p in out.glob("*.exr"))
    assert on_disk and on_disk == sorted(f["path"] for f in manifest["frames"]), (on_disk, manifest["frames"][:3])
    assert not manifest["complete"] and manifest["error"]
    assert f"{len(on_disk)} frame(s) already taken kept in {out}" in line


def _planes_kept(d: Path, line: str) -> None:
    """An MDA's planes acquired before the fault, in the OME file the line names (or none was written)."""
    stack = d / "stack.ome.tif"
    if stack.exists():
        assert f"kept in {stack}" in line
    else:
        assert "no plane was written" in line


# -- devices stopping mid-operation, in their own processes ---------------------------------------------------------
def _wait_for(check: Callable[[], bool], proc: subprocess.Popen, what: str, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not check():
        assert proc.poll() is None, f"the command ended before {what}: {proc.communicate()[1][-2000:]}"
        assert time.monotonic() < deadline, f"no {what} within {timeout_s} s"
        time.sleep(0.05)


def _log_has(log: Path, text: str, count: int = 1) -> Callable[[], bool]:
    return lambda: log.exists() and log.read_text().count(text) >= count


def _killed_stage(d: Path, stack: contextlib.ExitStack) -> Run:
    log = d / "pi.jsonl"
    port, emu = stack.enter_context(emulator("pi-gcs", "travel_mm=0,150", "max_velocity_mm_s=5", log=log))
    rig = _rig(d, f'[devices.x]\nkind = "stage"\ndriver = "pi-gcs"\nport = "{port}"\ntravel_mm = [0.0, 150.0]\n')

    def during(proc: subprocess.Popen) -> None:
        _wait_for(_log_has(log, '"request": "MOV 1'), proc, "move command")
        time.sleep(0.3)
        emu.kill()

    return Run(["rig", str(rig), "move", "x", "100"], process=True, during=during)


def _killed_board(d: Path, stack: contextlib.ExitStack) -> Run:
    port, emu = stack.enter_context(emulator("fpga-board"))
    rig = _emulated(d, {BOARD: f'"{port}"'})
    out = d / "frames"

    def frames() -> bool:
        try:
            return len(json.loads((out / "manifest.json").read_text())["frames"]) >= 3
        except (OSError, ValueError, KeyError):
            return False

    def during(proc: subprocess.Popen) -> None:
        _wait_for(frames, proc, "three frames")
        emu.kill()

    argv = ["rig", str(rig), "acquire", str(out), "--frames", "100000", "--light", "halogen", "--exposure-s", "0.01"]
    return Run(argv, process=True, during=during)


def _killed_focus(d: Path, stack: contextlib.ExitStack) -> Run:
    log = d / "piezo.jsonl"
    port, emu = stack.enter_context(emulator("jena-piezo", "--model", "nv40-1", log=log))
    rig = _emulated(d, {FOCUS: f'"{port}"'})
    seq = _sequence(d, {**SEQUENCE, "z_plan": {"top": 260.0, "bottom": 200.0, "step": 2.0}})

    def during(proc: subprocess.Popen) -> None:
        _wait_for(_log_has(log, '"request": "wr,', 4), proc, "four focus moves")
        emu.kill()

    return Run(_mda(rig, seq, d).argv, process=True, during=during)


def _fault_rows() -> list[Row]:
    """Each emulator's line failing each way, mid-move and mid-acquisition (in-process emu:// emulators)."""
    rows = []
    for fault in ("silent", "garbage", "flood", "drop"):
        rows.append(
            Row(
                f"board-{fault}-mid-acquire",
                lambda d, s, f=fault: Run(
                    [
                        "rig",
                        str(_emulated(d, {BOARD: _faulty(BOARD, f, 24)})),
                        "acquire",
                        str(d / "frames"),
                        "--frames",
                        "1000",
                        "--light",
                        "halogen",
                        "--exposure-s",
                        "0.01",
                    ]
                ),
                3,
                ["FPGA board", "stopped answering", "light 'halogen' may still be on", "safe state"],
                keep=_frames_kept,
            )
        )
        rows.append(
            Row(
                f"stage-{fault}-mid-move",
                lambda d, s, f=fault: Run(
                    ["rig", str(_emulated(d, {STAGE_X: _faulty(STAGE_X, f, 30)})), "move", "x", "120"]
                ),
                3,
                ["stage 'x'", "stopped answering", "may still be moving to 120 mm", "every other device"],
            )
        )
    for fault in ("silent", "flood"):
        rows.append(
            Row(
                f"focus-{fault}-mid-move",
                lambda d, s, f=fault: Run(
                    ["rig", str(_emulated(d, {FOCUS: _faulty(FOCUS, f, 5)})), "move", "focus", "300"]
                ),
                3,
                ["focus 'focus'", "stopped answering", "may still be moving to 300 um"],
            )
        )
    rows += [
        Row(
            "focus-silent-mid-mda",
            lambda d, s: _mda(
                _emulated(d, {FOCUS: _faulty(FOCUS, "silent", 12)}),
                _sequence(d, {**SEQUENCE, "z_plan": {"top": 260.0, "bottom": 200.0, "step": 2.0}}),
                d,
            ),
            3,
            ["focus 'focus'", "stopped answering", "may still be moving"],
            keep=_planes_kept,
            budget_s=60.0,
            slow=True,
        ),
        Row(
            "board-garbage-mid-mda",
            lambda d, s: _mda(
                _emulated(d, {BOARD: _faulty(BOARD, "garbage", 30)}),
                _sequence(d, {**SEQUENCE, "time_plan": {"interval": 0, "loops": 40}}),
                d,
            ),
            3,
            ["FPGA board", "stopped answering"],
            keep=_planes_kept,
            budget_s=60.0,
            slow=True,
        ),
        Row(
            "stage-emulator-killed-mid-move",
            _killed_stage,
            3,
            ["stage 'x'", "stopped answering", "may still be moving to 100 mm"],
            budget_s=60.0,
        ),
        Row(
            "board-emulator-killed-mid-acquire",
            _killed_board,
            3,
            ["FPGA board", "stopped answering", "light 'halogen' may still be on", "every other device"],
            keep=_frames_kept,
            budget_s=60.0,
        ),
        Row(
            "focus-emulator-killed-mid-mda",
            _killed_focus,
            3,
            ["focus 'focus'", "stopped answering"],
            keep=_planes_kept,
            budget_s=90.0,
            slow=True,
        ),
    ]
    return rows


# -- the table ------------------------------------------------------------------------------------------------------
ROWS: list[Row] = [
    # inputs that hang, recurse or exhaust
    Row(
        "setup-fifo",
        lambda d, s: Run(_render(_fifo(d, "s.toml"), d).argv, process=True),
        2,
        ["FIFO", "not a regular file"],
    ),
    Row("setup-dev-zero", lambda d, s: _render("/dev/zero", d), 2, ["/dev/zero is a device"]),
    Row("setup-base-dev-zero", lambda d, s: _render(_write(d, "s.toml", 'base = "/dev/zero"\n'), d), 2, ["device"]),
    Row(
        "setup-base-fifo",
        lambda d, s: Run(_render(_write(d, "s.toml", f'base = "{_fifo(d, "b.toml")}"\n'), d).argv, process=True),
        2,
        ["FIFO"],
    ),
    Row("setup-deep-array", lambda d, s: _render(_setup(d, f"x = {_deep_array()}"), d), 2, ["levels deep"]),
    Row(
        "setup-deep-inline-table",
        lambda d, s: _render(_setup(d, "x = " + "{a = " * DEEP + "1" + "}" * DEEP), d),
        2,
        ["levels deep"],
    ),
    Row(
        "setup-deep-dotted-keys",
        lambda d, s: _render(_setup(d, ".".join(["k"] * DEEP) + " = 1"), d),
        2,
        ["levels deep"],
    ),
    Row("setup-folder", lambda d, s: _render(_write(d, "dir.toml/x", "") and d / "dir.toml", d), 2, ["is a folder"]),
    Row(
        "setup-oversized", lambda d, s: _render(_sparse(d / "big.toml", 17 * 2**20), d), 2, ["over the limit of 16 MiB"]
    ),
    Row("setup-not-utf8", lambda d, s: _render(_bytes(d / "bin.toml", b"a = 1\n\xff\xfe\n"), d), 2, ["not UTF-8"]),
    Row(
        "rig-fifo", lambda d, s: Run(["rig", str(_fifo(d, "rig.toml")), "info"], process=True), 2, ["rig file", "FIFO"]
    ),
    Row(
        "rig-dev-zero-acquire",
        lambda d, s: Run(["rig", "/dev/zero", "acquire", str(d / "frames")]),
        2,
        ["rig file /dev/zero is a device"],
    ),
    Row("rig-deep", lambda d, s: Run(["rig", str(_stage_rig(d, f"x = {_deep_array()}")), "info"]), 2, ["levels deep"]),
    Row(
        "dataset-config-fifo",
        lambda d, s: Run(["dataset", "generate", str(_fifo(d, "c.toml")), "--out", str(d / "ds")], process=True),
        2,
        ["dataset configuration", "FIFO"],
    ),
    Row(
        "dataset-config-deep",
        lambda d, s: Run(["dataset", "generate", str(_dataset(d, f"x = {_deep_array()}")), "--out", str(d / "ds")]),
        2,
        ["levels deep"],
    ),
    Row(
        "dataset-set-deep",
        lambda d, s: Run(
            ["dataset", "generate", str(_dataset(d)), "--out", str(d / "ds"), "--set", f"dataset.spp={_deep_array()}"]
        ),
        2,
        ["levels deep"],
    ),
    Row(
        "mda-fifo",
        lambda d, s: Run(_mda(RIGS / "sim-cmu.toml", _fifo(d, "seq.json"), d).argv, process=True),
        2,
        ["MDA sequence", "FIFO"],
    ),
    Row(
        "mda-deep-json",
        lambda d, s: _mda(RIGS / "sim-cmu.toml", _sequence(d, text='{"metadata": ' + _deep_array() + "}"), d),
        2,
        ["levels deep"],
    ),
    Row(
        "mda-deep-yaml",
        lambda d, s: _mda(RIGS / "sim-cmu.toml", _sequence(d, name="seq.yaml", text="metadata: " + _deep_array()), d),
        2,
        ["levels deep"],
    ),
    Row(
        "image-fifo",
        lambda d, s: Run(["markers", str(_fifo(d, "i.exr")), "--pattern", "thesis-1.10-deflectometry"], process=True),
        2,
        ["EXR file", "FIFO"],
    ),
    Row(
        "image-dev-zero",
        lambda d, s: Run(
            ["reconstruct", "/dev/zero", "--setup", "thesis-1.10-deflectometry", "--out", str(d / "z.exr")]
        ),
        2,
        ["EXR file /dev/zero is a device"],
    ),
    Row(
        "heightmap-fifo",
        lambda d, s: Run(
            _render("thesis-1.10-deflectometry", d, "--surface", str(_fifo(d, "z.exr"))).argv, process=True
        ),
        2,
        ["FIFO"],
    ),
    # numbers out of their physical range
    Row(
        "setup-pixel-pitch-1e-300",
        lambda d, s: _render(_setup(d, "[camera]\npixel_pitch = 1e-300"), d),
        2,
        ["camera.pixel_pitch"],
    ),
    Row(
        "setup-pixel-pitch-1e300",
        lambda d, s: _render(_setup(d, "[camera]\npixel_pitch = 1e300"), d),
        2,
        ["camera.pixel_pitch"],
    ),
    Row(
        "setup-focal-length-1e300",
        lambda d, s: _render(_setup(d, "[camera]\nfocal_length = 1e300"), d),
        2,
        ["camera.focal_length"],
    ),
    Row(
        "setup-f-number-1e-300",
        lambda d, s: _render(_setup(d, "[camera]\nf_number = 1e-300"), d),
        2,
        ["camera.f_number"],
    ),
    Row(
        "setup-origin-1e300",
        lambda d, s: _render(_setup(d, "[camera]\norigin = [0.0, 0.0, 1e300]"), d),
        2,
        ["camera.origin"],
    ),
    Row(
        "setup-surface-range-1e300",
        lambda d, s: _render(_setup(d, "[substrate.surface]\nrange_um = 1e300"), d),
        2,
        ["substrate.surface.range_um"],
    ),
    Row(
        "setup-mirror-size-negative",
        lambda d, s: _render(_setup(d, "[mirror]\nsize = [-60.0, 80.0]", "thesis-2.8.3-mirror"), d),
        2,
        ["mirror.size"],
    ),
    Row(
        "setup-exposure-1e-300",
        lambda d, s: _render(_setup(d, "[sensor]\nexposure_s = 1e-300"), d),
        2,
        ["sensor.exposure_s"],
    ),
    Row(
        "grin-wavelength-1e300",
        lambda d, s: Run(["optics", "grin", str(_setup(d, "wavelength_nm = 1e300", "thesis-7.5.2-grin-egfp"))]),
        2,
        ["wavelength_nm"],
    ),
    Row(
        "cmu-pixel-1e-300",
        lambda d, s: Run(["optics", "cmu", "--setup", str(_setup(d, "[camera]\npixel_um = 1e-300", "thesis-cmu"))]),
        2,
        ["camera.pixel_um"],
    ),
    Row(
        "emulate-jena-range-nan",
        lambda d, s: Run(["emulate", "jena-piezo", "range_um=nan,400"]),
        2,
        ["range_um", "finite"],
    ),
    Row(
        "emulate-jena-range-falling",
        lambda d, s: Run(["emulate", "jena-piezo", "range_um=400,0"]),
        2,
        ["range_um must rise"],
    ),
    Row("emulate-pi-velocity-inf", lambda d, s: Run(["emulate", "pi-gcs", "max_velocity_mm_s=inf"]), 2, ["finite"]),
    Row("emulate-pi-travel-1e300", lambda d, s: Run(["emulate", "pi-gcs", "travel_mm=0,1e300"]), 2, ["travel_mm"]),
    Row("emulate-pi-no-axes", lambda d, s: Run(["emulate", "pi-gcs", "axes="]), 2, ["axes"]),
    Row(
        "emulate-board-index-0",
        lambda d, s: Run(["emulate", "fpga-board", "max_current_index=0"]),
        2,
        ["max_current_index"],
    ),
    Row(
        "emulate-unknown-fault", lambda d, s: Run(["emulate", "fpga-board", "fault=melt"]), 2, ["fault must be one of"]
    ),
    Row(
        "emu-url-range-nan",
        lambda d, s: Run(["rig", str(_emulated(d, {FOCUS: '"emu://jena-piezo?range_um=nan,400"'})), "info"]),
        2,
        ["range_um", "finite"],
    ),
    Row("rig-timeout-nan", lambda d, s: Run(["rig", str(_stage_rig(d, "timeout_s = nan")), "info"]), 2, ["timeout_s"]),
    Row("rig-timeout-0", lambda d, s: Run(["rig", str(_stage_rig(d, "timeout_s = 0")), "info"]), 2, ["timeout_s"]),
    Row(
        "rig-travel-1e300",
        lambda d, s: Run(
            ["rig", str(_rig(d, '[devices.x]\nkind = "stage"\ndriver = "sim"\ntravel_mm = [0.0, 1e300]\n')), "info"]
        ),
        2,
        ["travel_mm"],
    ),
    Row(
        "rig-velocity-1e300",
        lambda d, s: Run(
            [
                "rig",
                str(
                    _rig(
                        d,
                        '[devices.x]\nkind = "stage"\ndriver = "sim"\ntravel_mm = [0.0, 1.0]\n'
                        "max_velocity_mm_s = 1e300\n",
                    )
                ),
                "info",
            ]
        ),
        2,
        ["max_velocity_mm_s"],
    ),
    Row(
        "rig-baudrate-text",
        lambda d, s: Run(["rig", str(_emulated(d, {STAGE_X: STAGE_X + '\nbaudrate = "fast"'})), "info"]),
        2,
        ["baudrate"],
    ),
    Row("rig-move-nan", lambda d, s: Run(["rig", str(RIGS / "sim-cmu.toml"), "move", "x", "nan"]), 2, ["nan"]),
    # one clear line before any work
    Row(
        "exr-truncated",
        lambda d, s: Run(["markers", str(_truncated(_image(d))), "--pattern", "thesis-1.10-deflectometry"]),
        2,
        ["not a readable OpenEXR file", "truncated or corrupt"],
    ),
    Row(
        "heightmap-truncated",
        lambda d, s: _render("thesis-1.10-deflectometry", d, "--surface", str(_truncated(_heightmap(d)))),
        2,
        ["truncated or corrupt"],
    ),
    Row(
        "mda-pydantic",
        lambda d, s: _mda(RIGS / "sim-cmu.toml", _sequence(d, {"z_plan": {"range": "x", "step": 1}}), d),
        2,
        ["MDA sequence", "z_plan", "more problem"],
        refuses=["https://", "errors.pydantic.dev"],
    ),
    Row(
        "mda-not-json-or-yaml",
        lambda d, s: _mda(RIGS / "sim-cmu.toml", _write(d, "seq.toml", "a = 1\n"), d),
        2,
        ["must end in .json, .yaml or .yml"],
    ),
    Row(
        "setup-base-beside-the-toml",
        lambda d, s: Run(
            _render(_write(d, "sub/a.toml", 'base = "b.toml"\n'), d).argv,
            cwd=_write(d, "b.toml", 'base = "thesis-1.10-deflectometry"\n').parent,
        ),
        2,
        ["sub/b.toml does not exist", "base of a setup in"],
    ),
    Row(
        "json-equals-out",
        lambda d, s: Run(["render", "thesis-1.10-deflectometry", "--out", str(d / "r"), "--json", str(d / "r")]),
        2,
        ["--out and --json both name"],
        budget_s=10.0,
    ),
    *_fault_rows(),
]


def _sparse(path: Path, size: int) -> Path:
    with open(path, "wb") as fh:
        fh.truncate(size)
    return path


def _bytes(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path


def _heightmap(d: Path) -> Path:
    path = d / "surface.exr"
    write_heightmap(path, HeightMap(np.zeros((16, 32)), -13.0, 13.0, -29.0, 29.0))
    return path


# -- the runner -----------------------------------------------------------------------------------------------------
def _files(root: Path) -> set[str]:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def _in_process(run: Run, capfd: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    code: int
    with contextlib.ExitStack() as stack:
        if run.cwd is not None:
            stack.enter_context(contextlib.chdir(run.cwd))
        try:
            code = main(run.argv)
        except SystemExit as exc:
            code = int(exc.code) if isinstance(exc.code, int) else 2
        except BaseException:
            out, err = capfd.readouterr()
            pytest.fail(f"scopetwin {' '.join(run.argv)[:300]} raised:\n{traceback.format_exc()}\n{err[-2000:]}")
    out, err = capfd.readouterr()
    return code, out, err


def _in_own_process(run: Run, budget_s: float) -> tuple[int, str, str]:
    assert run.cwd is None, "a row in its own process runs in the repository root"
    proc = scopetwin(*run.argv)
    try:
        if run.during is not None:
            run.during(proc)
        out, err = proc.communicate(timeout=budget_s)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, err = proc.communicate()
        pytest.fail(f"scopetwin {' '.join(run.argv)[:300]} did not end within {budget_s} s (a hang): {err[-2000:]}")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return proc.returncode, out, err


def _params() -> list:
    return [pytest.param(row, id=row.id, marks=[pytest.mark.slow] if row.slow else []) for row in ROWS]


@pytest.mark.timeout(300)
@pytest.mark.filterwarnings("error::pytest.PytestUnhandledThreadExceptionWarning")  # a worker's traceback fails
@pytest.mark.parametrize("row", _params())
def test_row(row: Row, tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    RESULTS[row.id] = False
    d = tmp_path / "w"
    d.mkdir()
    with contextlib.ExitStack() as stack:
        run = row.make(d, stack)
        before = _files(tmp_path)
        t0 = time.monotonic()
        if run.process:
            code, out, err = _in_own_process(run, row.budget_s)
        else:
            code, out, err = _in_process(run, capfd)
        seconds = time.monotonic() - t0
    lines = [line for line in err.splitlines() if line.strip()]
    if lines and lines[0].startswith("usage:"):  # argparse's own refusal: its usage, then the one error line
        lines = [line for line in lines if ": error: " in line]
    shown = f"exit {code}; stderr:\n{err[-3000:]}\nstdout:\n{out[-1000:]}"
    assert code == row.code, shown
    assert "Traceback" not in err and "Traceback" not in out, shown
    assert len(lines) == 1 and lines[0].startswith("scopetwin") and ": error: " in lines[0], shown
    line = lines[0]
    for text in row.says:
        assert text in line, f"{text!r} not in the line: {line}"
    for text in row.refuses:
        assert text not in line, f"{text!r} in the line: {line}"
    assert row.stdout_may or "Warning" not in out, shown  # no library's own output (OpenEXR) on stdout
    assert seconds < row.budget_s, f"took {seconds:.1f} s, over the budget of {row.budget_s} s"
    created = _files(tmp_path) - before
    created = {p for p in created if not p.endswith((".jsonl",))}  # the emulators' own request logs
    if row.keep is not None:
        row.keep(d, line)
        created = {p for p in created if not p.startswith(("w/frames", "w/stack"))}
    assert not created, f"left behind: {sorted(created)[:10]}"
    assert not [p for p in _files(tmp_path) if ".part" in p or ".staging" in p], _files(tmp_path)
    RESULTS[row.id] = True


def test_tally() -> None:
    """The last test: how many rows ran and how many held (every one must)."""
    tried, held = len(RESULTS), sum(RESULTS.values())
    print(f"\nbad inputs and faults: tried {tried} / held {held}")
    failed = sorted(k for k, ok in RESULTS.items() if not ok)
    assert held == tried, f"failed: {failed}"
