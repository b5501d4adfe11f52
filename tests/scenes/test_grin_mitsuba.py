"""The Dr.Jit/Mitsuba GRIN tracer against the numpy float64 reference; images and illumination."""

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


def _rays_over_the_array(s, st, start, n, rng):
    """Rays over the whole array: from the image plane aimed at and around the last rods' exit faces, or from the
    object plane inside and around the rods' fields (some miss the rods: they meet the holders or walls)."""
    axes = np.array(s.array.axes())
    k = rng.integers(len(axes), size=n)
    ax, ay = axes[k, 0], axes[k, 1]
    rods = [layer for layer in st.layers if layer.rod is not None]
    r, phi = 1.3 * rods[-1].rod.radius * np.sqrt(rng.uniform(0, 1, n)), rng.uniform(0, 2 * np.pi, n)
    if start == "image":
        u, v = ax + rng.uniform(-0.4, 0.4, n), ay + rng.uniform(-0.4, 0.4, n)
        d = np.stack([ax + r * np.cos(phi) - u, ay + r * np.sin(phi) - v, np.full(n, rods[-1].z1 - st.layers[-1].z1)])
        d /= np.linalg.norm(d, axis=0)
        return (u, v, np.full(n, st.layers[-1].z1)), tuple(d), 1.0
    n0 = st.layers[0].index
    tx, ty = 0.5 * r / rods[-1].rod.radius * np.cos(phi), 0.5 * r / rods[-1].rod.radius * np.sin(phi)
    x, y = ax + rng.uniform(-0.3, 0.3, n), ay + rng.uniform(-0.3, 0.3, n)
    return (x, y, np.zeros(n)), (tx, ty, np.sqrt(n0 * n0 - tx * tx - ty * ty)), n0


@pytest.mark.parametrize("start", ["image", "object"])
def test_sequential_trace_equals_mitsuba_intersections(realized, mono_variant, start):
    """Intersecting the planes a sequential trace meets in their known order (no Mitsuba ray
    intersection) gives the very same rays as asking Mitsuba's intersection at every plane, fates included."""
    s, st = realized
    gs = grin.GrinScene(s, st, 0.9, variant=mono_variant)
    p, t, n_start = _rays_over_the_array(s, st, start, 20000, np.random.default_rng(7))
    for precision in ("float32", "float64"):
        a = gs.trace(p, t, n_start, precision, start=start)
        b = gs.trace(p, t, n_start, precision, start=start, sequential=True)
        alive = np.asarray(a["alive"])
        assert 0.2 < alive.mean() < 0.95  # both fates occur
        for key in a:
            np.testing.assert_array_equal(np.asarray(b[key]), np.asarray(a[key]), err_msg=f"{precision} {key}")


def test_sequential_image_equals_mitsuba_intersections(mono_variant):
    """The image of the whole array (every objective, rays missing the rods) is bit for bit the same with the planes
    intersected in their known order as with Mitsuba's ray intersection (the ~5x faster path)."""
    s = load_grin_setup("thesis-8.3.2-grin-realized", {"camera": {"pixel_um": 20.0}})
    st = s.stack(image_distance=11.4)
    kw = {"spp": 4, "width": 80, "height": 60, "variant": mono_variant}
    fast = grin.render_image(s, st, target("grid-25"), sequential=True, **kw)
    slow = grin.render_image(s, st, target("grid-25"), sequential=False, **kw)
    assert fast.mean() > 0 and (fast == 0).mean() > 0.05  # light and dark (between the objectives' images)
    np.testing.assert_array_equal(fast, slow)


def test_multijitter_counts_are_those_mitsuba_keeps(mi_mono):
    """``sampler_counts_exact`` is the installed Mitsuba's rule; a rounded count is refused before rendering."""
    from scopetwin.scenes.errors import ScopetwinError

    for spp in range(1, 130):
        kept = mi_mono.load_dict({"type": "multijitter", "sample_count": spp}).sample_count() == spp
        assert grin.sampler_counts_exact("multijitter", spp) == kept, spp
    s = load_grin_setup("thesis-8.3.2-grin-realized")
    with pytest.raises(ScopetwinError, match="rounds 32 spp up"):
        grin.render_image(
            s, s.stack(image_distance=11.4), target("grid-25"), spp=32, width=8, height=8, sampler="multijitter"
        )


def test_multijitter_at_25_spp_is_less_noisy_than_64_independent(realized, mono_variant):
    """Fewer paths for the same noise: stratified pixel and pupil samples (Mitsuba's multi-jittered
    sampler) at 25 spp give at most the per-pixel noise of 64 independent samples, around the same mean.

    The noise of each is the RMS difference of two renders with different seeds / sqrt 2 (no reference needed);
    ``benchmarks/grin_speed.py`` prints it on a larger window (348 x 260: ratio 0.93; 96 x 96: 0.80)."""
    s, st = realized
    kw = {"width": 96, "height": 96, "center": s.array.axes()[0], "variant": mono_variant}
    noise, mean = {}, {}
    for sampler, spp in (("independent", 64), ("multijitter", 25)):
        a, b = (grin.render_image(s, st, target("grid-25"), spp=spp, seed=sd, sampler=sampler, **kw) for sd in (3, 4))
        noise[sampler] = np.sqrt(np.mean((a.astype(np.float64) - b) ** 2) / 2)
        mean[sampler] = 0.5 * (a.mean() + b.mean())
    assert noise["independent"] > 0
    assert noise["multijitter"] <= noise["independent"]
    # the same image: the means agree within 5 standard errors of the pixel noise
    se = np.hypot(noise["independent"], noise["multijitter"]) / np.sqrt(2 * 96 * 96)
    assert abs(mean["multijitter"] - mean["independent"]) < 5 * se
