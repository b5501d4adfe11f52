"""One-shot calibration at poses and distances the presets lack: camera centre within its u.

The presets put the camera 233 mm from the target with f = 25 mm and b = 28 mm. Here a family of 24 views is drawn
from a seed fixed before anything was tuned (:data:`FAMILY_SEED`, a hash of a sentence): object distance 150-400 mm,
nominal focal length 16-35 mm, the lens's true focal length within +-1.5 % of it (the prior states a 1 % standard
uncertainty, :data:`~scopetwin.calib.oneshot.FOCAL_LENGTH_TOLERANCE`), the target in focus, tilt 2-40 deg (some
below ``AUTO_FREE_TILT``, where no free b is tried), any azimuth, sensor tilt +-0.3 rad, an 11 x 9 target whose
pitch makes it fill 50-70 % of the image height, the N_z estimate 3 deg off. The marker images are the exact
projections of :mod:`scopetwin.scenes.camera`, without and with Gaussian centroid noise (0.005 px: a rendered view at
40 % of the full well; 0.03 px: a dim one). The prior is what thesis §2.1 names: pixel size, focal length, a coarse
N_z, and no image distance (what ``scopetwin calibrate --target PRESET`` now takes for an image that the preset's
camera did not take).

Coverage when this test was written (72 axis errors per noise level, the same with and without the preset's b):
noise-free, all within 1.34 u, 92 % within 1 u (19 views estimate b freely and recover exact data to round-off; the 5
below 10 deg keep the thin-lens b with its focal-length uncertainty); 0.005 px, all within 1.82 u, 67 % within 1 u;
0.03 px, all within 1.82 u, 60 % within 1 u (9 views keep the thin-lens b). With the a-priori b always kept, the
calibration left 33, 29 and 25 of the 72 beyond 3 u (up to 6000 u): the thin-lens b of a lens 1.5 % off its nominal
f was reported exact, and a wrong a-priori b was kept (1.0 mm off, u 5 µm).
"""

from __future__ import annotations

import dataclasses
import warnings

import numpy as np
import pytest

from scopetwin.calib.oneshot import CalibrationWarning, Prior, calibrate
from scopetwin.calib.oneshot.refinement import with_image_distance_uncertainty
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.setup import load_setup

#: The family's seed: 8 hex digits of a SHA-256 of a fixed text, chosen before the calibration was tuned.
FAMILY_SEED = 1102511442
N_VIEWS = 24
NX, NY, PITCH = 1360, 1024, 0.00465  # the presets' sensor
ROUND_OFF_MM = 1e-9


@dataclasses.dataclass(frozen=True)
class View:
    """A camera the presets lack, its exact marker images and the thesis's a-priori values (§2.1)."""

    camera: Camera
    xy: np.ndarray
    px: np.ndarray
    prior: Prior
    tilt_deg: float


