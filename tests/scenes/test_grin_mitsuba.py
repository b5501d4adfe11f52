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
    assert res["efficiency"] == pytest.approx(res["efficiency_of_accepted"] * res["accepted_fraction"])
    assert res["irradiance_mw_per_mm2"].shape == (101, 101)


def test_illumination_matches_numpy_reference():
    """The Mitsuba light trace loses no ray the float64 numpy stack trace keeps (the zero-thickness layer bug)."""
    from scenes.grin.illumination import illumination_stack

    s = load_grin_setup("thesis-7.5.2-grin-egfp")
    st = illumination_stack(s)
    rng = np.random.default_rng(3)
    n = 20000
    x, y = rng.uniform(-0.25, 0.25, (2, n))
    r, phi = np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n)
    tx, ty = r * np.cos(phi), r * np.sin(phi)
    with np.errstate(over="ignore", invalid="ignore"):  # rays outside the rods blow up the polynomial: dead rays
        ref = trace_stack(st, x, y, tx, ty, until_layer=len(st.layers))
    gs = grin.GrinScene(s.model_copy(update={"array": s.array.model_copy(update={"nx": 1, "ny": 1})}), st)
    res = gs.trace((x, y, np.zeros(n)), (tx, ty, np.sqrt(1 - tx * tx - ty * ty)), 1.0, "float64", start="object")
    alive = np.asarray(res["alive"])
    assert alive.mean() > 0.05  # ~9 % of a Lambertian LED reaches the object plane
    assert np.mean(alive != ref.alive) < 1e-3
    both = alive & ref.alive
    assert np.max(np.hypot(np.asarray(res["x"])[both] - ref.x[both], np.asarray(res["y"])[both] - ref.y[both])) < 1e-6


def test_coincident_planes_are_rejected(realized):
    from scenes.errors import ScopetwinError
    from scenes.grin.setup import Layer, Stack

    s, st = realized
    last = st.layers[-1]
    bad = Stack(
        (*st.layers, Layer("empty", last.z1, last.z1, last.glass, last.index, None, None)),
        st.wavelength_nm,
        st.image_distance,
        st.stop_z,
        st.stop_radius,
    )
    with pytest.raises(ScopetwinError, match="zero or negative thickness"):
        grin.GrinScene(s, bad)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_interleaved_rkn_equals_plain(dtype):
    from scenes.grin.profiles import PolynomialProfile

    F = grin.float_type(dtype)
    prof = PolynomialProfile()
    rng = np.random.default_rng(5)
    n = 1001  # odd: the last group is padded
    x, y = rng.uniform(-0.9, 0.9, (2, n))
    tx, ty = rng.uniform(-0.3, 0.3, (2, n))
    tz = np.sqrt(prof.index(x * x + y * y) ** 2 - tx * tx - ty * ty)
    args = [F(a) for a in (x, y, tx, ty, tz)]
    plain = grin.rkn_rod_dr(*args, prof, 3.58, 36, 1.0)
    alive = np.asarray(plain[5])
    assert 0.5 < alive.mean() < 1.0  # some rays meet the wall
    for il in (2, 3):
        out = grin.rkn_rod_dr(*args, prof, 3.58, 36, 1.0, interleave=il)
        np.testing.assert_array_equal(np.asarray(out[5]), alive)
        for a, b in zip(out[:5], plain[:5], strict=True):
            np.testing.assert_array_equal(np.asarray(a)[alive], np.asarray(b)[alive])
