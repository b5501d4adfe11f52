"""The unit rendered in Mitsuba's spectral variant: plugins against the numpy tracer, and the Siemens-star
analysis (calib.channels) recovering known magnification, offset, tilt and resolution from rendered images."""

from __future__ import annotations

import numpy as np
import pytest

from calib.channels import measure_channel, relative_pose
from scenes.cmu.analysis import analyse, channel_optics
from scenes.cmu.layout import load_cmu_setup

pytestmark = pytest.mark.mitsuba
WINDOW = (90, 266, 860, 860)  # rows 90..949, cols 266..1125: the whole 775 px frame at m = 10


@pytest.fixture(scope="module")
def setup():
    return load_cmu_setup("thesis-cmu")


@pytest.fixture(scope="module")
def mc():
    from scenes.mitsuba import cmu

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
