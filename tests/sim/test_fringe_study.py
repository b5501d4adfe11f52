"""The ``fringes`` study: markers against phase-shifted fringes on the same surfaces.

Acceptance: the study is registered; both setups of a surface share the geometry (camera, pattern / display pose,
substrate, pattern stage); the table counts failures, errors within 2 u and acquisition times from its rows. On the
1.5 mm / 2 µm dimple (slow; 2 x 2 binned camera, 16 spp, sensor noise, both methods at one and two positions):
every reconstruction's absolute and shape errors lie within 3 of its reported uncertainty, the fringes recover the
dimple to 90-110 % of its depth and the two display positions the shape within 0.01 µm, the markers (1.5 mm apart)
less than half of it; the acquisition time is frames x exposure.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from scopetwin.cli.study import STUDY_NAMES
from scopetwin.sim.studies.context import StudyContext
from scopetwin.sim.studies.fringes import (
    BINNED_CAMERA,
    FringeStudyConfig,
    fringes,
    fringes_table,
    study_setups,
    surface_spec,
)
from scopetwin.sim.studies.runner import STUDIES


def test_the_study_is_registered_and_both_setups_share_the_geometry():
    assert {"fringes", "fringes-full"} <= set(STUDIES) and {"fringes", "fringes-full"} <= set(STUDY_NAMES)
    assert surface_spec("dimple", 5)["features"][0]["width_mm"] == 1.5
    with pytest.raises(ValueError, match="unknown family"):
        surface_spec("gauss", 1)
    markers, display = study_setups("cut", 9100, BINNED_CAMERA, 40.0)
    assert markers.fringe_display is None and display.fringe_display is not None
    assert markers.camera == display.camera and markers.camera.pixels == (680, 512)
    assert markers.pattern == display.pattern and markers.substrate == display.substrate
    assert markers.pattern_stage == display.pattern_stage and markers.pattern_stage.shift_mm == 40.0


def _row(method: str, n: int, ab: float, u_ab: float | None, error: bool = False) -> dict:
    row = {"family": "glass", "seed": 1, "method": method, "positions": n, "frames": 24 * n, "acquisition_s": 0.5 * n}
    if error:
        return {**row, "error": "ReconstructionError: no"}
    return {**row, "absolute_um": ab, "u_abs_um": u_ab, "shape_um": 0.01, "u_shape_um": 0.01, "seconds": 2.0}


def test_the_table_counts_failures_and_errors_within_2u():
    rows = [
        _row("fringes", 1, 0.1, 0.1),
        _row("fringes", 1, -0.3, 0.1),  # beyond 2 u
        _row("fringes", 1, 0.1, None),  # no uncertainty: outside
        _row("fringes", 1, 0.0, 0.1, error=True),
        _row("fringes", 2, 0.01, 0.01),
    ]
    table = fringes_table(rows, "t")
    first, second = (dict(zip(table.columns, c, strict=True)) for c in table.cells)
    assert first["surfaces"] == 4 and first["failed"] == 1 and first["absolute height"] == "frame criterion"
    assert first["|abs| <= 2 u (%)"] == pytest.approx(100 / 3) and first["shape <= 2 u (%)"] == pytest.approx(100)
    assert first["|abs| max (µm)"] == pytest.approx(0.3) and first["acquisition (ms)"] == pytest.approx(500)
    assert second["absolute height"] == "two positions" and second["frames"] == 48 and second["failed"] == 0


@pytest.mark.slow
@pytest.mark.mitsuba
def test_markers_against_fringes_on_the_dimple(tmp_path, mono_variant):
    ctx = StudyContext(tmp_path, None, progress=False)
    res = fringes(ctx, FringeStudyConfig(seeds=(), camera=BINNED_CAMERA, families=("dimple",)))
    rows = {(r["method"], r["positions"]): r for r in res.summary["rows"]}
    assert set(rows) == {("markers", 1), ("markers", 2), ("fringes", 1), ("fringes", 2)} and not res.notes
    for r in rows.values():
        assert abs(r["absolute_um"]) <= 3 * r["u_abs_um"] and r["shape_um"] <= 3 * r["u_shape_um"], r
        frames = 1 if r["method"] == "markers" else 24
        assert r["frames"] == frames * r["positions"]
        assert r["acquisition_s"] == pytest.approx(frames * r["positions"] * r["exposure_s"], rel=0.05)
    for n in (1, 2):
        assert 0.9 <= rows[("fringes", n)]["depth_share"] <= 1.1 and rows[("markers", n)]["depth_share"] < 0.5
    assert rows[("fringes", 2)]["shape_um"] < 0.01
    assert np.isfinite(json.loads(json.dumps(res.tables[0].cells[0][5])))
    assert (tmp_path / "fringes.png").is_file()
