"""`scopetwin run` end to end: simulate, render, calibrate, reconstruct, compare with the truth."""

import json

import numpy as np
import pytest

from scopetwin.cli import main


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
    # 40 µm surface, noise on, 4 spp: both reconstructions well inside the thesis's 0.414 µm ROI RMS
    for which in ("ideal", "calibrated"):
        rec = summary["reconstructions"][which]
        assert rec["roi_rms_um"] < 0.1, (which, rec["roi_rms_um"])
        assert rec["roi_shape_um"] < 0.05, (which, rec["roi_shape_um"])
        u = rec["uncertainty"]
        assert 0 < u["absolute_um"] < 0.2 and 0 < u["shape_um"] < 0.2
        assert rec["roi_coverage"] == pytest.approx(1.0, abs=0.02)  # the markers cover the §1.10 ROI
    assert "u(absolute)" in (out / "report.md").read_text() and "ROI covered" in (out / "report.md").read_text()
    import OpenEXR

    with OpenEXR.File(str(out / "heights-calibrated.exr")) as f:
        ch = f.channels()
        measured = np.asarray(ch["Z_measured"].pixels)
        z = np.asarray(ch["Z"].pixels)
    assert np.array_equal(np.isnan(z), measured == 0) and measured.mean() > 0.98
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


def test_the_worker_runs_its_calls_in_order_and_hands_back_their_errors():
    """The run's second thread (sim.pipeline._Worker): calls in the order given, results and exceptions through the
    futures, a daemon (an interrupted run does not wait for it)."""
    import threading
    import time

    from scopetwin.sim.pipeline import _Worker

    seen: list[str] = []

    def call(name: str, delay: float) -> str:
        time.sleep(delay)
        seen.append(name)
        return name.upper()

    def fail() -> None:
        raise ValueError("no such marker")

    worker = _Worker()
    first, broken, last = worker.submit(call, "a", 0.05), worker.submit(fail), worker.submit(call, "b", 0.0)
    assert last.result(timeout=5) == "B" and first.result(timeout=5) == "A"
    assert seen == ["a", "b"]
    with pytest.raises(ValueError, match="no such marker"):
        broken.result(timeout=5)
    assert all(t.daemon for t in threading.enumerate() if t.name == "scopetwin-run")
    worker.stop()


def test_a_stopped_worker_cancels_the_calls_it_has_not_started():
    import threading

    from scopetwin.sim.pipeline import _Worker

    gate = threading.Event()
    worker = _Worker()
    running = worker.submit(gate.wait, 5)
    queued = worker.submit(lambda: "never")
    for _ in range(250):
        if running.running():
            break
        threading.Event().wait(0.02)
    worker.stop()
    gate.set()
    assert running.result(timeout=5) is True
    for _ in range(100):
        if queued.cancelled():
            break
        threading.Event().wait(0.02)
    assert queued.cancelled()


@pytest.mark.slow
def test_the_two_threads_give_what_the_steps_give_one_after_the_other(tmp_path):
    """``_calibrate_and_reconstruct`` (calibration and calibrated reconstruction beside the ideal reconstruction and
    the truth reference) returns exactly what the steps return run one after the other."""
    from scopetwin.recon.reconstruct import single_thread_blas
    from scopetwin.recon.substrate import Substrate2D
    from scopetwin.sim import pipeline as p

    setup, target, mirror, heights = p._surface_and_setups(4, 3, None, None)
    sub = Substrate2D.from_setup(setup)
    img_t = p.render_with_noise(target, None, 4, 1)
    img_m = p.render_with_noise(mirror, None, 4, 2)
    image = p.render_with_noise(setup, heights, 4, 0)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    with single_thread_blas():
        cal, note, found, results, (exact, exact_err) = p._calibrate_and_reconstruct(
            image, setup, (target, img_t), (mirror, img_m), heights, tmp_path / "a", p._Steps(False)
        )
        cal1, note1 = p._calibrate(target, mirror, img_t, img_m, tmp_path / "b")
        found1, _, results1 = p._detect_and_reconstruct(
            image, {"ideal": setup, "calibrated": cal1 or setup}, tmp_path / "b", heights, sub
        )
        exact1, exact_err1 = p._truth_reference(setup, heights, sub)
    assert note == note1 and cal is not None and cal1 is not None and cal.to_json() == cal1.to_json()
    assert np.array_equal(found.ij, found1.ij) and np.array_equal(found.centroids, found1.centroids)
    for name in ("ideal", "calibrated"):
        assert results[name]["errors"] == results1[name]["errors"], name
        assert np.array_equal(results[name]["result"].surface.coef, results1[name]["result"].surface.coef), name
    assert exact_err == exact_err1 and np.array_equal(exact.surface.coef, exact1.surface.coef)
