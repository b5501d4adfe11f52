"""Setup calibration (thesis §2.7, §2.8.3): camera and pattern recovered in one global frame."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.calib.oneshot import Prior
from scopetwin.calib.setup_calibration import (
    calibrate_setup,
    compose,
    mirror_prior,
    pattern_in_camera,
    virtual_coordinates,
    write_setup_toml,
)
from scopetwin.recon.bias import spot_bias_model
from scopetwin.scenes.geometry import Frame
from scopetwin.scenes.setup import load_setup
from scopetwin.sim.truth import marker_truth


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.arccos(np.clip(a @ b, -1.0, 1.0)))


@pytest.fixture(scope="module")
def setups():
    return load_setup("thesis-2.8.3-substrate"), load_setup("thesis-2.8.3-mirror")


def exact_inputs(ss, sm):
    ts, tm = marker_truth(ss), marker_truth(sm)
    vs, vm = ts.visible, tm.visible
    return (
        ss.marker_pattern.centers_local(ts.ij[vs]),
        ts.center_px[vs],
        virtual_coordinates(sm.marker_pattern, tm.ij[vm]),
        tm.center_px[vm],
    )


def test_frame_transfer_round_trip():
    cam = Frame([1.0, -2.0, 30.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    pat_in_cam = pattern_in_camera(cam)
    back = compose(cam, pat_in_cam)  # the pattern in its own coordinates is the identity
    np.testing.assert_allclose(back.origin, 0.0, atol=1e-12)
    np.testing.assert_allclose(np.stack([back.tx, back.ty, back.nz]), np.eye(3), atol=1e-12)


def test_exact_positions_recover_camera_and_pattern(setups):
    ss, sm = setups
    xs, ps_, xm, pm_ = exact_inputs(ss, sm)
    res = calibrate_setup(xs, ps_, Prior.from_camera(ss.camera_model, 25.0), xm, pm_, mirror_prior(sm))
    cam, pat = ss.camera_model.frame, sm.marker_pattern.frame
    assert np.abs(res.camera.center - cam.origin).max() < 1e-9
    assert np.abs(res.pattern.origin - pat.origin).max() < 1e-9
    for k in ("tx", "ty", "nz"):
        assert _angle(getattr(res.pattern, k), getattr(pat, k)) < 1e-11
        assert _angle(getattr(res.camera.frame, k), getattr(cam, k)) < 1e-11
    np.testing.assert_allclose(res.virtual_pattern.origin, pat.origin * [1, 1, -1], atol=1e-9)


def test_per_view_thin_lens_misplaces_the_pattern(setups):
    """The thesis's way (a thin-lens b per view) fails when the camera focus does not fit the mirror distance."""
    ss, sm = setups
    xs, ps_, xm, pm_ = exact_inputs(ss, sm)
    res = calibrate_setup(
        xs,
        ps_,
        Prior.from_camera(ss.camera_model, 25.0),
        xm,
        pm_,
        mirror_prior(sm),
        lens="thin-lens",
        share_intrinsics=False,
    )
    err = np.linalg.norm(res.pattern.origin - sm.marker_pattern.frame.origin)
    assert err > 1.0  # mm: b = 27.1 from the thin-lens equation at 326 mm against the camera's real 28 mm


def test_setup_toml_round_trip(setups, tmp_path):
    ss, sm = setups
    xs, ps_, xm, pm_ = exact_inputs(ss, sm)
    res = calibrate_setup(xs, ps_, Prior.from_camera(ss.camera_model, 25.0), xm, pm_, mirror_prior(sm))
    path = tmp_path / "calibrated.toml"
    write_setup_toml(path, sm, res)
    back = load_setup(path)
    assert back.scene == "deflectometry"
    np.testing.assert_allclose(back.camera_model.frame.origin, res.camera.center, atol=1e-12)
    np.testing.assert_allclose(back.camera_model.frame.nz, res.camera.frame.nz, atol=1e-12)
    assert back.camera_model.b == pytest.approx(res.camera.b, abs=1e-12)
    np.testing.assert_allclose(back.marker_pattern.frame.origin, res.pattern.origin, atol=1e-12)
    np.testing.assert_allclose(back.marker_pattern.frame.ty, res.pattern.ty, atol=1e-12)
    assert back.marker_pattern.n_x == sm.marker_pattern.n_x


@pytest.mark.mitsuba
def test_rendered_images_meet_the_issue_targets(setups, rendered):
    """§2.8.3 from Mitsuba images: camera centre <= 2 µm, pattern centre <= 5 µm, angles <= 10 µrad."""
    from scopetwin.recon.markers import find_markers_for

    ss, sm = setups
    img_s, img_m = rendered
    fs, fm = find_markers_for(img_s, ss), find_markers_for(img_m, sm)
    xs = ss.marker_pattern.centers_local(fs.ij)
    xm = virtual_coordinates(sm.marker_pattern, fm.ij)
    res = calibrate_setup(
        xs,
        fs.centroids,
        Prior.from_camera(ss.camera_model, 25.0),
        xm,
        fm.centroids,
        mirror_prior(sm),
        substrate_bias=spot_bias_model(xs, ss.marker_pattern.radii(fs.ij)),
        mirror_bias=spot_bias_model(xm, sm.marker_pattern.radii(fm.ij)),
    )
    cam, pat = ss.camera_model.frame, sm.marker_pattern.frame
    assert np.linalg.norm(res.camera.center - cam.origin) < 2e-3
    assert np.linalg.norm(res.pattern.origin - pat.origin) < 5e-3
    for k in ("tx", "ty", "nz"):
        assert _angle(getattr(res.camera.frame, k), getattr(cam, k)) < 10e-6
        assert _angle(getattr(res.pattern, k), getattr(pat, k)) < 10e-6


def test_calibrated_setup_carries_its_pose_uncertainties(setups, tmp_path):
    """calibrate-setup writes [calibration] (camera and pattern pose standard deviations); --refine-setup reads it."""
    from scopetwin.recon.inverse import InverseConfig, pose_sigma_for

    ss, sm = setups
    xs, ps_, xm, pm_ = exact_inputs(ss, sm)
    rng = np.random.default_rng(3)
    noisy_s = ps_ + rng.normal(0.0, 0.05, ps_.shape)  # 0.05 px centroid noise
    noisy_m = pm_ + rng.normal(0.0, 0.05, pm_.shape)
    res = calibrate_setup(xs, noisy_s, Prior.from_camera(ss.camera_model, 25.0), xm, noisy_m, mirror_prior(sm))
    path = tmp_path / "calibrated.toml"
    write_setup_toml(path, sm, res)
    back = load_setup(path)
    assert back.calibration is not None
    cam, pat = back.calibration.camera, back.calibration.pattern
    assert cam.shift_mm == pytest.approx(float(np.max(res.substrate.sigma["r_c"])))
    assert 0 < cam.shift_mm <= pat.shift_mm  # the pattern is placed through both views
    assert 0 < cam.rotation_rad <= pat.rotation_rad
    # the camera centre's error lies within a few of its standard deviations
    assert np.max(np.abs(res.camera.center - ss.camera_model.frame.origin)) < 4 * cam.shift_mm
    assert pose_sigma_for(back) == (cam.shift_mm, cam.rotation_rad, pat.shift_mm, pat.rotation_rad)
    assert pose_sigma_for(sm) == InverseConfig().pose_sigma  # a nominal setup: the defaults
