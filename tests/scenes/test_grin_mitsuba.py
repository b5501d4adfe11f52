"""The Dr.Jit/Mitsuba GRIN tracer against the numpy float64 reference; images and illumination (issue 7)."""

from __future__ import annotations

import numpy as np
import pytest

from scenes.grin import load_grin_setup
from scenes.grin.analysis import analyse, chief_ray, pupil_disk
from scenes.grin.rkn import trace_stack
from scenes.grin.targets import target

grin = pytest.importorskip("scenes.mitsuba.grin")
pytestmark = pytest.mark.mitsuba


@pytest.fixture(scope="module")
def realized():
    s = load_grin_setup("thesis-8.3.2-grin-realized")
    return s, s.stack(image_distance=11.4)


def test_mitsuba_scene_trace_matches_numpy(realized):
    s, st = realized
    px, py = pupil_disk(10)
    h = 0.2
    tc = chief_ray(st, h)
    x0, y0, tx, ty = np.zeros_like(px), np.full_like(px, h), 0.4 * px, tc + 0.4 * py
    ref = trace_stack(st, x0, y0, tx, ty)
    rx, ry = ref.at(11.4)
    for precision, tol in (("float64", 1e-9), ("float32", 1e-5)):
        out = grin.trace_forward(s, st, x0, y0, tx, ty, precision)
        assert np.array_equal(out["alive"], ref.alive)
        ok = ref.alive
        assert ok.sum() > 20
        assert np.max(np.hypot(out["x"][ok] - rx[ok], out["y"][ok] - ry[ok])) < tol


def test_image_of_target_has_the_traced_magnification():
    s = load_grin_setup("thesis-8.3.2-grin-realized", {"camera": {"pixel_um": 10.0}})
    rep = analyse(s, samples=16)
    st = s.stack(image_distance=rep.image_distance_mm)
    img = grin.render_image(s, st, target("grid-25"), spp=4, width=256, height=256, center=s.array.axes()[0])
    assert img.dtype == np.float32 and img.shape == (256, 256)
    # the 400 µm pattern disk images to a disk of radius m * 0.2 mm on the camera: find the radius where the
    # azimuthally averaged brightness falls to half its value just inside the edge (robust to vignetting)
    expected = rep.magnification_real * 0.2 / 0.010
    yy, xx = np.mgrid[0:256, 0:256] + 0.5
    r = np.hypot(xx - 128.0, yy - 128.0)
    prof = np.bincount(r.astype(int).ravel(), img.ravel()) / np.bincount(r.astype(int).ravel())
    ref = prof[int(0.85 * expected)]
    start = int(0.85 * expected)
    k = start + int(np.argmax(prof[start:] < 0.5 * ref))
    radius = k - 1 + (prof[k - 1] - 0.5 * ref) / (prof[k - 1] - prof[k]) + 0.5
    assert radius == pytest.approx(expected, rel=0.02)


def test_registration_is_idempotent():
    grin.register()
    grin.register()
    assert grin.mi.load_dict({"type": "scopetwin_grin", "key": "x"}) is not None


def test_illumination_efficiency_is_a_fraction():
    s = load_grin_setup("thesis-7.5.2-grin-egfp")
    res = grin.illuminate(s, 20000)
    assert 0.0 <= res["efficiency"] <= res["reaching_object"] * res["loss_factor"] + 1e-12
    assert res["irradiance_mw_per_mm2"].shape == (101, 101)
