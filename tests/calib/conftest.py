"""Fixtures of the calibration tests (cases in calib_cases.py)."""

from __future__ import annotations

import pytest
from calib_cases import exact_case


@pytest.fixture
def angular():
    return exact_case("thesis-2.8.1-angular")


@pytest.fixture
def perpendicular():
    return exact_case("thesis-2.8.1-perpendicular")


@pytest.fixture(scope="session")
def rendered():
    """Mitsuba images of the §2.8.3 substrate and mirror scenes (16 spp)."""
    from scopetwin.scenes.mitsuba.render import render_setup
    from scopetwin.scenes.setup import load_setup

    return (
        render_setup(load_setup("thesis-2.8.3-substrate"), None, spp=16, seed=1),
        render_setup(load_setup("thesis-2.8.3-mirror"), None, spp=16, seed=2),
    )
