"""The default reconstruction on rendered bent glass it was not designed on (:mod:`scopetwin.sim.families`).

Two images whose re-chosen finer basis scale does not converge or loses the substrate (a glass-like sheet whose 6 mm
scale's frame maxima swing, a sheet with local features at 5 mm): the strategy keeps the converged result of the
first scale instead of failing, and it is right within its reported uncertainty. Seeds 9100-9105
of each family were fixed before the change; these are the two of them that failed without it. Mitsuba, 16 spp,
sensor noise (the render's seed = the surface's).
"""

from __future__ import annotations

import pytest

import scopetwin
from scopetwin.recon.substrate import Substrate2D
from scopetwin.sim.families import family_spec
from scopetwin.sim.pipeline import roi_errors

pytestmark = [pytest.mark.slow, pytest.mark.mitsuba]


@pytest.mark.parametrize(
    ("family", "seed", "kept"),
    [
        ("glass", 9100, "kept the first basis scale"),
        ("features", 9102, "kept the first basis scale"),
    ],
)
def test_a_step_that_does_not_converge_keeps_the_converged_result(mono_variant, family, seed, kept):
    setup = scopetwin.load_setup("thesis-1.10-deflectometry", {"substrate": {"surface": family_spec(family, seed)}})
    m = scopetwin.render(setup, spp=16, seed=seed)
    r = scopetwin.reconstruct(m.image, setup)
    assert any(step.startswith(kept) for step in r.strategy), r.strategy
    assert m.heights is not None
    e = roi_errors(r.result.surface.height, m.heights, Substrate2D.from_setup(setup))
    assert abs(e["roi_absolute_um"]) <= 2.0 * r.uncertainty.absolute_um  # measured: 1.2 u (glass)
    assert e["roi_shape_um"] <= 0.2  # measured: 0.154 µm (glass; 2.6 of its u)
