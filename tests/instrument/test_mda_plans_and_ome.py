"""Plans checked against the rig before anything moves (one line naming the event and the
limit, exit 2, nothing written), sizes in closed form (a 1e8-loop or 1e9 um plan in milliseconds), what the devices
reported recorded (never what was asked), and OME files that independent readers read right: ome-zarr-py's Reader
and ome-zarr-models at the store's root, tifffile and ome-types for OME-TIFF (one file per position, or one
multi-series file) - positions, pixel sizes, colours, wavelengths, objective and bit depth."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import pytest

useq = pytest.importorskip("useq", reason="useq-schema (optional extra 'mm') is not installed")
pytest.importorskip("pymmcore_plus", reason="pymmcore-plus (optional extra 'mm') is not installed")

from scopetwin.cli import main  # noqa: E402
from scopetwin.instrument import open_rig  # noqa: E402
from scopetwin.instrument.devices import Range  # noqa: E402
from scopetwin.instrument.errors import InstrumentError, RigError  # noqa: E402
from scopetwin.instrument.mdaplan import PlanLimits, plan_size  # noqa: E402
from scopetwin.instrument.micromanager import run_mda  # noqa: E402
from scopetwin.instrument.ome import wavelength_color  # noqa: E402

RIG = """
[rig]
name = "optics"
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
range_um = [0.0, 400.0]
position_um = 100.0
[devices.uv]
kind = "light"
driver = "sim"
max_current_ma = 500.0
wavelength_nm = 365.0
emission_nm = 455.0
[devices.deep_red]
kind = "light"
driver = "sim"
max_current_ma = 1000.0
wavelength_nm = 662.5
emission_nm = 785.0
[devices.cam]
kind = "camera"
driver = "sim"
sensor_shape = [32, 40]
pixel_size_um = 6.45
magnification = 10.0
numerical_aperture = 0.45
renderer = { kind = "texture", lights = ["uv"] }
"""
# 75.1 mm and 10.2 mm in µm are 75100.00000000001 and 10200.000000000002 in floating point: the files say 75100.0
POSITIONS = [(10000.0, 10000.0, 100.0), (75100.0, 10200.0, 120.0)]
SEQUENCE = {
    "stage_positions": [{"x": x, "y": y, "z": z} for x, y, z in POSITIONS],
    "channels": [{"config": "uv", "exposure": 10.0}, {"config": "deep_red", "exposure": 20.0}],
    "z_plan": {"range": 4.0, "step": 2.0},
    "axis_order": "pcz",
}
UV_BLUE = wavelength_color(455.0)  # each channel's colour: its emission band's
NIR_RED = wavelength_color(785.0)


@pytest.fixture
def rig_path(tmp_path):
    path = tmp_path / "rig.toml"
    path.write_text(RIG)
    return path


def test_colours_follow_the_wavelength():
    assert wavelength_color(455.0)[4:] == "FF" and wavelength_color(455.0)[2:4] < "80"  # blue
    assert wavelength_color(525.0)[2:4] == "FF" and wavelength_color(620.0)[:2] == "FF"  # green, red
    assert wavelength_color(785.0) == "FF0000" and wavelength_color(None) == "FFFFFF"  # infrared as red; unknown


@pytest.mark.parametrize(
    "change, message",
    [
        ({"stage_positions": [{"x": 1e12, "y": 10000.0, "z": 100.0}]}, "MDA event p=0: stage x: 1e+12 um is outside"),
        (
            {"channels": [{"config": "uv", "exposure": 1e12}]},
            "MDA event c=0 (channel 'uv'): exposure: 1e+12 ms is outside",
        ),
        ({"z_plan": {"range": 1e6, "step": 2.5e5}}, "MDA event p=0: focus z: -499900.0 um is outside [0.0, 400.0] um"),
        ({"channels": [{"config": "dapi"}]}, "no preset 'dapi' in group 'Channel'; presets: ['deep_red', 'uv']"),
        ({"grid_plan": {"rows": 1, "columns": 10**6}}, "MDA event p=0 (grid): stage x"),
    ],
)
def test_out_of_range_plans_are_refused_before_the_first_event(rig_path, tmp_path, capsys, change, message):
    seq = tmp_path / "SEQ.json"
    seq.write_text(json.dumps(SEQUENCE | change))
    out = tmp_path / "x.ome.tif"
    t0 = time.perf_counter()
    assert main(["rig", str(rig_path), "mda", str(seq), "--out", str(out)]) == 2
    assert time.perf_counter() - t0 < 30.0
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and message.replace("1e+12", "1000000000000.0").replace("-5e+08", "-500000000.0") in err[0]
    assert not out.exists() and not (tmp_path / "x").exists()  # nothing written


def test_nothing_moves_when_a_plan_is_refused(rig_path):
    with open_rig(rig_path) as rig:
        with pytest.raises(RigError, match="p=1: stage y"):
            run_mda(rig, SEQUENCE | {"stage_positions": [{"x": 20000.0, "y": 20000.0}, {"x": 0.0, "y": 1e9}]})
        assert rig.stage("x").position_mm == 10.0 and rig.stage("y").position_mm == 10.0  # not even position 0


def test_huge_plans_are_sized_in_milliseconds():
    limits = PlanLimits(None, None, None, Range(0.0, 1.0, "ms"), frame_shape=(1024, 1360), pixel_size_um=0.645)
    plan = useq.MDASequence(
        time_plan={"interval": 0.1, "loops": 10**8},
        z_plan={"range": 1e9, "step": 1.0},
        channels=[{"config": "uv", "exposure": 10.0}, {"config": "deep_red", "exposure": 20.0}],
        stage_positions=[(0.0, 0.0, 0.0)] * 3,
        grid_plan={"rows": 1000, "columns": 1000},
    )
    t0 = time.perf_counter()
    size = plan_size(plan, limits)
    assert time.perf_counter() - t0 < 0.05
    nz = 10**9 + 1
    assert size.sizes == {"t": 10**8, "p": 3, "g": 3 * 10**6, "c": 2, "z": nz}
    assert size.planes == 10**8 * 3 * 10**6 * 2 * nz
    assert size.bytes == size.planes * 1024 * 1360 * 2
    assert size.seconds == pytest.approx(10**8 * 3 * 10**6 * nz * 0.030, rel=1e-9)  # exposures beyond the 1e7 s span


def test_a_huge_plan_is_refused_for_its_size_at_once(rig_path, tmp_path, capsys):
    seq = tmp_path / "SEQ.json"
    seq.write_text(json.dumps(SEQUENCE | {"time_plan": {"interval": 0.1, "loops": 10**8}, "axis_order": "tpcz"}))
    t0 = time.perf_counter()
    assert main(["rig", str(rig_path), "mda", str(seq), "--out", str(tmp_path / "x.ome.zarr")]) == 2
    assert time.perf_counter() - t0 < 10.0
    assert "not enough free space" in capsys.readouterr().err
    assert not (tmp_path / "x.ome.zarr").exists()


def test_the_record_is_what_the_devices_reported(rig_path, monkeypatch):
    """A stage that lands 0.5 um short: the JSON and the OME planes carry where it is, not where it was sent."""
    with open_rig(rig_path) as rig:
        stage = rig.stage("x")
        real = type(stage)._do_get_position
        monkeypatch.setattr(type(stage), "_do_get_position", lambda self: real(self) - 0.0005)
        result = run_mda(rig, SEQUENCE)
    xs = sorted({f["x_um"] for f in result["frames"]})
    assert xs == [POSITIONS[0][0] - 0.5, POSITIONS[1][0] - 0.5]  # exactly: 0.5 um short, no conversion noise
    assert {f["channel"] for f in result["frames"]} == {"uv", "deep_red"}
    assert [f["exposure_ms"] for f in result["frames"][:6]] == [10.0] * 3 + [20.0] * 3
    assert result["estimate"]["planes"] == result["planes"] == 12


def test_a_device_fault_stops_the_run_and_keeps_no_plane_after_it(rig_path, tmp_path, monkeypatch):
    with open_rig(rig_path) as rig:
        focus = rig.focus()
        real = type(focus).move_absolute_um

        def flaky(self, um):
            if um > 110.0:
                raise InstrumentError("focus 'focus' did not answer")
            return real(self, um)

        monkeypatch.setattr(type(focus), "move_absolute_um", flaky)
        with pytest.raises(InstrumentError, match="focus 'focus' did not answer") as failed:
            run_mda(rig, SEQUENCE, output=str(tmp_path / "x.ome.zarr"))
        assert "Micro-Manager device 'Z': move" in failed.value.__notes__
        assert not any(lamp.is_on for lamp in rig.lights())
    kept = np.asarray(zarr_array(tmp_path / "x.ome.zarr" / "A" / "1" / "0" / "0"))
    assert all(kept[c, z].max() > 0 for c in range(2) for z in range(3))  # position 0: its 6 planes, then the fault
    assert not (tmp_path / "x.ome.zarr" / "A" / "2").exists()  # nothing at z = 118: position 1 has no well


def zarr_array(path):
    zarr = pytest.importorskip("zarr")
    return zarr.open_array(str(path), mode="r")


def _acquire(rig_path, out, **options):
    with open_rig(rig_path) as rig:
        result = run_mda(rig, SEQUENCE, output=str(out), **options)
    assert result["planes"] == 12
    return result


def test_ome_zarr_read_by_ome_zarr_py_and_ome_zarr_models(rig_path, tmp_path):
    pytest.importorskip("ome_zarr", reason="ome-zarr (ome-zarr-py) reads the store back")
    models = pytest.importorskip("ome_zarr_models", reason="ome-zarr-models validates the store")
    import zarr
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    out = tmp_path / "x.ome.zarr"
    result = _acquire(rig_path, out)
    first = {p: next(f for f in result["frames"] if f["index"]["p"] == p) for p in (0, 1)}
    nodes = list(Reader(parse_url(str(out)))())  # opened at the root: the NGFF plate, one well per position
    plate = nodes[0]
    assert plate.data[0].shape == (2, 3, 32, 80)  # c, z, y and both positions side by side
    assert plate.metadata["channel_names"] == ["uv", "deep_red"]
    assert plate.metadata["contrast_limits"] == [[0.0, 4095.0], [0.0, 4095.0]]  # 12 bit
    colours = [tuple(round(255 * v) for v in cmap[1]) for cmap in plate.metadata["colormap"]]
    assert colours == [tuple(int(c[i : i + 2], 16) for i in (0, 2, 4)) for c in (UV_BLUE, NIR_RED)]
    group = models.open_ome_zarr(zarr.open_group(str(out), mode="r"))
    assert type(group).__name__ == "HCS" and [w.path for w in group.attributes.ome.plate.wells] == ["A/1", "A/2"]
    from ome_zarr_models.v05.image import Image

    assert len(list(group.well_groups)) == 2
    for p in (0, 1):
        image = Image.from_zarr(zarr.open_group(str(out / well_path(p)), mode="r"))  # validated as an NGFF image
        (dataset,) = image.attributes.ome.multiscales[0].datasets
        scale, translation = dataset.coordinateTransformations
        assert list(scale.scale) == pytest.approx([1.0, 2.0, 0.645, 0.645])  # c, z (um), y, x (um)
        assert list(translation.translation) == pytest.approx(
            [0.0, first[p]["z_um"], first[p]["y_um"], first[p]["x_um"]]
        )  # where the stage and the focus reported the first plane of the position
        assert [a.unit for a in image.attributes.ome.multiscales[0].axes][1:] == ["micrometer"] * 3
        data = np.asarray(zarr.open_array(str(out / well_path(p) / "0"), mode="r"))
        assert data.shape == (2, 3, 32, 40) and data[0].mean() > 200 > data[1].mean()  # lit in uv only
        attrs = json.loads((out / well_path(p) / "zarr.json").read_text())["attributes"]["scopetwin"]
        assert attrs["significant_bits"] == 12 and attrs["objective"] == {
            "magnification": 10.0,
            "numerical_aperture": 0.45,
        }


def well_path(p):
    return f"A/{p + 1}/0"


def _check_ome_image(image, frames):
    px = image.pixels
    assert px.significant_bits == 12 and px.physical_size_x == pytest.approx(0.645)
    assert [c.name for c in px.channels] == ["uv", "deep_red"]
    assert [c.color.as_hex(format="long").upper().lstrip("#") for c in px.channels] == [UV_BLUE, NIR_RED]
    assert [(c.excitation_wavelength, c.emission_wavelength) for c in px.channels] == [(365.0, 455.0), (662.5, 785.0)]
    planes = {(pl.the_c, pl.the_z): pl for pl in px.planes}
    assert len(planes) == 6
    for frame in frames:
        plane = planes[(frame["index"]["c"], frame["index"]["z"])]
        assert (plane.position_x, plane.position_y, plane.position_z) == pytest.approx(
            (frame["x_um"], frame["y_um"], frame["z_um"])
        )
        assert (plane.position_x, plane.position_y) in {xyz[:2] for xyz in POSITIONS}  # exact: no conversion noise
        units = {plane.position_x_unit.value, plane.position_y_unit.value, plane.position_z_unit.value}
        assert units == {"µm"}
        assert plane.exposure_time == pytest.approx(frame["exposure_ms"] * 1e-3)


@pytest.mark.parametrize("single_file", [False, True])
def test_ome_tiff_read_by_tifffile_and_ome_types(rig_path, tmp_path, single_file):
    tifffile = pytest.importorskip("tifffile")
    ome_types = pytest.importorskip("ome_types")
    out = tmp_path / "x.ome.tif"
    result = _acquire(rig_path, out, single_file=single_file)
    files = result["files"]
    assert len(files) == (1 if single_file else 2)
    by_position = {p: [f for f in result["frames"] if f["index"]["p"] == p] for p in (0, 1)}
    seen = 0
    for path in files:
        ome = ome_types.from_tiff(path)
        (objective,) = ome.instruments[0].objectives
        assert (objective.nominal_magnification, objective.lens_na) == (10.0, 0.45)
        images = [im for im in ome.images if im.pixels.planes]
        with tifffile.TiffFile(path) as tif:
            series = [s for s in tif.series if s.shape]
            arrays = [s.asarray() for s in series]
        for image in images:
            p = seen if single_file else files.index(path)
            _check_ome_image(image, by_position[p])
            seen += 1
        for array in arrays[: len(images)]:
            assert array.shape == (2, 3, 32, 40) and array[0].mean() > 200 > array[1].mean()  # C, Z, Y, X
    assert seen == 2


@pytest.mark.parametrize("single_file", [False, True])
def test_ome_tiff_positions_carry_their_unit_and_no_float_noise(tmp_path, single_file):
    """The OME-XML as tifffile reads it: every plane's PositionX/Y/Z with its unit µm, values rounded to the pm."""
    import xml.etree.ElementTree as ET

    import tifffile

    from scopetwin.instrument.ome import AcquisitionInfo, ChannelInfo, Layout, OmeOutput

    layout = Layout(axes=("p", "c", "z"), sizes={"p": 2, "c": 1, "z": 1}, positions=((0, 0), (1, 0)), names=("a", "b"))
    info = AcquisitionInfo(shape=(8, 6), dtype="uint16", bit_depth=12, pixel_size_um=0.5, channels=(ChannelInfo("BF"),))
    out = OmeOutput(tmp_path / "x.ome.tif", layout, info, single_file=single_file)
    noisy = [(75100 * 1e-3 * 1e3, 10200 * 1e-3 * 1e3, 120.1), (1.0, 2.0, 3.0)]  # um -> mm -> um, as stages do
    assert noisy[0][:2] == (75100.00000000001, 10200.000000000002)
    for p, (x, y, z) in enumerate(noisy):
        reported = {"exposure_ms": 5.0, "x_um": x, "y_um": y, "z_um": z}
        out.append(np.full((8, 6), 100, np.uint16), {"p": p, "c": 0, "z": 0}, reported)
    files = out.close()
    assert len(files) == (1 if single_file else 2)
    planes = []
    for path in files:
        with tifffile.TiffFile(path) as tif:
            root = ET.fromstring(tif.ome_metadata)
        planes += [el.attrib for el in root.iter() if el.tag.endswith("}Plane")]
    assert len(planes) == 2
    for attrib in planes:
        assert attrib["PositionXUnit"] == attrib["PositionYUnit"] == attrib["PositionZUnit"] == "µm", attrib
    assert sorted((a["PositionX"], a["PositionY"], a["PositionZ"]) for a in planes) == [
        ("1.0", "2.0", "3.0"),
        ("75100.0", "10200.0", "120.1"),
    ]


