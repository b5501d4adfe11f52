"""Marker identification on rendered images of the thesis's setups, checked against sim.truth."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.recon.markers import find_markers_for
from scopetwin.scenes.setup import Setup, load_setup
from scopetwin.sim.surfaces import surface_for
from scopetwin.sim.truth import marker_truth


def _noisy(setup: Setup, image: np.ndarray, seed: int) -> np.ndarray:
    sensor = setup.sensor.sensor()
    exposure = sensor.exposure_for(float(image.max()), setup.sensor.photons_per_unit_s, 0.7)
    return sensor.capture(image, setup.sensor.photons_per_unit_s, exposure, rng=seed)


def _compare(markers, truth) -> tuple[int, int, int, np.ndarray]:
    """Wrong indices, visible markers missed, partial markers kept, and centroid errors of the kept ones."""
    key = {tuple(k): n for n, k in enumerate(truth.ij)}
    idx = np.array([key.get(tuple(k), -1) for k in markers.ij])
    err = np.linalg.norm(markers.centroids - truth.center_px[idx], axis=1)
    wrong = int(np.sum((idx < 0) | ~(err < 2.0)))
    found = np.zeros(len(truth.ij), dtype=bool)
    found[idx[idx >= 0]] = True
    return wrong, int(np.sum(truth.visible & ~found)), int(np.sum(found & ~truth.visible)), err


@pytest.mark.mitsuba
def test_deflectometry_1_10_every_whole_marker_found_and_indexed():
    from scopetwin.scenes.mitsuba.render import render_setup

    setup = load_setup("thesis-1.10-deflectometry")
    heights = surface_for(setup)
    truth = marker_truth(setup, heights)
    clean = render_setup(setup, heights, spp=8, seed=3)
    for image in (clean, _noisy(setup, clean, 7)):
        markers = find_markers_for(image, setup)
        wrong, missed, partial, err = _compare(markers, truth)
        assert wrong == 0 and missed == 0 and partial == 0, (wrong, missed, partial)
        assert len(markers) == truth.visible.sum() > 500
        # the whole-spot centroid is within 0.03 px of the true image of the centre on the bowed substrate
        assert np.sqrt(np.mean(err**2)) < 0.015 and err.max() < 0.04


def test_calibration_target_angular_view_analytic_render():
    # §2.8.1 angular view on a 4x coarser camera (same field of view), rendered with the numpy reference
    setup = load_setup("thesis-2.8.1-angular", {"camera": {"pixels": [340, 256], "pixel_pitch": 0.0186}})
    from scopetwin.scenes.analytic import render

    truth = marker_truth(setup)
    clean = render(setup, spp=4, seed=0)
    for image in (clean, _noisy(setup, clean, 3)):
        markers = find_markers_for(image, setup)
        wrong, missed, partial, err = _compare(markers, truth)
        assert (wrong, missed, partial) == (0, 0, 0)
        assert markers.ij.min() == 0 and tuple(markers.ij.max(axis=0)) == (10, 8)
        assert err.max() < 0.1


def test_deflectometry_on_a_coarser_camera_analytic_render():
    # the §1.10 setup on a 2x coarser camera (same field of view) with the numpy reference renderer,
    # so the mirror-view indexing is checked without Mitsuba
    setup = load_setup("thesis-1.10-deflectometry", {"camera": {"pixels": [680, 512], "pixel_pitch": 0.0093}})
    from scopetwin.scenes.analytic import render

    heights = surface_for(setup)
    truth = marker_truth(setup, heights)
    image = _noisy(setup, render(setup, heights, spp=4, seed=1), 5)
    markers = find_markers_for(image, setup)
    wrong, missed, partial, _ = _compare(markers, truth)
    assert wrong == 0
    assert missed + partial <= 3  # rims within ~0.5 px of the substrate edge cannot be told apart at 2x pixels
    assert len(markers) > 500
