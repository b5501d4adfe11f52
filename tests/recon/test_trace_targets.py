"""One ray-surface intersection for several pattern targets (``Reconstructor.trace_targets``, thesis §1.6.4, §1.7),
as the outlier test of the nested iteration uses it: the same gradients as one trace per target set."""

from __future__ import annotations

import numpy as np

from scopetwin.recon.config import ReconstructionConfig
from scopetwin.recon.reconstruct import MarkerObservations, Reconstructor
from scopetwin.recon.strategy import solve
from scopetwin.scenes.setup import load_setup
from scopetwin.sim.surfaces import make_surface
from scopetwin.sim.truth import marker_truth

SETUP = load_setup("thesis-1.10-deflectometry")


def test_one_intersection_gives_each_target_sets_gradients_of_its_own_trace():
    """On the §1.9 bowed substrate (known truth): the fitted surface's gradients at the markers towards their own
    pattern points agree with the true surface's slopes to 20 µrad, and those towards the neighbouring indices'
    points are bit for bit what a trace per target set gives (about one pitch's slope, ~mrad, away)."""
    truth = make_surface(SETUP.substrate.surface, SETUP.substrate)
    t = marker_truth(SETUP, truth)
    obs = MarkerObservations(t.ij[t.visible], t.center_px[t.visible])
    rec = Reconstructor.from_setup(SETUP, ReconstructionConfig.realtime())
    surface = solve(rec, obs).surface
    ij, px, own = rec.prepare(obs)
    sets = [own, *(rec.pattern.centers(ij + np.asarray(step)) for step in ((1, 0), (0, -1), (-1, 1)))]
    together, ok = rec.trace_targets(surface, px, sets)
    assert ok.sum() > 0.9 * len(ok)
    for targets, (xy, hx, hy) in zip(sets, together, strict=True):
        xy1, hx1, hy1, ok1 = rec.trace(surface, px, targets)
        assert np.array_equal(ok1, ok)
        assert np.array_equal(xy1, xy) and np.array_equal(hx1, hx) and np.array_equal(hy1, hy)
    xy, hx, hy = together[0]
    gx, gy = truth.gradient(xy[:, 0], xy[:, 1])
    assert np.max(np.abs(hx - gx)) < 2e-5 and np.max(np.abs(hy - gy)) < 2e-5
    _, nx, ny = together[1]
    assert np.median(np.hypot(nx - hx, ny - hy)) > 1e-3  # another target: another slope, not the same numbers
