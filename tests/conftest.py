"""Shared fixtures: a seeded RNG and explicit Dr.Jit cleanup after Mitsuba tests."""

from __future__ import annotations

import gc
import sys

import numpy as np
import pytest


@pytest.fixture
def rng() -> np.random.Generator:
    """A seeded generator: the same test draws the same numbers every run."""
    return np.random.default_rng(20130506)


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
