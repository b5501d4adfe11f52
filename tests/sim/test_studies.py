"""scopetwin.sim.studies: tables (thesis | ours | ratio), missing capabilities, the study runner, one study task on
truth."""

from __future__ import annotations

import json

import numpy as np
import pytest

from scopetwin.cli import main as scopetwin_main
from scopetwin.sim.studies import runner
from scopetwin.sim.studies.context import StudyContext, StudyError, StudyResult, require
from scopetwin.sim.studies.runner import run_study
from scopetwin.sim.studies.tables import Row, Table, ratio, table_markdown
from scopetwin.sim.studies.tasks import calibration_view_task


def test_ratio_and_table_rows():
    assert ratio(2.0, 1.0) == pytest.approx(0.5)
    assert ratio((3.0, 4.0), (0.0, 10.0)) == pytest.approx(2.0)  # |ours| / |thesis| for vectors
    assert ratio(0.0, 1e-3) is None and ratio(None, 1.0) is None and ratio(1.0, float("nan")) is None
    md = table_markdown(Table("T", [Row("Δb", 0.004, 0.001, "mm"), Row("rms", 0.0, 1e-15, "mm")]))
    lines = md.splitlines()
    assert lines[2] == "| quantity | thesis | ours | ratio ours/thesis |"
    assert "| Δb [mm] | 0.004 | 0.001 | 0.25 |" in md
    assert "| rms [mm] | 0 | 1.000e-15 | — |" in md


def test_missing_capability_is_named_and_nothing_is_written(tmp_path, monkeypatch):
    with pytest.raises(StudyError, match=r"height reconstruction \(scopetwin\.recon\.nonexistent\)"):
        require("demo", {"scopetwin.recon.nonexistent": "height reconstruction"})

    def needs_missing(ctx):
        require("demo", {"scopetwin.calib.not_there_yet": "channel registration"})

    monkeypatch.setitem(runner.STUDIES, "demo", needs_missing)
    out = tmp_path / "demo"
    with pytest.raises(StudyError, match="channel registration"):
        run_study("demo", out, workers=0, progress=False)
    assert not out.exists() and not list(tmp_path.iterdir())


def test_cli_unknown_study_exit_2(tmp_path, capsys):
    assert scopetwin_main(["study", "nope", "--out", str(tmp_path / "x"), "--workers", "0"]) == 2
    assert "unknown study 'nope'" in capsys.readouterr().err


def _square(x: float) -> float:
    return x * x


def test_runner_writes_report_with_thesis_ours_ratio(tmp_path, monkeypatch):
    def demo(ctx: StudyContext) -> StudyResult:
        values = ctx.map(_square, [(1.0,), (3.0,)], "demo")
        return StudyResult(
            "Demo", "intro", [Table("Table X", [Row("a", 2.0, values[1], "µm")])], summary={"values": values}
        )

    monkeypatch.setitem(runner.STUDIES, "demo", demo)
    res = run_study("demo", tmp_path / "demo", workers=0, progress=False)
    report = (tmp_path / "demo" / "report.md").read_text()
    assert "| a [µm] | 2 | 9 | 4.5 |" in report
    data = json.loads((tmp_path / "demo" / "results.json").read_text())
    assert data["tables"][0]["rows"][0]["ratio"] == pytest.approx(4.5) and data["data"]["values"] == [1.0, 9.0]
    assert res["report"].endswith("report.md")
    # a rerun replaces the folder's contents
    run_study("demo", tmp_path / "demo", workers=0, progress=False)
    assert sorted(p.name for p in (tmp_path / "demo").iterdir()) == ["report.md", "results.json"]


