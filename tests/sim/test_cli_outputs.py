"""Outputs checked before the work and written last: every failure is one line, exit 2, nothing written."""

from __future__ import annotations

import errno
import shutil
import sys
from collections import namedtuple
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_dataset_common import write_tiny  # noqa: E402

from scopetwin.cli import main  # noqa: E402
from scopetwin.cli import outputs as outputs_mod  # noqa: E402

SMALL = """
base = "thesis-2.8.1-angular"
[camera]
pixels = [68, 51]
pixel_pitch = 0.093
[render]
spp = 1
"""


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _one_error_line(err: str, *fragments: str) -> None:
    assert err.startswith("scopetwin: error: ") and err.count("\n") == 1, err
    for f in fragments:
        assert f in err, err


@pytest.fixture
def setup_file(tmp_path: Path) -> Path:
    work = tmp_path / "in"
    work.mkdir()
    (work / "small.toml").write_text(SMALL)
    (work / "afile").write_text("x")
    return work / "small.toml"


def _untouched(tmp_path: Path) -> None:
    """Only the inputs are there: no output, no staging folder, no probe file."""
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]
    assert sorted(p.name for p in (tmp_path / "in").iterdir()) == ["afile", "small.toml"]


@pytest.mark.parametrize(
    ("extra", "fragments"),
    [
        (["--out", "{in}/afile"], ["--out", "afile", "is an existing file, not a folder"]),
        (["--out", "{in}/afile/sub"], ["afile is a file, not a folder"]),
        (["--out", "/proc/scopetwin-out"], ["--out /proc/scopetwin-out", "cannot write in /proc"]),
        (["--out", "{tmp}/o", "--json", "{in}"], ["--json", "is an existing folder, not a file"]),
        (["--out", "{tmp}/o", "--json", "/proc/x/r.json"], ["--json /proc/x/r.json", "cannot write in /proc"]),
        (["--out", "{tmp}/o", "--json", "{in}/afile/r.json"], ["--json", "afile is a file"]),
    ],
)
def test_render_refuses_bad_outputs_before_any_work(tmp_path, capsys, setup_file, extra, fragments):
    argv = [a.format(tmp=tmp_path, **{"in": setup_file.parent}) for a in extra]
    code, _, err = _run(capsys, "render", setup_file, "--renderer", "analytic", *argv)
    assert code == 2
    _one_error_line(err, *fragments)
    _untouched(tmp_path)


def test_render_refuses_when_the_estimate_does_not_fit(tmp_path, capsys, setup_file, monkeypatch):
    usage = namedtuple("usage", "total used free")
    monkeypatch.setattr(outputs_mod.shutil, "disk_usage", lambda p: usage(10**9, 10**9 - 4000, 4000))
    code, _, err = _run(capsys, "render", setup_file, "--out", tmp_path / "o", "--renderer", "analytic")
    assert code == 2
    _one_error_line(err, "--out", "not enough free space", "needed", "4.0 kB free")
    _untouched(tmp_path)


def test_estimates_scale_with_the_image():
    from argparse import Namespace

    small = outputs_mod.estimate_render(Namespace(setup="thesis-2.8.1-angular"))["out"]
    assert small >= 1360 * 1024 * 5  # the preset's camera: float32 image + preview
    assert outputs_mod.estimate_run(Namespace())["out"] > small


def _failing_json(monkeypatch, name: str) -> None:
    """Make the atomic write of the file ``name`` fail as on a full disk (other files are written normally)."""
    import contextlib

    from scopetwin.scenes import io as scenes_io

    real = scenes_io.atomic_path

    @contextlib.contextmanager
    def atomic_path(path):
        if Path(path).name == name:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        with real(path) as tmp:
            yield tmp

    monkeypatch.setattr(scenes_io, "atomic_path", atomic_path)


def test_a_failing_json_after_the_render_leaves_no_result(tmp_path, capsys, setup_file, monkeypatch):
    _failing_json(monkeypatch, "r.json")
    out = tmp_path / "deep" / "o"
    code, _, err = _run(
        capsys, "render", setup_file, "--out", out, "--renderer", "analytic", "--json", tmp_path / "r.json"
    )
    assert code == 2
    _one_error_line(err, "r.json: No space left on device")
    _untouched(tmp_path)  # neither the image folder, nor its staging folder, nor the folders above it


def test_a_write_failing_inside_a_command_is_one_line(tmp_path, capsys, setup_file, monkeypatch):
    import scopetwin.sim.measurement as measurement

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device", "image.exr")

    monkeypatch.setattr(measurement, "write_measurement", full)  # the command imports it when run
    code, _, err = _run(capsys, "render", setup_file, "--out", tmp_path / "o", "--renderer", "analytic")
    assert code == 2
    _one_error_line(err, "image.exr: No space left on device")
    _untouched(tmp_path)


def test_openexr_write_errors_become_oserrors():
    from scopetwin.scenes.io import exr_write_error

    e = exr_write_error(
        "a.exr", RuntimeError('Failed to write pixel data to image file "a.exr". No space left on device.')
    )
    assert e.errno == errno.ENOSPC and e.filename == "a.exr"
    assert exr_write_error("b.exr", RuntimeError("boom")).errno == errno.EIO


