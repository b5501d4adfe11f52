"""`scopetwin run` end to end: simulate, render, calibrate, reconstruct, compare with the truth."""

import json

from sim.cli import main


def test_run_reconstructs_the_default_substrate(tmp_path, capsys):
    out = tmp_path / "report"
    code = main(["run", "--out", str(out), "--spp", "4", "--quiet", "--json", str(tmp_path / "run.json")])
    assert code == 0, capsys.readouterr().err
    summary = json.loads((tmp_path / "run.json").read_text())
    for name in (
        "report.md",
        "truth-heights.exr",
        "measurement.exr",
        "heights-calibrated.exr",
        "error.png",
        "calibrated-setup.toml",
        "focusmap.csv",
    ):
        assert (out / name).is_file(), name
    # 40 µm surface, noise on, 4 spp: both reconstructions well inside the seed's 0.414 µm ROI RMS
    for which in ("ideal", "calibrated"):
        rec = summary["reconstructions"][which]
        assert rec["roi_rms_um"] < 0.1, (which, rec["roi_rms_um"])
        assert rec["roi_shape_um"] < 0.05, (which, rec["roi_shape_um"])
    assert summary["markers"] > 500  # whole markers detected and indexed in the measurement image
    # the staging folder is gone: only the report folder and the JSON remain
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report", "run.json"]
