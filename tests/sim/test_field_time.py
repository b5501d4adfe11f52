"""Time per field and per slide (sim.field_time): the terms worked by hand, each term's source, and the
stages' velocities the same as the simulated unit's rig file."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path

import pytest

from scopetwin.sim import field_time as ft

ROOT = Path(__file__).resolve().parents[2]
SEED_MS = {"blue": 80.0, "green": 4000.0, "red": 9800.0, "nir": 6000.0}


def test_move_time_by_hand() -> None:
    # one field width along x (0.8978 mm) at 50 mm/s, 200 mm/s^2: v^2/a = 12.5 mm > d, so triangular:
    # t = 2 sqrt(0.8978 / 200) = 2 sqrt(0.004489) = 2 x 0.067 = 0.134 s
    assert ft.move_time_s(0.8978, 50.0, 200.0) == pytest.approx(0.134, rel=1e-9)
    # 100 mm: d / v + v / a = 2 + 0.25 s
    assert ft.move_time_s(100.0, 50.0, 200.0) == pytest.approx(2.25)
    # the two profiles meet at d = v^2 / a = 12.5 mm: 2 sqrt(12.5 / 200) = 0.5 = 12.5 / 50 + 50 / 200
    assert ft.move_time_s(12.5, 50.0, 200.0) == pytest.approx(0.5)
    assert ft.move_time_s(0.0, 50.0, 200.0) == 0.0


def test_field_times_by_hand() -> None:
    """The thesis's exposures, 80 x 25 fields: each term of both microscopes worked out by hand."""
    m = ft.TimingModel()
    # x: 0.134 + 0.1 settle; y (0.6708 mm at 100 mm/s, 200 mm/s^2): 2 sqrt(0.003354) + 0.1 = 0.2158284;
    # the serpentine's mean: (79 x 0.234 + 0.2158284) / 80 = 0.2337729 s
    move = 0.2337729
    assert m.move_s() == pytest.approx(move, rel=1e-6)
    cmu = ft.cmu_field_s(m, SEED_MS)
    assert cmu["focus"] == 0.0 and cmu["filters_readout"] == 0.0  # the piezo and the readout run during the move
    assert cmu["exposure"] == pytest.approx(9.8)  # the longest channel, all four at once
    assert cmu["total"] == pytest.approx(move + 9.8, rel=1e-7)
    seq = ft.sequential_field_s(m, SEED_MS)
    # autofocus: 20 frames x (0.02 settle + 0.08 blue exposure + 1/30 readout) = 2.6667 s
    assert seq["focus"] == pytest.approx(20 * (0.02 + 0.08 + 1 / 30))
    assert seq["exposure"] == pytest.approx(19.88)  # 80 + 4000 + 9800 + 6000 ms, one after the other
    assert seq["filters_readout"] == pytest.approx(3 * 0.05)  # three changes; the fourth during the move
    assert seq["total"] == pytest.approx(move + 2.666667 + 19.88 + 0.15, rel=1e-6)
    with_map = ft.sequential_field_s(m, SEED_MS, focus_map=True)
    assert with_map["total"] == pytest.approx(seq["total"] - seq["focus"])
    assert ft.slide_h(m, cmu) == pytest.approx(2000 * (move + 9.8) / 3600)


def test_comparison_table_and_sources() -> None:
    """The table has every term for the three microscopes; every term of the model names its source."""
    m = ft.TimingModel()
    table = ft.comparison(m, {"thesis": SEED_MS})["thesis"]
    for key in ("cmu_s", "sequential_map_s", "sequential_s"):
        terms = table[key]
        assert isinstance(terms, dict)
        assert set(terms) == {"move", "focus", "exposure", "filters_readout", "total"}
        assert terms["total"] == pytest.approx(sum(v for k, v in terms.items() if k != "total"))
    assert table["speedup"] == pytest.approx(22.930 / 10.034, rel=1e-3)
    for term, source in ft.TERM_SOURCES.items():
        assert "the thesis, §" in source or "our assumption" in source, term
    assert set(ft.TERM_SOURCES) >= {"field", "x", "y", "piezo", "readout", "filter", "autofocus", "exposure"}


def test_stages_match_the_simulated_units_rig() -> None:
    """One source of the stages' top speeds: the thesis's §4.2.2, as rigs/sim-cmu.toml has them."""
    rig = tomllib.loads((ROOT / "rigs" / "sim-cmu.toml").read_text())
    m = ft.TimingModel()
    assert m.x.velocity_mm_s == rig["devices"]["x"]["max_velocity_mm_s"] == 50.0
    assert m.y.velocity_mm_s == rig["devices"]["y"]["max_velocity_mm_s"] == 100.0
    # the field is the camera's: 1392 x 1040 px of 6.45 µm at 10x
    assert m.field_mm == pytest.approx((1392 * 0.000645, 1040 * 0.000645), rel=1e-4)


def test_faster_exposures_leave_the_moves_and_the_search() -> None:
    """With exposures of a few ms the unit's field time is the move; the sequential one's is the focus search."""
    m = ft.TimingModel()
    fast = {"blue": 3.0, "green": 2.0, "red": 50.0}
    cmu, seq = ft.cmu_field_s(m, fast), ft.sequential_field_s(m, fast)
    assert cmu["total"] < 0.3 and seq["focus"] > 0.5 * seq["total"]
    assert math.isclose(cmu["exposure"], 0.05)


def test_bad_parameters_are_refused() -> None:
    with pytest.raises(ft.FieldTimeError):
        ft.Axis("x", 0.0, 200.0, 0.1)
    with pytest.raises(ft.FieldTimeError):
        ft.TimingModel(columns=0)
    with pytest.raises(ft.FieldTimeError):
        ft.cmu_field_s(ft.TimingModel(), {"blue": 0.0})
    with pytest.raises(ft.FieldTimeError):
        ft.sequential_field_s(ft.TimingModel(), {})
