"""scopetwin.sim.datasets: config validation before work, per-sample determinism, truth, verify and resume."""

from __future__ import annotations

import json
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_dataset_common import write_tiny  # noqa: E402

from scopetwin.cli import main as scopetwin_main
from scopetwin.sim.datasets.config import DatasetError, config_from_dict, load_config  # noqa: E402
from scopetwin.sim.datasets.plan import Plan  # noqa: E402
from scopetwin.sim.datasets.seeding import draw_parameters  # noqa: E402
from scopetwin.sim.datasets.store import MANIFEST, SAMPLES, generate, load_plan, recover, verify  # noqa: E402

pytestmark = pytest.mark.mitsuba


def _cfg(**over) -> dict:
    base = {"dataset": {"kind": "deflectometry", "setup": "thesis-1.10-deflectometry", "count": 4, "master_seed": 1}}
    for k, v in over.items():
        base.setdefault(k, {}).update(v)
    return base


@pytest.mark.parametrize(
    ("data", "key"),
    [
        (_cfg(dataset={"colour": "red"}), "dataset.colour"),
        (_cfg(vary={"surface_rnage_um": {"uniform": [1, 2]}}), "vary.surface_rnage_um"),
        (_cfg(vary={"surface_range_um": {"uniform": [-5.0, 10.0]}}), "vary.surface_range_um"),
        (_cfg(vary={"surface_correlation_length": {"normal": [12.0, 1.0]}}), "vary.surface_correlation_length"),
        (_cfg(vary={"surface_range_um": {"uniform": [50.0, 10.0]}}), "vary.surface_range_um"),
        (_cfg(vary={"exposure_fill": {"sweep": [0.5, 1.5]}}), "vary.exposure_fill"),
        (_cfg(vary={"view_angle_deg": {"fixed": 45.0}}), "vary.view_angle_deg"),
        (_cfg(vary={"surface_kind": {"choice": ["random", "wavy"]}}), "vary.surface_kind"),
        (_cfg(vary={"camera_shift": {"uniform": [0, 1], "normal": [0, 1]}}), "vary.camera_shift"),
    ],
)
def test_bad_config_names_the_key(data, key):
    with pytest.raises(DatasetError, match=key.replace(".", r"\.")):
        config_from_dict(data, "cfg.toml")


def test_bad_setup_override_and_impossible_sample_rejected_before_work(tmp_path):
    cfg = config_from_dict(_cfg(setup={"camera": {"focal": 25.0}}))
    with pytest.raises(DatasetError, match=r"camera\.focal"):
        Plan.build(cfg)
    # a defocus without a thin lens cannot be rendered: found when the samples are checked, before any render
    cfg = config_from_dict(_cfg(vary={"defocus": {"uniform": [-1.0, 1.0]}}))
    with pytest.raises(DatasetError, match=r"vary\.defocus"):
        Plan.build(cfg)


def test_cli_rejects_bad_config_without_touching_the_output(tmp_path, capsys):
    cfg = write_tiny(tmp_path, extra='\n[vary.surface_kind]\nchoice = ["random", "wavy"]\n')
    out = tmp_path / "out"
    assert scopetwin_main(["dataset", "generate", str(cfg), "--out", str(out), "--workers", "0"]) == 2
    assert "vary.surface_kind" in capsys.readouterr().err
    assert not out.exists()


