"""``dataset export``: a target that another process creates while the export runs is neither replaced (a file,
HDF5) nor removed with what that process put in it (a folder, Zarr); the export says so in one error. Without a
race the export moves into place as before."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pytest

from scopetwin.sim.datasets import export as export_mod
from scopetwin.sim.datasets.config import DatasetError


def _plan(out: Path, to: str) -> SimpleNamespace:
    return SimpleNamespace(out=out, to=to, dataset=[], per_sample={}, stacked={})


def _writer_racing(other: Path, make_other: bool):
    """A writer that writes its export, while another process creates ``other`` (the target) meanwhile."""

    def write(path: Path, plan, progress) -> None:
        if plan.to == "zarr":
            path.mkdir()
            (path / "zarr.json").write_text("{}")
        else:
            path.write_bytes(b"\x89HDF export")
        if make_other:
            if plan.to == "zarr":
                other.mkdir()
                (other / "theirs.txt").write_text("another process's file")
            else:
                other.write_text("another process's file")

    return write


@pytest.mark.parametrize("to", ["hdf5", "zarr"])
def test_a_target_created_meanwhile_is_left_as_it_is(tmp_path, monkeypatch, to):
    out = tmp_path / ("x.h5" if to == "hdf5" else "x.zarr")
    monkeypatch.setattr(export_mod, f"_write_{to}", _writer_racing(out, make_other=True))
    with pytest.raises(DatasetError, match="appeared while the export ran"):
        export_mod.write_export(_plan(out, to))
    theirs = out / "theirs.txt" if to == "zarr" else out
    assert theirs.read_text() == "another process's file"  # not replaced, not removed
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]  # and no stage left behind


@pytest.mark.parametrize("to", ["hdf5", "zarr"])
def test_without_a_race_the_export_moves_into_place(tmp_path, monkeypatch, to):
    out = tmp_path / ("x.h5" if to == "hdf5" else "x.zarr")
    monkeypatch.setattr(export_mod, f"_write_{to}", _writer_racing(out, make_other=False))
    assert export_mod.write_export(_plan(out, to))["out"] == str(out)
    assert (out / "zarr.json").exists() if to == "zarr" else out.read_bytes() == b"\x89HDF export"
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]


def test_a_file_put_into_the_claimed_folder_is_kept(tmp_path, monkeypatch):
    """The folder claimed for a Zarr store gets another process's file before the rename: it stays, with it."""
    import os

    tmp = tmp_path / "stage" / "x.zarr"
    tmp.mkdir(parents=True)
    (tmp / "zarr.json").write_text("{}")
    out = tmp_path / "x.zarr"
    real_replace = os.replace

    def replace(src, dst):
        (Path(dst) / "theirs.txt").write_text("another process's file")
        return real_replace(src, dst)

    monkeypatch.setattr(export_mod.os, "replace", replace)
    with pytest.raises(DatasetError, match="appeared while the export ran"):
        export_mod._move_into_place(tmp, out)
    assert (out / "theirs.txt").read_text() == "another process's file"
