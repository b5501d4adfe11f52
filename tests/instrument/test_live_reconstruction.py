"""``scopetwin rig RIG live``: the simulated deflectometry rig's frames reconstructed as they come (thesis §1.4, §1.5).

The rig renders the §1.10 setup once (2 spp here) over a -40 µm bow (a dish touching the holding frame at the
substrate's corners, so the frame criterion holds: its maxima over the frame regions are 0) and each frame adds
its own sensor noise. The maps and the manifest are checked against that true surface.
"""

from __future__ import annotations

import json
import multiprocessing
import signal
import time
from pathlib import Path

import numpy as np
import psutil
import pytest

from scopetwin.cli import main
from scopetwin.instrument.live_reconstruction import live_reconstruction, rig_setup
from scopetwin.instrument.rig import open_rig
from scopetwin.recon.stream import WORKER_NAME
from scopetwin.recon.substrate import Substrate2D
from tests.instrument.cli_processes import ROOT, scopetwin, stop

pytestmark = pytest.mark.mitsuba

BOW_UM = -40.0
#: Error of a frame's absolute height (ROI mean) against the truth's, µm: the posterior-corrected frame criterion
#: gives 0.01-0.05 µm on these frames (u = 0.04-0.09 µm).
ABSOLUTE_TOL_UM = 0.2
#: RMS over the ROI's measured nodes of a written map minus the truth (mean removed), µm.
SHAPE_TOL_UM = 0.3


def _rig(tmp_path: Path) -> Path:
    """The shipped simulated deflectometry rig at 2 spp over the -40 µm bow."""
    text = (ROOT / "rigs" / "sim-deflectometry.toml").read_text()
    assert "spp = 4" in text and "bow_um = 40.0" in text
    path = tmp_path / "rig.toml"
    path.write_text(text.replace("spp = 4", "spp = 2").replace("bow_um = 40.0", f"bow_um = {BOW_UM}"))
    return path


def _truth():
    from scopetwin.instrument.simulated.renderers import DeflectometryRenderer

    return DeflectometryRenderer("thesis-1.10-deflectometry", bow_um=BOW_UM).heights


def _roi_points(step_mm: float = 0.2) -> tuple[np.ndarray, np.ndarray, Substrate2D]:
    """A grid over the substrate's ROI (the full width, |y| < ROI length / 2), as :func:`sim.pipeline.roi_errors`."""
    from scopetwin.scenes.setup import load_setup

    sub = Substrate2D.from_setup(load_setup("thesis-1.10-deflectometry"))
    xs = np.arange(-0.5 * sub.size_x, 0.5 * sub.size_x + 1e-9, step_mm)
    ys = np.arange(-0.5 * sub.roi_length + step_mm, 0.5 * sub.roi_length, step_mm)
    xx, yy = np.meshgrid(xs, ys)
    return xx, yy, sub


def _read_map(path: Path) -> tuple[np.ndarray, ...]:
    """A written map's channels Z, Z_std, Z_measured (mm; NaN in Z where no marker measures) and its nodes' x, y."""
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        channels = f.channels()
        extents = [float(f.header()[k]) for k in ("x_min_mm", "x_max_mm", "y_min_mm", "y_max_mm")]
        z, std, measured = (np.asarray(channels[c].pixels, dtype=float) for c in ("Z", "Z_std", "Z_measured"))
    ny, nx = z.shape
    xs, ys = np.linspace(*extents[:2], nx), np.linspace(*extents[2:], ny)
    xx, yy = np.meshgrid(xs, ys)
    return z, std, measured > 0.5, xx, yy


def _workers() -> list[multiprocessing.process.BaseProcess]:
    return [p for p in multiprocessing.active_children() if p.name == WORKER_NAME]


def test_live_maps_and_manifest_recover_the_rigs_surface(tmp_path):
    out, js = tmp_path / "live", tmp_path / "live.json"
    argv = ["rig", str(_rig(tmp_path)), "live", str(out), "--frames", "3", "--every", "2", "--json", str(js), "-q"]
    assert main(argv) == 0
    summary = json.loads(js.read_text())
    manifest = json.loads((out / "manifest.json").read_text())
    frames = manifest["frames"]
    assert manifest["complete"] and manifest["error"] is None
    assert summary["frames"] == summary["reconstructed"] == len(frames) == 3 and summary["failed"] == 0
    assert [f["path"] for f in frames] == ["heights_000000.exr", None, "heights_000002.exr"]  # --every 2
    assert summary["maps_written"] == 2 and sorted(p.name for p in out.glob("*.exr")) == [
        "heights_000000.exr",
        "heights_000002.exr",
    ]
    truth = _truth()
    xx, yy, sub = _roi_points()
    from scopetwin.recon.config import ReconstructionConfig

    gx, gy = sub.roi_grid(ReconstructionConfig.realtime().grid_step)  # the ROI grid the absolute height is the mean of
    true_um = 1e3 * float(truth.height(gx, gy).mean())
    times = [f["time"] for f in frames]
    assert times == sorted(times) and all(f["seconds"] > 0 and f["fps"] > 0 for f in frames)
    for f in frames:
        err = f["absolute_height_um"] - true_um
        assert abs(err) <= ABSOLUTE_TOL_UM, (f, true_um)
        assert abs(err) <= 4.0 * f["absolute_um"] + 0.01, (f, true_um)  # the uncertainty covers the error
        assert 0 < f["shape_um"] < SHAPE_TOL_UM
    assert summary["absolute_height_um"] == frames[-1]["absolute_height_um"]
    for f in frames:
        if f["path"] is None:
            continue
        z, std, measured, nx, ny = _read_map(out / f["path"])
        roi = measured & (np.abs(ny) < 0.5 * sub.roi_length)
        assert roi.sum() > 0.85 * (np.abs(ny) < 0.5 * sub.roi_length).sum()  # the ROI is measured
        assert np.array_equal(np.isfinite(z), measured)  # Z is NaN exactly where no marker measures
        diff = 1e3 * (z[roi] - truth.height(nx[roi], ny[roi]))
        assert abs(diff.mean() - (f["absolute_height_um"] - true_um)) < 0.1  # the map is the listed surface
        assert np.sqrt(np.mean((diff - diff.mean()) ** 2)) < SHAPE_TOL_UM
        assert np.all(std[roi] > 0) and np.median(1e3 * std[roi]) < 1.0
    assert not _workers()


