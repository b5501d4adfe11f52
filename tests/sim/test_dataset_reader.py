"""scopetwin.open_dataset: a generated dataset read back lazily as a sequence, without private code (issue 22)."""

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
