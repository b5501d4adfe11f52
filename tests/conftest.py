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


@pytest.fixture(autouse=True)
def _jit_cleanup():
    """Free Dr.Jit's kernel and memory caches after every test that loaded it."""
    yield
    dr = sys.modules.get("drjit")
    if dr is not None:
        gc.collect()
        try:
            dr.flush_malloc_cache()
        except Exception:  # pragma: no cover - older drjit
            pass


def pytest_configure(config: pytest.Config) -> None:
    """The signal tests send Ctrl-C as a terminal does; a suite started as a background job of a script (``cmd &``)
    inherits SIGINT ignored, and every process it starts would keep it ignored (as Python and the shell must). So the
    suite's own processes take Python's SIGINT handler: the processes they start get the default action back."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
