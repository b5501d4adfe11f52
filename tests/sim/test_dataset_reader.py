"""scopetwin.open_dataset: a generated dataset read back lazily as a sequence, without private code."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_dataset_common import write_tiny  # noqa: E402

import scopetwin  # noqa: E402
from scopetwin.scenes.io import read_image  # noqa: E402
from scopetwin.sim.datasets.config import load_config  # noqa: E402
from scopetwin.sim.datasets.plan import Plan  # noqa: E402
from scopetwin.sim.datasets.reader import DatasetReadError  # noqa: E402
from scopetwin.sim.datasets.store import SAMPLES, generate  # noqa: E402

pytestmark = pytest.mark.mitsuba


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("reader")
    root = folder / "ds"
    generate(Plan.build(load_config(write_tiny(folder, count=3))), root, workers=0, progress=False)
    return root


def test_the_reader_gives_every_sample_with_its_files(tiny):
    ds = scopetwin.open_dataset(tiny)
    assert len(ds) == 3 and ds.kind == "deflectometry" and "samples=3" in repr(ds)
    for i, sample in enumerate(ds):
        assert sample.index == i
        raw, _ = read_image(tiny / SAMPLES / f"{i:06d}" / "image.exr")
        assert np.array_equal(sample.image, raw)  # the bytes on disk, nothing added
        assert sample.truth == json.loads((tiny / SAMPLES / f"{i:06d}" / "truth.json").read_text())
        assert sample.truth["sample"] == i and sample.kind == "deflectometry"
        assert sample.setup.scene == "deflectometry"
        assert "image.exr" in sample.meta["files"]
    assert ds[-1].index == 2
    assert [s.index for s in ds[1:]] == [1, 2] and len(ds[::2]) == 2
    with pytest.raises(IndexError):
        ds[3]
    with pytest.raises(TypeError):
        ds["0"]  # type: ignore[call-overload]


def test_a_sample_folder_not_finished_is_not_listed(tiny, tmp_path):
    import shutil

    copy = tmp_path / "copy"
    shutil.copytree(tiny, copy)
    (copy / SAMPLES / "000001" / "sample.json").unlink()  # as a folder whose writer died before finishing
    assert [s.index for s in scopetwin.open_dataset(copy)] == [0, 2]


def test_not_a_dataset_is_one_clear_error(tmp_path):
    with pytest.raises(DatasetReadError, match="not a dataset folder"):
        scopetwin.open_dataset(tmp_path)
    with pytest.raises(DatasetReadError, match="not a folder"):
        scopetwin.open_dataset(tmp_path / "nothing")


def test_a_dataloader_takes_it_as_a_map_style_dataset(tiny):
    """The protocol torch's DataLoader uses for a map-style dataset: len() and integer indexing."""
    ds = scopetwin.open_dataset(tiny)
    batch = [ds[i].image for i in range(len(ds))]
    assert np.stack(batch).shape == (3, *ds[0].image.shape)
    torch = pytest.importorskip("torch")
    loader = torch.utils.data.DataLoader(ds, batch_size=2, collate_fn=lambda s: [x.image for x in s])
    assert [len(b) for b in loader] == [2, 1]


def _collatable(value: object) -> bool:
    """What torch's default collate batches: numpy arrays of numbers or bools, numbers, strings."""
    if isinstance(value, np.ndarray):
        return value.dtype.kind in "biuf"
    return isinstance(value, int | float | str) and not isinstance(value, bool)


def test_arrays_gives_plain_dicts_with_the_camera_and_the_marker_truth(tiny):
    ds = scopetwin.open_dataset(tiny)
    view = ds.arrays("image", "height", "mask", camera=True, markers=True)
    assert len(view) == 3 and len(view[1:]) == 2 and view[1:].camera and view[1:].markers
    for k, item in enumerate(view):
        assert type(item) is dict and all(_collatable(v) for v in item.values()), item
        sample = ds[k]
        assert item["index"] == k and item["kind"] == "deflectometry"
        assert np.array_equal(item["image"], sample.image) and item["mask"].dtype == bool
        assert np.array_equal(item["height"], sample.maps["height"], equal_nan=True)
        for name in ("K", "dist", "R", "t"):
            assert np.array_equal(item[name], getattr(sample.camera, name)) and item[name].dtype == np.float64
        assert item["K"].shape == (3, 3) and item["dist"].shape == (5,) and item["t"].shape == (3,)
        table = sample.truth.markers
        assert np.array_equal(item["marker_ij"], table.ij) and item["marker_ij"].dtype == np.int64
        assert np.array_equal(item["marker_px"], table.center_px, equal_nan=True)
        assert np.array_equal(item["marker_visible"], table.visible) and item["marker_visible"].dtype == bool
        assert item["marker_ij"].shape[0] == item["marker_px"].shape[0] == item["marker_visible"].shape[0] > 0
    plain = ds.arrays()[0]
    assert set(plain) == {"index", "kind", "image"}  # the camera and the markers only when asked for


def test_a_dataloader_batches_the_plain_dicts(tiny):
    torch = pytest.importorskip("torch")
    ds = scopetwin.open_dataset(tiny)
    loader = torch.utils.data.DataLoader(ds.arrays("image", "height", camera=True, markers=True), batch_size=2)
    first, second = list(loader)
    assert tuple(first["image"].shape) == (2, *ds[0].image.shape) and first["kind"] == ["deflectometry"] * 2
    assert tuple(first["K"].shape) == (2, 3, 3) and first["index"].tolist() == [0, 1]
    assert first["marker_ij"].shape[0] == 2 and tuple(second["t"].shape) == (1, 3)
