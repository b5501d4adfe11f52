"""`scopetwin markers IMAGE.exr --pattern SETUP [--json PATH] [--overlay PNG]` (scopetwin.cli.markers)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from scopetwin.cli import main as scopetwin_main
from scopetwin.cli.markers import register
from scopetwin.scenes.analytic import render
from scopetwin.scenes.io import write_image
from scopetwin.scenes.setup import load_setup
from scopetwin.sim.truth import marker_truth

SETUP_TOML = """base = "thesis-2.8.1-angular"
[camera]
pixels = [340, 256]
pixel_pitch = 0.0186
"""


@pytest.fixture(scope="module")
def case(tmp_path_factory) -> tuple[Path, Path, object]:
    d = tmp_path_factory.mktemp("markers_cli")
    toml = d / "angular-small.toml"
    toml.write_text(SETUP_TOML)
    setup = load_setup(toml)
    image = d / "view.exr"
    write_image(image, render(setup, spp=4, seed=0), setup_json=setup.to_json())
    return toml, image, marker_truth(setup)


def test_register_adds_the_markers_command():
    parser = argparse.ArgumentParser()
    register(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["markers", "a.exr", "--pattern", "thesis-2.8.1-angular", "--json", "o.json"])
    assert args.func.__name__ == "cmd_markers" and args.pattern == "thesis-2.8.1-angular" and args.json == "o.json"


def test_json_contract_and_overlay(case, tmp_path):
    toml, image, truth = case
    out, png = tmp_path / "m.json", tmp_path / "m.png"
    argv = ["markers", str(image), "--pattern", str(toml), "--json", str(out), "--overlay", str(png)]
    assert scopetwin_main(argv) == 0
    data = json.loads(out.read_text())
    assert set(data) >= {"markers", "rejected"} and data["rejected"] >= 0
    recs = data["markers"]
    assert len(recs) == 99 and set(recs[0]) >= {"i", "j", "col", "row", "area"}
    key = {tuple(k): c for k, c in zip(truth.ij, truth.center_px, strict=True)}
    err = [np.hypot(r["col"] - key[(r["i"], r["j"])][0], r["row"] - key[(r["i"], r["j"])][1]) for r in recs]
    assert max(err) < 0.1  # indices are pattern positions: each record sits on its marker's true image
    pic = cv2.imread(str(png))
    assert pic.shape == (256, 340, 3)


@pytest.mark.parametrize("kind", ["missing", "blank", "unknown-setup", "size"])
def test_bad_input_exits_2_and_writes_nothing(case, tmp_path, kind, capsys):
    toml, image, _ = case
    pattern = str(toml)
    if kind == "missing":
        image = tmp_path / "nope.exr"
    elif kind == "blank":
        image = tmp_path / "blank.exr"
        write_image(image, np.zeros((256, 340), dtype=np.float32))
    elif kind == "unknown-setup":
        pattern = "no-such-preset"
    else:
        pattern = "thesis-2.8.1-angular"  # a 1360x1024 camera for a 340x256 image
    out, png = tmp_path / "m.json", tmp_path / "m.png"
    assert scopetwin_main(["markers", str(image), "--pattern", pattern, "--json", str(out), "--overlay", str(png)]) == 2
    assert "error" in capsys.readouterr().err
    assert not out.exists() and not png.exists()
