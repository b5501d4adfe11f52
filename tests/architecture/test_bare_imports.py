"""A layer folder imported by its bare name from the checkout's root refuses in one line and names the right import.

From the repository root, ``import recon`` would find the folder ``recon/`` and load a second copy of
``scopetwin.recon`` whose classes are other objects than the package's. Each layer's ``__init__.py`` refuses that
import with an :class:`ImportError` whose message names ``scopetwin.<layer>`` and how to install it; the import under
``scopetwin`` is untouched.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LAYERS = ("scenes", "sim", "recon", "calib", "instrument")


def _python(code: str) -> subprocess.CompletedProcess[str]:
    """``python -c code`` with the repository root as the working directory (so the bare folders are importable)."""
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)


@pytest.mark.parametrize("layer", LAYERS)
def test_a_bare_layer_import_is_refused_in_one_line(layer: str) -> None:
    out = _python(f"import {layer}")
    assert out.returncode != 0, out.stdout + out.stderr
    last = out.stderr.strip().splitlines()[-1]
    assert last == (
        f"ImportError: {layer} is part of scopetwin: import scopetwin.{layer} "
        "(install with `make setup` or `pip install -e .`)"
    ), out.stderr


@pytest.mark.parametrize("layer", LAYERS)
def test_a_bare_submodule_import_is_refused_too(layer: str) -> None:
    """``import recon.markers`` loads ``recon`` first, which refuses: no module of the second copy is left behind."""
    sub = next(p.stem for p in sorted((ROOT / layer).glob("*.py")) if p.stem != "__init__")
    code = (
        "import sys\n"
        "try:\n"
        f"    import {layer}.{sub}\n"
        "except ImportError as exc:\n"
        "    print(exc)\n"
        f"print(sorted(m for m in sys.modules if m.split('.')[0] == {layer!r}))\n"
    )
    out = _python(code)
    assert out.returncode == 0, out.stderr
    assert out.stdout.splitlines() == [
        f"{layer} is part of scopetwin: import scopetwin.{layer} (install with `make setup` or `pip install -e .`)",
        "[]",
    ]


@pytest.mark.parametrize("layer", LAYERS)
def test_the_import_under_scopetwin_works_from_the_root(layer: str) -> None:
    out = _python(f"import scopetwin.{layer} as m; print(m.__name__)")
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == f"scopetwin.{layer}"