def test_a_plan_of_2_63_loops_is_sized_not_overflowed():
    """useq's own duration (a timedelta product) overflows for such a loop count; the size is computed in float."""
    limits = PlanLimits(None, None, None, Range(0.0, 1.0, "ms"), frame_shape=(8, 8), pixel_size_um=1.0)
    size = plan_size(useq.MDASequence(time_plan={"interval": 1.0, "loops": 2**63 - 1}), limits)
    assert size.sizes["t"] == 2**63 - 1 and size.seconds == pytest.approx(float(2**63 - 2))


def test_an_ome_tiff_run_stopped_before_a_position_keeps_the_positions_it_reached(tmp_path):
    """SIGTERM after the first position's planes (CI found it: ``tiffcomment`` on the second position's file, which had
    no page, raised IndexError during the clean-up): the file of the position reached is complete and read back with
    its OME-XML; the pageless file of the position never reached is gone."""
    import tifffile

    from scopetwin.instrument.ome import AcquisitionInfo, ChannelInfo, Layout, OmeOutput

    layout = Layout(axes=("p", "c", "z"), sizes={"p": 2, "c": 1, "z": 2}, positions=((0, 0), (1, 0)), names=("a", "b"))
    info = AcquisitionInfo(shape=(8, 6), dtype="uint16", bit_depth=12, pixel_size_um=0.5, channels=(ChannelInfo("BF"),))
    out = OmeOutput(tmp_path / "x.ome.tif", layout, info)
    for z in range(2):
        plane = np.full((8, 6), 100 + z, np.uint16)
        out.append(plane, {"p": 0, "c": 0, "z": z}, {"exposure_ms": 5.0, "x_um": 1.0, "y_um": 2.0, "z_um": float(z)})
    files = out.close()
    assert len(files) == 1 and Path(files[0]).exists(), files
    with tifffile.TiffFile(files[0]) as tif:
        assert len(tif.pages) == 2 and tif.ome_metadata and 'SignificantBits="12"' in tif.ome_metadata
        assert tif.asarray().max() == 101
    assert sorted(p.name for p in Path(files[0]).parent.iterdir()) == [Path(files[0]).name]