def test_a_failed_frame_is_listed_and_an_interrupt_leaves_the_lights_off(tmp_path, monkeypatch):
    """Frame 1 is blank (no markers): listed with its one-line error, frame 2 reconstructed after it; a
    KeyboardInterrupt after frame 2 switches the light off, ends the worker and keeps the two maps listed."""
    out = tmp_path / "live"
    with open_rig(_rig(tmp_path)) as rig:
        cam = rig.camera(None)
        grab = cam.grab
        grabs = [0]

        def blank_second(*args, **kwargs):  # the exposure is given: the live frames are the only grabs
            frame = grab(*args, **kwargs)
            grabs[0] += 1
            return np.full_like(frame, float(np.median(frame))) if grabs[0] == 2 else frame

        setup = rig_setup(rig)
        monkeypatch.setattr(cam, "grab", blank_second)

        def stop_after_third(entry):
            if entry["index"] == 2:
                assert rig.light(None).is_on
                raise KeyboardInterrupt

        with pytest.raises(KeyboardInterrupt):
            live_reconstruction(rig, out, setup, n_frames=10, exposure_s=0.03, on_frame=stop_after_third)
        assert not rig.world.any_light_on()
        assert not _workers()
    manifest = json.loads((out / "manifest.json").read_text())
    frames = manifest["frames"]
    assert len(frames) == 3 and not manifest["complete"] and manifest["error"] == "KeyboardInterrupt: SIGINT"
    assert frames[1]["path"] is None and frames[1]["error"].startswith("MarkerError: ")
    assert "\n" not in frames[1]["error"]
    assert [f["path"] for f in frames] == ["heights_000000.exr", None, "heights_000002.exr"]
    for f in (frames[0], frames[2]):
        assert _read_map(out / f["path"])[0].shape == (288, 128)


def _listed(manifest: Path) -> list[dict]:
    try:
        return json.loads(manifest.read_text())["frames"]
    except (OSError, ValueError, KeyError):
        return []


@pytest.mark.parametrize("sig", [signal.SIGTERM, pytest.param(signal.SIGINT, marks=pytest.mark.slow)])
def test_a_signal_mid_stream_ends_the_command_cleanly(tmp_path, sig):
    out = tmp_path / "live"
    proc = scopetwin("rig", str(_rig(tmp_path)), "live", str(out))  # no limit: live until interrupted
    deadline = time.monotonic() + 90.0
    while len(_listed(out / "manifest.json")) < 2 and time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()[1]
        time.sleep(0.05)
    children = psutil.Process(proc.pid).children(recursive=True)
    assert children, "no marker worker process"
    code, _, stderr = stop(proc, sig)
    lines = [line for line in stderr.splitlines() if line.strip()]
    assert code == 128 + sig, stderr[-3000:]
    assert "Traceback" not in stderr and len(lines) == 1 and signal.Signals(sig).name in lines[0], stderr
    gone, alive = psutil.wait_procs(children, timeout=5.0)
    assert not alive, alive  # the worker ended with the command
    manifest = json.loads((out / "manifest.json").read_text())
    assert not manifest["complete"] and signal.Signals(sig).name in manifest["error"]
    listed = [f["path"] for f in manifest["frames"]]
    assert len(listed) >= 2 and sorted(p.name for p in out.glob("*.exr")) == sorted(listed)
    for name in listed:
        z, _, measured, _, _ = _read_map(out / name)
        assert measured.mean() > 0.5 and np.isfinite(z[measured]).all()
    assert not list(out.glob(".*.part*"))


def test_bad_input_is_refused_before_the_light_goes_on(tmp_path, capsys):
    out = tmp_path / "live"
    assert main(["rig", "sim-cmu", "live", str(out), "--frames", "2"]) == 2
    err = capsys.readouterr().err
    assert "not a deflectometry camera" in err and "Traceback" not in err
    assert not (out / "manifest.json").exists()
    with pytest.raises(SystemExit) as exit_:
        main(["rig", str(_rig(tmp_path)), "live", str(out), "--frames", "0"])
    assert exit_.value.code == 2
    assert main(["rig", str(_rig(tmp_path)), "live", str(out), "--setup", "thesis-2.8.1-perpendicular"]) == 2
    assert "not a deflectometry setup" in capsys.readouterr().err
    assert not (out / "manifest.json").exists()
