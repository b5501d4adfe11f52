"""``optics cmu`` (scopetwin.cli.optics): the JSON contract of docs/contract.md and the user errors."""

from __future__ import annotations

import argparse
import json

import pytest

from scopetwin.cli import main
from scopetwin.cli.optics import cmd_cmu, register_cmu
from scopetwin.scenes.errors import ScopetwinError


def _parse(argv: list[str]) -> argparse.Namespace:
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="command")
    optics = sub.add_parser("optics").add_subparsers(dest="optics_command")
    register_cmu(optics)
    return ap.parse_args(["optics", "cmu", *argv])


@pytest.mark.slow
def test_json_contract(tmp_path) -> None:
    out = tmp_path / "cmu.json"
    assert main(["optics", "cmu", "--json", str(out)]) == 0
    data = json.loads(out.read_text())
    assert set(data["channels"]) == {"blue", "green", "red", "nir"}
    for ch in data["channels"].values():
        assert {"magnification", "rms_spot_um", "delta_x_um", "image_distance_mm"} <= set(ch)
    assert data["channels"]["nir"]["magnification"] == pytest.approx(10.0, rel=1e-3)
    assert len(data["excitation_crosstalk"]) == 4 and len(data["excitation_crosstalk"][0]) == 4
    assert data["section_5_1_2"]["mirror_magnification"] == pytest.approx(10.0, rel=1e-6)


def test_bad_splitter_map_arguments(tmp_path) -> None:
    with pytest.raises(ScopetwinError, match="NAME=PATH"):
        cmd_cmu(_parse(["--splitter-maps", "770DCXR"]))
    with pytest.raises(ScopetwinError):
        cmd_cmu(_parse(["--splitter-maps", f"770DCXR={tmp_path / 'missing.exr'}"]))
