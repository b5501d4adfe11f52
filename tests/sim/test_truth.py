"""Marker truth: traced images of marker centres equal independent closed-form answers."""

import numpy as np

from scopetwin.scenes.setup import load_setup
from scopetwin.scenes.surface import HeightMap
from scopetwin.sim.surfaces import surface_for
from scopetwin.sim.truth import marker_truth


def test_target_truth_is_the_projection():
    s = load_setup("thesis-2.8.1-angular")
    t = marker_truth(s)
    expected = s.camera_model.project(s.marker_pattern.centers(t.ij))
    np.testing.assert_allclose(t.center_px, expected, atol=1e-9)
    assert t.visible.all()


def test_flat_substrate_truth_is_the_mirror_image():
    s = load_setup("thesis-1.10-deflectometry")
    flat = HeightMap(np.zeros((8, 8)), -12.6, 12.6, -28.5, 28.5)
    t = marker_truth(s, flat)
    mirrored = s.marker_pattern.centers(t.ij) * [1, 1, -1]
    expected = s.camera_model.project(mirrored)
    np.testing.assert_allclose(t.center_px[t.converged], expected[t.converged], atol=1e-7)
    # only markers reflected inside the 48 mm ROI of the 25.2 mm wide substrate are whole
    assert 100 < t.visible.sum() < len(t.ij)


def test_bowed_substrate_truth_reflects_exactly(rng):
    from scopetwin.scenes.analytic import AnalyticScene

    s = load_setup("thesis-1.10-deflectometry")
    hm = surface_for(s)
    t = marker_truth(s, hm)
    scene = AnalyticScene(s, hm)
    vis = t.visible
    o, d = s.camera_model.rays(t.center_px[vis])
    xy, ok = scene.pattern_hits(o, d)
    assert ok.all()
    np.testing.assert_allclose(xy, s.marker_pattern.centers_local(t.ij[vis]), atol=1e-8)
    # the bow moves the images by up to several pixels against the flat mirror
    flat = s.camera_model.project(s.marker_pattern.centers(t.ij[vis]) * [1, 1, -1])
    assert np.abs(t.center_px[vis] - flat).max() > 1.0
