"""Bias correction (recon.bias): predicted spot centroids against analytic renders with known truth."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.recon.bias import (
    BiasError,
    PlaneTarget,
    correct_centroids,
    model_for_setup,
    predict_spots,
    spot_bias_model,
)
from scopetwin.recon.markers import centroids
from scopetwin.scenes.analytic import render
from scopetwin.scenes.setup import Setup, load_setup
from scopetwin.scenes.surface import HeightMap
from scopetwin.sim.surfaces import surface_for
from scopetwin.sim.truth import marker_truth


def target_at(alpha_deg: float) -> Setup:
    """§2.8.1 target seen from alpha above its plane, 233.24 mm from its centre (the §2.8.2 angle scan)."""
    a = np.radians(alpha_deg)
    s, c = float(np.sin(a)), float(np.cos(a))
    cam = {"origin": [0.0, -233.24 * c, 233.24 * s], "t_x": [1.0, 0.0, 0.0], "t_y": [0.0, s, c], "n_z": [0.0, -c, s]}
    return load_setup("thesis-2.8.1-perpendicular", {"camera": cam})


def window_centroids(setup: Setup, heights, centre_px: np.ndarray, half: int, spp: int = 64) -> np.ndarray:
    """Whole-spot centroids measured on analytic renders of windows around the given positions."""
    out = []
    for k, (c, r) in enumerate(centre_px):
        r0, c0 = int(r) - half, int(c) - half
        img = render(setup, heights, spp=spp, seed=k, window=(r0, r0 + 2 * half, c0, c0 + 2 * half))
        sp = centroids(img, background=0.0)
        best = np.argmax(sp.mass)
        out.append(sp.centroids[best] + [c0, r0])
    return np.array(out)


def test_tilted_target_perspective_bias_is_removed():
    setup = target_at(30.0)
    truth = marker_truth(setup)
    pick = np.array([0, 10, 49, 88, 98])  # corners and centre of the 11 x 9 target
    ij, centre = truth.ij[pick], truth.center_px[pick]
    raw = window_centroids(setup, None, centre, half=46)
    corrected, pred = correct_centroids(raw, ij, PlaneTarget(setup.camera_model, setup.marker_pattern))
    raw_err = np.linalg.norm(raw - centre, axis=1)
    cor_err = np.linalg.norm(corrected - centre, axis=1)
    assert raw_err.max() > 0.03  # perspective moves the centroid by several hundredths of a pixel
    assert cor_err.max() < 0.003
    np.testing.assert_allclose(pred.center, centre, atol=1e-6)
    assert pred.reaches.all() and pred.fit_rms.max() < 1e-4


def test_plane_target_and_setup_model_agree():
    setup = target_at(50.0)
    ij = np.array([[0, 0], [5, 4], [10, 8]])
    a = predict_spots(PlaneTarget(setup.camera_model, setup.marker_pattern), ij)
    b = predict_spots(model_for_setup(setup), ij)
    np.testing.assert_allclose(a.centroid, b.centroid, atol=1e-9)
    np.testing.assert_allclose(a.center, setup.camera_model.project(setup.marker_pattern.centers(ij)), atol=1e-7)


def test_flat_mirror_has_no_bias_beyond_perspective():
    setup = load_setup("thesis-1.10-deflectometry")
    flat = HeightMap(np.zeros((8, 8)), -12.6, 12.6, -28.5, 28.5)
    ij = np.array([[0, 0], [-5, 3], [6, -4]])
    pred = predict_spots(model_for_setup(setup, flat), ij)
    mirrored = setup.marker_pattern.centers(ij) * [1.0, 1.0, -1.0]
    np.testing.assert_allclose(pred.center, setup.camera_model.project(mirrored), atol=1e-6)


def test_bowed_substrate_bias_is_removed():
    # a strongly bowed substrate (200 µm) makes the reflected spots' bias large
    setup = load_setup("thesis-1.10-deflectometry", {"substrate": {"surface": {"range_um": 200.0, "seed": 4}}})
    heights = surface_for(setup)
    truth = marker_truth(setup, heights)
    model = model_for_setup(setup, heights)
    vis = np.flatnonzero(truth.visible)
    pred = predict_spots(model, truth.ij[vis])
    pick = vis[np.argsort(-np.linalg.norm(pred.correction, axis=1))[:4]]
    centre = truth.center_px[pick]
    raw = window_centroids(setup, heights, centre, half=16)
    corrected, _ = correct_centroids(raw, truth.ij[pick], model)
    raw_err = np.linalg.norm(raw - centre, axis=1)
    cor_err = np.linalg.norm(corrected - centre, axis=1)
    assert raw_err.max() > 0.02
    assert cor_err.max() < 0.004


def test_markers_the_model_cannot_image_are_an_error():
    setup = target_at(90.0)
    with pytest.raises(BiasError):
        predict_spots(PlaneTarget(setup.camera_model, setup.marker_pattern), [[0, 0]], guess_px=[[np.nan, 1.0]])


def test_pixel_sampled_and_continuous_evaluations_of_the_bias_agree():
    """spot_bias_model (pixels, used by the calibration) and predict_spots (continuous first moment) are one model.

    Face-on the bias vanishes; on an oblique view both predict the same perspective bias up to the pixel
    sampling of the pixel-sampled evaluation (well below a thousandth of a pixel).
    """
    from scopetwin.scenes.geometry import Frame

    for alpha, expect_bias in ((90.0, False), (35.0, True)):
        setup = target_at(alpha)
        pat, cam = setup.marker_pattern, setup.camera_model
        ij = np.array([[0, 0], [5, 4], [10, 8], [10, 0], [0, 8]])
        f = pat.frame
        local = Frame(
            f.to_local(cam.frame.origin),
            f.vectors_to_local(cam.frame.tx),
            f.vectors_to_local(cam.frame.ty),
            f.vectors_to_local(cam.frame.nz),
        )
        sampled = spot_bias_model(pat.centers_local(ij), pat.radii(ij))(cam.with_(frame=local))
        pred = predict_spots(PlaneTarget(cam, pat), ij)
        continuous = pred.centroid - pred.center
        assert np.abs(sampled - continuous).max() < 1e-3
        assert (np.linalg.norm(continuous, axis=1).max() > 0.01) == expect_bias


class _Blind:
    """A plane-target model whose rays near the centres of the given markers do not converge (NaN, as a secant
    that runs out of steps near a caustic)."""

    def __init__(self, inner: PlaneTarget, blind_xy: np.ndarray, within_mm: float) -> None:
        self.inner, self.blind_xy, self.within_mm = inner, blind_xy, within_mm
        self.camera, self.pattern = inner.camera, inner.pattern

    def pattern_hits(self, o, d):
        xy, ok = self.inner.pattern_hits(o, d)
        near = np.min(np.linalg.norm(xy[:, None, :] - self.blind_xy[None], axis=-1), axis=1) < self.within_mm
        return np.where(near[:, None], np.nan, xy), ok & ~near


def test_one_marker_the_model_cannot_image_keeps_its_centroid_and_the_others_are_predicted():
    """A ray that does not converge near one marker leaves that marker uncorrected (``predicted`` False, its guess
    as centroid and centre) instead of ending the whole prediction; beyond ``max_unpredicted`` it is an error."""
    setup = target_at(40.0)
    plane = PlaneTarget(setup.camera_model, setup.marker_pattern)
    truth = marker_truth(setup)
    ij, guess = truth.ij[:40], truth.center_px[:40] + 0.3
    full = predict_spots(plane, ij, guess_px=guess)
    blind = _Blind(plane, setup.marker_pattern.centers_local(ij[[7]]), 0.2)
    part = predict_spots(blind, ij, guess_px=guess)
    assert full.predicted.all() and part.predicted.sum() == 39 and not part.predicted[7]
    np.testing.assert_array_equal(part.centroid[7], guess[7])
    np.testing.assert_array_equal(part.center[7], guess[7])
    others = np.arange(40) != 7
    np.testing.assert_allclose(part.center[others], full.center[others], atol=1e-9)
    np.testing.assert_allclose(part.centroid[others], full.centroid[others], atol=1e-9)
    three = _Blind(plane, setup.marker_pattern.centers_local(ij[[3, 7, 20]]), 0.2)
    with pytest.raises(BiasError, match="3 of 40 markers"):
        predict_spots(three, ij, guess_px=guess)  # 7.5 % > 5 %
    assert predict_spots(three, ij, guess_px=guess, max_unpredicted=0.1).predicted.sum() == 37


def test_the_target_hits_shortcut_is_the_camera_rays_on_the_plane():
    """recon.bias._target_hits writes the pinhole ray (Camera.rays) and the plane hit (plane_hits) component-wise for
    the millions of supersampled pixels of the calibration's bias model: it must be those two, to rounding,
    including the rays that miss the target's front (a camera looking past the plane's edge, views from behind)."""
    from scopetwin.recon.bias import _target_hits, plane_hits
    from scopetwin.scenes.geometry import Frame

    rng = np.random.default_rng(11)
    for alpha in (90.0, 30.0, 5.0):
        cam = target_at(alpha).camera_model
        px = rng.uniform(-200, [cam.nx + 200, cam.ny + 200], (5000, 2))
        xy, ok = _target_hits(cam, px)
        xy_ref, ok_ref = plane_hits(Frame.identity(), *cam.rays(px))
        assert (ok == ok_ref).all() and ok.any()
        np.testing.assert_allclose(xy[ok], xy_ref[ok], rtol=0, atol=1e-9)
    assert not ok.all()  # at 5 degrees the top of the image looks past the plane: the misses agree too


def test_one_singular_marker_map_leaves_only_that_marker_unfitted():
    """recon.bias._solve_each: the batched normal equations with one singular system (too few rays near a caustic)
    solve the others one by one, as the batch would, and leave the singular one NaN."""
    from scopetwin.recon.bias import _solve_each

    rng = np.random.default_rng(3)
    a = rng.standard_normal((6, 40, 10))
    lhs = a.transpose(0, 2, 1) @ a
    rhs = rng.standard_normal((6, 10, 2))
    lhs[4] = 0.0
    fitted = np.array([True, True, False, True, True, True])
    coef = _solve_each(lhs, rhs, fitted)
    for i in (0, 1, 3, 5):
        np.testing.assert_allclose(coef[i], np.linalg.solve(lhs[i], rhs[i]), rtol=1e-12)
    assert np.isnan(coef[[2, 4]]).all()


def test_one_pass_from_near_the_centre_images_is_two_passes():
    """The bias step fits its local maps once (BIAS_PASSES), around the measured centroids: started 0.3 px off the
    centre images of a 200 µm bowed substrate's markers, one pass and two agree within 1e-6 px (measured 2e-7 px;
    the corrections reach 0.06 px)."""
    from scopetwin.recon.reconstruct import BIAS_PASSES

    setup = load_setup("thesis-1.10-deflectometry", {"substrate": {"surface": {"range_um": 200.0, "seed": 4}}})
    heights = surface_for(setup)
    truth = marker_truth(setup, heights)
    vis = np.flatnonzero(truth.visible)
    model = model_for_setup(setup, heights)
    start = truth.center_px[vis] + 0.3
    one = predict_spots(model, truth.ij[vis], guess_px=start, passes=BIAS_PASSES)
    two = predict_spots(model, truth.ij[vis], guess_px=start, passes=2)
    assert BIAS_PASSES == 1 and one.predicted.all() and two.predicted.all()
    assert np.abs(two.correction).max() > 0.05
    np.testing.assert_allclose(one.correction, two.correction, atol=1e-6)
