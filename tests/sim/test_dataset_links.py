"""No link followed by the dataset writers: the manifest and an export are never written through a
symbolic link planted at their paths."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_dataset_common import write_tiny  # noqa: E402

from scopetwin.sim.datasets.config import load_config  # noqa: E402
from scopetwin.sim.datasets.plan import Plan  # noqa: E402
from scopetwin.sim.datasets.store import MANIFEST, generate  # noqa: E402

pytestmark = pytest.mark.mitsuba


@pytest.fixture(scope="module")
def plan(tmp_path_factory) -> Plan:
    return Plan.build(load_config(write_tiny(tmp_path_factory.mktemp("cfg"), count=1)))


def test_a_link_at_the_manifest_is_never_written_through(plan, tmp_path):
    """The recovery step replaces such a link by the manifest it rewrites (atomically: the link itself is
    replaced); the appends then go to that regular file (``open_append`` refuses a link); the target is untouched."""
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me\n")
    root = tmp_path / "ds"
    root.mkdir()
    os.symlink(victim, root / MANIFEST)
    try:
        generate(plan, root, workers=0, progress=False)
    except OSError as exc:  # refused outright is as good
        assert "symbolic link" in str(exc)
    assert victim.read_text() == "keep me\n"
    assert not (root / MANIFEST).is_symlink()


def test_open_append_refuses_a_link(tmp_path):
    from scopetwin.scenes.io import open_append

    victim = tmp_path / "victim.txt"
    victim.write_text("keep me\n")
    os.symlink(victim, tmp_path / "link")
    with pytest.raises(OSError, match="symbolic link"):
        open_append(tmp_path / "link")
    assert victim.read_text() == "keep me\n"


def test_an_export_writes_through_no_link_at_a_temporary_name(plan, tmp_path):
    from scopetwin.sim.datasets.export import export
    from scopetwin.sim.datasets.reader import open_dataset

    root = tmp_path / "ds"
    generate(plan, root, workers=0, progress=False)
    victim = tmp_path / "victim.h5"
    victim.write_bytes(b"keep me")
    out = tmp_path / "out.h5"
    for pid in range(os.getpid() - 2, os.getpid() + 3):  # the old predictable temporary names, all planted
        os.symlink(victim, tmp_path / f".{out.name}.export-{pid}")
    export(open_dataset(root), out, "hdf5")
    assert out.is_file() and not out.is_symlink() and victim.read_bytes() == b"keep me"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(f".{out.name}.export-") and not p.is_symlink()]
