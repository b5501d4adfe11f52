"""An MDA that a device fault stops, or that has nothing to do: no file without a plane (single OME-TIFF, OME-Zarr,
per-position OME-TIFFs and their folder), no file referring to a removed one, a rerun not blocked, and the line
saying how many of the plan's planes are on disk. Faults from the simulated devices' injection."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import pytest

pytest.importorskip("useq", reason="useq-schema (optional extra 'mm') is not installed")
pytest.importorskip("pymmcore_plus", reason="pymmcore-plus (optional extra 'mm') is not installed")
tifffile = pytest.importorskip("tifffile")

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
    assert "never acquired are missing" in line
