"""Shared fixtures: a seeded RNG, the Mitsuba variants the tests render in, and Dr.Jit cleanup after Mitsuba tests.

Tests never rely on a variant set by an import: a test that renders asks for ``mono_variant`` or
``spectral_variant`` (the variant names :func:`scopetwin.scenes.mitsuba.variant.choose` gives on this machine) and
passes it to
the builders and renderers, or asks for ``mi_mono`` / ``mi_spectral`` (the ``mitsuba`` module with that variant set).
"""

from __future__ import annotations

import gc
import signal
import sys
from typing import Any, Literal

import numpy as np
import pytest


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded generator: the same test draws the same numbers every run."""
    return np.random.default_rng(20130506)


def _variant_or_skip(kind: Literal["mono", "spectral"]) -> str:
    """The variant :func:`scopetwin.scenes.mitsuba.variant.choose` names for ``kind``; skips when it cannot run here."""
    pytest.importorskip("mitsuba")
    from scopetwin.scenes.mitsuba.variant import choose, unavailable

    name = choose(kind)
    reason = unavailable(name)
    if reason is not None:
        pytest.skip(reason)
    return name


@pytest.fixture(autouse=True)
def _mitsuba_available(request: pytest.FixtureRequest) -> None:
    """Tests marked ``mitsuba`` are skipped (with the reason) where their variants cannot run (no LLVM >= 16)."""
    if request.node.get_closest_marker("mitsuba") is not None:
        _variant_or_skip("mono")


@pytest.fixture
def mono_variant() -> str:
    """The variant of the monochrome renderers (Part I, GRIN, widefield); skips the test without it."""
    return _variant_or_skip("mono")


@pytest.fixture
def spectral_variant() -> str:
    """The variant of the spectral renderer (the CMU); skips the test without it."""
    return _variant_or_skip("spectral")


@pytest.fixture
def mi_mono(mono_variant: str) -> Any:
    """The ``mitsuba`` module with :func:`mono_variant` set in this thread."""
    from scopetwin.scenes.mitsuba.variant import mitsuba

    return mitsuba(mono_variant)


@pytest.fixture
def mi_spectral(spectral_variant: str) -> Any:
    """The ``mitsuba`` module with :func:`spectral_variant` set in this thread."""
    from scopetwin.scenes.mitsuba.variant import mitsuba

    return mitsuba(spectral_variant)


#: The fixtures through which a test renders with Mitsuba (besides the ``mitsuba`` mark).
_JIT_FIXTURES = frozenset({"mono_variant", "spectral_variant", "mi_mono", "mi_spectral"})


@pytest.fixture(autouse=True)
def _jit_cleanup(request: pytest.FixtureRequest):
    """Free Dr.Jit's kernel and memory caches after every test that renders (marked ``mitsuba`` or using a variant
    fixture). Not after the others: once a worker has loaded Dr.Jit, a full ``gc.collect()`` costs ~0.2 s, and after
    every test it was a fifth of the whole suite's time (335 of 1709 worker-seconds, measured); the garbage of a test
    that renders without saying so is collected after the next one that does, or by Python's own collector."""
    yield
    dr = sys.modules.get("drjit")
    renders = request.node.get_closest_marker("mitsuba") is not None or not _JIT_FIXTURES.isdisjoint(
        request.fixturenames
    )
    if dr is not None and renders:
        gc.collect()
        try:
            dr.flush_malloc_cache()
        except Exception:  # pragma: no cover - older drjit
            pass


def _hangup_ignored(signum: int, frame: object) -> None:
    """The suite's SIGHUP handler under ``nohup``: the hangup is ignored, as ``nohup`` asked."""


def pytest_configure(config: pytest.Config) -> None:
    """The signal tests send Ctrl-C and SIGHUP as a terminal does; a suite started as a background job of a script
    (``cmd &``) inherits SIGINT ignored, one started under ``nohup`` inherits SIGHUP ignored, and every process it
    starts would keep it ignored (as Python, the shell and the command line must: ``nohup scopetwin ...`` survives a
    hangup). So the suite's own processes take a handler instead (Python's for SIGINT, one that does nothing for
    SIGHUP, so the suite itself still survives a hangup): a handler is reset by ``exec``, and the processes the tests
    start get the default action back."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    hangup = getattr(signal, "SIGHUP", None)  # POSIX only
    if hangup is not None and signal.getsignal(hangup) is signal.SIG_IGN:
        signal.signal(hangup, _hangup_ignored)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The tests marked slow first (each group in its collected order): with two workers that steal work from each
    other (``--dist worksteal``), the minute-long tests start early and the run ends on short ones, instead of one
    worker finishing a two-minute inverse fit while the other has nothing left."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
