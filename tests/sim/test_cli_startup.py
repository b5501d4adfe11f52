"""Start-up of the command line: ``--version`` and the parsers (``--help``) load none of the heavy libraries; the
command modules import them inside the command functions. Each check runs in a fresh interpreter."""

from __future__ import annotations

import subprocess
import sys

from scopetwin.cli import GROUPS

#: Libraries that a parser never needs (scipy's heavy modules, renderers, clusters, file formats, plots).
HEAVY = (
    "scipy.optimize",
    "scipy.linalg",
    "scipy.interpolate",
    "scipy.spatial",
    "scipy.ndimage",
    "mitsuba",
    "drjit",
    "dask",
    "distributed",
    "pymmcore_plus",
    "tifffile",
    "zarr",
    "h5py",
    "matplotlib",
    "cv2",
)


def _loaded_after(code: str) -> list[str]:
    """The modules of :data:`HEAVY` and numpy in ``sys.modules`` after running ``code`` in a fresh interpreter."""
    probe = f"{code}\nimport sys\nprint(' '.join(sorted(m for m in NAMES if m in sys.modules)))"
    out = subprocess.run(
        [sys.executable, "-c", f"NAMES = {HEAVY + ('numpy',)!r}\n{probe}"],
        capture_output=True,
        text=True,
        check=True,
        timeout=120,
    ).stdout
    return out.splitlines()[-1].split()  # the last line: the probe's (``--version`` prints before it)


def test_version_loads_no_library():
    code = "import contextlib\nfrom scopetwin.cli import main\n"
    code += "with contextlib.suppress(SystemExit):\n    main(['--version'])"
    assert _loaded_after(code) == []  # not even numpy


def _parser_loads(groups: str) -> list[str]:
    return [m for m in _loaded_after(f"from scopetwin.cli import build_parser\nbuild_parser({groups})") if m != "numpy"]


def test_the_parser_of_every_command_loads_no_heavy_library():
    assert _parser_loads("") == []  # every group, as --help builds it


def test_each_group_alone_loads_no_heavy_library():
    for group in GROUPS:
        assert _parser_loads(repr([group])) == [], group


def test_the_names_spelt_out_for_the_parsers_are_the_libraries():
    from scopetwin.calib.oneshot import LENS_MODES
    from scopetwin.cli.calibrate import LENS_MODES as CLI_LENS_MODES
    from scopetwin.cli.study import STUDY_NAMES
    from scopetwin.sim.studies.runner import STUDIES

    assert CLI_LENS_MODES == LENS_MODES
    assert STUDY_NAMES == tuple(STUDIES)


def test_the_program_exit_skips_the_collections_but_runs_the_exit_handlers(tmp_path):
    """After a command the program (``console_main``) freezes the collector's objects (the interpreter's final
    collections then skip them), while exit handlers still run and the command's outputs are whole."""
    flag, out = tmp_path / "atexit.txt", tmp_path / "presets.json"
    code = (
        "import atexit, gc, sys\n"
        "from scopetwin.cli import console_main\n"
        f"atexit.register(lambda: open({str(flag)!r}, 'w').write('ran'))\n"
        f"sys.argv = ['scopetwin', 'presets', '--json', {str(out)!r}]\n"
        "status = console_main()\n"
        "print('frozen', gc.get_freeze_count())\n"
        "sys.exit(status)"
    )
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=False)
    assert proc.returncode == 0, proc.stderr
    assert int(proc.stdout.split()[-1]) > 1000  # the command's objects were frozen
    assert flag.read_text() == "ran"
    import json

    assert "thesis-1.10-deflectometry" in json.dumps(json.loads(out.read_text()))
