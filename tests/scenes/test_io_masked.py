"""A reconstruction's height map with nodes no marker measured: NaN in Z, the mask in Z_measured, refused as a
surface with one line naming why."""

from __future__ import annotations

import numpy as np
import OpenEXR
import pytest

from scopetwin.scenes.errors import FileFormatError
from scopetwin.scenes.io import read_heightmap, write_heightmap
from scopetwin.scenes.surface import HeightMap


def test_masked_height_map_holds_nan_and_its_mask(tmp_path):
    z = np.arange(6 * 5, dtype=np.float64).reshape(6, 5) * 1e-3
    hm = HeightMap(z, -2.0, 2.0, -3.0, 3.0)
    measured = np.ones_like(z, dtype=bool)
    measured[2:4, 1:3] = False
    path = tmp_path / "heights.exr"
    write_heightmap(path, hm, hm, measured)
    with OpenEXR.File(str(path)) as f:
        channels = f.channels()
        zz = np.asarray(channels["Z"].pixels, dtype=np.float64)
        mm = np.asarray(channels["Z_measured"].pixels)
        sd = np.asarray(channels["Z_std"].pixels, dtype=np.float64)
    assert np.isnan(zz[~measured]).all()
    np.testing.assert_allclose(zz[measured], z[measured], rtol=1e-6)
    np.testing.assert_array_equal(mm, measured.astype(np.float32))
    np.testing.assert_allclose(sd, z, rtol=1e-6)  # the uncertainty stays finite everywhere
    with pytest.raises(FileFormatError, match=r"4 node\(s\) of Z are NaN.*Z_measured"):
        read_heightmap(path)


def test_mask_of_another_grid_is_refused(tmp_path):
    hm = HeightMap(np.zeros((6, 5)), -2.0, 2.0, -3.0, 3.0)
    with pytest.raises(FileFormatError, match="Z_measured"):
        write_heightmap(tmp_path / "h.exr", hm, measured=np.ones((5, 5), dtype=bool))
    assert not (tmp_path / "h.exr").exists()
