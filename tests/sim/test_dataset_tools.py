"""The dataset tools: ``generate --set``, ``show`` (a contact sheet), ``export --to zarr | hdf5`` (one
array with named dimensions that xarray opens), the reader on the four-channel and GRIN kinds."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_dataset_common import write_tiny  # noqa: E402

import scopetwin  # noqa: E402
from scopetwin.cli import main as scopetwin_main  # noqa: E402
from scopetwin.sim.datasets.config import DatasetError, apply_overrides, load_config  # noqa: E402
from scopetwin.sim.datasets.store import verify  # noqa: E402

pytestmark = pytest.mark.mitsuba


@pytest.fixture(scope="module")
def small(tmp_path_factory) -> Path:
    """A 3-sample deflectometry set made through the command line with --set overrides."""
    folder = tmp_path_factory.mktemp("tools")
    out = folder / "ds"
    cfg = write_tiny(folder, count=3)
    code = scopetwin_main(
        ["dataset", "generate", str(cfg), "--out", str(out), "--workers", "0", "-q", "--set", "render.spp=2"]
        + ["--set", "setup.camera.pixels=[85, 64]", "--set", "setup.camera.pixel_pitch=0.0744"]
    )
    assert code == 0
    return out


def test_set_overrides_config_keys_with_the_files_validation(small, tmp_path, capsys):
    stored = json.loads((small / "dataset.json").read_text())
    assert stored["config"]["dataset"]["spp"] == 2 and stored["base_setup"]["camera"]["pixels"] == [85, 64]
    assert scopetwin.open_dataset(small)[0].image.shape == (64, 85)
    cfg = write_tiny(tmp_path, count=2)
    for bad, says in (
        ("dataset.spp=0", "dataset.spp"),  # validated like the file
        ("dataset.colour=red", "dataset.colour"),  # unknown key, named
        ("vary.surface_range_um.uniform=[0, 1e300]", "physical range"),
        ("spp", "key=value"),
    ):
        assert scopetwin_main(["dataset", "generate", str(cfg), "--out", str(tmp_path / "x"), "--set", bad]) == 2
        assert says in capsys.readouterr().err
        assert not (tmp_path / "x").exists()
    data = apply_overrides({"dataset": {"kind": "deflectometry"}}, ['vary.surface_kind.choice=["plane", "sphere"]'])
    assert data["vary"]["surface_kind"]["choice"] == ["plane", "sphere"]
    assert apply_overrides({}, ["dataset.setup=thesis-1.10-deflectometry"])["dataset"]["setup"].startswith("thesis")
    with pytest.raises(DatasetError, match="is a value, not a table"):
        apply_overrides({"dataset": {"spp": 4}}, ["dataset.spp.x=1"])
    assert load_config(cfg, overrides=["render.noise=false"]).dataset.noise is False


def test_the_readme_reads_a_dataset_in_five_lines(small):
    import re

    text = (Path(__file__).resolve().parents[2] / "README.md").read_text().split("## Datasets", 1)[1]
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    assert len([line for line in code.splitlines() if line.strip()]) == 5
    scope: dict[str, object] = {}
    exec(compile(code.replace('"ds-deflectometry"', repr(str(small))), "README.md", "exec"), scope)  # noqa: S102
    image, height, mask, K = scope["image"], scope["height"], scope["mask"], scope["K"]
    assert image.shape == height.shape == mask.shape == (64, 85) and mask.dtype == bool  # type: ignore[attr-defined]
    assert K.shape == (3, 3)  # type: ignore[attr-defined]


def test_show_draws_a_contact_sheet(small, tmp_path):
    import matplotlib.image as mpimg

    out = tmp_path / "sheet.png"
    assert scopetwin_main(["dataset", "show", str(small), "--indices", "0:2", "--out", str(out), "-q"]) == 0
    img = mpimg.imread(out)
    assert img.ndim == 3 and img.shape[0] > 200 and img.shape[1] > 400
    assert np.ptp(img[..., :3]) > 0.5  # drawn, not blank
    assert scopetwin_main(["dataset", "show", str(small), "--indices", "0:9", "--out", str(out)]) == 2  # 9 > count


@pytest.mark.parametrize("to", ["zarr", "hdf5"])
def test_export_stacks_every_sample_as_named_arrays(small, tmp_path, to):
    xr = pytest.importorskip("xarray")
    out = tmp_path / ("ds.zarr" if to == "zarr" else "ds.h5")
    assert scopetwin_main(["dataset", "export", str(small), "--to", to, str(out), "-q"]) == 0
    x = xr.open_zarr(out) if to == "zarr" else xr.open_dataset(out, engine="h5netcdf")
    ds = scopetwin.open_dataset(small)
    assert x["image"].dims == ("sample", "y", "x") and x.sizes["sample"] == 3
    assert x["point"].dims == ("sample", "y", "x", "xyz") and x["marker"].dims[-1] == "ij"
    assert list(x["sample"].values) == [0, 1, 2]
    for k, sample in enumerate(ds):
        assert np.array_equal(x["image"].values[k], sample.image)
        assert np.array_equal(x["mask"].values[k].astype(bool), sample.maps["mask"])
        assert np.array_equal(x["height"].values[k], sample.maps["height"], equal_nan=True)
        assert np.array_equal(x["marker_id"].values[k], sample.maps["marker_id"])
        assert x["surface_range_um"].values[k] == sample.truth.parameters["surface_range_um"]
    x.close()
    assert scopetwin_main(["dataset", "export", str(small), "--to", to, str(out)]) == 2  # never overwritten


def _read_back(out: Path, to: str) -> tuple[dict[str, np.ndarray], dict[str, dict[str, object]]]:
    """Every array and its attributes of an export, read with zarr or h5py themselves."""
    if to == "zarr":
        import zarr

        group = zarr.open_group(str(out), mode="r")
        names = [name for name, _ in group.arrays()]
        return {n: group[n][...] for n in names}, {n: dict(group[n].attrs) for n in names}
    h5py = pytest.importorskip("h5py")
    with h5py.File(out, "r") as f:
        return {n: f[n][...] for n in f}, {n: {k: _text(v) for k, v in f[n].attrs.items()} for n in f}


def _text(value: object) -> object:
    return value.decode() if isinstance(value, bytes) else value


@pytest.mark.parametrize("to", ["zarr", "hdf5"])
def test_export_carries_the_camera_the_marker_truth_and_units(small, tmp_path, to):
    pytest.importorskip("zarr" if to == "zarr" else "h5py")
    out = tmp_path / ("ds.zarr" if to == "zarr" else "ds.h5")
    assert scopetwin_main(["dataset", "export", str(small), "--to", to, str(out), "-q"]) == 0
    values, attrs = _read_back(out, to)
    ds = scopetwin.open_dataset(small)
    for k, sample in enumerate(ds):
        for name in ("K", "dist", "R", "t"):
            assert np.array_equal(values[name][k], getattr(sample.camera, name))
        table = sample.truth.markers
        n = len(table.ij)
        assert np.array_equal(values["marker_ij"][k, :n], table.ij)
        assert np.array_equal(values["marker_px"][k, :n], table.center_px, equal_nan=True)
        assert np.array_equal(values["marker_visible"][k, :n].astype(bool), table.visible)
        assert (values["marker_ij"][k, n:] == -1).all() and not values["marker_visible"][k, n:].any()
    units = {name: a.get("units") for name, a in attrs.items()}
    assert units["K"] == "px" and units["t"] == "mm" and units["dist"] == "1" and units["R"] == "1"
    assert units["marker_px"] == "px" and units["marker_ij"] is None and units["marker_visible"] is None
    assert units["height"] == "mm" and units["point"] == "mm" and units["normal"] == "1" and units["mask"] is None
    assert units["surface_range_um"] == "um" and units["x"] == "px" and units["image"] is None
    assert all(isinstance(a.get("description"), str) for a in attrs.values())


def test_export_with_xarray_names_the_camera_and_marker_dimensions(small, tmp_path):
    xr = pytest.importorskip("xarray")
    out = tmp_path / "ds.h5"
    assert scopetwin_main(["dataset", "export", str(small), "--to", "hdf5", str(out), "-q", "--only", "K", "t"]) == 0
    with xr.open_dataset(out, engine="h5netcdf") as x:
        assert x["K"].dims == ("sample", "cam_row", "cam_col") and x["t"].dims == ("sample", "xyz")
        assert x["K"].attrs["units"] == "px" and "image" not in x
    out = tmp_path / "ds.zarr"
    assert scopetwin_main(["dataset", "export", str(small), "--to", "zarr", str(out), "-q"]) == 0
    x = xr.open_zarr(out)
    assert x["marker_px"].dims == ("sample", "markers", "xy") and x["marker_ij"].dims[-1] == "ij"
    assert x["marker"].dims == ("sample", "y", "x", "ij") and x["height"].attrs["units"] == "mm"


def test_export_refuses_before_the_progress_bar_starts(small, tmp_path, capsys):
    out = tmp_path / "taken.zarr"
    out.mkdir()
    assert scopetwin_main(["dataset", "export", str(small), "--to", "zarr", str(out)]) == 2
    err = capsys.readouterr().err
    assert "already exists" in err and "export:" not in err and "sample/s" not in err  # no tqdm bar drawn
    fresh = tmp_path / "fresh.zarr"
    assert scopetwin_main(["dataset", "export", str(small), "--to", "zarr", str(fresh), "--only", "nothing"]) == 2
    err = capsys.readouterr().err
    assert "no variable 'nothing'" in err and "export:" not in err and not fresh.exists()


TINY_CMU = """
[dataset]
kind = "cmu"
setup = "thesis-cmu"
count = 1
master_seed = 51
spp = 4
noise = false
preview = false

