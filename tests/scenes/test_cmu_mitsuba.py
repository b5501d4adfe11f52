"""The unit rendered in Mitsuba's spectral variant: plugins against the numpy tracer, and the Siemens-star
analysis (calib.channels) recovering known magnification, offset, tilt and resolution from rendered images."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from scopetwin.calib.channels import measure_channel, relative_pose
from scopetwin.scenes.cmu.analysis import CHANNEL_WAVELENGTH_NM, Optics, analyse, channel_optics, image_rays
from scopetwin.scenes.cmu.layout import load_cmu_setup
from scopetwin.scenes.cmu.plates import plate_heightmap
from scopetwin.scenes.cmu.trace import Rays, System
from scopetwin.scenes.spots import pupil_disk

pytestmark = pytest.mark.mitsuba
WINDOW = (90, 266, 860, 860)  # rows 90..949, cols 266..1125: the whole 775 px frame at m = 10


@pytest.fixture(scope="module")
def setup():
    return load_cmu_setup("thesis-cmu")


@pytest.fixture(scope="module")
def mc():
    from scopetwin.scenes.mitsuba import cmu

    return cmu


def _measure(setup, img):
    t = setup.target
    return measure_channel(img, setup.camera.pixel_um, t.frame_side * 1e3, t.star_radius * 1e3, t.spokes)


def test_ideal_lens_plugin_focuses_parallel_light(mc, setup) -> None:
    """A point at the object maps to one pixel: the NIR image of the star centre region is pixel-sharp."""
    img = mc.render_channel(setup, "nir", mc.CameraPose(164.5), "star", spp=4, window=(480, 656, 80, 80), flat=True)
    meas_mod = np.abs(np.diff(img, axis=1)).max()
    assert meas_mod > 0.5 * img.max()  # edges go from chrome to clear within one pixel


def test_known_magnification_offset_tilt_recovered(mc, setup) -> None:
    """Flat unit; the blue camera behind a 160 mm tube lens (m = 9.7264), tilted 0.1°, shifted (12.3, -7.6) px."""
    ref_img = mc.render_channel(setup, "nir", mc.CameraPose(164.5), "star", spp=4, window=WINDOW, flat=True)
    pose = mc.CameraPose(160.0, tilt_deg=0.1, offset_px=(12.3, -7.6))
    img = mc.render_channel(setup, "blue", pose, "star", spp=4, window=WINDOW, flat=True, tube_f=160.0, seed=1)
    ref, meas = _measure(setup, ref_img), _measure(setup, img)
    assert ref.magnification == pytest.approx(10.0, rel=0.002)
    assert meas.magnification == pytest.approx(160.0 / 16.45, rel=0.002)
    rel = relative_pose(meas, ref, setup.camera.pixel_um)
    assert rel["offset_x_px"] == pytest.approx(12.3, abs=0.5)
    assert rel["offset_y_px"] == pytest.approx(-7.6, abs=0.5)
    assert rel["tilt_deg"] == pytest.approx(0.1, abs=0.02)
    assert ref.delta_x_um < 1.0  # pixel-limited, as the NIR channel of Table 5.2


def test_rendered_bowed_channel_matches_numpy_tracer(mc, setup) -> None:
    """Red channel with the bowed 770DCXR at 45°, refocused: the rendered image's magnification (calib) agrees
    with the numpy tracer's, and the star is visibly less resolved than in the flat unit."""
    res = analyse(setup, channel_optics(setup, "red"), n_pupil=21)
    img = mc.render_channel(setup, "red", mc.CameraPose(res.image_distance_mm), "star", spp=4, window=WINDOW)
    meas = _measure(setup, img)
    assert meas.magnification == pytest.approx(res.magnification, rel=0.003)
    assert meas.delta_x_um > 1.5


def _reversed_tracer_rays(opt, b: float, x0: float, y0: float, n_pupil: int):
    """The float64 tracer's rays of object point (x0, y0), reversed at the image plane b: (origins, directions)."""
    r = image_rays(opt, x0, y0, *pupil_disk(n_pupil))
    u, v = r.at(b)
    fr = opt.tube.frame
    o = fr.origin + u[:, None] * fr.tx + v[:, None] * fr.ty + b * fr.nz
    d = -(r.su[:, None] * fr.tx + r.sv[:, None] * fr.ty + fr.nz)
    return o, d


def _direction_keeping_landing(opt, o, d):
    """Object-plane points (float64) of the reversed rays when a transmitted plate keeps the ray's direction and
    position (the former thin-plate BSDF): the tube lens, the reflecting faces in reverse order, the objective."""
    r = System([opt.tube, *[s for s in reversed(opt.middle) if s.mode == "R"], opt.objective]).trace(Rays.start(o, d))
    return r.o[:, :2] - (r.o[:, 2] / r.d[:, 2])[:, None] * r.d[:, :2]


