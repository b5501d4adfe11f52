"""`scopetwin calibrate` / `calibrate-setup` end to end on rendered EXR images."""

from __future__ import annotations

import argparse
import json

import numpy as np
import pytest

from scopetwin.cli.calibrate import register
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.io import write_image, write_json_atomic
from scopetwin.scenes.setup import load_setup

pytestmark = pytest.mark.mitsuba


def run(argv: list[str]) -> int:
    """The same contract as scopetwin.cli's main: result -> --json, ScopetwinError -> exit 2."""
    parser = argparse.ArgumentParser(prog="scopetwin")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    try:
        result = args.func(args)
        if args.json:
            write_json_atomic(args.json, result)
    except ScopetwinError:
        return 2
    return 0


@pytest.fixture(scope="module")
def images(rendered, tmp_path_factory):
    d = tmp_path_factory.mktemp("calib-images")
    ss, sm = load_setup("thesis-2.8.3-substrate"), load_setup("thesis-2.8.3-mirror")
    write_image(d / "substrate.exr", rendered[0], ss.to_json())
    write_image(d / "mirror.exr", rendered[1], sm.to_json())
    return d


def test_calibrate_json(images, tmp_path):
    out = tmp_path / "cal.json"
    assert run(["calibrate", str(images / "substrate.exr"), "--json", str(out)]) == 0
    d = json.loads(out.read_text())
    truth = load_setup("thesis-2.8.3-substrate").camera_model
    assert np.linalg.norm(np.subtract(d["camera"]["r_c"], truth.center)) < 2e-3
    assert d["markers_used"] == 99 and d["bias_corrected"]
    assert d["residual_rms_px"] < 0.01


def test_calibrate_setup_writes_loadable_toml(images, tmp_path):
    out, js = tmp_path / "setup.toml", tmp_path / "setup.json"
    assert (
        run(
            [
                "calibrate-setup",
                "--substrate-image",
                str(images / "substrate.exr"),
                "--mirror-image",
                str(images / "mirror.exr"),
                "--out",
                str(out),
                "--json",
                str(js),
            ]
        )
        == 0
    )
    s = load_setup(out)
    truth = load_setup("thesis-2.8.3-mirror")
    assert np.linalg.norm(s.marker_pattern.frame.origin - truth.marker_pattern.frame.origin) < 5e-3
    d = json.loads(js.read_text())
    assert {"origin", "t_x", "t_y", "n_z"} <= set(d["pattern"]) and "r_c" in d["camera"]


def test_errors_exit_2_and_write_nothing(images, tmp_path):
    out = tmp_path / "x.json"
    # a mirror image is not a calibration target
    assert run(["calibrate", str(images / "mirror.exr"), "--json", str(out)]) == 2
    # a face-on view cannot give a free b
    assert (
        run(
            [
                "calibrate",
                str(images / "substrate.exr"),
                "--lens",
                "free",
                "--target",
                "thesis-2.8.1-perpendicular",
                "--nz-estimate",
                "0,0,-1",
                "--json",
                str(out),
            ]
        )
        == 2
    )
    assert run(["calibrate", str(tmp_path / "missing.exr"), "--json", str(out)]) == 2
    toml = tmp_path / "s.toml"
    assert (
        run(
            [
                "calibrate-setup",
                "--substrate-image",
                str(images / "mirror.exr"),
                "--mirror-image",
                str(images / "mirror.exr"),
                "--out",
                str(toml),
                "--json",
                str(out),
            ]
        )
        == 2
    )
    assert not out.exists() and not toml.exists()
