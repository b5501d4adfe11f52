"""An MDA that a device fault stops, or that has nothing to do: no file without a plane (single OME-TIFF, OME-Zarr,
per-position OME-TIFFs and their folder), no file referring to a removed one, a rerun not blocked, and the line
saying how many of the plan's planes are on disk. The files kept declare only the planes acquired: tifffile,
ome-types, zarr, ome-zarr-py and ome-zarr-models read back every plane at its plan index and no other (the main
image of each position, the rest in extra images). Faults from the simulated devices' injection."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import pytest

pytest.importorskip("useq", reason="useq-schema (optional extra 'mm') is not installed")
pytest.importorskip("pymmcore_plus", reason="pymmcore-plus (optional extra 'mm') is not installed")
tifffile = pytest.importorskip("tifffile")
ome_types = pytest.importorskip("ome_types")
zarr = pytest.importorskip("zarr")

from scopetwin.cli import main  # noqa: E402
from scopetwin.instrument import open_rig  # noqa: E402
from scopetwin.instrument.errors import DeviceLost, DisconnectedError, RigError  # noqa: E402
from scopetwin.instrument.micromanager import run_mda  # noqa: E402
from tests.instrument.test_micromanager import RIG, SEQUENCE_2X2X3  # noqa: E402


@pytest.fixture
def rig_path(tmp_path: Path) -> Path:
    path = tmp_path / "rig.toml"
    path.write_text(RIG)
    return path


def _faulted(rig_path: Path, out: Path, after: int, *, single_file: bool = False) -> None:
    with open_rig(rig_path) as rig:
        rig["focus"].inject_fault("disconnect", after=after)
        with pytest.raises(DisconnectedError):
            run_mda(rig, SEQUENCE_2X2X3, output=str(out), single_file=single_file)


def _written(tmp_path: Path) -> list[str]:
    return sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*") if p.name != "rig.toml")


@pytest.mark.parametrize("name", ["x.ome.tif", "x.ome.zarr"])
@pytest.mark.parametrize("single_file", [False, True])
def test_a_fault_before_the_first_plane_leaves_nothing(rig_path, tmp_path, name, single_file):
    out = tmp_path / name
    _faulted(rig_path, out, after=1, single_file=single_file)
    assert _written(tmp_path) == []  # no 16-byte TIFF, no empty store, no empty folder
    with open_rig(rig_path) as rig:  # and the rerun is not blocked
        assert run_mda(rig, SEQUENCE_2X2X3, output=str(out), single_file=single_file)["planes"] == 12


def test_kept_position_files_refer_to_no_removed_file(rig_path, tmp_path):
    _faulted(rig_path, tmp_path / "x.ome.tif", after=8)
    files = sorted((tmp_path / "x").glob("*.ome.tif"))
    assert [f.name for f in files] == ["x_p000.ome.tif"]  # the second position was never reached
    with tifffile.TiffFile(files[0]) as tif:
        assert len(tif.pages) > 0
        xml = tif.ome_metadata
    assert "x_p001" not in xml  # its image (in the companion layout) went with it


def test_a_single_file_after_a_fault_holds_the_planes_it_says(rig_path, tmp_path):
    out = tmp_path / "x.ome.tif"
    _faulted(rig_path, out, after=14, single_file=True)
    with tifffile.TiffFile(out) as tif:
        assert 0 < len(tif.pages) < 12


def test_a_plan_without_events_is_one_error_before_work(rig_path, tmp_path, capsys):
    seq = tmp_path / "empty.json"
    seq.write_text("{}")
    with open_rig(rig_path) as rig, pytest.raises(RigError, match="no events"):
        run_mda(rig, seq, output=str(tmp_path / "lib.ome.tif"))
    out, report = tmp_path / "x.ome.tif", tmp_path / "r.json"
    code = main(["rig", str(rig_path), "mda", str(seq), "--out", str(out), "--json", str(report), "-q"])
    captured = capsys.readouterr()
    assert code == 2 and captured.err.count("\n") == 1 and "no events" in captured.err, captured.err
    assert "wrote" not in captured.out
    assert _written(tmp_path) == ["empty.json"]  # no OME file, no JSON naming one


def test_the_line_after_a_fault_says_how_many_planes_are_on_disk(rig_path, tmp_path, capsys, monkeypatch):
    import scopetwin.cli.rig as cli_rig

    real = cli_rig.open_rig

    @contextlib.contextmanager
    def faulty(path):  # the focus drive stops answering at its 6th operation, as a lost device does
        with real(path) as rig:
            focus, calls = rig["focus"], []
            original = focus.move_absolute_um

            def move(um, *a, **k):
                calls.append(um)
                if len(calls) > 5:
                    raise DeviceLost("focus 'focus' stopped answering", [focus.name])
                return original(um, *a, **k)

            monkeypatch.setattr(focus, "move_absolute_um", move)
            yield rig

    monkeypatch.setattr(cli_rig, "open_rig", faulty)
    seq = tmp_path / "seq.json"
    seq.write_text(json.dumps(SEQUENCE_2X2X3))
    out = tmp_path / "x.ome.zarr"
    code = main(["rig", str(rig_path), "mda", str(seq), "--out", str(out), "-q"])
    err = capsys.readouterr().err
    assert code == 3, err
    line = err.strip().splitlines()[-1]
    assert "stopped answering" in line and f"of 12 plane(s) kept in {out}" in line, line
    assert "never acquired are not in them" in line


# --- a stopped run's files declare the planes they hold -------------------------------------------------------------

PLAN_AXES = "tcz"


def test_boxes_of_a_first_part_of_the_plan():
    from scopetwin.instrument.ome_pieces import boxes

    assert boxes((2, 3), 0, 6) == [((0, 0), (2, 3))]
    assert boxes((2, 3), 0, 4) == [((0, 0), (1, 3)), ((1, 0), (1, 1))]  # the whole first row, then one plane
    assert boxes((3, 2, 3), 0, 10) == [((0, 0, 0), (1, 2, 3)), ((1, 0, 0), (1, 1, 3)), ((1, 1, 0), (1, 1, 1))]
    assert boxes((2, 3), 2, 5) == [((0, 2), (1, 1)), ((1, 0), (1, 2))]
    assert boxes((), 0, 1) == [((), ())] and boxes((2, 3), 3, 3) == []


def _stopped_output(path, axes, sizes, positions, stop, *, single_file=False):
    """An OmeOutput of a plan of ``axes`` (with ``p`` for ``positions`` > 0) stopped after ``stop`` planes; each
    plane holds its acquisition number + 1. Returns the files, ``{(position, plan index): value}`` and the layout."""
    import itertools

    import numpy as np

    from scopetwin.instrument.ome import AcquisitionInfo, ChannelInfo, Layout, OmeOutput

    sizes = dict(sizes, **({"p": positions} if positions else {}))
    layout = Layout(
        axes=axes,
        sizes=sizes,
        positions=tuple((p, 0) for p in range(positions)),
        names=tuple(f"pos{p}" for p in range(positions)),
        z_step_um=2.0,
        interval_s=1.5 if "t" in axes else None,
    )
    channels = tuple(ChannelInfo(f"ch{c}") for c in range(sizes.get("c", 1)))
    info = AcquisitionInfo(shape=(4, 6), dtype="uint16", bit_depth=12, pixel_size_um=0.5, channels=channels)
    out = OmeOutput(path, layout, info, single_file=single_file)
    acquired = {}
    for n, at in enumerate(itertools.islice(itertools.product(*(range(sizes[a]) for a in axes)), stop)):
        index = dict(zip(axes, at, strict=True))
        reported = {"x_um": 1.0, "y_um": 2.0, "z_um": 10.0 + 2.0 * index.get("z", 0), "exposure_ms": 5.0}
        out.append(np.full((4, 6), n + 1, dtype=np.uint16), index, reported)
        acquired[(index.get("p", 0), tuple(index.get(a, 0) for a in PLAN_AXES))] = n + 1
    return out.close(), acquired, layout


def _start(name, names):
    """(position, plan index of the first plane) of an OME image named ``<position>`` or ``<position> t1c0z0``."""
    import re

    position, _, piece = name.partition(" ")
    start = {axis: int(i) for axis, i in re.findall(r"([tcz])(\d+)", piece)}
    return (names.index(position) if names else 0), tuple(start.get(a, 0) for a in PLAN_AXES)


def _tiff_images(files, names):
    """Every image of OME-TIFF files as tifffile reads it: ``(position, first plan index, {axis: size}, array)``
    (the array's axes T, C, Z, Y, X with size-1 ones put back), checked against ome-types' reading."""
    import numpy as np

    images = []
    for path in files:
        ome = ome_types.from_tiff(path)  # parses and validates the OME-XML
        with tifffile.TiffFile(path) as tif:
            assert len(tif.series) == len(ome.images)
            for series, image in zip(tif.series, ome.images, strict=True):
                assert series.name == image.name
                px = image.pixels
                sizes = {"t": px.size_t, "c": px.size_c, "z": px.size_z}
                data = series.asarray()
                assert data.size == px.size_t * px.size_c * px.size_z * px.size_y * px.size_x  # no plane added
                data = data.reshape(px.size_t, px.size_c, px.size_z, px.size_y, px.size_x)
                assert len(px.planes) == len(px.tiff_data_blocks) == px.size_t * px.size_c * px.size_z
                assert len(px.channels) == px.size_c
                images.append((*_start(image.name, names), sizes, np.asarray(data)))
    return images


def _zarr_images(store, names, channels):
    """Every image of an OME-Zarr store, each validated as an NGFF image (ome-zarr-models) and read by ome-zarr-py:
    ``(position, first plan index, {axis: size}, array as t, c, z, y, x)``; its channels must be those of
    ``channels`` it holds."""
    import numpy as np
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader
    from ome_zarr_models.v05.image import Image

    images = []
    for meta in sorted(store.rglob("zarr.json")):
        attrs = json.loads(meta.read_text()).get("attributes", {})
        if "multiscales" not in attrs.get("ome", {}):
            continue
        Image.from_zarr(zarr.open_group(str(meta.parent), mode="r"))
        (node, *_) = Reader(parse_url(str(meta.parent)))()
        axes = [a["name"] for a in attrs["ome"]["multiscales"][0]["axes"]]
        data = np.asarray(zarr.open_array(str(meta.parent / "0"), mode="r"))
        assert node.data[0].shape == data.shape
        full = [data.shape[axes.index(a)] if a in axes else 1 for a in PLAN_AXES]
        data = data.reshape(*full, *data.shape[-2:])
        first = attrs["scopetwin"]["plan_index"]
        labels = [c["label"] for c in attrs["ome"]["omero"]["channels"]]
        assert labels == list(channels[first.get("c", 0) :][: full[1]])
        position = attrs["scopetwin"]["position"]
        images.append(
            (
                names.index(position) if names else 0,
                tuple(first.get(a, 0) for a in PLAN_AXES),
                dict(zip(PLAN_AXES, full, strict=True)),
                data,
            )
        )
    return images


def _check_holds_what_was_acquired(images, acquired):
    """Every image's every plane is the acquired plane of its plan index (none filled in), every acquired plane in
    exactly one image."""
    import itertools

    seen = []
    for position, start, sizes, data in images:
        for rel in itertools.product(*(range(sizes[a]) for a in PLAN_AXES)):
            key = (position, tuple(s + r for s, r in zip(start, rel, strict=True)))
            assert key in acquired, f"{key} was never acquired"
            assert (data[rel] == acquired[key]).all(), key
            seen.append(key)
    assert sorted(seen) == sorted(acquired)


#: (axes, sizes, positions): time points outside the positions; positions outermost; no positions (one image).
PLANS = [
    (("t", "p", "c", "z"), {"t": 3, "c": 2, "z": 3}, 2),
    (("p", "z", "c"), {"c": 2, "z": 3}, 3),
    (("c", "z"), {"c": 2, "z": 3}, 0),
]


@pytest.mark.parametrize("kind", ["tiff", "single", "zarr"])
@pytest.mark.parametrize(("axes", "sizes", "positions"), PLANS)
def test_a_stopped_run_declares_only_the_planes_it_acquired(tmp_path, kind, axes, sizes, positions):
    import math

    total = math.prod(sizes.values()) * max(positions, 1)
    name = "x.ome.zarr" if kind == "zarr" else "x.ome.tif"
    for stop in sorted({1, 2, 4, 7, total - 1} & set(range(1, total))):  # stopped before the last plane
        out = tmp_path / str(stop) / name
        files, acquired, layout = _stopped_output(out, axes, sizes, positions, stop, single_file=kind == "single")
        if kind == "zarr":
            images = _zarr_images(out, layout.names, [f"ch{c}" for c in range(sizes.get("c", 1))])
        else:
            images = _tiff_images(files, list(layout.names))
        _check_holds_what_was_acquired(images, acquired)


def test_a_stopped_plate_has_wells_of_one_shape_and_the_rest_beside_them(tmp_path):
    """t outside the positions, stopped in the second time point at position 1: both wells hold time point 0 (what
    ome-zarr-py lays side by side), the rest are images beside the wells' fields, listed by the main images."""
    import numpy as np
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    out = tmp_path / "x.ome.zarr"
    _files, acquired, _layout = _stopped_output(out, ("t", "p", "c", "z"), {"t": 3, "c": 2, "z": 3}, 2, 12 + 6 + 4)
    (plate, *_) = Reader(parse_url(str(out)))()
    stitched = np.asarray(plate.data[0])
    assert stitched.shape == (1, 2, 3, 4, 12) and stitched.min() > 0  # one time point, both wells, no zero
    wells = [json.loads((out / f"A/{n}/0/zarr.json").read_text())["attributes"]["scopetwin"] for n in (1, 2)]
    assert [w["more_images"] for w in wells] == [["A/1/t1c0z0"], ["A/2/t1c0z0", "A/2/t1c1z0"]]
    well = json.loads((out / "A/2/zarr.json").read_text())["attributes"]["ome"]["well"]
    assert well["images"] == [{"path": "0"}]
    extra = json.loads((out / "A/2/t1c1z0/zarr.json").read_text())["attributes"]
    assert extra["scopetwin"]["plan_index"] == {"t": 1, "c": 1, "z": 0}
    assert [c["label"] for c in extra["ome"]["omero"]["channels"]] == ["ch1"]
    translation = extra["ome"]["multiscales"][0]["datasets"][0]["coordinateTransformations"][-1]["translation"]
    assert translation == [1.5, 0.0, 10.0, 2.0, 1.0]  # t: one interval; z, y, x: where its first plane was taken
    _check_holds_what_was_acquired(_zarr_images(out, ("pos0", "pos1"), ("ch0", "ch1")), acquired)


def test_a_plate_stopped_before_a_position_drops_its_well(tmp_path):
    out = tmp_path / "x.ome.zarr"
    _stopped_output(out, ("p", "c", "z"), {"c": 2, "z": 3}, 3, 6 + 2)
    plate = json.loads((out / "zarr.json").read_text())["attributes"]["ome"]["plate"]
    assert [w["path"] for w in plate["wells"]] == ["A/1", "A/2"] and [c["name"] for c in plate["columns"]] == ["1", "2"]
    assert not (out / "A" / "3").exists()


def _captured(rig_path, out, after, *, single_file=False):
    """Run SEQUENCE_2X2X3 into ``out`` with the focus lost after ``after`` operations; the planes the camera gave,
    by (position, plan index)."""
    import numpy as np

    planes = {}

    def keep(image, event, _meta):
        index = dict(event.index)
        planes[(index.get("p", 0), tuple(index.get(a, 0) for a in PLAN_AXES))] = np.array(image)

    with open_rig(rig_path) as rig:
        rig["focus"].inject_fault("disconnect", after=after)
        with pytest.raises(DisconnectedError):
            run_mda(rig, SEQUENCE_2X2X3, output=str(out), single_file=single_file, on_frame=keep)
    return planes


@pytest.mark.parametrize("kind", ["tiff", "single", "zarr"])
def test_files_after_a_device_fault_hold_the_planes_the_camera_gave(rig_path, tmp_path, kind):
    """The rig's focus lost mid-position: tifffile, ome-types, zarr and ome-zarr-py read back the planes the camera
    gave, at their plan index, and nothing else."""
    out = tmp_path / ("x.ome.zarr" if kind == "zarr" else "x.ome.tif")
    planes = _captured(rig_path, out, after=40, single_file=kind == "single")
    assert 6 < len(planes) < 12  # the second position was reached, not finished
    names = ["0", "1"]  # the plan's positions have no names: their index
    if kind == "zarr":
        images = _zarr_images(out, names, ["uv", "deep_red"])
    else:
        images = _tiff_images([out] if kind == "single" else sorted((tmp_path / "x").glob("*.ome.tif")), names)
    mains = [tuple(s.values()) for _p, start, s, _data in images if not any(start)]
    if kind == "zarr":  # the plate's wells: one shape, what both positions acquired (uv); the rest beside them
        assert mains == [(1, 1, 3), (1, 1, 3)] and len(images) == 3
    else:
        assert mains[0] == (1, 2, 3)  # position 0: all of it
    seen = set()
    for position, start, sizes, data in images:
        for c in range(sizes["c"]):
            for z in range(sizes["z"]):
                key = (position, (0, start[1] + c, start[2] + z))
                assert (data[0, c, z] == planes[key]).all(), key
                seen.add(key)
    assert seen == set(planes)