def test_cmu_kind_names_the_missing_capability(monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(
        importlib.util, "find_spec", lambda name, *a: None if name == "scopetwin.scenes.mitsuba.cmu" else real(name, *a)
    )
    cfg = config_from_dict({"dataset": {"kind": "cmu", "setup": "thesis-cmu", "count": 1, "master_seed": 0}})
    with pytest.raises(DatasetError, match=r"scenes\.mitsuba\.cmu"):
        Plan.build(cfg)


def test_draws_depend_only_on_master_seed_and_index(tmp_path):
    cfg = load_config(write_tiny(tmp_path, count=10))
    big = load_config(write_tiny(tmp_path, count=1000))
    for i in (0, 3, 9):
        assert draw_parameters(cfg, i) == draw_parameters(big, i)
    # the sweep walks its grid: corr. length alternates 8, 16 with the index
    assert [draw_parameters(cfg, i)["surface_correlation_length"] for i in range(4)] == [8.0, 16.0, 8.0, 16.0]
    assert draw_parameters(cfg, 0)["surface_range_um"] != draw_parameters(cfg, 2)["surface_range_um"]


def _files(root: Path, index: int) -> dict[str, bytes]:
    folder = root / SAMPLES / f"{index:06d}"
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


@pytest.mark.slow
def test_determinism_truth_verify_and_resume(tmp_path):
    from scopetwin.scenes.io import read_heightmap, read_image

    cfg = load_config(write_tiny(tmp_path, count=10))
    plan = Plan.build(cfg)
    a, b, c = tmp_path / "a", tmp_path / "b", tmp_path / "c"
    generate(plan, a, workers=0, progress=False)
    generate(plan, b, workers=0, progress=False)
    generate(plan, c, workers=0, indices=range(5, 10), progress=False)
    for i in range(10):
        assert _files(a, i) == _files(b, i), f"sample {i} differs between two runs"
    for i in range(5, 10):
        assert _files(a, i) == _files(c, i), f"sample {i} differs when generated alone"
    assert not (c / SAMPLES / "000000").exists()

    # truth: the stored surface has the drawn range; the image carries the setup; markers are listed
    for i in (0, 1):
        truth = json.loads((a / SAMPLES / f"{i:06d}" / "truth.json").read_text())
        params = draw_parameters(cfg, i)
        hm = read_heightmap(a / SAMPLES / f"{i:06d}" / "surface.exr")
        assert np.ptp(hm.z) * 1e3 == pytest.approx(params["surface_range_um"], rel=1e-5)
        assert truth["parameters"] == params and truth["sample"] == i
        assert truth["setup_json"]["substrate"]["surface"]["correlation_length"] == params["surface_correlation_length"]
        assert sum(m["visible"] for m in truth["markers"]) > 10
        image, attrs = read_image(a / SAMPLES / f"{i:06d}" / "image.exr")
        assert image.shape == (128, 170) and "scopetwin_setup" in attrs
        raw = b"".join(_files(a, i).values())
        assert b"finished_utc" not in raw and b"hostname" not in raw
    rep = verify(a)
    assert rep["ok"] and rep["complete"] == 10

    # damage the set in every way verify knows, check it is seen, then resume repairs it
    img = a / SAMPLES / "000002" / "image.exr"
    data = bytearray(img.read_bytes())
    data[len(data) // 2] ^= 0xFF
    img.write_bytes(bytes(data))
    shutil.rmtree(a / SAMPLES / "000004")
    lines = (a / MANIFEST).read_text().splitlines()
    (a / MANIFEST).write_text("\n".join(lines + [lines[7], lines[8][:40]]) + "\n")
    (a / SAMPLES / ".tmp-000004-x").mkdir()
    rep = verify(a)
    assert not rep["ok"]
    assert [c["index"] for c in rep["corrupt"]] == [2]
    assert rep["missing"] == [4] and rep["duplicates"] == [int(json.loads(lines[7])["index"])]
    assert rep["temporary"] == [".tmp-000004-x"] and rep["bad_manifest_lines"] == 1
    out = tmp_path / "verify.json"
    assert scopetwin_main(["dataset", "verify", str(a), "--json", str(out)]) == 1
    assert set(json.loads(out.read_text())) >= {"complete", "missing", "corrupt", "duplicates"}

    generate(load_plan(a), a, workers=0, progress=False)
    rep = verify(a)
    assert rep["ok"] and rep["complete"] == 10, rep
    for i in (2, 4):
        assert _files(a, i) == _files(b, i)


def test_recover_relists_samples_the_manifest_lost(tmp_path):
    cfg = load_config(write_tiny(tmp_path, count=2))
    root = tmp_path / "d"
    generate(Plan.build(cfg), root, workers=0, progress=False)
    (root / MANIFEST).write_text("")  # the client died after renaming the samples, before writing their lines
    assert verify(root)["unlisted"] == [0, 1]
    state = recover(root)
    assert state["relisted"] == [0, 1] and state["done"] == [0, 1]
    assert verify(root)["ok"]


def test_other_dataset_in_the_folder_is_refused(tmp_path):
    root = tmp_path / "d"
    generate(Plan.build(load_config(write_tiny(tmp_path, count=1))), root, workers=0, progress=False)
    other = load_config(write_tiny(tmp_path, count=1, extra=""), count=2)
    with pytest.raises(DatasetError, match="different dataset"):
        generate(Plan.build(other), root, workers=0, progress=False)
