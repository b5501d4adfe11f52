"""DESIGN.md's dependency rules, checked on the source: imports only point down.

sim -> everything; calib | instrument -> recon, scenes (not each other); recon -> scenes;
scenes -> nothing of ours. Mitsuba/Dr.Jit are imported only under scenes/mitsuba/, and
``import scenes`` (and recon, calib) never loads them.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("scenes", "sim", "recon", "calib", "instrument")
FORBIDDEN = {
    "scenes": {"sim", "recon", "calib", "instrument"},
    "recon": {"sim", "calib", "instrument"},
    "calib": {"sim", "instrument"},
    "instrument": {"sim", "calib"},
    "sim": set(),
}
RENDERERS = {"mitsuba", "drjit"}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("package", PACKAGES)
def test_imports_point_down(package):
    bad = []
    for path in sorted((ROOT / package).rglob("*.py")):
        names = _imports(path)
        for name in names & FORBIDDEN[package]:
            bad.append(f"{path.relative_to(ROOT)} imports {name}")
        in_mitsuba_pkg = path.is_relative_to(ROOT / "scenes" / "mitsuba")
        if names & RENDERERS and not in_mitsuba_pkg:
            bad.append(f"{path.relative_to(ROOT)} imports {sorted(names & RENDERERS)} outside scenes/mitsuba/")
    assert not bad, "\n".join(bad)


def test_importing_the_world_model_does_not_load_mitsuba():
    code = (
        "import sys, scenes, scenes.setup, scenes.analytic, scenes.io, scenes.grin, recon, recon.markers, calib;"
        "import sim.cli;"
        "print(sorted(m for m in ('mitsuba', 'drjit') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr
