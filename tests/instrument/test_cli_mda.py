"""``scopetwin rig rigs/sim-cmu.toml mda SEQ.json --camera cam_nir --out x.ome.tif`` with
2 positions x 2 channels x 3 z gives 12 planes with a real pixel size, the channel names and the positions asked for
(read back with tifffile and ome-types); and a signal mid-MDA keeps the planes written, readable, lights off."""

from __future__ import annotations

import json
import os
import re
import signal
import threading
import time

import pytest

pytest.importorskip("useq", reason="useq-schema (optional extra 'mm') is not installed")
pytest.importorskip("pymmcore_plus", reason="pymmcore-plus (optional extra 'mm') is not installed")
tifffile = pytest.importorskip("tifffile", reason="the OME-TIFF writer needs tifffile")
ome_types = pytest.importorskip("ome_types", reason="ome-types reads the OME metadata back")

from scopetwin.cli import main  # noqa: E402
from tests.instrument.cli_processes import ROOT, emulator, scopetwin, stop  # noqa: E402

POSITIONS = [(75000.0, 150000.0, 200.0), (75100.0, 150050.0, 210.0)]  # um, inside the sim-cmu stages' travel
SEQUENCE = {
    "stage_positions": [{"x": x, "y": y, "z": z} for x, y, z in POSITIONS],
    "channels": [
        {"config": "deep_red", "group": "Channel", "exposure": 10.0},
        {"config": "uv", "group": "Channel", "exposure": 20.0},
    ],
    "z_plan": {"range": 4.0, "step": 2.0},
    "axis_order": "pcz",
}


def _images_with_planes(files):
    """(file, OME image) for every image whose planes are stored in that file."""
    out = []
    for f in files:
        for image in ome_types.from_tiff(f).images:
            if image.pixels.planes:
                out.append((f, image))
    return out