[setup.camera]
width_px = 160
height_px = 144

[setup.target]
star_radius = 0.03
frame_side = 0.075
frame_line = 0.003

[cmu]
channels = ["green", "nir"]

[vary]
channel_offset_px = { uniform = [-8.0, 8.0] }
channel_tilt_deg = { uniform = [-0.3, 0.3] }
"""


def test_the_reader_on_a_four_channel_sample(tmp_path):
    from scopetwin.sim.datasets.plan import Plan
    from scopetwin.sim.datasets.store import generate

    cfg = tmp_path / "cmu.toml"
    cfg.write_text(TINY_CMU)
    root = tmp_path / "ds"
    generate(Plan.build(load_config(cfg)), root, workers=0, progress=False)
    assert verify(root)["ok"]
    sample = scopetwin.open_dataset(root)[0]
    assert set(sample.images) == {"image_green", "image_nir"}
    maps = sample.maps
    assert set(maps) == {"object_xy_green", "object_xy_nir"}
    for ch in ("green", "nir"):
        entry = sample.truth["channels"][ch]
        assert maps[f"object_xy_{ch}"].shape == (144, 160, 2)
        # the star's centre (object (0, 0)) is imaged at frame_center_px: that pixel maps back onto the centre
        col, row = np.floor(entry["frame_center_px"]).astype(int)
        mm_per_px = 1e-3 * sample.setup["camera"]["pixel_um"] / entry["magnification"]
        assert np.abs(maps[f"object_xy_{ch}"][row, col]).max() < 1.5 * mm_per_px
        assert entry["object_to_pixel_residual_px"] < 0.5
    with pytest.raises(scopetwin.sim.datasets.reader.DatasetReadError, match="no single pinhole camera"):
        _ = sample.camera


def test_the_reader_on_grin_samples_with_their_object_coordinates(tmp_path):
    """GRIN samples: object_xy is where each pixel centre's chief ray comes from; the target seen through it is the
    image (the lines run along y: swapping the axes or shifting the pattern by half a period destroys that)."""
    from scopetwin.scenes.grin.targets import target
    from scopetwin.sim.datasets.plan import Plan
    from scopetwin.sim.datasets.store import generate

    cfg = tmp_path / "grin.toml"
    cfg.write_text(
        '[dataset]\nkind = "grin"\nsetup = "thesis-8.3.2-grin-realized"\ncount = 2\nmaster_seed = 8\nspp = 4\n'
        "preview = false\n[grin]\nwidth = 96\nheight = 96\nstep_mm = 0.9\n[vary]\n"
        'target = { sweep = ["lines-8", "dots-25"] }\n'
    )
    root = tmp_path / "ds"
    generate(Plan.build(load_config(cfg)), root, workers=0, progress=False)
    assert verify(root)["ok"]
    for sample in scopetwin.open_dataset(root):
        assert sample.kind == "grin" and sample.image.shape == (96, 96) and sample.truth.format == 2
        xy = sample.maps["object_xy"]
        assert xy.shape == (96, 96, 2) and np.isfinite(xy).all()
        cx, cy = sample.truth["centre_mm"]  # the objective's axis (a one-objective window)
        tgt = target(sample.truth["target"]["name"])
        img = sample.image.ravel()
        u, v = (xy[..., 0] - cx).ravel(), (xy[..., 1] - cy).ravel()
        seen = np.corrcoef(img, tgt.transmission(u, v))[0, 1]
        assert seen > 0.7, seen
        shifted = np.corrcoef(img, tgt.transmission(u + 0.5 * tgt.period, v + 0.5 * tgt.period))[0, 1]
        assert shifted < 0.0, shifted
        if tgt.pattern == "lines":
            assert abs(np.corrcoef(img, tgt.transmission(v, u))[0, 1]) < 0.3  # x and y swapped
    with pytest.raises(scopetwin.sim.datasets.reader.DatasetReadError, match="no single pinhole camera"):
        _ = sample.camera
