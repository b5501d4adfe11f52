"""A dataset handed over by someone else: the reader (``scopetwin.open_dataset``), ``dataset verify`` and ``dataset
resume`` open nothing outside the dataset folder, nothing that is not a regular file, no JSON nested without bound,
no newer format, and no EXR larger than its header allows. Each hostile folder is built here from a real one, its
hashes and manifest rewritten so that only the safety checks can catch it."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import struct
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_dataset_common import write_tiny  # noqa: E402

import scopetwin  # noqa: E402
from scopetwin.cli import main  # noqa: E402
from scopetwin.sim.datasets.config import load_config  # noqa: E402
from scopetwin.sim.datasets.plan import Plan  # noqa: E402
from scopetwin.sim.datasets.reader import DatasetReadError  # noqa: E402
from scopetwin.sim.datasets.store import MANIFEST, SAMPLES, generate, recover, verify  # noqa: E402

pytestmark = pytest.mark.mitsuba
posix_only = pytest.mark.skipif(sys.platform == "win32", reason="FIFOs and /dev/zero are POSIX")


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("hostile")
    root = folder / "ds"
    generate(Plan.build(load_config(write_tiny(folder, count=2))), root, workers=0, progress=False)
    return root


@pytest.fixture
def copy(tiny, tmp_path) -> Path:
    root = tmp_path / "ds"
    shutil.copytree(tiny, root)
    (tmp_path / "elsewhere.exr").write_bytes((tiny / SAMPLES / "000000" / "surface.exr").read_bytes())
    return root


def sample0(root: Path) -> Path:
    return root / SAMPLES / "000000"


def rehash(root: Path, index: int = 0) -> None:
    """Rewrite sample ``index``'s sample.json and manifest line to match its files as they are now (as the author of
    a hostile dataset would), so that the hash check alone cannot catch what was changed."""
    folder = root / SAMPLES / f"{index:06d}"
    body = json.loads((folder / "sample.json").read_text())
    for name, meta in body["files"].items():
        path = folder / name
        if path.is_file() and not path.is_symlink():
            data = path.read_bytes()
            meta.update(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
    (folder / "sample.json").write_text(json.dumps(body))
    rows = [json.loads(line) for line in (root / MANIFEST).read_text().splitlines() if line.strip()]
    for row in rows:
        if row["index"] == index:
            row["files"] = body["files"]
    (root / MANIFEST).write_text("".join(json.dumps(r) + "\n" for r in rows))


def edit_truth(root: Path, **changes: object) -> None:
    path = sample0(root) / "truth.json"
    truth = json.loads(path.read_text())
    truth.update(changes)
    path.write_text(json.dumps(truth))
    rehash(root)


def verdict(root: Path) -> tuple[dict, str]:
    """verify's result and the reason it gives for sample 0 (corrupt or invalid)."""
    result = verify(root)
    reasons = [c["reason"] for c in result["corrupt"] if c["index"] == 0]
    reasons += [r for v in result["invalid"] if v["index"] == 0 for r in v["reasons"]]
    assert not result["ok"] and result["complete"] == 1, result
    return result, " | ".join(reasons)


def test_the_untouched_copy_is_complete(copy):
    assert verify(copy)["ok"]
    assert scopetwin.open_dataset(copy)[0].heights is not None


@pytest.mark.parametrize(
    ("surface", "message"),
    [("../../../elsewhere.exr", "leaves"), ("/etc/passwd", "absolute path"), ("../../../elsewhere.exr\0", "NUL")],
)
def test_a_truth_surface_outside_the_sample_is_not_opened(copy, surface, message):
    edit_truth(copy, surface=surface)
    with pytest.raises(DatasetReadError, match=message):
        _ = scopetwin.open_dataset(copy)[0].heights
    _, reason = verdict(copy)
    assert message in reason


def test_an_image_linked_out_of_the_folder_is_not_returned(copy):
    image = sample0(copy) / "image.exr"
    outside = copy.parent / "other-image.exr"
    shutil.move(image, outside)
    os.symlink(outside, image)  # the same bytes: its hash matches
    with pytest.raises(DatasetReadError, match="link to .*other-image.exr, outside"):
        _ = scopetwin.open_dataset(copy)[0].image
    _, reason = verdict(copy)
    assert "outside" in reason


def test_a_sample_folder_linked_out_of_the_dataset_is_not_listed(copy):
    outside = copy.parent / "sample-elsewhere"
    shutil.move(sample0(copy), outside)
    os.symlink(outside, sample0(copy))
    assert [s.index for s in scopetwin.open_dataset(copy)] == [1]
    _, reason = verdict(copy)
    assert "symbolic link" in reason
    state = recover(copy)  # resume: the link is removed and the sample redone; what it points to is kept
    assert state["corrupt_removed"] == [0]
    assert not sample0(copy).exists() and (outside / "truth.json").is_file()


