"""`scopetwin run` end to end: simulate, render, calibrate, reconstruct, compare with the truth."""

import json

import numpy as np
import pytest

from scopetwin.sim.cli import main


@pytest.mark.slow
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
        u = rec["uncertainty"]
        assert 0 < u["absolute_um"] < 0.2 and 0 < u["shape_um"] < 0.2
    assert "u(absolute)" in (out / "report.md").read_text()
    assert "std_um" in (out / "focusmap.csv").read_text().splitlines()[0]
    assert summary["markers"] > 500  # whole markers detected and indexed in the measurement image
    # the staging folder is gone: only the report folder and the JSON remain
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report", "run.json"]


def test_run_rejects_a_surface_that_does_not_cover_the_substrate(tmp_path, capsys):
    from scopetwin.scenes.io import write_heightmap
    from scopetwin.scenes.surface import HeightMap

    small = tmp_path / "small.exr"
    write_heightmap(small, HeightMap(np.zeros((8, 8)), -5.0, 5.0, -5.0, 5.0))
    code = main(["run", "--out", str(tmp_path / "r"), "--quiet", "--surface", str(small)])
    assert code == 2
    assert "must cover it" in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def test_run_setups_give_the_calibration_scenes_the_users_camera(tmp_path):
    from scopetwin.sim.pipeline import run_setups

    toml = tmp_path / "mine.toml"
    toml.write_text('base = "thesis-1.10-deflectometry"\n[camera]\norigin = [0.0, -201.0, 120.0]\n')
    meas, target, mirror = run_setups(str(toml), None, {"render": {"spp": 2}})
    assert meas.camera.origin == (0.0, -201.0, 120.0)
    assert target.camera.origin == meas.camera.origin and mirror.camera.origin == meas.camera.origin
    assert target.scene == "target" and mirror.scene == "mirror" and mirror.render.spp == 2
    default = run_setups(None, None, {"render": {}})
    assert default[0].camera.origin == (0.0, -200.0, 120.0)


@pytest.mark.slow
def test_run_measures_a_users_surface_with_a_users_setup(tmp_path, capsys):
    from scopetwin.scenes.io import write_heightmap
    from scopetwin.scenes.setup import SubstrateSpec, SurfaceSpec
    from scopetwin.sim.surfaces import make_surface

    spec = SurfaceSpec(kind="psd", correlation_length=14.0, psd_exponent=4.0, broadband_rms_nm=2.0, seed=21)
    surf = tmp_path / "glass.exr"
    write_heightmap(surf, make_surface(spec, SubstrateSpec(surface=spec)))
    toml = tmp_path / "rig.toml"
    toml.write_text('base = "thesis-1.10-deflectometry"\n[render]\nspp = 4\n')
    out = tmp_path / "report"
    code = main(
        [
            "run",
            "--out",
            str(out),
            "--quiet",
            "--surface",
            str(surf),
            "--setup",
            str(toml),
            "--json",
            str(tmp_path / "r.json"),
        ]
    )
    assert code == 0, capsys.readouterr().err
    summary = json.loads((tmp_path / "r.json").read_text())
    assert summary["surface"]["kind"] == "file" and str(surf) in summary["surface"]["description"]
    rec = summary["reconstructions"]["ideal"]
    assert abs(rec["roi_absolute_um"]) <= 3 * rec["uncertainty"]["absolute_um"] + 0.01
    assert rec["roi_shape_um"] < 0.1
