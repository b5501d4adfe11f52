"""The display's calibration: a fringe setup's display shows the marker pattern, and the setup calibration of thesis
§2.7 (``calibrate_setup_from_images``) finds its pose from the rendered calibration images.

Acceptance: the display pose within the tolerance of the marker setup's rendered calibration test
(tests/calib/test_setup_calibration.py: pattern centre <= 5 µm, axes <= 10 µrad; camera centre <= 2 µm), 16 spp as
there; the calibrated setup keeps its ``[fringes]`` table. The display's marker image: each marker's radiance
centroid lies on the marker centre (the display pixels' boxes and blur are symmetric about it).
"""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.mitsuba.scene import TEXEL
from scopetwin.scenes.setup import load_setup


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.arccos(np.clip(a @ b, -1.0, 1.0)))


def test_the_display_shows_the_markers_through_its_pixels():
    setup = load_setup("thesis-1.10-fringes")
    display, pattern = setup.fringe_display, setup.marker_pattern
    values = display.marker_values(pattern)
    assert values.shape == (1000, 1000) and 0.0 <= values.min() and values.max() <= 1.0
    tex = display.image_texture(values, TEXEL).astype(np.float64)
    assert tex.shape == (4000, 4000)
    u, v = display.texel_centres(TEXEL)
    for ij in ([0, 0], [3, -5], [-16, 16]):
        (cx, cy) = pattern.centers_local(np.array([ij]))[0, :2]
        r = pattern.radii(np.array([ij]))[0] + 0.2
        cols, rows = np.abs(u - cx) < r, np.abs(v - cy) < r
        w = tex[np.ix_(rows, cols)] - display.black_level
        uu, vv = np.meshgrid(u[cols], v[rows])
        centroid = np.array([np.sum(w * uu), np.sum(w * vv)]) / w.sum()
        assert np.abs(centroid - [cx, cy]).max() < 1e-3, (ij, centroid, (cx, cy))  # mm: < 1 µm on the display
    with pytest.raises(SetupError, match="display's 1000 x 1000 pixels"):
        display.image_texture(values[:10], TEXEL)


@pytest.mark.mitsuba
def test_the_calibrated_fringe_setup_s_display_pose_is_recovered(mono_variant):
    from scopetwin.sim.fringes import calibrate_display, render_display_calibration

    setup = load_setup("thesis-1.10-fringes")
    images = render_display_calibration(setup, 16, 3, variant=mono_variant)
    assert images.mirror_setup.scene == "mirror" and images.target_setup.scene == "target"
    done = calibrate_display(setup, images)
    assert done.setup.fringe_display == setup.fringe_display and done.setup.fringe_sequence == setup.fringe_sequence
    pat, true = done.setup.marker_pattern.frame, setup.marker_pattern.frame
    assert np.linalg.norm(pat.origin - true.origin) < 5e-3
    for k in ("tx", "ty", "nz"):
        assert _angle(getattr(pat, k), getattr(true, k)) < 10e-6
    assert np.linalg.norm(done.setup.camera_model.center - setup.camera_model.center) < 2e-3
    assert len(done.mirror.markers.ij) > 1000  # the display's 33 x 33 markers are found in the mirror


def test_a_marker_setup_has_no_display_to_calibrate():
    from scopetwin.sim.fringes import render_display_calibration

    with pytest.raises(SetupError, match="no \\[fringes\\] table"):
        render_display_calibration(load_setup("thesis-1.10-deflectometry"), 4, 1)
