"""The examples in the front door's docstrings run as written (``scopetwin.api``, ``scopetwin.shipped``), one test per
docstring, so that those that render (a few seconds each) may run on different workers.

Examples that need files this suite does not make (a dataset folder) or take long (a second image) are marked
``+SKIP`` in their docstrings and shown, not run."""

from __future__ import annotations

import doctest
import io

import pytest

import scopetwin.api
import scopetwin.shipped

MODULES = (scopetwin.api, scopetwin.shipped)
FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def _docstrings() -> dict[str, doctest.DocTest]:
    finder = doctest.DocTestFinder(exclude_empty=True)
    found = [test for module in MODULES for test in finder.find(module, module.__name__)]
    return {
        test.name: test for test in found if any(_runs(e) and not e.source.startswith("import ") for e in test.examples)
    }


def _runs(example: doctest.Example) -> bool:
    return not example.options.get(doctest.SKIP)


DOCSTRINGS = _docstrings()


def _params() -> list[object]:
    """Each docstring with runnable examples; those that render with Mitsuba carry the ``mitsuba`` mark (skipped
    where no LLVM library lets Mitsuba run)."""
    params = []
    for name, test in sorted(DOCSTRINGS.items()):
        renders = any("render(" in e.source and _runs(e) for e in test.examples)
        params.append(pytest.param(name, marks=[pytest.mark.mitsuba] if renders else [], id=name))
    return params


def test_the_front_doors_functions_have_running_examples():
    names = {name.rsplit(".", 1)[-1] for name in DOCSTRINGS}
    assert {"load_setup", "render", "reconstruct", "calibrate", "calibrate_setup", "open_rig"} <= names, sorted(names)


@pytest.mark.parametrize("name", _params())
def test_docstring_examples_run(name):
    test = DOCSTRINGS[name]
    out = io.StringIO()
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    result = runner.run(
        doctest.DocTest(test.examples, dict(test.globs), test.name, test.filename, test.lineno, test.docstring),
        out=out.write,
    )
    assert result.failed == 0, out.getvalue()
    assert result.attempted > 0
