"""Datasets under concurrency and after interruptions: the folder lock, live temporaries, traceability.

One run at a time holds a dataset folder (a second is refused with one line naming the holder); a temporary sample
folder that a live process writes is never removed; the manifest names the worker process that made each sample;
the progress bar shows failures; ``resume`` says what it found and repaired.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_dataset_common import write_tiny  # noqa: E402

from scopetwin.cli import main  # noqa: E402
from scopetwin.sim.datasets import store  # noqa: E402
from scopetwin.sim.datasets.config import DatasetError, load_config  # noqa: E402
from scopetwin.sim.datasets.lock import LOCK_FILE, DatasetBusy, DatasetLock, holder  # noqa: E402
from scopetwin.sim.datasets.plan import Plan  # noqa: E402
from scopetwin.sim.datasets.store import MANIFEST, SAMPLES, generate, recover, remove_stale_temporaries, verify  # noqa: E402
from scopetwin.sim.measurement import StagedOutput, remove_stale_stage  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]


def test_a_held_folder_is_refused_with_the_holders_name(tmp_path, capsys):
    cfg = write_tiny(tmp_path, count=2)
    root = tmp_path / "set"
    root.mkdir()
    with DatasetLock(root, command="scopetwin dataset generate (test)"):
        assert holder(root)["pid"] == os.getpid()
        with pytest.raises(DatasetBusy, match=rf"in use by pid {os.getpid()} on "):
            DatasetLock(root).acquire()
        code = main(["dataset", "generate", str(cfg), "--out", str(root), "--workers", "0", "--quiet"])
        err = capsys.readouterr().err
        assert code == 2 and err.count("\n") == 1
        assert f"pid {os.getpid()}" in err and "scopetwin dataset generate (test)" in err
    assert sorted(p.name for p in root.iterdir()) == [LOCK_FILE]  # the refused run wrote nothing
    assert holder(root) is None  # released: the next run takes it over
    DatasetLock(root).acquire().release()


def test_a_live_stage_is_kept_and_a_dead_one_removed(tmp_path):
    samples = tmp_path / SAMPLES
    live = StagedOutput(samples / "000001", prefix=".tmp-000001-", lock=True)
    dead = samples / ".tmp-000002-x"
    dead.mkdir()
    removed, kept = remove_stale_temporaries(tmp_path)
    assert removed == [dead.name] and kept == [live.stage.name] and live.stage.is_dir()
    live.path("image.exr").write_bytes(b"x")
    assert live.rename() and (samples / "000001" / "image.exr").exists()
    assert remove_stale_stage(samples / "000001")  # unlocked after the rename: a plain folder again


def test_a_stage_removed_under_its_writer_is_never_renamed_into_place(tmp_path):
    stage = StagedOutput(tmp_path / "samples" / "000003", prefix=".tmp-000003-", lock=True)
    shutil.rmtree(stage.stage)  # what a careless clean-up would do
    stage.stage.mkdir()  # ... and a late write re-creating it
    (stage.stage / "truth.json").write_text("{}")
    with pytest.raises(Exception, match="removed while it was written"):
        stage.rename()
    assert not (tmp_path / "samples" / "000003").exists() and not stage.stage.exists()


@pytest.mark.mitsuba
def test_manifest_names_the_worker_the_bar_shows_failures_and_resume_reports(tmp_path, capsys, monkeypatch):
    cfg = write_tiny(tmp_path, count=3)
    root = tmp_path / "set"
    real = store.generate_sample

    def flaky(plan_json, index, *rest):
        if index == 1:
            raise RuntimeError("render failed")
        return real(plan_json, index, *rest)

    monkeypatch.setattr(store, "generate_sample", flaky)
    with pytest.raises(DatasetError, match=r"1 of 3 sample\(s\) failed \(first: sample 1: RuntimeError"):
        generate(Plan.build(load_config(cfg)), root, workers=0, progress=True)
    bar = capsys.readouterr().err
    assert "failed=1" in bar and "2/3" in bar and "3/3" not in bar and "100%" not in bar
    rows = [json.loads(line) for line in (root / MANIFEST).read_text().splitlines()]
    assert [r["index"] for r in rows] == [0, 2]
    assert all(r["worker"] == "local" and r["pid"] == os.getpid() and r["host"] for r in rows)

    # damage it: a line lost, a temporary folder of a dead run; resume repairs and says so
    monkeypatch.setattr(store, "generate_sample", real)
    (root / MANIFEST).write_text(json.dumps(rows[0]) + "\n")
    (root / SAMPLES / ".tmp-000001-dead").mkdir()
    assert main(["dataset", "resume", str(root), "--workers", "0", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "found 1 sample(s) listed, 1 re-listed from disk, 1 temporary folder(s) removed" in out
    assert "1 sample(s) queued" in out
    rep = verify(root)
    assert rep["ok"] and rep["in_use_by"] is None
    relisted = [json.loads(line) for line in (root / MANIFEST).read_text().splitlines()]
    by_index = {r["index"]: r for r in relisted}
    assert by_index[2]["status"] == "recovered" and by_index[2]["pid"] is None and by_index[2]["recovered_by"]
    assert by_index[1]["pid"] == os.getpid()
    assert recover(root)["listed"] == 3


def _start(cfg: Path, out: Path, indices: str) -> subprocess.Popen:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "scopetwin.cli",
            "dataset",
            "generate",
            str(cfg),
            "--out",
            str(out),
            "--indices",
            indices,
        ]
        + ["--workers", "0", "--quiet"],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.mark.mitsuba
@pytest.mark.slow
def test_two_concurrent_generates_on_one_folder_leave_nothing_unlisted(tmp_path):
    """The split ``--indices`` invites two runs on one folder: the second is refused while the first runs."""
    cfg = write_tiny(tmp_path, count=8)
    out = tmp_path / "set"
    first = _start(cfg, out, "0:6")
    try:
        t0 = time.monotonic()
        while not (out / MANIFEST).exists() or not (out / MANIFEST).read_text():
            assert first.poll() is None, first.communicate()
            assert time.monotonic() - t0 < 120
            time.sleep(0.05)
        second = _start(cfg, out, "6:8")
        _, err = second.communicate(timeout=120)
        still_running = first.poll() is None
        assert first.wait(timeout=300) == 0, first.communicate()
    finally:
        if first.poll() is None:
            first.kill()
            first.wait()
    if still_running:  # refused while the first held the folder
        assert second.returncode == 2 and err.count("\n") == 1, err
        assert f"is in use by pid {first.pid} on " in err
        assert _start(cfg, out, "6:8").wait(timeout=300) == 0
    rep = verify(out)
    assert rep["ok"] and rep["unlisted"] == [] and rep["complete"] == 8, rep
