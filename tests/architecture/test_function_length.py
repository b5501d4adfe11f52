"""No library function over 80 lines: small functions of one job each.

Counted from the ``def`` line to the last line, docstring included (``ast``: end_lineno - lineno + 1). Declarative
tables are data, not functions, and live at module level; a parser declaration with one ``add_argument`` per option
is the one kind of long function allowed, and only where it is listed here with the reason.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
LIBRARY = ("scopetwin", "scenes", "sim", "recon", "calib", "instrument")
LIMIT = 80
#: (file, function) allowed to be longer, each a declaration: why.
DECLARATIVE: dict[tuple[str, str], str] = {}


def _long_functions() -> list[str]:
    out = []
    for folder in LIBRARY:
        for path in sorted((ROOT / folder).rglob("*.py")):
            rel = str(path.relative_to(ROOT))
            for node in ast.walk(ast.parse(path.read_text(), filename=rel)):
                if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                    length = (node.end_lineno or node.lineno) - node.lineno + 1
                    if length > LIMIT and (rel, node.name) not in DECLARATIVE:
                        out.append(f"{rel}:{node.lineno} {node.name} ({length} lines)")
    return out


def test_no_library_function_is_longer_than_80_lines():
    long = _long_functions()
    assert not long, "split these into functions of one job each:\n" + "\n".join(long)


def test_the_exemptions_are_still_needed():
    """An exemption whose function got short (or went away) is removed from the list."""
    for (rel, name), why in DECLARATIVE.items():
        tree = ast.parse((ROOT / rel).read_text())
        lengths = [
            (n.end_lineno or n.lineno) - n.lineno + 1
            for n in ast.walk(tree)
            if isinstance(n, ast.FunctionDef | ast.AsyncFunctionDef) and n.name == name
        ]
        assert lengths and max(lengths) > LIMIT, f"{rel} :: {name} is no longer long ({why}): drop its exemption"
