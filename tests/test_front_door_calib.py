"""The front door's calibration and rig entries: the same answers as the command line on one image."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest

import scopetwin
from scopetwin.cli import main
from scopetwin.scenes.io import write_image

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.mitsuba


def _cli(*args: str) -> None:
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(list(args)) == 0


def test_calibrate_recovers_the_camera_and_agrees_with_the_cli(tmp_path):
    m = scopetwin.render("thesis-2.8.1-perpendicular", spp=4, seed=2)
    cal = scopetwin.calibrate(m.image, m.setup)
    plane = m.setup.marker_pattern.frame
    true_c = m.setup.camera_model.center
    found_c = cal.to_global(plane).center
    assert np.linalg.norm(found_c - true_c) < 0.05  # mm, from one noisy 4 spp view face-on (thesis §2.8.1)
    exr = tmp_path / "target.exr"
    write_image(exr, m.image, m.setup.to_json())
    _cli("calibrate", str(exr), "--target", "thesis-2.8.1-perpendicular", "--json", str(tmp_path / "c.json"))
    cli = json.loads((tmp_path / "c.json").read_text())
    assert np.array_equal(np.array(cli["camera"]["r_c"]), found_c)


@pytest.mark.slow
def test_calibrate_setup_gives_the_cli_s_setup(tmp_path):
    t = scopetwin.render("thesis-2.8.3-substrate", spp=4, seed=1)
    mi = scopetwin.render("thesis-2.8.3-mirror", spp=4, seed=2)
    done = scopetwin.calibrate_setup(t.image, mi.image)
    assert done.setup.scene == "deflectometry"
    moved = np.linalg.norm(done.setup.camera_model.center - mi.setup.camera_model.center)
    assert moved < 0.1  # mm: the calibrated camera lies where the nominal one is (the renders' own camera)
    write_image(tmp_path / "t.exr", t.image, t.setup.to_json())
    write_image(tmp_path / "m.exr", mi.image, mi.setup.to_json())
    out = tmp_path / "setup.toml"
    _cli(
        "calibrate-setup",
        "--substrate-image",
        str(tmp_path / "t.exr"),
        "--mirror-image",
        str(tmp_path / "m.exr"),
        "--out",
        str(out),
    )
    cli = scopetwin.load_setup(out)
    assert np.array_equal(cli.camera_model.center, done.setup.camera_model.center)
    assert np.array_equal(cli.marker_pattern.frame.origin, done.setup.marker_pattern.frame.origin)


def test_open_rig_gives_the_devices_and_closes_them():
    with scopetwin.open_rig(ROOT / "rigs" / "sim-deflectometry.toml") as rig:
        assert rig.devices, "a rig with no devices"
        names = sorted(rig.devices)
    assert names == sorted(names)
