"""Scan-time models (thesis §7.2-7.4) and the objective count (§8.2.2)."""

from __future__ import annotations

import pytest

from scopetwin.sim import scan_time as tp


def test_demonstrator_geometry_matches_seed():
    geo = tp.demonstrator_geometry()
    assert geo["n_max"] == 2
    assert geo["d_l_max_mm"] == pytest.approx(2.848, abs=5e-4)
    assert geo["n_at_d_l"] == 2
    # The thesis's d_L,max formula is not the inverse of its eq. 8.1: solving eq. 8.1 for d_L at N = 2 gives
    # (S - N m FOV)/(N + 1) + D_L = 2.283 mm, so eq. 8.1 already yields N = 1 at 2.848 mm (reported, not fixed).
    assert tp.objective_count(4.28, 2.0, 2.28, 4.29, 0.4) == 2
    assert tp.objective_count(4.28, 2.0, 2.848, 4.29, 0.4) == 1


def test_classic_and_scan_times():
    c = tp.classic_time(10.0, 5.0, 1.0, 0.5, 0.2, 2.0)
    assert c["t_i_s"] == pytest.approx(10 * 10 * 0.2)
    assert c["t_m_s"] == pytest.approx((10 * 5 + 10) / 2.0)
    assert tp.scan_time(10.0, 5.0, 0.5, 2.0, 4) == pytest.approx((5 / 2 * 10 / 0.5 + 10 / 2) / 4)
    assert tp.scan_time_parallel(2.0, 0.4, 25.0, 1.0, 5) == pytest.approx(2 / 0.4 * 25 / 5)


def test_scaling_law_is_s_to_the_1p5_without_aberration_offset():
    m = tp.ScalingModel(a=0.0, b=0.02, wavelength=0.0005, na=0.3, magnification=4.0)
    t1 = m.scan_time(1.0, 2.0, 25.0, 1.0, 1)
    tq = m.scan_time(0.25, 2.0, 25.0, 1.0, 1)
    assert tq / t1 == pytest.approx(0.25**1.5, rel=1e-12)  # one eighth (eq. 7.6)
    assert m.scan_time(0.25, 2.0, 25.0, 1.0, 1, pack_rows=False) / t1 == pytest.approx(0.5, rel=1e-12)


def test_bad_parameters():
    with pytest.raises(tp.ScanTimeError, match="positive"):
        tp.scan_time(-1.0, 5.0, 0.5, 2.0)
    with pytest.raises(tp.ScanTimeError, match="smaller than the lens diameter"):
        tp.objective_count(4.28, 2.0, 1.5, 4.29, 0.4)
    with pytest.raises(tp.ScanTimeError, match="no field is left"):
        tp.ScalingModel(a=0.01, b=0.02, wavelength=0.0005, na=0.3, magnification=4.0).r_max(1.0)
