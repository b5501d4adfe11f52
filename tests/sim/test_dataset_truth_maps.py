"""Per-pixel truth, OpenCV cameras, schemas and value checks of a dataset.

Acceptance: ``cv2.projectPoints`` of each pixel's ``point`` with the sample's ``K, dist, R, t`` lands on the pixel
centre within 0.01 px; ``height`` equals the sample's true surface at ``surface_xy`` within 1e-6 mm; ``pattern_xy``
of a marker's pixels lies inside that marker's disc; a DataLoader's protocol iterates the dataset.
"""

from __future__ import annotations

import json
import pickle
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_dataset_common import write_tiny  # noqa: E402

import scopetwin  # noqa: E402
from scopetwin.scenes.io import read_heightmap, read_image, write_image  # noqa: E402
from scopetwin.sim.datasets.config import DatasetError, config_from_dict, load_config  # noqa: E402
from scopetwin.sim.datasets.plan import Plan  # noqa: E402
from scopetwin.sim.datasets.reader import DatasetReadError  # noqa: E402
from scopetwin.sim.datasets.store import MANIFEST, SAMPLES, generate, sha256_file, verify  # noqa: E402

pytestmark = pytest.mark.mitsuba

TINY_CALIBRATION = """
[dataset]
kind = "calibration"
setup = "thesis-2.8.1-perpendicular"
count = {count}
master_seed = 3
spp = 4
noise = true
preview = false

[setup.camera]
pixels = [136, 102]
pixel_pitch = 0.0465

[vary]
view_angle_deg = {{ sweep = [90.0, 55.0] }}
view_distance = {{ fixed = 233.24 }}
camera_shift = {{ normal = [0.0, 0.5] }}
{extra}
"""


def _calibration(folder: Path, count: int = 2, extra: str = "") -> Path:
    path = folder / "tiny-calibration.toml"
    path.write_text(TINY_CALIBRATION.format(count=count, extra=extra))
    return path


