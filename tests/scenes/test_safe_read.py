"""scenes.safe_read: file names kept inside their folder, regular files only, bounded JSON, format versions, and EXR
sizes checked from the header before any pixel is decoded. Every hostile input is built here."""

from __future__ import annotations

import json
import os
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.inputs import InputError
from scopetwin.scenes.io import read_heightmap, read_image, write_image
from scopetwin.scenes.limits import LimitError
from scopetwin.scenes.safe_read import (
    UnsafeInput,
    check_exr_header,
    check_format,
    check_regular,
    exr_shape,
    read_json_inside,
    resolve_inside,
)

posix_only = pytest.mark.skipif(sys.platform == "win32", reason="FIFOs and /dev/zero are POSIX")


def declare_size(path: Path, cols: int, rows: int) -> None:
    """Rewrite the data window of the EXR at ``path`` so that its header declares ``cols`` x ``rows`` px (the pixel
    data stays that of the small image: decoding it would fail or allocate the declared size)."""
    data = bytearray(path.read_bytes())
    key = b"dataWindow\x00box2i\x00"
    at = data.index(key) + len(key)
    assert struct.unpack("<i", data[at : at + 4]) == (16,)
    data[at + 4 : at + 20] = struct.pack("<4i", 0, 0, cols - 1, rows - 1)
    path.write_bytes(bytes(data))


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    inside = tmp_path / "dataset"
    inside.mkdir()
    (inside / "truth.json").write_text('{"format": 2}')
    (tmp_path / "elsewhere.exr").write_text("not yours")
    return inside


def test_a_name_inside_the_folder_is_resolved(folder):
    assert resolve_inside(folder, "truth.json", "t") == Path(os.path.realpath(folder / "truth.json"))
    (folder / "sub").mkdir()
    os.symlink("../truth.json", folder / "sub" / "link.json")  # a link that stays inside is followed
    assert resolve_inside(folder, "sub/link.json", "t") == Path(os.path.realpath(folder / "truth.json"))


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("../elsewhere.exr", "leaves"),
        ("../../../elsewhere.exr", "leaves"),
        ("sub/../../elsewhere.exr", "leaves"),
        ("..\\elsewhere.exr", "leaves"),
        ("/etc/passwd", "absolute path"),
        ("C:\\Windows\\win.ini", "absolute path"),
        ("", "not a file name"),
        (None, "not a file name"),
        (["truth.json"], "not a file name"),
        ("truth.json\0.exr", "NUL"),
    ],
)
def test_names_that_leave_the_folder_are_refused(folder, name, message):
    with pytest.raises(UnsafeInput, match=message):
        resolve_inside(folder, name, "truth.json surface")


def test_a_link_out_of_the_folder_is_refused(folder):
    os.symlink(folder.parent / "elsewhere.exr", folder / "surface.exr")
    with pytest.raises(UnsafeInput, match="link to .*elsewhere.exr, outside"):
        resolve_inside(folder, "surface.exr", "surface")
    os.symlink(folder.parent, folder / "up")  # a folder link out: every name through it is outside
    with pytest.raises(UnsafeInput, match="outside"):
        resolve_inside(folder, "up/elsewhere.exr", "surface")


@posix_only
def test_a_link_to_dev_zero_is_refused_both_ways(folder):
    os.symlink("/dev/zero", folder / "zero.json")
    with pytest.raises(UnsafeInput, match="outside"):
        read_json_inside(folder, "zero.json", "truth.json")
    with pytest.raises(UnsafeInput, match="a device"):
        check_regular(folder / "zero.json", "truth.json")  # stat follows the link: the device is seen


@posix_only
@pytest.mark.timeout(30)
def test_a_fifo_is_refused_without_opening_it(folder):
    os.mkfifo(folder / "sample.json")  # nobody writes to it: an open for reading would block
    with pytest.raises(UnsafeInput, match="FIFO"):
        read_json_inside(folder, "sample.json", "sample.json")


def test_a_file_over_the_limit_is_refused_before_reading(folder):
    (folder / "big.json").write_text(" " * 2000 + "{}")
    with pytest.raises(UnsafeInput, match="over the limit of 1000 bytes"):
        read_json_inside(folder, "big.json", "big.json", limit=1000)


