"""Names written into OME files (position names from the plan, channel presets, the camera, the output file's
name): OME-XML escapes what it can hold and reads it back as it was (tifffile, ome-types); what XML cannot hold
(NUL, other control characters, text that is not Unicode) is one clear error before anything is written; OME-Zarr
keeps every name in JSON and reads any of them back (zarr), except text that is not Unicode (one clear error)."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("ome_writers", reason="ome-writers (optional extra 'mm') is not installed")
tifffile = pytest.importorskip("tifffile")
ome_types = pytest.importorskip("ome_types")

from scopetwin.instrument.errors import RigError  # noqa: E402
from scopetwin.instrument.ome import AcquisitionInfo, ChannelInfo, Layout, OmeOutput  # noqa: E402
from scopetwin.instrument.ome_xml import xml_text_problem  # noqa: E402

#: Names XML holds once escaped: quotes, markup, an entity, line breaks, a tab, a carriage return, non-ASCII.
ESCAPED = ["q\"uote's", "<b>&amp;</b>", "two\nlines", "tab\tcr\r", "ünï €"]
#: Names XML 1.0 cannot hold at all (NUL, BEL, ESC, U+FFFE, a lone surrogate: a file name in another encoding).
UNWRITABLE = ["nul\x00x", "bell\x07", "esc\x1b[31m", "not\ufffe", "latin1\udce9"]


def _write(path, name, single_file=False):
    """Two positions, one channel, the camera: each called after ``name``; returns the files written."""
    layout = Layout(
        axes=("p", "c", "z"),
        sizes={"p": 2, "c": 1, "z": 1},
        positions=((0, 0), (1, 0)),
        names=(f"{name} 1", f"{name} 2"),
    )
    info = AcquisitionInfo(
        shape=(8, 6), dtype="uint16", bit_depth=12, pixel_size_um=0.5, channels=(ChannelInfo(name),), camera=name
    )
    out = OmeOutput(path, layout, info, single_file=single_file)
    for p in range(2):
        out.append(np.full((8, 6), 100 + p, np.uint16), {"p": p, "c": 0, "z": 0}, {"exposure_ms": 5.0, "x_um": 1.0})
    return out.close()


@pytest.mark.parametrize("name", ESCAPED)
@pytest.mark.parametrize("single_file", [True, False], ids=["single-file", "file-per-position"])
def test_names_xml_escapes_read_back_as_they_were(tmp_path, name, single_file):
    path = tmp_path / f"{name}.ome.tif"  # the file's own name too (the single file's image names)
    files = _write(path, name, single_file)
    assert len(files) == (1 if single_file else 2)
    images = []
    for file in files:
        with tifffile.TiffFile(file) as tif:
            ome = ome_types.from_xml(tif.ome_metadata)
        assert [d.model for d in ome.instruments[0].detectors] == [name]
        images += [im for im in ome.images if im.pixels.planes]
        assert all([c.name for c in im.pixels.channels] == [name] for im in ome.images)
    assert len(images) == 2
    if single_file:
        assert [im.name for im in images] == [f"{name} 1", f"{name} 2"]


@pytest.mark.parametrize(
    "where, name",
    [
        (where, name)
        for where in ("position", "channel", "camera", "output file name")
        for name in UNWRITABLE
        if not (where == "output file name" and "\x00" in name)  # no file system takes a NUL in a file name
    ],
)
def test_a_name_xml_cannot_hold_is_one_error_and_nothing_is_written(tmp_path, name, where):
    assert xml_text_problem(name) is not None
    safe = "ok"
    layout = Layout(
        axes=("p", "c", "z"),
        sizes={"p": 1, "c": 1, "z": 1},
        positions=((0, 0),),
        names=(name if where == "position" else safe,),
    )
    info = AcquisitionInfo(
        shape=(8, 6),
        dtype="uint16",
        bit_depth=12,
        pixel_size_um=0.5,
        channels=(ChannelInfo(name if where == "channel" else safe),),
        camera=name if where == "camera" else safe,
    )
    folder = tmp_path / "out"
    stem = name if where == "output file name" else safe
    with pytest.raises(RigError) as info_:
        OmeOutput(folder / f"{stem}.ome.tif", layout, info, single_file=True)
    message = str(info_.value)
    shown = f"{stem}.ome.tif" if where == "output file name" else name
    assert message.startswith(f"{where} {shown!r} holds the character(s) ") and "\n" not in message
    assert "OME-TIFF cannot carry it" in message
    assert not folder.exists()  # nothing written, not even the folder


@pytest.mark.parametrize("name", ESCAPED + UNWRITABLE[:-1])
def test_ome_zarr_keeps_any_name_in_its_json(tmp_path, name):
    zarr = pytest.importorskip("zarr")
    (store,) = _write(tmp_path / "x.ome.zarr", name)
    for p in range(2):
        group = zarr.open_group(f"{store}/A/{p + 1}/0", mode="r")
        ours = group.attrs["scopetwin"]
        assert ours["position"] == f"{name} {p + 1}"
        assert ours["camera"] == name and [c["name"] for c in ours["channels"]] == [name]
        assert [c["label"] for c in group.attrs["ome"]["omero"]["channels"]] == [name]
    json.loads((tmp_path / "x.ome.zarr" / "zarr.json").read_text())  # strict JSON, any name escaped


@pytest.mark.parametrize("where", ["position", "channel", "camera"])
def test_ome_zarr_refuses_a_name_that_is_not_unicode_before_writing(tmp_path, where):
    name = UNWRITABLE[-1]
    layout = Layout(
        axes=("p", "c"), sizes={"p": 1, "c": 1}, positions=((0, 0),), names=(name if where == "position" else "a",)
    )
    info = AcquisitionInfo(
        shape=(8, 6),
        dtype="uint16",
        bit_depth=12,
        pixel_size_um=0.5,
        channels=(ChannelInfo(name if where == "channel" else "BF"),),
        camera=name if where == "camera" else "cam",
    )
    with pytest.raises(RigError, match=f"^{where} .* which is not Unicode text: an OME-Zarr cannot carry it"):
        OmeOutput(tmp_path / "out" / "x.ome.zarr", layout, info)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name, code", [('stage "A" <1> & B\nrow 2', 0), ("stage\x00A", 2)], ids=["escaped", "NUL"])
def test_rig_mda_writes_a_plans_position_names_or_refuses_them_in_one_line(tmp_path, capsys, name, code):
    pytest.importorskip("pymmcore_plus", reason="pymmcore-plus (optional extra 'mm') is not installed")
    from scopetwin.cli import main
    from tests.instrument.test_mda_plans_and_ome import RIG, SEQUENCE

    rig = tmp_path / "rig.toml"
    rig.write_text(RIG)
    plan = dict(SEQUENCE, z_plan={"range": 0.0, "step": 1.0}, channels=SEQUENCE["channels"][:1])
    plan["stage_positions"] = [dict(p, name=f"{name} {k}") for k, p in enumerate(SEQUENCE["stage_positions"])]
    seq = tmp_path / "plan.json"
    seq.write_text(json.dumps(plan))
    out = tmp_path / "acq" / "x.ome.tif"
    assert main(["rig", str(rig), "mda", str(seq), "--out", str(out), "--single-file", "-q"]) == code
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    if code:
        assert len(err) == 1 and f"position {name + ' 0'!r} holds the character(s) '\\x00'" in err[0], err
        assert not (tmp_path / "acq").exists()
        return
    ome = ome_types.from_tiff(out)
    assert [im.name for im in ome.images] == [f"{name} 0", f"{name} 1"]
