"""scopetwin.sim.measurement.StagedOutput: the one stage-then-rename helper (nothing partial is ever left behind)."""

from __future__ import annotations

import pytest

from scopetwin.sim.measurement import StagedOutput


def test_commit_moves_files_into_place_and_replaces_old_entries(tmp_path):
    out = tmp_path / "report"
    (out / "plots").mkdir(parents=True)
    (out / "plots" / "old.png").write_text("old")
    stage = StagedOutput(out)
    assert stage.stage.parent == tmp_path and stage.stage.name.startswith(".report.staging-")
    stage.path("report.md").write_text("new")
    (stage.path("plots")).mkdir()
    (stage.path("plots") / "new.png").write_text("new")
    moved = stage.commit()
    assert sorted(moved) == ["plots", "report.md"]
    assert (out / "report.md").read_text() == "new"
    assert [p.name for p in (out / "plots").iterdir()] == ["new.png"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]


def test_rename_is_atomic_and_refuses_an_existing_folder(tmp_path):
    final = tmp_path / "samples" / "000001"
    with StagedOutput(final, prefix=".tmp-000001-") as stage:
        assert stage.stage.name.startswith(".tmp-000001-")
        stage.path("image.exr").write_bytes(b"x")
        assert stage.rename()
    assert (final / "image.exr").read_bytes() == b"x"
    with StagedOutput(final, prefix=".tmp-000001-") as second:
        second.path("image.exr").write_bytes(b"y")
        assert not second.rename()
    assert (final / "image.exr").read_bytes() == b"x"
    assert sorted(p.name for p in final.parent.iterdir()) == ["000001"]


def test_a_failing_block_leaves_nothing(tmp_path):
    out = tmp_path / "render"
    with pytest.raises(RuntimeError), StagedOutput(out) as stage:
        stage.path("image.exr").write_bytes(b"partial")
        raise RuntimeError("render failed")
    assert not out.exists() and not list(tmp_path.iterdir())


def test_deferred_commits_wait_for_the_caller_and_are_discarded_on_failure(tmp_path):
    from scopetwin.sim.measurement import deferred_commits

    out = tmp_path / "report"
    with deferred_commits() as pending:
        stage = StagedOutput(out)
        stage.path("report.md").write_text("done")
        assert stage.commit() == {"report.md": out / "report.md"}  # where it will be ...
        assert not out.exists() and pending == [stage]  # ... once the caller has written --json
        pending[0].commit_now()
    assert (out / "report.md").read_text() == "done"

    with pytest.raises(OSError), deferred_commits():
        stage = StagedOutput(tmp_path / "other")
        stage.path("image.exr").write_bytes(b"x")
        stage.commit()
        raise OSError(28, "No space left on device", "r.json")  # the --json write failed
    assert sorted(p.name for p in tmp_path.iterdir()) == ["report"]