@pytest.fixture(scope="module")
def deflectometry(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("maps")
    root = folder / "ds"
    generate(Plan.build(load_config(write_tiny(folder, count=2))), root, workers=0, progress=False)
    return root


@pytest.fixture(scope="module")
def calibration(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("maps-cal")
    root = folder / "ds"
    cfg = _calibration(
        folder, extra="distortion_c2 = { fixed = 0.00123 }\nprincipal_offset = { fixed = [0.05, -0.03] }"
    )
    generate(Plan.build(load_config(cfg)), root, workers=0, progress=False)
    return root


def _project(sample, points: np.ndarray) -> np.ndarray:
    cv2 = pytest.importorskip("cv2")
    cam = sample.camera
    out, _ = cv2.projectPoints(points.reshape(-1, 1, 3).astype(np.float64), cam.rvec, cam.t, cam.K, cam.dist)
    return out.reshape(-1, 2)


def _pixel_centres(mask: np.ndarray) -> np.ndarray:
    rows, cols = np.nonzero(mask)
    return np.stack([cols, rows], axis=-1).astype(np.float64)  # OpenCV: pixel centres at integer coordinates


def test_every_pixel_point_projects_onto_its_pixel_centre(deflectometry):
    for sample in scopetwin.open_dataset(deflectometry):
        maps = sample.maps
        mask = maps["mask"]
        assert mask.shape == sample.image.shape and mask.sum() > 1000
        assert sample.camera.max_error_px == 0.0  # c2 = 0: OpenCV's model is the thesis's exactly
        got = _project(sample, maps["point"][mask])
        err = np.hypot(*(got - _pixel_centres(mask)).T)
        assert err.max() < 0.01, err.max()


def test_height_is_the_true_surface_at_surface_xy(deflectometry):
    for sample in scopetwin.open_dataset(deflectometry):
        maps = sample.maps
        heights = read_heightmap(sample.folder / "surface.exr")  # the sample's truth surface file
        m = maps["mask"]
        xy = maps["surface_xy"][m].astype(np.float64)
        assert np.abs(maps["height"][m] - heights.height(xy[:, 0], xy[:, 1])).max() < 1e-6
        assert np.isnan(maps["height"][~m]).all() and np.isnan(maps["point"][~m]).all()
        # the point lies on the substrate at its surface coordinates and height (the substrate frame is global)
        assert np.abs(maps["point"][m][:, :2] - maps["surface_xy"][m]).max() < 1e-5
        assert np.abs(maps["point"][m][:, 2] - maps["height"][m]).max() < 1e-6
        n = maps["normal"][m]
        assert np.allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-6) and (n[:, 2] > 0.99).all()
        assert maps["roi"][m].any() and not maps["roi"][~m].any()


def _check_markers(sample) -> None:
    maps = sample.maps
    pattern = sample.setup.marker_pattern
    ids = maps["marker_id"]
    seen = ids >= 0
    assert seen.sum() > 100
    ij = maps["marker"][seen].astype(np.int64)
    table = sample.truth.markers
    assert np.array_equal(table.ij[ids[seen]], ij)  # marker_id indexes truth.json's markers
    rel = maps["pattern_xy"][seen] - pattern.centers_local(ij)
    assert (np.hypot(rel[:, 0], rel[:, 1]) < pattern.radii(ij) + 1e-5).all()  # inside that marker's disc
    assert np.isnan(maps["marker"][~seen]).all()
    # independent cross-check: the pixel holding the exact image of a visible marker centre sees that marker
    vis = table.visible & np.isfinite(table.center_px).all(axis=1)
    col, row = np.floor(table.center_px[vis]).astype(int).T
    assert (ids[row, col] == np.flatnonzero(vis)).mean() > 0.99
    # and the image is bright where markers are seen, dark elsewhere
    img = sample.image
    assert img[seen].mean() > img[~seen].mean() + 3 * img[~seen].std() / 4


def test_marker_pixels_lie_inside_their_marker_disc(deflectometry):
    for sample in scopetwin.open_dataset(deflectometry):
        _check_markers(sample)


def test_calibration_views_with_distortion(calibration):
    ds = scopetwin.open_dataset(calibration)
    assert ds.kind == "calibration" and len(ds) == 2
    for sample in ds:
        maps = sample.maps
        assert "surface_xy" not in maps and "height" not in maps
        m = maps["mask"]
        pattern = sample.setup.marker_pattern
        local = pattern.frame.to_local(maps["point"][m].astype(np.float64))
        assert np.abs(local[:, 2]).max() < 1e-5  # on the target
        assert np.abs(local[:, :2] - maps["pattern_xy"][m]).max() < 1e-5
        cam = sample.camera
        # c2 != 0: OpenCV has no |r| term; the fit's error is stated, and it is what projectPoints shows
        assert 0 < cam.max_error_px < 1.0 and 0 < cam.rms_error_px <= cam.max_error_px
        err = np.hypot(*(_project(sample, maps["point"][m]) - _pixel_centres(m)).T)
        assert err.max() <= cam.max_error_px + 1e-3
        # the stated size is the real one over the whole image, not a loose bound: rays of every pixel centre
        thesis = sample.thesis_camera
        o, d = thesis.rays(thesis.pixel_centers().reshape(-1, 2))
        every = np.hypot(*(_project(sample, o + 150.0 * d) - (thesis.pixel_centers().reshape(-1, 2) - 0.5)).T)
        assert abs(every.max() - cam.max_error_px) < 1e-6
        assert abs(np.sqrt(np.mean(every**2)) - cam.rms_error_px) < 1e-6
        _check_markers(sample)


def test_the_dataset_satisfies_the_dataloader_protocol(deflectometry):
    ds = scopetwin.open_dataset(deflectometry)
    view = ds.arrays("image", "height", "mask")
    clone = pickle.loads(pickle.dumps(view))  # worker processes receive the dataset pickled
    assert len(clone) == len(ds)
    items = [clone[i] for i in range(len(clone))]
    batch = {k: np.stack([it[k] for it in items]) for k in items[0]}  # what default_collate does with numpy
    assert batch["image"].shape == (2, *ds[0].image.shape) and batch["mask"].dtype == bool
    assert np.array_equal(batch["image"][1], ds[1].image)
    with pytest.raises(DatasetReadError, match="no map"):
        ds[0].arrays(["nothing"])
    torch = pytest.importorskip("torch")
    loader = torch.utils.data.DataLoader(view, batch_size=2)
    (first,) = list(loader)
    assert tuple(first["image"].shape) == (2, *ds[0].image.shape)


def test_truth_is_typed_and_versioned(deflectometry):
    sample = scopetwin.open_dataset(deflectometry)[0]
    truth = sample.truth
    assert truth == json.loads((sample.folder / "truth.json").read_text())  # still the JSON object
    assert truth.format == 2 and truth.kind == "deflectometry" and truth.index == 0
    assert set(truth.parameters) >= {"surface_range_um", "camera_shift"}
    assert truth["maps"]["format"] == "maps/1" and "height" in truth["maps"]["layers"]
    assert sample.format == 2 and sample.meta["format"] == 2
    assert json.loads((deflectometry / "dataset.json").read_text())["format"] == 2


def _rehash(folder: Path, root: Path) -> None:
    """Make a tampered sample's hashes consistent again (so only the value checks can find it)."""
    body = json.loads((folder / "sample.json").read_text())
    for name in body["files"]:
        p = folder / name
        body["files"][name] = {"sha256": sha256_file(p), "bytes": p.stat().st_size}
    (folder / "sample.json").write_text(json.dumps(body))
    lines = [json.loads(x) for x in (root / MANIFEST).read_text().splitlines()]
    for line in lines:
        if line["index"] == body["index"]:
            line["files"] = body["files"]
    (root / MANIFEST).write_text("".join(json.dumps(x) + "\n" for x in lines))


def test_verify_validates_schemas_and_values(deflectometry, tmp_path):
    assert verify(deflectometry)["ok"]
    copy = tmp_path / "copy"
    shutil.copytree(deflectometry, copy)
    s0 = copy / SAMPLES / "000000"
    img, attrs = read_image(s0 / "image.exr")
    write_image(s0 / "image.exr", np.zeros_like(img))  # a black image with consistent hashes
    _rehash(s0, copy)
    s1 = copy / SAMPLES / "000001"
    truth = json.loads((s1 / "truth.json").read_text())
    truth["parameters"]["surface_range_um"] = 1e300  # a value no substrate has
    del truth["camera_opencv"]
    (s1 / "truth.json").write_text(json.dumps(truth))
    _rehash(s1, copy)
    result = verify(copy)
    assert not result["ok"] and result["complete"] == 0
    reasons = {r["index"]: " ".join(r["reasons"]) for r in result["invalid"]}
    assert "black" in reasons[0]
    assert "surface_range_um" in reasons[1] and "physical range" in reasons[1] and "camera_opencv" in reasons[1]


# -- varied values checked like fixed ones, before any work; no untrue render is listed --------
def _cfg(**vary) -> dict:
    return {
        "dataset": {"kind": "deflectometry", "setup": "thesis-1.10-deflectometry", "count": 3, "master_seed": 1},
        "vary": vary,
    }


@pytest.mark.parametrize(
    ("vary", "key"),
    [
        ({"surface_range_um": {"uniform": [0.0, 1e300]}}, "vary.surface_range_um"),
        ({"surface_range_um": {"loguniform": [1.0, 1e30]}}, "vary.surface_range_um"),
        ({"surface_range_um": {"fixed": 1e300}}, "vary.surface_range_um"),
        ({"camera_shift": {"normal": [1e9, 1.0]}}, "vary.camera_shift"),
        ({"camera_rotation": {"sweep": [[0.0, 0.0, 100.0]]}}, "vary.camera_rotation"),
        ({"exposure_s": {"uniform": [1.0, 1e12]}}, "vary.exposure_s"),
    ],
)
def test_out_of_range_varied_values_are_refused_in_the_config(vary, key):
    with pytest.raises(DatasetError, match=key.replace(".", r"\.") + ".*physical range"):
        config_from_dict(_cfg(**vary))


def test_drawn_values_out_of_range_are_refused_before_work(tmp_path):
    cfg = config_from_dict(_cfg(camera_shift={"normal": [0.0, 1e12]}))  # the mean is fine, the draws are not
    with pytest.raises(DatasetError, match=r"sample 0: key vary\.camera_shift: drawn value .* physical range"):
        Plan.build(cfg)


def test_a_render_without_signal_is_refused_and_never_listed(tmp_path, monkeypatch):
    import scopetwin.sim.datasets.part1 as part1

    real = part1.render_measurement

    def black_for_sample_1(setup, heights, spp, seed, noise, renderer="mitsuba"):
        image, seconds = real(setup, heights, spp, seed, noise, renderer)
        return (image * 0 if setup.name.endswith("000001") else image), seconds

    monkeypatch.setattr(part1, "render_measurement", black_for_sample_1)
    root = tmp_path / "ds"
    with pytest.raises(DatasetError, match="1 of 2 sample.*sample 1: the render is black"):
        generate(Plan.build(load_config(write_tiny(tmp_path, count=2))), root, workers=0, progress=False)
    assert (root / SAMPLES / "000000").is_dir() and not (root / SAMPLES / "000001").exists()
    result = verify(root)
    assert not result["ok"] and result["missing"] == [1] and result["complete"] == 1


# -- format versions ---------------------------------------------------------------------------------------------
def _as_format_1(src: Path, dst: Path) -> None:
    """The dataset as an older scopetwin wrote it: no maps.exr, no camera_opencv, no format numbers in its samples."""
    shutil.copytree(src, dst)
    cfg = json.loads((dst / "dataset.json").read_text())
    cfg["format"] = 1
    cfg["config"]["dataset"].pop("maps")
    (dst / "dataset.json").write_text(json.dumps(cfg))
    for folder in sorted((dst / SAMPLES).iterdir()):
        (folder / "maps.exr").unlink()
        truth = json.loads((folder / "truth.json").read_text())
        for key in ("format", "camera_opencv", "maps"):
            truth.pop(key)
        for key in ("nx", "ny", "pitch"):
            truth["camera"].pop(key)
        (folder / "truth.json").write_text(json.dumps(truth))
        body = json.loads((folder / "sample.json").read_text())
        body.pop("format")
        body["files"].pop("maps.exr")
        (folder / "sample.json").write_text(json.dumps(body))
        _rehash(folder, dst)


def test_an_older_format_is_read_and_not_extended(deflectometry, tmp_path):
    old = tmp_path / "old"
    _as_format_1(deflectometry, old)
    ds = scopetwin.open_dataset(old)
    new = scopetwin.open_dataset(deflectometry)
    assert ds.format == 1 and ds[0].format == 1 and ds[0].truth.format == 1
    computed, stored = ds[0].maps, new[0].maps  # format 1: computed on reading, with the writer's code
    assert list(computed) == list(stored)
    for k in stored:
        assert computed[k].dtype == stored[k].dtype
        assert np.allclose(computed[k], stored[k], atol=1e-5, equal_nan=True), k
    assert np.allclose(ds[0].camera.K, new[0].camera.K)
    assert verify(old)["ok"] and verify(old)["format"] == 1
    with pytest.raises(DatasetError, match="format 1.*writes format 2"):
        generate(Plan.build(load_config(write_tiny(tmp_path, count=2))), old, workers=0, progress=False)


def test_a_newer_format_names_the_version_it_needs(deflectometry, tmp_path):
    newer = tmp_path / "newer"
    shutil.copytree(deflectometry, newer)
    cfg = json.loads((newer / "dataset.json").read_text())
    cfg["format"] = 99
    (newer / "dataset.json").write_text(json.dumps(cfg))
    with pytest.raises(DatasetReadError, match="format 99.*newer scopetwin"):
        scopetwin.open_dataset(newer)
    maps = newer / SAMPLES / "000000" / "maps.exr"
    cfg["format"] = 2
    (newer / "dataset.json").write_text(json.dumps(cfg))
    import OpenEXR

    f = OpenEXR.File(str(maps))
    f.header()["scopetwin_format"] = "maps/7"
    f.write(str(maps))
    with pytest.raises(DatasetReadError, match="maps format 7.*reads maps format 1"):
        _ = scopetwin.open_dataset(newer)[0].maps


@pytest.mark.parametrize("preset", ["thesis-2.8.3-mirror", "thesis-1.10-deflectometry"])
def test_maps_agree_with_the_renderers_own_trace(preset):
    """The maps' vectorised trace against the analytic renderer's (scenes.analytic.AnalyticScene.pattern_hits: fitpack
    spline, its own secant) on every pixel centre: the same pixels reach the pattern, at the same points."""
    from scopetwin.scenes.analytic import AnalyticScene
    from scopetwin.sim.datasets.maps import part1_maps
    from scopetwin.sim.surfaces import surface_for

    setup = scopetwin.load_setup(preset, {"camera": {"pixels": [170, 128], "pixel_pitch": 0.0372}})
    heights = surface_for(setup)
    maps = part1_maps(setup, heights)
    cam = setup.camera_model
    o, d = cam.rays(cam.pixel_centers().reshape(-1, 2))
    xy, ok = AnalyticScene(setup, heights).pattern_hits(o, d)  # ok: reaches the pattern through the ROI / mirror
    seen = maps["mask"].ravel() & np.isfinite(maps["pattern_xy"].reshape(-1, 2)).all(axis=1)
    if "roi" in maps:
        seen &= maps["roi"].ravel()
    assert ok.sum() > 1000 and np.array_equal(seen, ok)
    assert np.abs(maps["pattern_xy"].reshape(-1, 2)[ok] - xy[ok]).max() < 1e-5
    if preset.endswith("mirror"):
        m = maps["mask"]
        assert np.abs(maps["point"][m][:, 2]).max() < 1e-9 and (maps["normal"][m] == [0, 0, 1]).all()


@pytest.mark.parametrize("compression", ["zstd", "zip"])
def test_maps_read_back_bit_for_bit_with_either_compression(deflectometry, tmp_path, compression):
    import OpenEXR

    from scopetwin.sim.datasets.maps import read_maps, write_maps

    maps = scopetwin.open_dataset(deflectometry)[0].maps
    path = tmp_path / "maps.exr"
    write_maps(path, maps, compression)
    header = OpenEXR.File(str(path)).header()
    assert header["compression"] == getattr(OpenEXR.Compression, f"{compression.upper()}_COMPRESSION")
    back = read_maps(path, maps["mask"].shape)
    assert list(back) == list(maps)
    for name, arr in maps.items():
        assert back[name].dtype == arr.dtype and np.array_equal(back[name], arr, equal_nan=arr.dtype.kind == "f")


def test_the_maps_compression_is_checked(deflectometry, tmp_path):
    from scopetwin.sim.datasets.maps import write_maps

    assert config_from_dict(_cfg()).dataset.maps_compression == "zstd"  # the default
    cfg = _cfg()
    cfg["dataset"]["maps_compression"] = "piz"
    with pytest.raises(DatasetError, match="maps_compression"):
        config_from_dict(cfg)
    with pytest.raises(ValueError, match="zstd, zip"):
        write_maps(tmp_path / "maps.exr", scopetwin.open_dataset(deflectometry)[0].maps, "piz")
    assert not (tmp_path / "maps.exr").exists()


def test_the_compressions_are_the_same_list_everywhere():
    """The config's choices, the writer's and the dataset schema's are one list."""
    import typing
    from importlib.resources import files

    from scopetwin.sim.datasets.config import DatasetSection
    from scopetwin.sim.datasets.maps import MAPS_COMPRESSION

    schema = json.loads((files("scopetwin.sim.datasets") / "schemas" / "dataset.schema.json").read_text())
    enum = schema["properties"]["config"]["properties"]["dataset"]["properties"]["maps_compression"]["enum"]
    assert typing.get_args(DatasetSection.model_fields["maps_compression"].annotation) == MAPS_COMPRESSION
    assert tuple(enum) == MAPS_COMPRESSION