@pytest.mark.parametrize(
    "argv",
    [
        ["reconstruct", "{in}/small.toml", "--setup", "thesis-1.10-deflectometry", "--out", "{in}"],
        ["markers", "{in}/small.toml", "--pattern", "thesis-2.8.1-angular", "--overlay", "/proc/o.png"],
        ["presets", "--json", "/proc/x.json"],
        ["study", "thesis", "--out", "{in}/afile", "--workers", "0"],
        ["dataset", "verify", "{in}", "--json", "{in}"],
        ["optics", "grin", "thesis-8.3.2-grin-realized", "--spots", "{in}"],
        ["optics", "scan", "--json", "{in}/afile/x.json"],
    ],
)
def test_every_command_checks_its_outputs_first(tmp_path, capsys, setup_file, argv):
    code, _, err = _run(capsys, *[a.format(**{"in": setup_file.parent}) for a in argv])
    assert code == 2
    _one_error_line(err)
    _untouched(tmp_path)


@pytest.fixture
def tiny(tmp_path: Path) -> Path:
    work = tmp_path / "in"
    work.mkdir(exist_ok=True)
    return write_tiny(work, count=4)


def _dataset_untouched(tmp_path: Path) -> None:
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in"]


@pytest.mark.parametrize(
    ("extra", "fragments"),
    [
        (["--scheduler", "notanaddress"], ["--scheduler 'notanaddress' is not a Dask scheduler address"]),
        (["--scheduler", "tcp://:8786"], ["--scheduler", "expected e.g. tcp://host:8786"]),
        (["--workers", "0", "--json", "/proc/r.json"], ["--json /proc/r.json"]),
    ],
)
def test_dataset_generate_refuses_before_creating_the_folder(tmp_path, capsys, tiny, extra, fragments):
    code, _, err = _run(capsys, "dataset", "generate", tiny, "--out", tmp_path / "set", *extra)
    assert code == 2
    _one_error_line(err, *fragments)
    _dataset_untouched(tmp_path)


def test_dataset_generate_refuses_a_file_and_too_little_space(tmp_path, capsys, tiny, monkeypatch):
    code, _, err = _run(capsys, "dataset", "generate", tiny, "--out", tiny, "--workers", "0")
    assert code == 2
    _one_error_line(err, "is an existing file, not a folder")
    usage = namedtuple("usage", "total used free")
    calls = []

    def small_disk(path):
        calls.append(path)
        return usage(10**9, 10**9 - 1_100_000, 1_100_000)  # enough for the 1 MiB minimum, not for 4 samples

    monkeypatch.setattr(outputs_mod.shutil, "disk_usage", small_disk)
    code, _, err = _run(capsys, "dataset", "generate", tiny, "--out", tmp_path / "set", "--workers", "0")
    assert code == 2 and calls
    _one_error_line(err, "4 sample(s) of about", "not enough free space", "1.1 MB free")
    _dataset_untouched(tmp_path)


def test_a_scheduler_that_does_not_answer_leaves_no_folder(tmp_path, capsys, tiny, monkeypatch):
    import distributed

    def no_answer(address, timeout=None):
        raise OSError(f"Timed out trying to connect to {address} after {timeout}")

    monkeypatch.setattr(distributed, "Client", no_answer)
    code, _, err = _run(
        capsys, "dataset", "generate", tiny, "--out", tmp_path / "a" / "set", "--scheduler", "tcp://127.0.0.1:9"
    )
    assert code == 2
    _one_error_line(err, "cannot connect to the Dask scheduler tcp://127.0.0.1:9")
    assert not (tmp_path / "a" / "set").exists()


def test_the_check_names_the_path_and_creates_nothing(tmp_path):
    from scopetwin.cli.outputs import OutputError, check_output_path

    (tmp_path / "f").write_text("x")
    assert check_output_path(tmp_path / "new" / "deeper", "dir", "--out") == tmp_path / "new" / "deeper"
    assert check_output_path(tmp_path / "f", "file", "--json") == tmp_path / "f"
    with pytest.raises(OutputError, match="names a folder"):
        check_output_path(f"{tmp_path}/x/", "file", "--json")
    with pytest.raises(OutputError, match="the path is empty"):
        check_output_path("", "file", "--json")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]
    shutil.rmtree(tmp_path / "f", ignore_errors=True)


def test_json_dash_writes_the_result_to_stdout_alone(tmp_path, capsys, setup_file, monkeypatch):
    """``--json -``: the JSON is all of standard output (the command's own lines go to stderr); no file named ``-``."""
    import json

    monkeypatch.chdir(tmp_path)
    code, out, err = _run(capsys, "presets", "--json", "-")
    assert code == 0
    names = [p["name"] for p in json.loads(out)["presets"]]
    assert "thesis-1.10-deflectometry" in names and "thesis-1.10-deflectometry" in err  # the table, on stderr
    code, out, err = _run(
        capsys, "render", setup_file, "--renderer", "analytic", "--out", tmp_path / "o", "--json", "-"
    )
    assert code == 0
    assert Path(json.loads(out)["image"]).is_file()  # printed once the staged folder was in place
    assert not (tmp_path / "-").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["in", "o"]


def test_json_in_a_missing_folder_is_refused_before_the_work(tmp_path, capsys, setup_file):
    missing = tmp_path / "missing" / "dir"
    code, _, err = _run(capsys, "presets", "--json", missing / "x.json")
    assert code == 2
    _one_error_line(err, f"--json {missing / 'x.json'}: the folder {missing} does not exist")
    code, _, err = _run(
        capsys, "render", setup_file, "--renderer", "analytic", "--out", tmp_path / "o", "--json", missing / "r.json"
    )
    assert code == 2
    _one_error_line(err, "does not exist")
    _untouched(tmp_path)  # neither the folders of --json nor the render's --out