@pytest.mark.filterwarnings("ignore::UserWarning")  # tifffile on ome-writers' multi-file OME ("index out of range")
def test_mda_acceptance_sim_cmu_cam_nir(tmp_path, capsys):
    seq = tmp_path / "SEQ.json"
    seq.write_text(json.dumps(SEQUENCE))
    out = tmp_path / "x.ome.tif"
    argv = ["rig", str(ROOT / "rigs" / "sim-cmu.toml"), "mda", str(seq), "--camera", "cam_nir", "--out", str(out)]
    assert main([*argv, "--json", str(tmp_path / "r.json")]) == 0
    result = json.loads((tmp_path / "r.json").read_text())
    assert result["planes"] == 12 and result["pixel_size_um"] == pytest.approx(0.645) and result["bit_depth"] == 12
    assert len(result["files"]) == 2  # one OME-TIFF per stage position
    assert "wrote 12 plane(s)" in capsys.readouterr().out

    images = _images_with_planes(result["files"])
    assert len(images) == 2
    planes, names, xy, z = 0, set(), set(), set()
    for f, image in images:
        px = image.pixels
        assert px.physical_size_x == pytest.approx(0.645) and px.physical_size_y == pytest.approx(0.645)
        assert px.physical_size_x_unit.value == "µm"  # 6.45 um pixels behind the 10x objective
        assert [c.name for c in px.channels] == ["deep_red", "uv"]
        names |= {c.name for c in px.channels}
        planes += len(px.planes)
        for p in px.planes:
            xy.add((round(p.position_x, 3), round(p.position_y, 3)))  # the stages' read-back positions (um)
            z.add(round(p.position_z, 3))
            assert p.exposure_time == pytest.approx(0.01 if p.the_c == 0 else 0.02)
        with tifffile.TiffFile(f) as tif:
            means = [page.asarray().mean() for page in tif.pages]
        assert len(means) == 6
        for k, mean in enumerate(means):  # XYZCT: page k holds z = k % 3 of channel k // 3
            assert (mean > 200) == (k // 3 == 0)  # cam_nir sees the deep_red LED, not the uv one
    assert planes == 12 and names == {"deep_red", "uv"}
    assert xy == {(x, y) for x, y, _ in POSITIONS}
    assert z == {198.0, 200.0, 202.0, 208.0, 210.0, 212.0}


def test_mda_refuses_bad_outputs_before_opening_the_rig(tmp_path, capsys):
    seq = tmp_path / "SEQ.json"
    seq.write_text(json.dumps(SEQUENCE))
    rig = str(ROOT / "rigs" / "sim-cmu.toml")
    assert main(["rig", rig, "mda", str(seq), "--out", str(tmp_path / "x.tif")]) == 2
    assert "--out" in capsys.readouterr().err
    (tmp_path / "y").mkdir()
    assert main(["rig", rig, "mda", str(seq), "--out", str(tmp_path / "y.ome.tif")]) == 2
    assert "exists already" in capsys.readouterr().err
    assert main(["rig", rig, "mda", str(tmp_path / "none.json"), "--out", str(tmp_path / "z.ome.zarr")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert not (tmp_path / "z.ome.zarr").exists()


def _planes_done(err):
    """The count of the progress bar (``mda:  3%|...| 17/600 ...``) so far."""
    return max((int(n) for n in re.findall(r"\| *(\d+)/\d+ ", "".join(err))), default=0)


def _collect(stream, sink):
    while chunk := os.read(stream.fileno(), 4096):
        sink.append(chunk.decode(errors="replace"))


@pytest.mark.filterwarnings("ignore::UserWarning")
def test_sigterm_mid_mda_keeps_the_planes_and_switches_the_board_off(tmp_path):
    """The emulated-hardware rig with its board in a ``scopetwin emulate`` process: SIGTERM after a few planes."""
    sequence = dict(SEQUENCE, channels=[{"config": "halogen", "exposure": 5.0}, {"config": "uv", "exposure": 5.0}])
    sequence["stage_positions"] = [{"x": 1000.0, "y": 1000.0, "z": 100.0}, {"x": 2000.0, "y": 1500.0, "z": 150.0}]
    sequence["time_plan"] = {"interval": 0.1, "loops": 50}  # 50 x 2 x 2 x 3 = 600 planes in >= 5 s: cut short
    sequence["axis_order"] = (
        "tpcz"  # SEQUENCE's "pcz" would leave the time plan out (12 planes, done before the signal)
    )
    seq = tmp_path / "SEQ.json"
    seq.write_text(json.dumps(sequence))
    log = tmp_path / "board.jsonl"
    with emulator("fpga-board", log=log) as (port, board):
        rig = tmp_path / "rig.toml"
        rig.write_text(
            (ROOT / "rigs" / "emulated-hardware.toml").read_text().replace('"emu://fpga-board"', f'"{port}"')
        )
        out = tmp_path / "x.ome.tif"
        proc = scopetwin("rig", str(rig), "mda", str(seq), "--out", str(out))
        err: list[str] = []
        reader = threading.Thread(target=_collect, args=(proc.stderr, err), daemon=True)
        reader.start()
        deadline = time.monotonic() + 90.0
        while _planes_done(err) < 5 and time.monotonic() < deadline:
            assert proc.poll() is None, "".join(err)[-3000:]
            time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        code = proc.wait(30)
        reader.join(5)
        stderr = "".join(err)
        assert code == 128 + signal.SIGTERM, stderr[-3000:]
        assert "Traceback" not in stderr and "SIGTERM" in stderr.splitlines()[-1]
        records = [json.loads(line) for line in log.read_text().splitlines()]
        assert any(r["state"]["lights_on"] for r in records)  # lights did switch during the MDA
        assert records[-1]["state"]["lights_on"] == []
        assert stop(board)[0] == 0
    files = sorted((tmp_path / "x").glob("*.ome.tif"))
    assert files  # the planes acquired so far, in files that read back
    pages = 0
    for f in files:
        with tifffile.TiffFile(f) as tif:
            pages += len(tif.pages)
            assert all(page.asarray().shape == (128, 128) for page in tif.pages)
    assert 5 <= pages < 600
