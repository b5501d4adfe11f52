"""Micro-Manager interop as a Micro-Manager user meets it: Channel presets per light, exposure presets as
text, the rig's pixel size and bit depth, and a 2 positions x 2 channels x 3 z MDA through pymmcore-plus."""

from __future__ import annotations

import json

import pytest

useq = pytest.importorskip("useq", reason="useq-schema (optional extra 'mm') is not installed")
pytest.importorskip("pymmcore_plus", reason="pymmcore-plus (optional extra 'mm') is not installed")

from scopetwin.instrument import open_rig  # noqa: E402
from scopetwin.instrument.micromanager import load_into_core, run_mda  # noqa: E402

RIG = """
[devices.x]
kind = "stage"
driver = "sim"
travel_mm = [0.0, 150.0]
max_velocity_mm_s = 50.0
position_mm = 10.0
[devices.y]
kind = "stage"
driver = "sim"
travel_mm = [0.0, 300.0]
max_velocity_mm_s = 100.0
position_mm = 10.0
[devices.focus]
kind = "focus"
driver = "sim"
position_um = 100.0
[devices.uv]
kind = "light"
driver = "sim"
max_current_ma = 500.0
[devices.deep_red]
kind = "light"
driver = "sim"
max_current_ma = 1000.0
[devices.cam]
kind = "camera"
driver = "sim"
sensor_shape = [32, 40]
pixel_size_um = 6.45
magnification = 10.0
renderer = { kind = "texture", lights = ["uv"] }
"""


@pytest.fixture
def rig_path(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text(RIG)
    return path


def test_every_light_is_a_channel_preset(rig_path):
    with open_rig(rig_path) as rig:
        core = load_into_core(rig)
        assert core.getChannelGroup() == "Channel"
        assert set(core.getAvailableConfigs("Channel")) == {"uv", "deep_red"}
        core.setConfig("Channel", "deep_red")
        assert core.getProperty("Light", "Lamp") == "deep_red"
        core.snapImage()
        dark = core.getImage()
        core.setConfig("Channel", "uv")
        core.snapImage()
        lit = core.getImage()
        assert lit.mean() > dark.mean() + 200  # the camera sees uv only: switching the preset switched the LED
        assert not rig.light("uv").is_on and not rig.light("deep_red").is_on  # lights only during exposure


def test_exposure_preset_as_text_pixel_size_and_bit_depth(rig_path):
    with open_rig(rig_path) as rig:
        core = load_into_core(rig)
        core.defineConfig("Channel", "uv", "Camera", "Exposure", "12.5")  # as a Micro-Manager config file has it
        core.setConfig("Channel", "uv")
        assert rig.camera().exposure_s == pytest.approx(0.0125) and core.getExposure() == pytest.approx(12.5)
        assert core.getPixelSizeUm() == pytest.approx(0.645)  # 6.45 um pixels behind a 10x objective
        assert core.getImageBitDepth() == 12


def test_mda_2_positions_2_channels_3_z(rig_path, tmp_path):
    sequence = {
        "stage_positions": [{"x": 10000.0, "y": 10000.0, "z": 100.0}, {"x": 10250.0, "y": 10050.0, "z": 120.0}],
        "channels": [{"config": "uv", "group": "Channel", "exposure": 10.0}, {"config": "deep_red", "exposure": 20.0}],
        "z_plan": {"range": 4.0, "step": 2.0},
        "axis_order": "pcz",
    }
    path = tmp_path / "seq.json"
    path.write_text(json.dumps(sequence))
    seen = []
    with open_rig(rig_path) as rig:
        result = run_mda(
            rig,
            path,
            on_frame=lambda img, event, meta: seen.append(
                (float(img.mean()), rig.stage("x").position_mm, rig.focus().position_um, rig.camera().exposure_s)
            ),
        )
        assert not any(lamp.is_on for lamp in rig.lights())
    assert result["planes"] == 12 and len(seen) == 12
    assert result["channels"] == ["deep_red", "uv"] and result["pixel_size_um"] == pytest.approx(0.645)
    assert result["bit_depth"] == 12
    for frame, (mean, x_mm, z_um, exposure_s) in zip(result["frames"], seen, strict=True):
        assert x_mm == pytest.approx(frame["x_um"] * 1e-3) and z_um == pytest.approx(frame["z_um"])
        assert exposure_s == pytest.approx(frame["exposure_ms"] * 1e-3)
        assert (mean > 200) == (frame["channel"] == "uv")  # lit in the uv channel only
    assert {f["z_um"] for f in result["frames"]} == {98.0, 100.0, 102.0, 118.0, 120.0, 122.0}


SEQUENCE_2X2X3 = {
    "stage_positions": [{"x": 10000.0, "y": 10000.0, "z": 100.0}, {"x": 10250.0, "y": 10050.0, "z": 120.0}],
    "channels": [{"config": "uv", "group": "Channel", "exposure": 10.0}, {"config": "deep_red", "exposure": 20.0}],
    "z_plan": {"range": 4.0, "step": 2.0},
    "axis_order": "pcz",
}


def test_mda_to_ome_tiff_has_pixel_size_channels_and_positions(rig_path, tmp_path):
    tifffile = pytest.importorskip("tifffile", reason="the OME-TIFF writer needs tifffile")
    out = tmp_path / "x.ome.tif"
    with open_rig(rig_path) as rig:
        assert run_mda(rig, SEQUENCE_2X2X3, output=str(out))["planes"] == 12
    files = sorted(tmp_path.rglob("*.ome.tif"))  # one file per position
    planes, names, positions = 0, set(), set()
    for f in files:
        with tifffile.TiffFile(f) as tif:
            planes += len(tif.pages)
            xml = tif.ome_metadata
        assert 'PhysicalSizeX="0.645"' in xml
        names |= {n for n in ("uv", "deep_red") if f'Name="{n}"' in xml}
        positions |= {p for p in ('PositionX="10000.0"', 'PositionX="10250.0"') if p in xml}
        assert 'ExposureTime="0.01"' in xml and 'ExposureTime="0.02"' in xml
    assert planes == 12 and names == {"uv", "deep_red"} and len(positions) == 2


def test_mda_to_ome_zarr_has_pixel_size_and_channel_names(rig_path, tmp_path):
    out = tmp_path / "x.ome.zarr"
    with open_rig(rig_path) as rig:
        assert run_mda(rig, SEQUENCE_2X2X3, output=str(out))["planes"] == 12
    root = json.loads((out / "zarr.json").read_text())["attributes"]["ome"]
    assert [w["path"] for w in root["plate"]["wells"]] == ["A/1", "A/2"]  # an NGFF plate, one well per position
    metas = [json.loads(p.read_text()) for p in sorted(out.glob("A/*/0/zarr.json"))]
    images = [m["attributes"]["ome"] for m in metas if "multiscales" in m.get("attributes", {}).get("ome", {})]
    assert len(images) == 2  # one image per stage position
    for ome in images:
        scale = ome["multiscales"][0]["datasets"][0]["coordinateTransformations"][0]["scale"]
        assert scale[-2:] == [0.645, 0.645]
        assert [c["label"] for c in ome["omero"]["channels"]] == ["uv", "deep_red"]