@posix_only
@pytest.mark.timeout(60)
@pytest.mark.parametrize("name", ["truth.json", "sample.json"])
def test_a_fifo_hangs_nothing(copy, name):
    path = sample0(copy) / name
    path.unlink()
    os.mkfifo(path)
    sample = scopetwin.open_dataset(copy)[0]
    with pytest.raises(DatasetReadError, match="FIFO"):
        _ = sample.truth if name == "truth.json" else sample.meta
    _, reason = verdict(copy)
    assert "FIFO" in reason


@posix_only
@pytest.mark.timeout(60)
def test_a_truth_linked_to_dev_zero_is_not_read(copy):
    path = sample0(copy) / "truth.json"
    path.unlink()
    os.symlink("/dev/zero", path)
    with pytest.raises(DatasetReadError, match="/dev/zero, outside"):
        _ = scopetwin.open_dataset(copy)[0].truth
    _, reason = verdict(copy)
    assert "/dev/zero" in reason


@pytest.mark.timeout(120)
def test_a_100000_deep_truth_is_one_clear_reason(copy):
    (sample0(copy) / "truth.json").write_text('{"a": ' + "[" * 100_000 + "]" * 100_000 + "}")
    rehash(copy)
    with pytest.raises(DatasetReadError, match="more than 64 levels deep"):
        _ = scopetwin.open_dataset(copy)[0].truth
    _, reason = verdict(copy)
    assert "more than 64 levels deep" in reason


@pytest.mark.parametrize("name", ["truth.json", "sample.json"])
def test_a_newer_sample_format_is_refused(copy, name):
    if name == "truth.json":
        edit_truth(copy, format=99)
    else:
        path = sample0(copy) / name
        body = json.loads(path.read_text())
        path.write_text(json.dumps({**body, "format": 99}))
    sample = scopetwin.open_dataset(copy)[0]
    with pytest.raises(DatasetReadError, match="format 99, newer than this scopetwin reads"):
        _ = sample.truth if name == "truth.json" else sample.meta
    _, reason = verdict(copy)
    assert "format 99, newer" in reason


def test_an_image_declaring_20000_px_is_not_decoded(copy):
    image = sample0(copy) / "image.exr"
    data = bytearray(image.read_bytes())
    key = b"dataWindow\x00box2i\x00"
    at = data.index(key) + len(key) + 4
    data[at : at + 16] = struct.pack("<4i", 0, 0, 19999, 19999)
    image.write_bytes(bytes(data))
    rehash(copy)
    with pytest.raises(DatasetReadError, match="declares 20000 x 20000 px, but 170 x 128 px are expected"):
        _ = scopetwin.open_dataset(copy)[0].image
    _, reason = verdict(copy)
    assert "declares 20000 x 20000 px" in reason


def test_verify_on_the_command_line_gives_the_reason(copy, capsys):
    edit_truth(copy, surface="../../../elsewhere.exr")
    code = main(["dataset", "verify", str(copy), "-q"])
    out = capsys.readouterr()
    assert code == 1 and "Traceback" not in out.err
    assert "leaves" in out.out + out.err


@posix_only
@pytest.mark.timeout(60)
@pytest.mark.parametrize("command", ["verify", "resume"])
def test_a_fifo_dataset_json_is_one_line_exit_2(copy, capsys, command):
    (copy / "dataset.json").unlink()
    os.mkfifo(copy / "dataset.json")
    code = main(["dataset", command, str(copy), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and "FIFO" in err and len(err.strip().splitlines()) == 1, err


def test_a_newer_dataset_json_is_one_line_exit_2(copy, capsys):
    cfg = json.loads((copy / "dataset.json").read_text())
    (copy / "dataset.json").write_text(json.dumps({**cfg, "format": 99}))
    code = main(["dataset", "verify", str(copy), "-q"])
    err = capsys.readouterr().err
    assert code == 2 and "newer scopetwin" in err and len(err.strip().splitlines()) == 1, err


def test_resume_redoes_a_sample_whose_image_links_out_and_keeps_the_target(copy, capsys):
    image = sample0(copy) / "image.exr"
    outside = copy.parent / "other-image.exr"
    shutil.move(image, outside)
    os.symlink(outside, image)
    before = outside.read_bytes()
    code = main(["dataset", "resume", str(copy), "--workers", "0", "-q"])
    assert code == 0, capsys.readouterr().err
    assert outside.read_bytes() == before and not image.is_symlink()
    assert verify(copy)["ok"]
