"""``dataset export``: the names of a dataset from someone else (image files, map layers, its folder) written into
Zarr and HDF5. A name either array format takes comes back as it was (zarr, h5py); one that neither takes as an
array's name (a path separator, a path step, NUL or another control character, text that is not Unicode, Zarr's
reserved ``__``, a coordinate's name) is one clear error before anything is written."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.sim.datasets import export as export_mod
from scopetwin.sim.datasets.config import DatasetError

zarr = pytest.importorskip("zarr")
h5py = pytest.importorskip("h5py")


class _Sample:
    """A ``grin``-like sample: images and map layers by name, nothing else."""

    def __init__(self, index, images, maps):
        self.index, self.kind, self.truth = index, "grin", {}
        self.images = {n: np.full((4, 3), index, np.float32) for n in images}
        self.maps = {n: np.full((4, 3), index + 0.5, np.float32) for n in maps}

    def arrays(self, names):
        return {n: self.images[n] if n in self.images else self.maps[n] for n in names}


class _Dataset(list):
    def __init__(self, root, images=("image",), maps=()):
        super().__init__(_Sample(k, images, maps) for k in range(2))
        self.root, self.kind, self.format, self.indices = root, "grin", 2, [0, 1]


def _read(out, to, name):
    if to == "zarr":
        group = zarr.open_group(str(out), mode="r")
        return np.asarray(group[name]), dict(group.attrs)
    with h5py.File(out, "r") as f:
        return f[name][()], {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}


@pytest.mark.parametrize("to", ["zarr", "hdf5"])
def test_names_either_format_takes_come_back_as_they_were(tmp_path, to):
    folder = tmp_path / 'lab "A" <1> & co\nrun 2'  # the dataset's folder names the export (its attributes)
    image, layer = "image_q\"<&>'", "ünï €..x"
    dataset = _Dataset(folder, images=(image,), maps=(layer,))
    out = tmp_path / f"x.{to}"
    result = export_mod.export(dataset, out, to)
    assert sorted(result["variables"]) == sorted([image, layer])
    data, attrs = _read(out, to, image)
    assert data.shape == (2, 4, 3) and data[1].max() == 1.0
    assert _read(out, to, layer)[0][0].max() == 0.5
    assert attrs["title"] == f"scopetwin dataset {folder.name}" and attrs["scopetwin_dataset"] == str(folder)


@pytest.mark.parametrize("to", ["zarr", "hdf5"])
def test_a_folder_name_in_another_encoding_is_written_as_text(tmp_path, to):
    folder = tmp_path / "caf\udce9"  # b"caf\xe9": Latin-1, not UTF-8
    out = tmp_path / f"x.{to}"
    export_mod.export(_Dataset(folder), out, to)
    assert _read(out, to, "image")[1]["title"] == "scopetwin dataset caf\\xe9"


HOSTILE = {
    "image_a/b": "holds a '/'",
    "image_\x00x": "holds the character(s) '\\x00'",
    "image_two\nlines": "holds the character(s) '\\n'",
    "image_esc\x1b": "holds the character(s) '\\x1b'",
    "image_caf\udce9": "holds the character(s) '\\udce9'",
    "__image": "begins with '__'",
    "..": "is a path step",
    "x": "has the name of a dimension",
}


@pytest.mark.parametrize("to", ["zarr", "hdf5"])
@pytest.mark.parametrize("name", list(HOSTILE), ids=[repr(n) for n in HOSTILE])
def test_a_name_no_array_can_take_is_one_error_before_anything_is_written(tmp_path, to, name):
    images, maps = ((name,), ()) if name.startswith("image") else (("image",), (name,))
    out = tmp_path / f"x.{to}"
    with pytest.raises(DatasetError) as info:
        export_mod.export(_Dataset(tmp_path / "ds", images, maps), out, to)
    message = str(info.value)
    assert message.startswith(f"sample 0: variable {name!r} {HOSTILE[name]}") and "\n" not in message
    assert list(tmp_path.iterdir()) == []  # no target, no stage


def test_leaving_the_name_out_with_only_exports_the_rest(tmp_path):
    out = tmp_path / "x.zarr"
    export_mod.export(_Dataset(tmp_path / "ds", maps=("bad/name",)), out, "zarr", names=["image"])
    assert _read(out, "zarr", "image")[0].shape == (2, 4, 3)
