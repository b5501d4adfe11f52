"""Shared cases of the calibration tests: the thesis's §2.8 setups with exact marker images."""

from __future__ import annotations

import numpy as np

from scopetwin.calib.oneshot import Prior
from scopetwin.scenes.setup import Setup, load_setup


def exact_case(name: str) -> tuple[Setup, np.ndarray, np.ndarray, Prior]:
    """Setup, marker coordinates (target frame), exact marker images (scenes.camera) and the prior."""
    s = load_setup(name)
    pat = s.marker_pattern
    xy = pat.centers_local()
    px = s.camera_model.project(pat.centers())
    prior = Prior.from_camera(s.camera_model, s.camera.focal_length, r_cs=(0.0, 0.0), c0=1.0, c2=0.0)
    return s, xy, px, prior
