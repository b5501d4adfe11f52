"""``rig RIG mm-config``: a device name a Micro-Manager ``.cfg`` line cannot hold (a line break that would write
lines of its own, a comma, a NUL, spaces around it) is refused with one line and exit 2 before anything is written,
and ``--out`` is written atomically, never through a link. The hostile rigs are built here from a shipped one."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from scopetwin.cli import main
from scopetwin.instrument.errors import RigError
from scopetwin.instrument.micromanager import check_config_fields, config_field_problem

ROOT = Path(__file__).resolve().parents[2]

HOSTILE = {
    "a line break writing its own line": '"uv\\n#py pyDevice,Evil,os,system"',
    "a carriage return": '"uv\\r"',
    "a comma": '"uv,blue"',
    "a NUL": '"uv\\u0000"',
    "a leading space": '" uv"',
    "a trailing space": '"uv "',
    "a tab": '"uv\\t"',
}


def hostile_rig(folder: Path, key: str) -> Path:
    text = (ROOT / "rigs" / "sim-cmu.toml").read_text()
    assert "[devices.uv]" in text
    path = folder / "hostile.toml"
    path.write_text(text.replace("[devices.uv]", f"[devices.{key}]"))
    return path


@pytest.mark.parametrize("case", sorted(HOSTILE))
def test_a_name_the_cfg_cannot_hold_is_one_line_exit_2(tmp_path, capsys, case):
    rig = hostile_rig(tmp_path, HOSTILE[case])
    out = tmp_path / "rig.cfg"
    code = main(["rig", str(rig), "mm-config", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2, err
    assert len(err.strip().splitlines()) == 1 and "light name" in err and "Micro-Manager configuration" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hostile.toml"]  # nothing written, no temporary left


@pytest.mark.parametrize(
    ("value", "problem"),
    [
        ("a\nb", "control"),
        ("a\x00", "control"),
        ("a\u2028b", "control"),
        ("a,b", "comma"),
        (" a", "white space"),
        ("a ", "white space"),
        ("", "empty"),
    ],
)
def test_field_problems(value, problem):
    assert problem in (config_field_problem(value) or "")
    with pytest.raises(RigError, match="cannot hold it"):
        check_config_fields([("camera name", "cam"), ("light name", value)])


def test_ordinary_names_pass():
    for value in ("uv", "blue_led", "deep red", "cam-nir 2", "µ-stage", "rigs/sim-cmu.toml"):
        assert config_field_problem(value) is None
    check_config_fields([("rig path", "rigs/sim-cmu.toml"), ("stage name", "x")])


def test_out_is_written_atomically_and_never_through_a_link(tmp_path, capsys):
    victim = tmp_path / "victim.cfg"
    victim.write_text("keep me\n")
    out = tmp_path / "rig.cfg"
    os.symlink(victim, out)
    code = main(["rig", str(ROOT / "rigs" / "sim-cmu.toml"), "mm-config", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err
    assert victim.read_text() == "keep me\n"
    assert not out.is_symlink() and "#py pyDevice" in out.read_text()  # the link replaced by the file
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rig.cfg", "victim.cfg"]  # no temporary left