@pytest.mark.mitsuba
def test_calibration_view_task_recovers_the_camera(tmp_path):
    """A generated 60° calibration view (noise-free): centroids and camera recovered against the truth."""
    ctx = StudyContext(tmp_path, None, progress=False)
    cfg = {
        "dataset": {
            "kind": "calibration",
            "setup": "thesis-2.8.1-perpendicular",
            "count": 1,
            "master_seed": 3,
            "spp": 16,
            "preview": False,
        },
        "setup": {"camera": {"pixels": [680, 512], "pixel_pitch": 0.0093}},
        "vary": {"view_angle_deg": {"fixed": 60.0}, "view_distance": {"fixed": 233.24}},
    }
    root = ctx.dataset(cfg, "views")
    row = calibration_view_task(str(root / "samples" / "000000"))
    assert row["markers"] == 99
    assert row["corrected_rms_px"] < 0.03
    assert row["corrected_rms_px"] <= row["raw_rms_px"] + 1e-3
    assert row["corrected_r_c_um"] < 100.0  # 233 mm away, 9.3 µm pixels
    assert np.isfinite(row["corrected_angle_urad"])


def test_coverage_table_counts_errors_within_2u():
    """The coverage columns are the share of surfaces whose |error| lies within 2 u (absolute and shape)."""
    from scopetwin.sim.studies.coverage import coverage_table

    def row(fam: str, a: float, ua: float, s: float, us: float) -> dict:
        return {
            "family": fam,
            "roi_absolute_um": a,
            "uncorrected_absolute_um": 2 * a,
            "u_abs_um": ua,
            "roi_shape_um": s,
            "u_shape_um": us,
        }

    rows = [row("gauss", 0.01, 0.01, 0.002, 0.002), row("gauss", -0.03, 0.01, 0.005, 0.002)]
    rows += [row("abc+broadband", 0.1, 0.2, 0.03, 0.02), row("abc+broadband", -0.25, 0.1, 0.02, 0.02)]
    rows += [{"family": "gauss", "error": "NotConvergedError: ..."}]  # a failed surface is counted, not measured
    t = coverage_table(rows, "T")
    by_family = {c[0]: c for c in t.cells}
    assert set(by_family) == {"gauss", "abc+broadband", "all"}
    cols = {name: k for k, name in enumerate(t.columns)}
    assert by_family["gauss"][cols["|abs| <= 2 u_abs (%)"]] == pytest.approx(50.0)  # 0.03 > 2 x 0.01
    assert by_family["gauss"][cols["shape <= 2 u_shape (%)"]] == pytest.approx(50.0)  # 0.005 > 2 x 0.002
    assert by_family["abc+broadband"][cols["|abs| <= 2 u_abs (%)"]] == pytest.approx(50.0)
    assert by_family["all"][cols["surfaces"]] == 4
    assert by_family["gauss"][cols["failed"]] == 1 and by_family["abc+broadband"][cols["failed"]] == 0
    assert by_family["all"][cols["|abs| max (µm)"]] == pytest.approx(0.25)
    assert by_family["all"][cols["|abs| max, fit (µm)"]] == pytest.approx(0.5)


@pytest.mark.slow
def test_coverage_study_end_to_end(tmp_path, monkeypatch):
    """One surface per family through the runner: the report's coverage agrees with the rows' errors and u."""
    from functools import partial

    from scopetwin.sim.studies.coverage import FAMILIES, coverage

    monkeypatch.setitem(runner.STUDIES, "coverage", partial(coverage, per_family=1))
    run_study("coverage", tmp_path / "cov", workers=0, progress=False)
    data = json.loads((tmp_path / "cov" / "results.json").read_text())
    rows = data["data"]["rows"]
    assert sorted(r["family"] for r in rows) == sorted(FAMILIES) and not any("error" in r for r in rows)
    within = np.mean([abs(r["roi_absolute_um"]) <= 2 * r["u_abs_um"] for r in rows]) * 100
    report = (tmp_path / "cov" / "report.md").read_text()
    assert f"Coverage of the reported uncertainty ({len(FAMILIES)} surfaces)" in report
    all_row = next(line for line in report.splitlines() if line.startswith("| all |"))
    assert f"| {within:g} |" in all_row or f"| {within:.3g} |" in all_row, all_row
    assert (tmp_path / "cov" / "coverage.png").stat().st_size > 0
