"""Exactness of the GRIN integrators against closed-form rays, numpy and Dr.Jit float64."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.scenes.grin.paraxial import rod_paraxial, stack_matrix, system_paraxial
from scopetwin.scenes.grin.profiles import ParabolicN2Profile, PolynomialProfile, SechProfile
from scopetwin.scenes.grin.rkn import rkn_rod, trace_stack

N0, G = 1.62893, 0.3074745


def _dr_rkn(x, y, tx, ty, tz, profile, length, steps, radius=10.0):
    grin = pytest.importorskip("scopetwin.scenes.mitsuba.grin")
    from scopetwin.scenes.mitsuba.variant import choose, mitsuba

    F = mitsuba(choose("mono")).Float64  # the variant is chosen here, not by importing the renderer
    out = grin.rkn_rod_dr(F(x), F(y), F(tx), F(ty), F(tz), profile, length, steps, radius)
    return tuple(np.asarray(v, dtype=np.float64) for v in out[:5])


def _meridional(x0: np.ndarray, slope: np.ndarray, profile: SechProfile):
    n = profile.index(x0 * x0)
    sin_t = slope / np.sqrt(1 + slope**2)
    return n * sin_t, n * np.sqrt(1 - sin_t**2)


@pytest.mark.parametrize("engine", ["numpy", "drjit"])
def test_sech_meridional_period_returns_within_1nm(engine):
    prof = SechProfile(N0, G)
    x0 = np.array([0.05, 0.3, 0.6, -0.8, 0.0])
    slope = np.array([0.0, 0.05, -0.1, 0.2, 0.25])
    tx, tz = _meridional(x0, slope, prof)
    pitch = 2 * np.pi / G
    args = (x0, np.zeros_like(x0), tx, np.zeros_like(x0), tz, prof, pitch, 600)
    x, y, tx1, ty1, _ = rkn_rod(*args, radius=10.0)[:5] if engine == "numpy" else _dr_rkn(*args)
    assert np.max(np.abs(x - x0)) < 1e-6  # 1 nm
    assert np.max(np.abs(tx1 / tz - slope)) < 1e-6
    assert np.max(np.abs(y)) < 1e-12


@pytest.mark.parametrize("engine", ["numpy", "drjit"])
def test_parabolic_n2_skew_rays_follow_closed_form(engine, rng):
    prof = ParabolicN2Profile(N0, G)
    m = 64
    x0, y0 = rng.uniform(-0.6, 0.6, (2, m))
    tx0, ty0 = rng.uniform(-0.3, 0.3, (2, m))
    n = prof.index(x0 * x0 + y0 * y0)
    tz = np.sqrt(n * n - tx0 * tx0 - ty0 * ty0)
    length = 3.58
    args = (x0, y0, tx0, ty0, tz, prof, length, 36)
    x, y, tx, ty, opl = rkn_rod(*args, radius=10.0)[:5] if engine == "numpy" else _dr_rkn(*args)
    w = N0 * G
    t = length / tz
    ex = x0 * np.cos(w * t) + tx0 / w * np.sin(w * t)
    ey = y0 * np.cos(w * t) + ty0 / w * np.sin(w * t)
    assert np.max(np.hypot(x - ex, y - ey)) < 1e-6  # 1 nm
    etx = -x0 * w * np.sin(w * t) + tx0 * np.cos(w * t)
    assert np.max(np.abs(tx - etx)) < 1e-8
    # OPL = ∫ n² dt with n² = n0² (1 - g² r(t)²): closed form of the sinusoid's square
    a2 = x0**2 + y0**2
    b2 = (tx0**2 + ty0**2) / w**2
    c = (x0 * tx0 + y0 * ty0) / w
    r2_int = 0.5 * (a2 + b2) * t + 0.25 * (a2 - b2) * np.sin(2 * w * t) / w + c * (1 - np.cos(2 * w * t)) / (2 * w)
    e_opl = N0**2 * (t - G**2 * r2_int)
    assert np.max(np.abs(opl - e_opl)) < 1e-7


@pytest.mark.parametrize("length", [0.7, 3.58, 5.0])
def test_single_rod_paraxial_matches_abcd(length):
    prof = PolynomialProfile()
    ref = rod_paraxial(prof, length)
    h = 1e-4
    # collimated ray of height h in air -> T⊥ = 0 inside; exit slope in air = T_x (n_air = 1)
    x, _, tx, _, _, _ = rkn_rod(
        np.array([h]), np.zeros(1), np.zeros(1), np.zeros(1), np.array([prof.index(h * h)]), prof, length, 400
    )
    u = tx[0] / np.sqrt(1 - tx[0] ** 2)
    efl = -h / u
    bfl = -x[0] / u
    assert efl == pytest.approx(ref.efl, rel=1e-6)
    assert bfl == pytest.approx(ref.bfl, rel=1e-6)
    assert ref.pitch == pytest.approx(2 * np.pi / prof.g, rel=1e-15)


def test_objective_paraxial_matches_abcd():
    from scopetwin.scenes.grin import load_grin_setup

    setup = load_grin_setup("thesis-8.3.2-grin-realized")
    st = setup.stack()
    par = system_paraxial(st)
    a, b, c, d = stack_matrix(st).ravel()
    h, u = 1e-5, 1e-5
    # two near-axis rays: (y, nu) = (h, 0) and (0, u); ABCD columns from their end states
    s1 = trace_stack(st, np.zeros(1), np.array([h]), np.zeros(1), np.zeros(1))
    s2 = trace_stack(st, np.zeros(1), np.zeros(1), np.zeros(1), np.array([u]))
    assert s1.y[0] / h == pytest.approx(a, rel=1e-6)
    assert s1.ty[0] / h == pytest.approx(c, rel=1e-6)
    assert s2.y[0] / u == pytest.approx(b, rel=1e-6)
    assert s2.ty[0] / u == pytest.approx(d, rel=1e-6)
    assert par.magnification == pytest.approx(1 / d, rel=1e-12)
