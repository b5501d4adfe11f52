"""The Dr.Jit/Mitsuba GRIN tracer against the numpy float64 reference; images and illumination (issue 7)."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.scenes.grin import load_grin_setup
from scopetwin.scenes.grin.analysis import analyse, chief_ray
from scopetwin.scenes.grin.rkn import trace_stack
from scopetwin.scenes.grin.targets import target
from scopetwin.scenes.spots import pupil_disk

grin = pytest.importorskip("scopetwin.scenes.mitsuba.grin")
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


def test_registration_is_idempotent(mi_mono, mono_variant):
    grin.register(mono_variant)
    grin.register(mono_variant)
    assert mi_mono.load_dict({"type": "scopetwin_grin"}) is not None


def test_illumination_conserves_energy():
    """No light is made on the way: what reaches the object plane entered the illumination rod's face, and the
    power in the field is at most what arrives with the losses applied (the two fractions come from independent
    code: the face test is numpy geometry of the launched rays, the arrival is the Mitsuba trace)."""
    s = load_grin_setup("thesis-7.5.2-grin-egfp")
    res = grin.illuminate(s, 20000)
    assert 0.0 < res["reaching_object"] <= res["accepted_fraction"] <= 1.0
    assert 0.0 < res["efficiency"] <= res["reaching_object"] * res["loss_factor"] + 1e-12
    assert 0.0 < res["loss_factor"] <= 1.0
    power_in_field = float(res["irradiance_mw_per_mm2"].sum()) * (2 * res["extent_mm"] / 101) ** 2
    assert power_in_field <= res["reaching_object"] * res["loss_factor"] * s.illumination.power_mw * (1 + 1e-6)
    assert res["irradiance_mw_per_mm2"].shape == (101, 101)


def test_rod_acceptance_has_the_closed_form_of_the_parabolic_profile(mono_variant):
    """Rays from an on-axis point through a rod with n² = n0²(1 - g²r²): exactly those whose orbit fits inside.

    In that medium the transverse motion is a harmonic oscillator in the Sharma parameter t,
    r(t) = r0 cos(w t) + (T/w) sin(w t) with w = n0 g (meridional rays from an on-axis point), so a ray entering at
    r0 with transverse direction cosine T (conserved across the flat face: T = sin θ in air) reaches the radius
    A = sqrt(r0² + (T/w)²) within a quarter period and is absorbed at the wall iff A > R. The rod is half a pitch
    long, so every ray passes its largest radius inside. Each traced ray's fate must follow (a 1e-3 band around
    A = R allows for the wall being tested at the step points); the surviving share of a Lambertian source is
    then T_max² (the T with A = R), which the sampled share reproduces.
    """
    from scopetwin.scenes.grin.glass import AIR
    from scopetwin.scenes.grin.setup import Layer, ParabolicN2Spec, RodSpec, Stack

    n0, g, radius, gap = 1.6, 1.0, 0.5, 0.05
    spec = ParabolicN2Spec(kind="parabolic_n2", n0=n0, g=g)
    length = np.pi / g  # half a pitch (paraxially; steeper rays oscillate faster in z)
    rod = RodSpec(length=length, radius=radius, profile=spec, step_mm=0.01)
    layers = (
        Layer("gap", 0.0, gap, AIR, 1.0),
        Layer("rod", gap, gap + length, AIR, 1.0, rod, spec.at(500.0)),
        Layer("tail", gap + length, gap + length + 0.5, AIR, 1.0),
    )
    stack = Stack(layers, 500.0, 0.5, -1.0, None)
    base = load_grin_setup("thesis-8.3.2-grin-realized")
    single = base.model_copy(update={"array": base.array.model_copy(update={"nx": 1, "ny": 1})})
    gs = grin.GrinScene(single, stack, variant=mono_variant)
    # a Lambertian point source: sin θ = sqrt(u), uniform azimuth (stratified, deterministic)
    n = 4000
    u = (np.arange(n) + 0.5) / n
    phi = 2.0 * np.pi * ((np.arange(n) * 0.618033988749895) % 1.0)
    sin_t = np.sqrt(u) * 0.999
    tx, ty = sin_t * np.cos(phi), sin_t * np.sin(phi)
    tz = np.sqrt(1.0 - sin_t**2)
    res = gs.trace((np.zeros(n), np.zeros(n), np.zeros(n)), (tx, ty, tz), 1.0, "float64", start="object")
    alive = np.asarray(res["alive"])
    w = n0 * g
    r0 = gap * sin_t / tz
    amplitude = np.sqrt(r0**2 + (sin_t / w) ** 2)
    inside, outside = amplitude < radius * (1 - 1e-3), amplitude > radius * (1 + 1e-3)
    assert inside.sum() > 100 and outside.sum() > 100
    assert alive[inside].all()
    assert not alive[outside].any()
    # T_max from A(T) = R (bisection), and the Lambertian share T_max²
    lo, hi = 0.0, 0.999
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        a = np.sqrt((gap * mid / np.sqrt(1 - mid * mid)) ** 2 + (mid / w) ** 2)
        lo, hi = (mid, hi) if a < radius else (lo, mid)
    assert alive.mean() == pytest.approx(lo * lo / 0.999**2, abs=2.0 / n)


def test_illumination_matches_numpy_reference():
    """The Mitsuba light trace loses no ray the float64 numpy stack trace keeps (the zero-thickness layer bug)."""
    from scopetwin.scenes.grin.illumination import illumination_stack

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
    from scopetwin.scenes.errors import ScopetwinError
    from scopetwin.scenes.grin.setup import Layer, Stack

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
def test_interleaved_rkn_equals_plain(dtype, mono_variant):
    from scopetwin.scenes.grin.profiles import PolynomialProfile

    F = grin.float_type(dtype, mono_variant)
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
