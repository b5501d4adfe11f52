"""scopetwin.sim.datasets, sample kind 'cmu' (thesis Part II): config checks before work, per-sample determinism,
and truth: calib.channels recovers each camera's known magnification, frame centre and tilt from the images.

The unit is the thesis-cmu preset with a 160 x 144 px sensor and a Siemens star scaled to a 0.075 mm frame
(116 px at m ~ 10) so that a four-channel sample renders in about a second.
"""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from scopetwin.cli import main as scopetwin_main
from scopetwin.sim.datasets.config import DatasetError, config_from_dict, load_config
from scopetwin.sim.datasets.plan import Plan
from scopetwin.sim.datasets.seeding import draw_parameters
from scopetwin.sim.datasets.store import SAMPLES, generate, verify

pytestmark = pytest.mark.mitsuba

TINY_CMU = """
[dataset]
kind = "cmu"
setup = "thesis-cmu"
count = {count}
master_seed = 51
spp = 8
noise = true
preview = false

[setup.camera]
width_px = 160
height_px = 144

[setup.target]
star_radius = 0.03
frame_side = 0.075
frame_line = 0.003

[vary]
target = {{ sweep = ["star", "cells"] }}
bow_scale = {{ uniform = [0.5, 1.5] }}
channel_offset_px = {{ uniform = [-8.0, 8.0] }}
channel_tilt_deg = {{ uniform = [-0.3, 0.3] }}
channel_defocus = {{ normal = [0.0, 0.01] }}
exposure_fill = {{ uniform = [0.5, 0.9] }}
"""
CHANNELS = ("blue", "green", "red", "nir")


def _write(folder: Path, count: int = 2) -> Path:
    path = folder / "tiny-cmu.toml"
    path.write_text(TINY_CMU.format(count=count))
    return path


def _data(**over: dict) -> dict:
    data = tomllib.loads(TINY_CMU.format(count=2))
    for k, v in over.items():
        data.setdefault(k, {}).update(v)
    return data


@pytest.mark.parametrize(
    ("over", "key"),
    [
        ({"cmu": {"colour": "red"}}, "cmu.colour"),
        ({"vary": {"channel_tilt_deg": {"uniform": [-50.0, 1.0]}}}, "vary.channel_tilt_deg"),
        ({"vary": {"target": {"choice": ["star", "dots-25"]}}}, "vary.target"),
        ({"vary": {"bow_range_um": {"fixed": 5.0}}}, "vary.bow_scale"),
        ({"vary": {"residual_rms_um": {"normal": [0.1, 0.05]}}}, "vary.residual_rms_um"),
        ({"vary": {"surface_range_um": {"fixed": 5.0}}}, "vary.surface_range_um"),
        ({"grin": {"width": 64}}, "grin"),
    ],
)
def test_bad_config_names_the_key(over, key):
    with pytest.raises(DatasetError, match=key.replace(".", r"\.")):
        config_from_dict(_data(**over), "cfg.toml")


@pytest.mark.parametrize(
    ("over", "key"),
    [
        ({"cmu": {"channels": ["green", "uv"]}}, "cmu.channels"),
        ({"cmu": {"window": [0, 0, 200, 100]}}, "cmu.window"),
        ({"setup": {"splitters": {"770DCXR": {"bow_range_um": -1.0}}}}, "bow_range_um"),
        ({"vary": {"channel_offset_px": {"uniform": [-40.0, 40.0]}}}, "vary.channel_offset_px"),
    ],
)
def test_impossible_sample_rejected_before_work(over, key):
    """Found when the plan checks every sample's unit and cameras, before anything is rendered."""
    with pytest.raises(DatasetError, match=key.replace(".", r"\.")):
        Plan.build(config_from_dict(_data(**over), "cfg.toml"))


def test_cli_rejects_bad_config_without_touching_the_output(tmp_path, capsys):
    cfg = _write(tmp_path)
    cfg.write_text(cfg.read_text().replace("[-8.0, 8.0]", "[-60.0, 60.0]"))
    out = tmp_path / "out"
    assert scopetwin_main(["dataset", "generate", str(cfg), "--out", str(out), "--workers", "0"]) == 2
    assert "vary.channel_offset_px" in capsys.readouterr().err
    assert not out.exists()


