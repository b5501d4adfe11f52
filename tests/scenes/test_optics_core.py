"""The one optics core: pixel grid, camera description, RKN step, spot metrics, objective model."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.scenes.camera import PixelGrid
from scopetwin.scenes.camera_spec import CameraGridSpec
from scopetwin.scenes.cmu.layout import load_cmu_setup
from scopetwin.scenes.grin.profiles import NP, PolynomialProfile
from scopetwin.scenes.grin.rkn import rkn_rod, rkn_step
from scopetwin.scenes.grin.setup import load_grin_setup
from scopetwin.scenes.objective import Objective
from scopetwin.scenes.setup import NoiseModelSpec, load_setup
from scopetwin.scenes.spots import airy_radius, pupil_disk, rms_radius


# -- the pixel grid ------------------------------------------------------------------------------------------
def test_grid_maps_pixel_centres_and_corners_as_design_md_says():
    g = PixelGrid(4, 2, 0.5, (0.1, -0.2))
    u, v = g.uv(np.array([0.0, 4.0, 0.5]), np.array([0.0, 2.0, 0.5]))
    # the top-left corner is (-nx/2, +ny/2) pitches from the grid centre; columns along +u, rows against +v
    np.testing.assert_allclose(u, [-1.0 + 0.1, 1.0 + 0.1, -0.75 + 0.1])
    np.testing.assert_allclose(v, [0.5 - 0.2, -0.5 - 0.2, 0.25 - 0.2])
    x, y = g.xy(u, v)
    np.testing.assert_allclose(x, [0.0, 4.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(y, [0.0, 2.0, 0.5], atol=1e-12)


def test_content_shift_is_an_offset_of_the_grid_centre_in_pixels(rng):
    g = PixelGrid(1392, 1040, 0.00645)
    shift = (3.25, -2.5)
    moved = PixelGrid(1392, 1040, 0.00645, (-shift[0] * 0.00645, shift[1] * 0.00645))
    x, y = rng.uniform(0, 1392, 50), rng.uniform(0, 1040, 50)
    np.testing.assert_allclose(g.uv(x, y, shift_px=shift), moved.uv(x, y), atol=1e-12)
    u, v = g.uv(x, y, shift_px=shift)
    np.testing.assert_allclose(g.xy(u, v, shift_px=shift), (x, y), atol=1e-9)


def test_film_coordinates_follow_the_same_convention(rng):
    g = PixelGrid(64, 48, 0.0022, (0.3, -1.2))
    fx, fy = rng.uniform(0, 1, 40), rng.uniform(0, 1, 40)
    np.testing.assert_allclose(g.uv_film(fx, fy), g.uv(fx * 64, fy * 48), atol=1e-12)


def test_zero_terms_emit_no_operation():
    class Probe:
        """Records the arithmetic applied to it (a stand-in for a Dr.Jit array)."""

        def __init__(self, ops=()):
            self.ops = list(ops)

        def _op(self, name):
            return Probe([*self.ops, name])

        __sub__ = lambda self, o: self._op("-")  # noqa: E731
        __rsub__ = lambda self, o: self._op("r-")  # noqa: E731
        __add__ = lambda self, o: self._op("+")  # noqa: E731
        __mul__ = lambda self, o: self._op("*")  # noqa: E731

    u, v = PixelGrid(8, 8, 0.1).uv(Probe(), Probe())
    assert u.ops == ["-", "*"] and v.ops == ["r-", "*"]
    u, v = PixelGrid(8, 8, 0.1, (0.5, 0.5)).uv(Probe(), Probe(), shift_px=(1.0, 1.0))
    assert u.ops == ["-", "-", "*", "+"] and v.ops == ["r-", "+", "*", "+"]


# -- one camera description ------------------------------------------------------------------------------------
def test_every_setup_camera_gives_its_pixel_grid():
    part1 = load_setup("thesis-1.10-deflectometry")
    unit = load_cmu_setup("thesis-cmu")
    rod = load_grin_setup("thesis-8.3.2-grin-realized")
    for cam in (part1.camera, unit.camera, rod.camera):
        assert isinstance(cam, CameraGridSpec)
    assert part1.camera.grid() == part1.camera_model.grid
    assert part1.camera.grid_dict() == {"nx": 1360, "ny": 1024, "pitch": 0.00465, "r_cs": [0.0, 0.0]}
    assert unit.camera.grid() == PixelGrid(1392, 1040, 6.45e-3)
    assert rod.camera.grid().pitch == pytest.approx(2.2e-3)
    assert unit.camera.pitch_mm == unit.camera.pixel_um * 1e-3


def test_camera_dict_keeps_the_contract_keys():
    cam = load_setup("thesis-2.8.1-perpendicular").camera_model
    d = cam.as_dict()
    assert list(d) == ["r_c", "t_x", "t_y", "n_z", "b", "r_cs", "c0", "c2", "nx", "ny", "pitch"]
    assert {k: d[k] for k in ("nx", "ny", "pitch", "r_cs")} == cam.grid.as_dict()


def test_toml_keys_still_load():
    s = load_setup("thesis-2.8.1-perpendicular", {"camera": {"pixels": [68, 51], "pixel_pitch": 0.093}})
    assert (s.camera_model.nx, s.camera_model.ny, s.camera_model.pitch) == (68, 51, 0.093)
    g = load_grin_setup("thesis-8.3.2-grin-realized", {"camera": {"pixel_um": 10.0}})
    assert g.camera.pitch_mm == pytest.approx(0.010)
    assert isinstance(s.sensor, NoiseModelSpec)  # the noise model keeps its TOML key [sensor]


# -- one RKN step ----------------------------------------------------------------------------------------------
def test_rod_is_the_step_repeated(rng):
    prof = PolynomialProfile()
    x, y = rng.uniform(-0.5, 0.5, (2, 200))
    tx, ty = rng.uniform(-0.2, 0.2, (2, 200))
    tz = np.sqrt(prof.index(x * x + y * y) ** 2 - tx * tx - ty * ty)
    ref = rkn_rod(x, y, tx, ty, tz, prof, 1.2, 12)
    dt = 1.2 / (12 * tz)
    n2, k = prof.sharma(x * x + y * y, NP)
    state = (x, y, tx, ty, np.zeros_like(x), n2, k)
    for _ in range(12):
        state = rkn_step(*state, dt, prof, NP)[:7]
    for a, b in zip(ref[:5], state[:5], strict=True):
        np.testing.assert_array_equal(a, b)


def test_drjit_loop_runs_the_same_step(monkeypatch, mono_variant):
    grin = pytest.importorskip("scopetwin.scenes.mitsuba.grin")
    calls = []

    def counting(*args, **kwargs):
        calls.append(kwargs.get("xp", args[-1]) if len(args) >= 10 else None)
        return rkn_step(*args, **kwargs)

    monkeypatch.setattr(grin, "rkn_step", counting)
    F = grin.float_type("float64", mono_variant)
    prof = PolynomialProfile()
    x = F(np.linspace(-0.3, 0.3, 16))
    out = grin.rkn_rod_dr(x, x * 0.5, x * 0.1, x * 0.0, F(np.full(16, 1.6)), prof, 1.0, 8, 1.0)
    np.asarray(out[0])
    assert calls and calls[0] is grin.DR  # traced once into the loop body, with the Dr.Jit namespace


# -- spot metrics -----------------------------------------------------------------------------------------------
def test_spot_metrics():
    px, py = pupil_disk(41)
    assert np.all(px * px + py * py <= 1.0)
    assert np.mean(px * px + py * py) == pytest.approx(0.5, rel=0.01)  # uniform on the disk
    t = np.linspace(0, 2 * np.pi, 360, endpoint=False)
    assert rms_radius(3.0 + 2.0 * np.cos(t), -1.0 + 2.0 * np.sin(t)) == pytest.approx(2.0)
    assert np.isnan(rms_radius(np.array([]), np.array([])))
    assert airy_radius(500.0, 0.5) == pytest.approx(0.61e-3)


# -- one objective model -----------------------------------------------------------------------------------------
def test_one_objective_for_the_focus_map_and_the_widefield_renderer():
    from scopetwin.recon.focusmap import Objective as FocusObjective
    from scopetwin.scenes.mitsuba.widefield import WidefieldOptics

    assert FocusObjective is Objective
    obj = Objective()
    assert obj.depth_of_field_um == 4.001234567901235  # the figure `scopetwin run` reports
    assert obj.field_of_view_mm == pytest.approx((1392 * 0.000645, 1040 * 0.000645))
    wf = WidefieldOptics()
    assert (wf.magnification, wf.na, wf.pixel_pitch_mm) == (obj.magnification, obj.na, 0.00645)
    assert wf.aperture_radius_mm == obj.aperture_radius_mm(wf.working_distance_mm)
    assert wf.blur_radius_mm(0.01) == pytest.approx(0.01 * np.tan(np.arcsin(0.45)))
    assert wf.field_mm == (256 * wf.object_pixel_mm, 256 * wf.object_pixel_mm)


def test_one_camera_writer_covers_the_calibration_and_the_truth_records():
    cam = load_setup("thesis-2.8.1-angular").camera_model
    calib = cam.as_dict(pose=(np.array([1.0, 2.0, 0.0]), 0.1, 230.0), grid=False)
    assert list(calib) == ["r_c", "t_x", "t_y", "n_z", "b", "g", "r_0", "phi", "r_cs", "c0", "c2"]  # `calibrate`
    assert calib["r_0"] == [1.0, 2.0] and calib["g"] == 230.0
    truth = cam.as_dict(focus=True, grid=False)
    assert list(truth) == ["r_c", "t_x", "t_y", "n_z", "b", "r_cs", "c0", "c2", "focus_distance"]
    assert truth["focus_distance"] is None  # a pinhole
