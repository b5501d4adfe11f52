"""The layers' dependency rules (ARCHITECTURE.md), checked on the source: imports only point down.

scopetwin's two public faces, the front door (scopetwin.api) and the command line (scopetwin.cli), -> every layer,
and no layer imports them; sim -> everything below; calib | instrument -> recon, scenes (not each other);
recon -> scenes; scenes -> nothing of ours. Mitsuba/Dr.Jit are imported only under scenes/mitsuba/, and
``import scopetwin.scenes`` (and recon, calib) never loads them. The layer folders at the repository root install
as ``scopetwin.<layer>`` (setup.py): every module is named, and imported, under ``scopetwin``.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("scopetwin.scenes", "scopetwin.sim", "scopetwin.recon", "scopetwin.calib", "scopetwin.instrument")
#: The top package's modules above every layer: the two public faces (``import scopetwin`` is the front door) and
#: ``python -m scopetwin``. They may import any layer; no layer imports them. (A layer may use the top package's
#: helpers below the faces, ``scopetwin._version`` and ``scopetwin.shipped``.)
FACES = {"scopetwin", "scopetwin.api", "scopetwin.cli", "scopetwin.__main__"}
FORBIDDEN = {
    "scopetwin.scenes": {"scopetwin.sim", "scopetwin.recon", "scopetwin.calib", "scopetwin.instrument", *FACES},
    "scopetwin.recon": {"scopetwin.sim", "scopetwin.calib", "scopetwin.instrument", *FACES},
    "scopetwin.calib": {"scopetwin.sim", "scopetwin.instrument", *FACES},
    "scopetwin.instrument": {"scopetwin.sim", "scopetwin.calib", *FACES},
    "scopetwin.sim": FACES,
}
RENDERERS = {"mitsuba", "drjit"}
#: The one reconstruction package that renders (ARCHITECTURE.md): it fits the surface to the image through
#: a differentiable render, so its modules may import the renderer (Mitsuba, Dr.Jit, scenes.mitsuba) -- lazily, inside
#: their functions only, so that importing it (and ``import recon``) loads no renderer.
RENDERING_RECON = ROOT / "recon" / "inverse"


def _folder(package: str) -> Path:
    """The repository folder of a layer package (``scopetwin.recon`` -> ``recon/``; setup.py maps them)."""
    return ROOT / package.removeprefix("scopetwin.")


def _top(name: str) -> str:
    """The layer (``scopetwin.recon``) or the outside package (``mitsuba``) an imported module belongs to."""
    parts = name.split(".")
    return ".".join(parts[:2]) if parts[0] == "scopetwin" and len(parts) > 1 else parts[0]


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(_top(alias.name) for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(_top(node.module))
    return names


@pytest.mark.parametrize("package", PACKAGES)
def test_imports_point_down(package):
    bad = []
    for path in sorted(_folder(package).rglob("*.py")):
        names = _imports(path)
        for name in names & FORBIDDEN[package]:
            bad.append(f"{path.relative_to(ROOT)} imports {name}")
        in_mitsuba_pkg = path.is_relative_to(ROOT / "scenes" / "mitsuba")
        if path.is_relative_to(RENDERING_RECON):
            continue  # the named exception: checked by test_inverse_rendering_imports_the_renderer_lazily
        if names & RENDERERS and not in_mitsuba_pkg:
            bad.append(f"{path.relative_to(ROOT)} imports {sorted(names & RENDERERS)} outside scenes/mitsuba/")
    assert not bad, "\n".join(bad)


def test_the_command_line_lives_beside_the_front_door():
    """``scopetwin.cli`` is a subpackage of the top package, in ``scopetwin/cli/``; no layer holds a command line."""
    assert (ROOT / "scopetwin" / "cli" / "__init__.py").is_file() and (ROOT / "scopetwin" / "api.py").is_file()
    inside = [p.relative_to(ROOT) for pkg in PACKAGES for p in sorted(_folder(pkg).glob("cli/**/*.py"))]
    assert not inside, f"a command line inside a layer: {inside}"


def test_a_layer_importing_a_face_is_refused():
    """The rule sees an import of the front door or the command line from a layer (``_top`` names the face)."""
    assert {_top(n) for n in ("scopetwin", "scopetwin.api", "scopetwin.cli.rig", "scopetwin.cli")} <= FACES
    assert _top("scopetwin.shipped") not in FACES and _top("scopetwin.sim.signals") == "scopetwin.sim"


def _module_imports(path: Path, top_level_only: bool) -> set[str]:
    """Full module names imported by ``path`` (``import a.b``, ``from a.b import c``), optionally outside functions."""
    tree = ast.parse(path.read_text(), filename=str(path))
    stack: list[ast.AST] = [tree]
    out: set[str] = set()
    while stack:
        node = stack.pop()
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
        for c in ast.iter_child_nodes(node):
            if top_level_only and isinstance(c, ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda):
                continue
            if isinstance(c, ast.If) and isinstance(c.test, ast.Name) and c.test.id == "TYPE_CHECKING":
                continue  # typing-only imports run nothing
            stack.append(c)
    return out


def test_inverse_rendering_imports_the_renderer_lazily():
    """recon/inverse/ is the one recon package that renders: renderer imports only inside its modules' functions."""
    modules = sorted(RENDERING_RECON.rglob("*.py"))
    assert modules

    def renders(names: set[str]) -> set[str]:
        return {m for m in names if m.split(".")[0] in RENDERERS or m.startswith("scopetwin.scenes.mitsuba")}

    for path in modules:
        top = renders(_module_imports(path, top_level_only=True))
        assert not top, f"{path.relative_to(ROOT)} imports {sorted(top)} at module level (must be lazy)"
    lazy = {m for p in modules for m in _module_imports(p, top_level_only=False)}
    assert any(m.startswith("scopetwin.scenes.mitsuba") for m in lazy), (
        "recon/inverse/ no longer renders: drop the exception"
    )
    others = [
        p.relative_to(ROOT)
        for p in sorted((ROOT / "recon").rglob("*.py"))
        if not p.is_relative_to(RENDERING_RECON) and renders(_module_imports(p, False))
    ]
    assert not others, f"only recon/inverse/ may import the renderer, also: {others}"
    out = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys, scopetwin.recon.inverse; print('mitsuba' in sys.modules or 'drjit' in sys.modules)",
        ],
        capture_output=True,
        text=True,
        cwd=ROOT,
        check=True,
    )
    assert out.stdout.strip() == "False", out.stdout + out.stderr