@pytest.mark.timeout(60)
def test_a_100000_deep_json_is_one_clear_error(folder):
    (folder / "deep.json").write_text('{"a": ' + "[" * 100_000 + "]" * 100_000 + "}")
    with pytest.raises(InputError, match="more than 64 levels deep"):
        read_json_inside(folder, "deep.json", "truth.json")


def test_json_that_is_not_an_object_is_refused(folder):
    (folder / "list.json").write_text("[1, 2]")
    with pytest.raises(InputError, match="does not hold a JSON object"):
        read_json_inside(folder, "list.json", "truth.json")
    assert read_json_inside(folder, "truth.json", "truth.json") == {"format": 2}


def test_a_newer_format_is_one_clear_error():
    assert check_format(2, (1, 2), "truth.json") == 2
    with pytest.raises(UnsafeInput, match="format 99, newer than this scopetwin reads .1, 2.; install a newer"):
        check_format(99, (1, 2), "truth.json")
    for value in ("2", 2.0, True, None, [2]):
        with pytest.raises(UnsafeInput, match="is not a format version"):
            check_format(value, (1, 2), "truth.json")
    with pytest.raises(UnsafeInput, match="format 0 is not one"):
        check_format(0, (1, 2), "truth.json")


def test_every_refusal_is_a_bad_input_error():
    """The command line maps ScopetwinError to one line and exit 2."""
    assert issubclass(UnsafeInput, InputError) and issubclass(UnsafeInput, ScopetwinError)


def test_exr_dimensions_come_from_the_header(tmp_path):
    path = tmp_path / "image.exr"
    write_image(path, np.ones((4, 6), np.float32))
    header = check_exr_header(path, "image", shape=(4, 6))
    assert exr_shape(header) == (4, 6)
    with pytest.raises(UnsafeInput, match="declares 6 x 4 px, but 7 x 5 px are expected"):
        check_exr_header(path, "image", shape=(5, 7))
    with pytest.raises(LimitError, match="6 x 4 px image needs"):
        check_exr_header(path, "image", memory=100)


def test_a_20000_px_header_is_refused_before_any_pixel_is_decoded(tmp_path, monkeypatch):
    """An EXR whose header declares 20000 x 20000 px: refused by the header check (the camera's size, or the
    memory), and OpenEXR is never asked for its pixels."""
    import OpenEXR

    path = tmp_path / "big.exr"
    write_image(path, np.ones((4, 6), np.float32))
    declare_size(path, 20000, 20000)
    assert path.stat().st_size < 4096
    opened: list[bool] = []
    real = OpenEXR.File

    def spy(*args, **kwargs):
        opened.append(bool(kwargs.get("header_only", False)))
        return real(*args, **kwargs)

    monkeypatch.setattr(OpenEXR, "File", spy)
    with pytest.raises(UnsafeInput, match="declares 20000 x 20000 px, but 170 x 128 px are expected"):
        read_image(path, shape=(128, 170))
    # without an expected size (markers, calibrate, render --surface): refused by its pixel count, whatever the memory
    for memory in (8 << 30, 1 << 40):
        monkeypatch.setattr("scopetwin.scenes.limits.physical_memory", lambda memory=memory: memory)
        with pytest.raises(UnsafeInput, match=r"declares 20000 x 20000 px \(400 Mpx\), more than the 268 Mpx"):
            read_image(path)
        with pytest.raises(UnsafeInput, match="declares 20000 x 20000 px"):
            read_heightmap(path)
    assert opened and not any(not header_only for header_only in opened)  # only ever the header
    assert opened and all(opened), "a pixel decode was started"


def test_an_empty_data_window_is_refused(tmp_path):
    path = tmp_path / "empty.exr"
    write_image(path, np.ones((4, 6), np.float32))
    declare_size(path, 0, 0)
    with pytest.raises(InputError, match="empty image|not a readable OpenEXR"):
        read_image(path)


def test_a_json_dump_of_a_sample_reads_back(folder):
    body = {"format": 2, "files": {"image.exr": {"bytes": 3, "sha256": "ab"}}}
    (folder / "sample.json").write_text(json.dumps(body))
    assert read_json_inside(folder, "sample.json", "sample.json") == body