def test_per_member_draws_do_not_depend_on_the_other_members():
    cfg = config_from_dict(_data())
    full = draw_parameters(cfg, 3, {"channel": CHANNELS, "splitter": ["565DCXR", "770DCXR"]})
    part = draw_parameters(cfg, 3, {"channel": ["nir"], "splitter": ["770DCXR"]})
    assert part["channel_offset_px"]["nir"] == full["channel_offset_px"]["nir"]
    assert part["bow_scale"]["770DCXR"] == full["bow_scale"]["770DCXR"]
    assert full["channel_tilt_deg"]["red"] != full["channel_tilt_deg"]["nir"]  # independent per channel
    assert [Plan.build(cfg).parameters(i)["target"] for i in range(3)] == ["star", "cells", "star"]


def _files(root: Path, index: int) -> dict[str, bytes]:
    folder = root / SAMPLES / f"{index:06d}"
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.mark.slow
def test_determinism_and_truth(tmp_path):
    from scopetwin.calib.channels import measure_channel
    from scopetwin.scenes.io import read_heightmap, read_image

    cfg = load_config(_write(tmp_path, count=2))
    plan = Plan.build(cfg)
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    generate(plan, a, workers=0, progress=False)
    generate(plan, b, workers=0, progress=False)
    generate(plan, c, workers=0, indices=[1], progress=False)
    for i in range(2):
        assert _files(a, i) == _files(b, i), f"sample {i} differs between two runs"
    assert _files(a, 1) == _files(c, 1), "sample 1 differs when generated alone"
    rep = verify(a)
    assert rep["ok"] and rep["complete"] == 2

    folder = a / SAMPLES / "000000"
    names = set(_files(a, 0))
    assert {f"image_{ch}.exr" for ch in CHANNELS} | {"truth.json", "sample.json", "height_770DCXR.exr"} <= names
    truth = json.loads((folder / "truth.json").read_text())
    params = plan.parameters(0)
    assert truth["parameters"] == params and truth["target"]["name"] == "star"
    raw = b"".join(_files(a, 0).values())
    assert b"finished_utc" not in raw and b"hostname" not in raw

    # the splitter maps: the drawn bow factor times the preset's range (§5.1.1: 10.2 µm), stored as height maps
    plate = truth["plates"]["770DCXR"]
    assert plate["bow_range_um"] == pytest.approx(10.2 * params["bow_scale"]["770DCXR"], rel=1e-12)
    hm = read_heightmap(folder / plate["file"])
    assert np.ptp(hm.z) * 1e3 == pytest.approx(plate["bow_range_um"], rel=0.1)  # + the 0.1 µm RMS residual

    setup = truth["setup_json"]
    for ch in ("green", "nir"):  # sharp channels (blue/red spots are ~6 px: too blurred for a 116 px frame)
        t = truth["channels"][ch]
        assert t["camera"]["offset_px"] == params["channel_offset_px"][ch]
        assert t["camera"]["tilt_deg"] == params["channel_tilt_deg"][ch]
        img, attrs = read_image(folder / t["image"])
        assert img.shape == (144, 160) and img.dtype == np.float32
        assert json.loads(attrs["scopetwin_provenance"])["channel"] == ch and "scopetwin_setup" in attrs
        meas = measure_channel(
            img,
            setup["camera"]["pixel_um"],
            setup["target"]["frame_side"] * 1e3,
            setup["target"]["star_radius"] * 1e3,
            setup["target"]["spokes"],
        )
        # the renderer refracts at both plate faces: the images follow the exact tracer's truth.
        # Tolerances of calib.channels' own tests: 0.2 % in magnification, 0.5 px in position
        assert meas.magnification == pytest.approx(t["magnification"], rel=0.002)
        assert meas.frame.center == pytest.approx(t["frame_center_px"], abs=0.5)
        # tilt: the frame is 7x smaller than in calib's tests (0.02 deg there)
        assert meas.frame.angle_deg == pytest.approx(t["image_tilt_deg"], abs=0.1)

    cells = json.loads((a / SAMPLES / "000001" / "truth.json").read_text())
    assert cells["target"]["name"] == "cells" and cells["target"]["seed"] == cells["seeds"]["cells"]
    assert cells["seeds"]["cells"] != truth["seeds"]["cells"]
