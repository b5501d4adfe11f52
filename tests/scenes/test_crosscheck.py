"""The Mitsuba renders reproduce the analytic ray model of thesis §1.6.

Both renderers image the same scene; the same grey-weighted centroid code
measures every marker spot in both images; the centroids must agree. What is
compared is the renderer, not the marker centres: on a bowed substrate a spot's
centroid is not the image of the marker centre (docs/rendering.md), and both
renderers must show the same bias.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from scopetwin.scenes.analytic import render_pixels
from scopetwin.scenes.setup import load_setup
from scopetwin.scenes.surface import HeightMap
from scopetwin.sim.surfaces import surface_for
from scopetwin.sim.truth import marker_truth

pytestmark = pytest.mark.mitsuba
SPP = 16


def _spot_boxes(image: np.ndarray, centers: np.ndarray) -> list[tuple[slice, slice]]:
    """Bounding box (1 px margin) of the spot under each centre."""
    labels, _ = ndimage.label(image > 0)
    objects = ndimage.find_objects(labels)
    boxes = []
    for col, row in centers:
        lab = labels[int(row), int(col)]
        assert lab > 0, "no spot under a visible marker's centre"
        rs, cs = objects[lab - 1]
        boxes.append((slice(max(rs.start - 1, 0), rs.stop + 1), slice(max(cs.start - 1, 0), cs.stop + 1)))
    return boxes


def _centroid(image: np.ndarray, box: tuple[slice, slice]) -> np.ndarray:
    """Grey-weighted centroid (col, row) of the pixels in a box, continuous pixel coordinates."""
    w = image[box].astype(np.float64)
    rows, cols = np.mgrid[box[0], box[1]]
    return np.array([(w * (cols + 0.5)).sum(), (w * (rows + 0.5)).sum()]) / w.sum()


def _compare(setup, heights, max_markers: int = 160, seed: int = 1):
    from scopetwin.scenes.mitsuba.render import render_setup

    truth = marker_truth(setup, heights)
    vis = np.flatnonzero(truth.visible)
    pick = vis[np.linspace(0, len(vis) - 1, min(max_markers, len(vis))).astype(int)]
    mi_img = render_setup(setup, heights, spp=SPP, seed=seed)
    boxes = _spot_boxes(mi_img, truth.center_px[pick])
    mask = np.zeros(mi_img.shape, dtype=bool)
    for box in boxes:
        mask[box] = True
    rows, cols = np.nonzero(mask)
    ref = np.zeros_like(mi_img)
    ref[rows, cols] = render_pixels(setup, rows, cols, heights, spp=SPP, seed=seed + 1)
    c_mi = np.array([_centroid(mi_img, b) for b in boxes])
    c_ref = np.array([_centroid(ref, b) for b in boxes])
    err = np.linalg.norm(c_mi - c_ref, axis=1)
    return err, c_mi, truth.center_px[pick]


@pytest.mark.parametrize("name", ["thesis-1.10-deflectometry", "thesis-2.8.3-substrate", "thesis-2.8.3-mirror"])
def test_mitsuba_centroids_match_the_analytic_renderer(name):
    setup = load_setup(name)
    err, _, _ = _compare(setup, surface_for(setup))
    rms, worst = float(np.sqrt(np.mean(err**2))), float(err.max())
    print(f"{name}: {len(err)} markers, centroid difference RMS {rms:.4f} px, max {worst:.4f} px")
    assert rms <= 0.005
    assert worst <= 0.02


def test_flat_substrate_centroids_are_the_projected_marker_centres():
    """A flat substrate is a plane mirror parallel-imaging the pattern: no spot bias, centroid = centre image."""
    from scopetwin.scenes.mitsuba.render import render_setup

    setup = load_setup("thesis-1.10-deflectometry")
    flat = HeightMap(np.zeros((8, 8)), -12.6, 12.6, -28.5, 28.5)
    truth = marker_truth(setup, flat)
    vis = truth.visible
    projected = setup.camera_model.project(setup.marker_pattern.centers(truth.ij[vis]) * [1, 1, -1])
    image = render_setup(setup, flat, spp=64, seed=3)
    boxes = _spot_boxes(image, projected)
    c = np.array([_centroid(image, b) for b in boxes])
    err = np.linalg.norm(c - projected, axis=1)
    rms = float(np.sqrt(np.mean(err**2)))
    print(f"flat substrate: {len(err)} markers, RMS {rms:.4f} px, max {err.max():.4f} px")
    assert rms <= 0.002
