"""The second-measurement study: registered, its families, and its table's figures from the rows
(the renders themselves run in ``scopetwin study second-measurement``; the method is tested in
tests/recon/test_two_positions*.py)."""

from __future__ import annotations

import pytest

from scopetwin.sim.studies.runner import STUDIES
from scopetwin.sim.studies.second_measurement import FAMILIES, second_measurement_table, surface_spec


def test_the_study_is_registered_and_its_families_are_the_glass_like_one_with_and_without_micro_waviness():
    assert "second-measurement" in STUDIES
    glass, smooth = (surface_spec(f, 2731) for f in FAMILIES)
    assert 20.0 <= glass["broadband_rms_nm"] <= 100.0 and smooth["broadband_rms_nm"] == 0.0
    assert {k: v for k, v in glass.items() if k != "broadband_rms_nm"} == {
        k: v for k, v in smooth.items() if k != "broadband_rms_nm"
    }
    with pytest.raises(ValueError):
        surface_spec("sphere", 1)


def _row(family: str, single: float | None, pair: float, pair_u: float, both: float, u: float) -> dict:
    row = {
        "family": family,
        "pair_absolute_um": pair,
        "pair_u_abs_um": pair_u,
        "absolute_um": both,
        "u_abs_um": u,
        "shape_um": 0.05,
        "u_shape_um": 0.1,
    }
    if single is not None:
        row.update(single_absolute_um=single, single_u_abs_um=1.0, single_shape_um=0.2)
    return row


def test_the_table_counts_errors_within_2u_and_within_the_goal():
    rows = [
        _row(FAMILIES[1], 2.5, 0.02, 0.03, 0.05, 0.05),  # single beyond 2 u; two positions within the goal
        _row(FAMILIES[1], 0.5, -0.08, 0.03, 0.2, 0.05),  # two positions beyond 2 u; combined beyond the goal
        _row(FAMILIES[1], None, 0.01, 0.02, 0.01, 0.02),  # image 1 alone failed
    ]
    table = second_measurement_table(rows, 40.0, 16)
    (cells,) = table.cells
    col = dict(zip(table.columns, cells, strict=True))
    assert col["surfaces"] == 3 and col["single failed"] == 1
    assert col["single |abs| <= 2u (%)"] == pytest.approx(50.0)
    assert col["two positions |abs| <= 2u (%)"] == pytest.approx(200 / 3)
    assert col["two positions |abs| max (µm)"] == pytest.approx(0.08)
    assert col["combined |abs| <= 0.1 µm (%)"] == pytest.approx(200 / 3)
    assert col["combined |abs| <= 2u (%)"] == pytest.approx(200 / 3)