def _rotated(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    axis = axis / np.linalg.norm(axis)
    return v * np.cos(angle) + np.cross(axis, v) * np.sin(angle) + axis * (axis @ v) * (1 - np.cos(angle))


def _target(pitch: float) -> np.ndarray:
    i, j = np.meshgrid(np.arange(11) - 5.0, np.arange(9) - 4.0)
    return np.column_stack([i.ravel(), j.ravel()]) * pitch


def make_view(
    g: float,
    f_nominal: float,
    f_error: float,
    tilt_deg: float,
    azimuth: float,
    phi: float,
    r0: tuple[float, float],
    fill: float,
    est_deg: float,
    pitch: float | None = None,
) -> View:
    """The camera ``g`` mm from the axis point ``r0``, its lens's f ``f_error`` (relative) off ``f_nominal``, the
    target in focus (b = g f/(g - f), thesis §2.5.2) filling ``fill`` of the image height (or of marker ``pitch``),
    and the prior with ``f_nominal`` and N_z ``est_deg`` off."""
    t = np.deg2rad(tilt_deg)
    nz = np.array([np.sin(t) * np.sin(azimuth), -np.sin(t) * np.cos(azimuth), np.cos(t)])
    r0_ = np.asarray(r0, dtype=np.float64)
    cam = Camera.from_pose(np.append(r0_, 0.0) + g * nz, r0_, phi, f_nominal * (1 + f_error), NX, NY, PITCH)
    xy = _target(pitch if pitch is not None else fill * NY * PITCH / (cam.b / g) / 8)
    px = cam.project(np.column_stack([xy, np.zeros(len(xy))]))
    inside = (px[:, 0] > 5) & (px[:, 0] < NX - 5) & (px[:, 1] > 5) & (px[:, 1] < NY - 5)
    off = np.cross(nz, [np.cos(3 * azimuth), np.sin(3 * azimuth), 0.3])
    est = _rotated(nz, off, np.deg2rad(est_deg))
    return View(cam, xy[inside], px[inside], Prior(f_nominal, NX, NY, PITCH, tuple(est)), tilt_deg)


def family() -> list[View]:
    rng = np.random.default_rng(FAMILY_SEED)
    views = []
    for _ in range(N_VIEWS):
        g, f, err = rng.uniform(150, 400), rng.uniform(16, 35), rng.uniform(-0.015, 0.015)
        tilt, az, phi = rng.uniform(2, 40), rng.uniform(0, 2 * np.pi), rng.uniform(-0.3, 0.3)
        r0 = (rng.uniform(-5, 5), rng.uniform(-5, 5))
        views.append(make_view(g, f, err, tilt, az, phi, r0, rng.uniform(0.5, 0.7), 3.0))
    return views


def _calibrate(view: View, px: np.ndarray, prior: Prior | None = None):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", CalibrationWarning)
        return calibrate(view.xy, px, prior or view.prior)


def _ratios(cal, truth: Camera) -> np.ndarray:
    """|error| / u per axis of the camera centre (0 where the error is round-off)."""
    err = np.abs(cal.camera.center - truth.center)
    return np.where(err < ROUND_OFF_MM, 0.0, err / np.asarray(cal.sigma["r_c"]))


@pytest.fixture(scope="module")
def views() -> list[View]:
    return family()


@pytest.mark.parametrize("stated_b", [None, 28.0])
@pytest.mark.parametrize("noise_px", [0.0, 0.005, 0.03])
def test_family_camera_centre_within_its_reported_u(views, noise_px, stated_b):
    """Every axis within 3 u (Gaussian: 99.7 %; one of 72 may reach 4 u); at least 85 % within 2 u.

    ``stated_b`` 28 mm: the prior states the presets' b (``scopetwin.calibrate(image, preset)``); it is the
    candidate only where the thin-lens relation agrees and then carries 1 % of itself. A stated b that agrees yet
    is more than 3 of those off, on a view where no free b is tried, is what can fall outside (3.2 u in another
    draw of this family).
    """
    ratios = []
    for k, v in enumerate(views):
        px = v.px + np.random.default_rng(FAMILY_SEED + k).normal(0.0, noise_px, v.px.shape)
        prior = dataclasses.replace(v.prior, image_distance=stated_b)
        ratios.append(_ratios(_calibrate(v, px, prior), v.camera))
    r = np.array(ratios)
    assert np.all(r <= 4.0), f"worst camera-centre error {r.max():.2f} u"
    assert np.sum(r > 3.0) <= 1, f"{np.sum(r > 3.0)} of {r.size} axis errors beyond 3 u"
    assert np.mean(r <= 2.0) >= 0.85
    if noise_px == 0:
        assert np.all(r <= 3.0)


def _issue_view(noise_px: float = 0.0):
    """The failing case: a view 242 mm away, tilted 11 deg, f = 25 mm; the 233 mm preset's prior (b = 28 mm)."""
    v = make_view(242.0, 25.0, 0.0, 11.0, np.deg2rad(20.0), 0.05, (1.5, -2.0), 0.0, 0.0, pitch=4.0)
    prior = Prior.from_camera(load_setup("thesis-2.8.1-angular").camera_model, 25.0)  # its b and N_z estimate
    px = v.px + np.random.default_rng(5).normal(0.0, noise_px, v.px.shape)
    return v, prior, px


def test_the_issue_case_a_preset_b_the_data_reject_gives_way():
    """Before: b = 28 mm kept (z = 1.2e12, sigma_b at the prior noise 0.050 mm > MAX_SIGMA_B), r_c 1.01 mm off, u
    4.7 µm. Now the free b's own sigma at the residuals' noise decides: the data determine b and reject 28 mm."""
    v, prior, px = _issue_view()
    assert v.camera.b == pytest.approx(27.880, abs=1e-3)
    cal = _calibrate(v, px, prior)
    assert cal.lens == "free" and cal.lens_test is not None
    assert cal.lens_test["candidate"] == "a-priori" and cal.lens_test["determined"] and cal.lens_test["z"] > 5
    assert np.abs(cal.camera.center - v.camera.center).max() < 1e-6
    v, prior, px = _issue_view(0.005)
    cal = _calibrate(v, px, prior)
    assert cal.lens == "free"
    assert np.all(_ratios(cal, v.camera) <= 3.0)


def test_a_stated_b_the_thin_lens_relation_contradicts_is_not_the_candidate():
    """A face-on view 400 mm away with f = 16 mm (b = 16.7 mm) and the preset's b = 28 mm: the thin-lens b of the
    measured magnification replaces it (a note says so), with its focal-length uncertainty propagated."""
    v = make_view(400.0, 16.0, 0.008, 4.0, 1.0, 0.1, (2.0, 1.0), 0.6, 1.0)
    prior = dataclasses.replace(v.prior, image_distance=28.0)
    with pytest.warns(CalibrationWarning, match="disagrees with the thin-lens b"):
        cal = calibrate(v.xy, v.px, prior)
    assert cal.lens == "thin-lens" and cal.lens_test is not None and cal.lens_test["candidate"] == "thin-lens"
    assert cal.lens_test["b_free"] is None  # below AUTO_FREE_TILT: no free b
    assert np.all(_ratios(cal, v.camera) <= 3.0)


def test_a_kept_candidate_carries_its_focal_length_uncertainty():
    """A nearly face-on view cannot estimate b; the thin-lens b is 1.2 % of f off (the lens's tolerance). Its
    uncertainty (1 % of f) propagated covers the camera-centre error; declared exact (tolerance 0) it does not."""
    v = make_view(300.0, 20.0, 0.012, 5.0, 2.0, -0.2, (0.0, 3.0), 0.6, 1.0)
    cal = _calibrate(v, v.px)
    assert cal.lens == "thin-lens"
    r = _ratios(cal, v.camera)
    assert np.all(r <= 3.0) and r.max() > 0.5  # covered, and not by a u that is far too large
    exact_f = _calibrate(v, v.px, dataclasses.replace(v.prior, focal_length_tolerance=0.0))
    assert _ratios(exact_f, v.camera).max() > 100


def test_propagated_b_uncertainty_is_the_pose_s_response_to_b(views):
    """with_image_distance_uncertainty's first-order dp/db against two fixed-b refits 1 µm apart."""
    v = next(w for w in views if w.tilt_deg > 15)
    prior = dataclasses.replace(v.prior, image_distance=v.camera.b)
    a = calibrate(v.xy, v.px, prior, lens="fixed")
    b = calibrate(v.xy, v.px, prior, lens="fixed", b=v.camera.b + 1e-3)
    slope = np.abs(b.camera.center - a.camera.center) / 1e-3
    zero = dataclasses.replace(a, sigma={**a.sigma, "r_c": np.zeros(3), "b": 0.0})
    prop = with_image_distance_uncertainty(zero, v.xy, v.px, prior, 0.1)
    assert np.allclose(np.asarray(prop.sigma["r_c"]) / 0.1, slope, rtol=1e-3)
    assert prop.sigma["b"] == pytest.approx(0.1)
    assert with_image_distance_uncertainty(a, v.xy, v.px, prior, 0.0) is a


@pytest.mark.slow
@pytest.mark.mitsuba
def test_rendered_view_at_a_pose_no_preset_has(tmp_path):
    """That failure rendered (Mitsuba, 16 spp): the target 242 mm away, tilted 11 deg, f = 25 mm.

    Through the API with the 233 mm preset as the target setup (its b = 28 mm as the a-priori b): before, r_c 1.04 mm
    off with u 4.7 µm (lens test z = 625, kept); now the data reject b = 28 mm. Through the command line with
    ``--target`` naming that preset for an image without a header: the thin-lens b of the measured magnification.
    Both within 3 u, and with the EMVA sensor noise too (70 % of the full well: 0.005 px rms residual, free b,
    r_c 35 µm off with u 32 µm along the axis).
    """
    import contextlib
    import io
    import json

    from scopetwin.calib.oneshot.from_image import calibrate_image
    from scopetwin.cli import main
    from scopetwin.scenes.io import write_image
    from scopetwin.scenes.mitsuba.render import render_setup
    from scopetwin.sim.measurement import apply_sensor

    v, _, _ = _issue_view()
    f = v.camera.frame
    over = {"camera": {"origin": f.origin.tolist(), "t_x": f.tx.tolist(), "t_y": f.ty.tolist(), "n_z": f.nz.tolist()}}
    over["camera"]["image_distance"] = v.camera.b
    truth = load_setup("thesis-2.8.1-angular", over)
    preset = load_setup("thesis-2.8.1-angular")
    clean = render_setup(truth, None, spp=16, seed=3)
    for image in (clean, apply_sensor(truth, clean, 7)):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", CalibrationWarning)
            cal, _ = calibrate_image(image, preset, focal_length=25.0)
        err = np.abs(cal.to_global(preset.marker_pattern.frame).center - truth.camera_model.center)
        assert np.all(err <= 3 * np.asarray(cal.sigma["r_c"])), (err, cal.sigma["r_c"])
        assert np.linalg.norm(cal.sigma["r_c"]) < 0.05  # mm: covered by the free b's own u, not an inflated one
    write_image(tmp_path / "foreign.exr", clean)  # no header: an image the preset's camera did not take
    argv = ["calibrate", str(tmp_path / "foreign.exr"), "--target", "thesis-2.8.1-angular", "--focal-length", "25"]
    with contextlib.redirect_stdout(io.StringIO()):
        assert main([*argv, "--json", str(tmp_path / "c.json")]) == 0
    d = json.loads((tmp_path / "c.json").read_text())
    assert d["lens_test"]["candidate"] == "thin-lens"
    err = np.abs(np.subtract(d["camera"]["r_c"], truth.camera_model.center))
    assert np.all(err <= 3 * np.asarray(d["uncertainty"]["r_c"])), (err, d["uncertainty"]["r_c"])
