"""EXR files of the contract: round trips, header attributes, clear errors, atomic writes."""

import json

import numpy as np
import pytest

from scopetwin.scenes.errors import FileFormatError
from scopetwin.scenes.io import read_heightmap, read_image, write_heightmap, write_image
from scopetwin.scenes.surface import HeightMap


def test_heightmap_round_trip(tmp_path, rng):
    hm = HeightMap(rng.normal(size=(16, 12)) * 1e-3, -12.6, 12.6, -28.5, 28.5)
    write_heightmap(tmp_path / "z.exr", hm)
    back = read_heightmap(tmp_path / "z.exr")
    np.testing.assert_array_equal(back.z, hm.z.astype(np.float32))
    # extents are EXR float attributes (32-bit): a few nm at these sizes
    np.testing.assert_allclose([back.x_min, back.x_max, back.y_min, back.y_max], [-12.6, 12.6, -28.5, 28.5], atol=1e-6)
    assert [p.name for p in tmp_path.iterdir()] == ["z.exr"]


def test_image_round_trip_with_setup_and_provenance(tmp_path, rng):
    img = rng.random((20, 30)).astype(np.float32)
    write_image(tmp_path / "i.exr", img, '{"name": "x"}', {"seed": 3, "spp": 16})
    back, attrs = read_image(tmp_path / "i.exr")
    np.testing.assert_array_equal(back, img)
    assert json.loads(attrs["scopetwin_setup"]) == {"name": "x"}
    assert json.loads(attrs["scopetwin_provenance"])["spp"] == 16


def test_wrong_channel_and_unreadable_files(tmp_path):
    write_image(tmp_path / "i.exr", np.zeros((4, 4)))
    with pytest.raises(FileFormatError, match="no channel 'Z'"):
        read_heightmap(tmp_path / "i.exr")
    (tmp_path / "junk.exr").write_text("not an exr")
    with pytest.raises(FileFormatError, match="not a readable OpenEXR"):
        read_heightmap(tmp_path / "junk.exr")
    with pytest.raises(FileFormatError, match="does not exist"):
        read_image(tmp_path / "missing.exr")


def test_failed_write_leaves_nothing(tmp_path):
    with pytest.raises(FileFormatError):
        write_image(tmp_path / "bad.exr", np.zeros((2, 2, 2)))
    assert list(tmp_path.iterdir()) == []
