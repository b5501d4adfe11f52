"""One installed package: the wheel holds ``scopetwin/`` and its metadata only, and its modules import
from the wheel's files — not from the repository's folders."""

from __future__ import annotations

import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

import scopetwin

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    cmd = [sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--no-build-isolation", "-q", "-w", str(out)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    assert done.returncode == 0, done.stderr[-3000:]
    (path,) = out.glob("scopetwin-*.whl")
    return path


def test_the_wheel_holds_one_top_level_package(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names}
    assert tops == {"scopetwin", f"scopetwin-{scopetwin.__version__}.dist-info"}, tops
    for layer in ("scenes", "sim", "recon", "calib", "instrument"):
        assert f"scopetwin/{layer}/__init__.py" in names
    assert "scopetwin/scenes/presets/thesis-1.10-deflectometry.toml" in names  # the presets travel with it
    assert "scopetwin/sim/datasets/schemas/truth.schema.json" in names  # and the datasets' JSON Schemas
    entry = next(n for n in names if n.endswith("entry_points.txt"))
    assert "scopetwin = scopetwin.sim.cli:console_main" in zipfile.ZipFile(wheel).read(entry).decode()


def test_the_wheel_imports_from_its_own_files(wheel, tmp_path):
    site = tmp_path / "site"
    done = subprocess.run(
        [sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site), str(wheel)],
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    code = (
        "import sys, scopetwin, scopetwin.recon.strategy, scopetwin.scenes.setup as s;"
        "print(scopetwin.__file__); print(s.load_setup('thesis-1.10-deflectometry').name);"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('recon', 'scenes', 'sim', 'calib', 'instrument')))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path, env={"PYTHONPATH": str(site)}
    )
    assert out.returncode == 0, out.stderr[-3000:]
    lines = out.stdout.splitlines()
    assert lines[0].startswith(str(site)), lines  # the wheel's copy, not the repository's
    assert lines[1] == "thesis-1.10-deflectometry" and lines[2] == "[]"
    version = subprocess.run(
        [sys.executable, "-m", "scopetwin", "--version"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env={"PYTHONPATH": str(site)},
    )
    assert version.stdout.strip() == f"scopetwin {scopetwin.__version__}", version.stderr[-2000:]
