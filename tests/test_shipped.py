"""The shipped rigs and examples (:mod:`scopetwin.shipped`): a file in the current folder comes first; a path that
does not exist names the shipped file by its documented relative path or, for a rig, its bare name."""

from __future__ import annotations

from pathlib import Path

from scopetwin.instrument.micromanager import config_rig_path, resolve_rig_path
from scopetwin.instrument.rig import load_rig
from scopetwin.shipped import find_input, find_rig, rig_names, root, shipped

ROOT = Path(__file__).resolve().parents[1]


def test_the_shipped_folder_is_the_checkouts_here():
    assert root() == ROOT
    assert rig_names() == sorted(p.stem for p in (ROOT / "rigs").glob("*.toml"))


def test_bare_names_and_documented_paths_name_the_shipped_files(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    rig = ROOT / "rigs" / "sim-cmu.toml"
    assert find_rig("sim-cmu") == find_rig("sim-cmu.toml") == find_rig("rigs/sim-cmu.toml") == rig
    example = "examples/datasets/01-deflectometry-small.toml"
    assert find_input(example) == ROOT / example
    assert load_rig("sim-deflectometry").path == str(ROOT / "rigs" / "sim-deflectometry.toml")
    assert find_rig("no-such-rig") == Path("no-such-rig")  # the reader's error names what was asked for
    assert shipped("../rigs/sim-cmu.toml") is None and shipped(rig) is None and shipped("setup.py") is None


def test_a_file_in_the_current_folder_comes_first(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "rigs").mkdir()
    own = tmp_path / "rigs" / "sim-cmu.toml"
    own.write_text((ROOT / "rigs" / "sim-cmu.toml").read_text().replace('name = "sim-cmu"', 'name = "mine"'))
    assert find_rig("rigs/sim-cmu.toml") == Path("rigs/sim-cmu.toml")
    assert load_rig("rigs/sim-cmu.toml").name == "mine"
    assert resolve_rig_path("rigs/sim-cmu.toml") == own
    assert config_rig_path("rigs/sim-cmu.toml") == str(own)  # not shipped: its absolute path
    assert config_rig_path("sim-cmu") == "sim-cmu"  # the bare name means the shipped rig in every folder