def test_importing_the_world_model_does_not_load_mitsuba():
    code = (
        "import sys, scopetwin, scopetwin.scenes, scopetwin.scenes.setup, scopetwin.scenes.analytic;"
        "import scopetwin.scenes.io, scopetwin.scenes.grin, scopetwin.recon, scopetwin.recon.markers, scopetwin.calib;"
        "import scopetwin.cli;"
        "print(sorted(m for m in ('mitsuba', 'drjit') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


# -- import circles and import-time renderer state -------------------------------------------------------


def _module_name(path: Path) -> str:
    """The installed name of a source file: ``recon/markers/indexing.py`` -> ``scopetwin.recon.markers.indexing``."""
    rel = path.relative_to(ROOT).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts if parts[0] == "scopetwin" else ("scopetwin", *parts))


def _project_modules() -> dict[str, Path]:
    files = [p for pkg in PACKAGES for p in sorted(_folder(pkg).rglob("*.py"))]
    files += sorted((ROOT / "scopetwin").rglob("*.py"))  # scopetwin/*.py and scopetwin/cli/
    return {_module_name(p): p for p in files}


def _edges(name: str, path: Path, modules: dict[str, Path]) -> set[str]:
    """Every project module that ``name`` imports, anywhere in the file (also inside functions)."""
    is_pkg = path.name == "__init__.py"
    here = name.split(".") if is_pkg else name.split(".")[:-1]
    out: set[str] = set()

    def add(target: str) -> None:
        # `import a.b.c` / `from a.b import c`: the deepest project module named
        while target and target not in modules:
            target = target.rpartition(".")[0]
        if target and target != name:
            out.add(target)

    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = ".".join(here[: len(here) - node.level + 1])
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module or ""
            for alias in node.names:
                full = f"{module}.{alias.name}"
                add(full if full in modules else module)
    return out


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_circles():
    """No two modules import each other, directly or through others — function-level imports included."""
    modules = _project_modules()
    graph = {name: _edges(name, path, modules) for name, path in modules.items()}
    circles = _cycles(graph)
    assert not circles, "import circles:\n" + "\n".join(" <-> ".join(c) for c in circles)


def test_cycle_finder_finds_a_circle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_variant_switch_at_import():
    """Importing every module of the project, the renderers included, leaves Mitsuba without a variant."""
    names = sorted(n for n in _project_modules() if not n.endswith("__main__"))
    code = (
        "import importlib, sys\n"
        f"for name in {names!r}:\n"
        "    importlib.import_module(name)\n"
        "mi = sys.modules.get('mitsuba')\n"
        "print(None if mi is None else mi.variant())\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip() == "None", f"a module set the Mitsuba variant {out.stdout.strip()!r} at import"


# -- one package: the layers install and import only as scopetwin.<layer> ---------------------------------

BARE = {pkg.removeprefix("scopetwin.") for pkg in PACKAGES}


def test_nothing_imports_a_layer_by_its_bare_name():
    """Library, tests, benchmarks and examples import ``scopetwin.recon``, never ``recon`` (a second copy)."""
    bad = []
    for path in sorted(ROOT.rglob("*.py")):
        rel = path.relative_to(ROOT)
        if rel.parts[0] in {".venv", "build", ".git"}:
            continue
        for name in _module_imports(path, top_level_only=False):
            if name.split(".")[0] in BARE:
                bad.append(f"{rel} imports {name}")
    assert not bad, "\n".join(bad)


def test_importing_everything_loads_no_bare_layer():
    """Importing every module leaves no module named after a bare layer (``recon``) in ``sys.modules``."""
    names = sorted(n for n in _project_modules() if not n.endswith("__main__"))
    code = (
        "import importlib, sys\n"
        f"for name in {names!r}:\n"
        "    importlib.import_module(name)\n"
        f"print(sorted(m for m in sys.modules if m.split('.')[0] in {sorted(BARE)!r}))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT / "tests")
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip() == "[]", out.stdout
