"""The optional Z_std channel of height-map EXR files (a reconstruction's per-node uncertainty)."""


def test_height_map_carries_an_optional_z_std_channel(tmp_path):
    import numpy as np

    from scopetwin.scenes.io import read_heightmap, read_heightmap_std, write_heightmap
    from scopetwin.scenes.surface import HeightMap

    z = HeightMap(np.arange(30.0).reshape(5, 6) * 1e-3, -1.0, 1.0, -2.0, 2.0)
    s = HeightMap(np.full((5, 6), 2e-5), -1.0, 1.0, -2.0, 2.0)
    write_heightmap(tmp_path / "a.exr", z, s)
    write_heightmap(tmp_path / "b.exr", z)
    assert np.allclose(read_heightmap(tmp_path / "a.exr").z, z.z)
    std = read_heightmap_std(tmp_path / "a.exr")
    assert std is not None and np.allclose(std.z, 2e-5) and std.x_max == 1.0
    assert read_heightmap_std(tmp_path / "b.exr") is None
