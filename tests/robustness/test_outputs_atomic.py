"""Every output written atomically and never through a symbolic link, per kind of output: a file is written beside
its place and renamed over it (a link there is replaced, its target untouched; a write that fails half-way leaves
no file and no temporary one), a folder of its own that is a link is refused before anything is written, and the
OME files of an MDA (the single multi-series file, the files rewritten after a stop) follow the same rules."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from scopetwin.scenes.errors import ScopetwinError


@pytest.fixture
def victim(tmp_path: Path) -> Path:
    """A file elsewhere that no output may touch."""
    path = tmp_path / "elsewhere" / "precious.txt"
    path.parent.mkdir()
    path.write_text("precious")
    return path


def _leftovers(folder: Path) -> list[str]:
    """Temporary files (``.NAME.*.part*``) or stages left in ``folder``."""
    return sorted(p.name for p in folder.iterdir() if p.name.startswith("."))


def _half_then_fail(monkeypatch: pytest.MonkeyPatch) -> None:
    """``Path.write_bytes`` writes half of its data, then the disk is full."""

    def write_bytes(self: Path, data: bytes) -> int:
        with open(self, "wb") as fh:
            fh.write(bytes(data)[: len(data) // 2])
        raise OSError(28, "No space left on device", str(self))

    monkeypatch.setattr(Path, "write_bytes", write_bytes)


# -- PNG previews: sim.measurement.write_preview, sim.cmu_budget's full-scale preview ------------------------------


def _previews(out: Path) -> list[Path]:
    from scopetwin.sim.cmu_budget import _write_previews
    from scopetwin.sim.measurement import write_preview

    image = np.linspace(0.0, 4000.0, 48 * 64).reshape(48, 64)
    write_preview(out / "preview.png", image)
    written = _write_previews(out / "cells_blue.exr", image, 4095)
    return [out / "preview.png", Path(written["preview"]), Path(written["fullscale"])]


def test_a_preview_replaces_a_link_at_its_path_and_leaves_the_target(tmp_path, victim):
    import cv2

    out = tmp_path / "out"
    out.mkdir()
    for name in ("preview.png", "cells_blue.png", "cells_blue_fullscale.png"):
        (out / name).symlink_to(victim)
    for path in _previews(out):
        assert not path.is_symlink() and path.is_file()
        assert cv2.imread(str(path), cv2.IMREAD_UNCHANGED).shape == (48, 64)
    assert victim.read_text() == "precious" and _leftovers(out) == []


def test_a_preview_cut_short_leaves_no_file(tmp_path, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    _half_then_fail(monkeypatch)
    with pytest.raises(OSError, match="No space"):
        _previews(out)
    assert list(out.iterdir()) == []  # neither a half PNG nor a temporary file


# -- the files of `scopetwin run` (sim.pipeline): text and JSON through the helpers, plots through _save_png -----


def test_a_run_plot_replaces_a_link_and_a_failed_one_leaves_nothing(tmp_path, victim, monkeypatch):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from scopetwin.sim.pipeline import _save_png

    fig = Figure(figsize=(2, 2))
    FigureCanvasAgg(fig)
    fig.subplots().plot([0, 1], [1, 0])
    (tmp_path / "height.png").symlink_to(victim)
    _save_png(fig, tmp_path / "height.png", 50)
    assert not (tmp_path / "height.png").is_symlink()
    assert (tmp_path / "height.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert victim.read_text() == "precious"

    def cut(path: Path, **_: object) -> None:
        Path(path).write_text("half a PNG")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(fig, "savefig", cut)
    with pytest.raises(OSError):
        _save_png(fig, tmp_path / "error.png", 50)
    assert not (tmp_path / "error.png").exists() and _leftovers(tmp_path) == []


# -- folders of their own: a link there is refused before anything is written ---------------------------------------


def test_folder_outputs_refuse_a_link_to_another_folder(tmp_path, victim):
    from scopetwin.instrument.acquisition import FrameWriter
    from scopetwin.instrument.errors import RigError
    from scopetwin.sim.cmu_budget import render_cells
    from scopetwin.sim.cmu_unit import render_and_measure
    from scopetwin.sim.pipeline import run_pipeline

    link = tmp_path / "out"
    link.symlink_to(victim.parent, target_is_directory=True)
    with pytest.raises(RigError, match="symbolic link"):
        FrameWriter(link)
    with pytest.raises(ScopetwinError, match="symbolic link"):
        run_pipeline(link, spp=1, seed=0, progress=False)
    with pytest.raises(ScopetwinError, match="symbolic link"):
        render_cells(None, link)
    with pytest.raises(ScopetwinError, match="symbolic link"):
        render_and_measure(None, {}, {}, link, 1, False, False)
    assert [p.name for p in victim.parent.iterdir()] == ["precious.txt"]


def test_a_dataset_is_not_generated_into_a_linked_folder(tmp_path, victim):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "sim"))
    from test_dataset_common import write_tiny

    from scopetwin.sim.datasets.config import load_config
    from scopetwin.sim.datasets.plan import Plan
    from scopetwin.sim.datasets.store import generate

    plan = Plan.build(load_config(write_tiny(tmp_path, count=1)))
    link = tmp_path / "ds"
    link.symlink_to(victim.parent, target_is_directory=True)
    with pytest.raises(ScopetwinError, match="symbolic link"):
        generate(plan, link, workers=0, progress=False)
    assert [p.name for p in victim.parent.iterdir()] == ["precious.txt"]


# -- the OME files of an MDA ------------------------------------------------------------------------------------------


def _ome_output(path: Path, *, positions: int = 2, single_file: bool = False):
    pytest.importorskip("ome_writers", reason="ome-writers (optional extra 'mm') is not installed")
    from scopetwin.instrument.ome import AcquisitionInfo, ChannelInfo, Layout, OmeOutput

    layout = Layout(
        axes=("p", "c", "z"),
        sizes={"p": positions, "c": 2, "z": 2},
        positions=tuple((p, 0) for p in range(positions)),
        names=tuple(f"pos{p}" for p in range(positions)),
        z_step_um=1.0,
    )
    info = AcquisitionInfo(
        shape=(4, 6), dtype="uint16", bit_depth=12, pixel_size_um=0.5, channels=(ChannelInfo("a"), ChannelInfo("b"))
    )
    return OmeOutput(path, layout, info, single_file=single_file)


def _append(out, planes: int) -> None:
    for n in range(planes):
        index = {"p": n // 4, "c": n // 2 % 2, "z": n % 2}
        out.append(np.full((4, 6), n + 1, dtype=np.uint16), index, {"x_um": 0.0, "y_um": 0.0, "exposure_ms": 1.0})


@pytest.mark.parametrize(("name", "link", "single_file"), [
    ("x.ome.tif", "x.ome.tif", True),
    ("x.ome.tif", "x", False),
    ("x.ome.zarr", "x.ome.zarr", False),
])  # fmt: skip
def test_an_mda_output_at_a_link_is_refused_before_anything_is_written(tmp_path, victim, name, link, single_file):
    from scopetwin.instrument.errors import RigError

    target = victim if "." in link else victim.parent
    (tmp_path / link).symlink_to(target, target_is_directory=target.is_dir())
    with pytest.raises(RigError, match="symbolic link"):
        _ome_output(tmp_path / name, single_file=single_file)
    assert [p.name for p in victim.parent.iterdir()] == ["precious.txt"] and victim.read_text() == "precious"


def test_the_single_ome_tiff_appears_whole_or_not_at_all(tmp_path, monkeypatch):
    """Written beside its place while the planes come; renamed into place when closed with its OME-XML. A failure
    while the metadata is written leaves neither the file nor a temporary one."""
    tifffile = pytest.importorskip("tifffile")
    out = _ome_output(tmp_path / "x.ome.tif", single_file=True)
    _append(out, 3)
    assert not (tmp_path / "x.ome.tif").exists()  # not at its place while it is written
    monkeypatch.setattr(tifffile, "tiffcomment", _fail)
    with pytest.raises(OSError, match="No space"):
        out.close()
    assert list(tmp_path.iterdir()) == []
    monkeypatch.undo()
    out = _ome_output(tmp_path / "x.ome.tif", single_file=True)
    _append(out, 3)
    assert out.close() == [str(tmp_path / "x.ome.tif")] and _leftovers(tmp_path) == []
    with tifffile.TiffFile(tmp_path / "x.ome.tif") as tif:
        assert tif.is_ome and len(tif.pages) == 3


def _fail(*_: object, **__: object) -> None:
    raise OSError(28, "No space left on device")


def test_a_stopped_runs_tiff_rewrite_that_fails_leaves_the_file_as_it_was(tmp_path, monkeypatch):
    """The OME-XML of a stopped run is written on a copy beside the file: a failure there leaves the file's bytes
    as they were and no copy."""
    tifffile = pytest.importorskip("tifffile")
    import scopetwin.instrument.ome_pieces as pieces

    out = _ome_output(tmp_path / "x.ome.tif", positions=1)
    _append(out, 3)
    before = {}
    real = pieces.rewrite_tiff_files

    def fail_after_copy(out_, files):
        before.update({p: path.read_bytes() for p, path in files.items()})
        monkeypatch.setattr(tifffile, "tiffcomment", _fail)
        real(out_, files)

    monkeypatch.setattr(pieces, "rewrite_tiff_files", fail_after_copy)
    with pytest.raises(OSError, match="No space"):
        out.close()
    assert (tmp_path / "x.ome.tif").read_bytes() == before[0] and _leftovers(tmp_path) == []


def test_a_stopped_runs_zarr_extra_image_that_fails_leaves_no_part_of_it(tmp_path, monkeypatch):
    """An extra image is built in a hidden folder beside its place: a failure while its planes are copied leaves
    neither the image nor the folder."""
    zarr = pytest.importorskip("zarr")
    out = _ome_output(tmp_path / "x.ome.zarr", positions=1)
    _append(out, 3)  # c0 (z0, z1), then c1 z0: the main image c0, the extra image c1z0
    real = zarr.open_array

    def open_array(store, *args, **kwargs):
        if ".partial" in str(store):
            raise OSError(28, "No space left on device")
        return real(store, *args, **kwargs)

    monkeypatch.setattr(zarr, "open_array", open_array)
    with pytest.raises(OSError, match="No space"):
        out.close()
    assert sorted(p.name for p in (tmp_path / "x.ome.zarr").iterdir()) == ["0", "zarr.json"]