@pytest.fixture(scope="module")
def bowed(mc, setup):
    """Plate maps with every splitter bowed (the 61002BS given a convex 9.4 µm bow here), and their scene."""
    bs = setup.splitters["61002BS"].model_copy(
        update={"bow_range_um": 9.4, "residual_rms_um": 0.1, "residual_seed": 4, "concave": False}
    )
    elements = {**setup.splitters, "61002BS": bs, **setup.mirrors}
    maps = {name: plate_heightmap(spec, setup.plate) for name, spec in elements.items()}
    return maps, mc.unit_scene(setup, maps)


def _path_counts(spec) -> tuple[int, int]:
    """Reflections and surfaces met (tube lens, 1 per reflection, 2 per transmission, objective) on a path."""
    steps = spec.steps()
    n_refl = sum(mode == "R" for _, mode in steps)
    return n_refl, 2 + n_refl + 2 * (len(steps) - n_refl)


@pytest.mark.slow
def test_transmitted_bowed_plates_land_rays_like_the_exact_tracer(mc, setup, bowed) -> None:
    """Every channel transmits through bowed splitters. Rays of the exact float64 tracer (refraction at both faces
    of each 1 mm plate), reversed at the refocused image plane and traced back through the Mitsuba scene, land on
    their object point: the image position (mean over the pupil) agrees within 0.05 px at the frame's centre and
    corner, each ray within 0.1 px. The check resolves the plates: keeping a transmitted ray's direction (the
    former thin-plate BSDF, here in float64) misses by > 0.2 px."""
    maps, scene = bowed
    p_mm = setup.camera.pixel_um * 1e-3
    for ch, spec in setup.channels.items():
        opt = channel_optics(setup, ch, maps)
        res = analyse(setup, opt, n_pupil=11)
        n_refl, n_events = _path_counts(spec)
        to_px = res.magnification / p_mm
        for x0, y0 in ((0.0, 0.0), (0.25, 0.25)):
            o, d = _reversed_tracer_rays(opt, res.image_distance_mm, x0, y0, 11)
            land = mc.land_rays(scene, o, d, CHANNEL_WAVELENGTH_NM[ch], seed=3)
            ok = land.hit & (land.reflections == n_refl) & (land.events == n_events)  # the channel's own path
            assert ok.sum() > 0.8 * len(o)
            err_px = (land.points[ok, :2] - (x0, y0)) * to_px
            assert np.hypot(*err_px.mean(axis=0)) < 0.05, (ch, x0, err_px.mean(axis=0))
            assert np.hypot(*err_px.T).max() < 0.1, ch
            thin_px = (_direction_keeping_landing(opt, o, d) - (x0, y0)) * to_px
            assert np.hypot(*thin_px.mean(axis=0)) > 0.2, (ch, x0, thin_px.mean(axis=0))


@pytest.mark.slow
def test_transmitted_plates_shift_the_beam_at_the_objective_aperture(mc, setup, bowed) -> None:
    """The plates' lateral shift (0.33 mm per 1 mm plate at 45°) is modelled: the exact tracer's rays of the field
    centre through the rim of the objective's 10 mm aperture (radius 0.98 of it) come back through it in Mitsuba,
    rays at 1.02 of it miss it. A plate that only bends rays (the former BSDF) moves this aperture by 0.33-1 mm:
    10-19 of these 48 rays land on the wrong side of it, and an aberrated bundle vignetted on one side shifts its
    centroid (0.27 px in the blue channel's star image)."""
    maps, scene = bowed
    phi = np.linspace(0.0, 2.0 * np.pi, 48, endpoint=False)
    for ch, spec in setup.channels.items():
        opt = channel_optics(setup, ch, maps)
        b = analyse(setup, opt, n_pupil=11).image_distance_mm
        big = Optics(
            dataclasses.replace(opt.objective, radius=1.1 * opt.objective.radius),
            opt.middle,
            opt.tube,
            None,
            opt.wavelength_nm,
        )
        n_refl, n_events = _path_counts(spec)
        for rim, inside in ((0.98, True), (1.02, False)):
            r = image_rays(big, 0.0, 0.0, rim / 1.1 * np.cos(phi), rim / 1.1 * np.sin(phi))
            assert len(r.u0) == len(phi)
            u, v = r.at(b)
            fr = opt.tube.frame
            o = fr.origin + u[:, None] * fr.tx + v[:, None] * fr.ty + b * fr.nz
            d = -(r.su[:, None] * fr.tx + r.sv[:, None] * fr.ty + fr.nz)
            land = mc.land_rays(scene, o, d, CHANNEL_WAVELENGTH_NM[ch], seed=5)
            own = land.hit & (land.reflections == n_refl) & (land.events == n_events)
            if inside:
                assert own.sum() >= 0.9 * len(phi), (ch, own.sum())
            else:
                assert not own.any(), (ch, own.sum())
