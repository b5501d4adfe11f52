"""Kill tests: SIGKILL the generating process, or one Dask worker, at a random moment; resume; verify.

Real subprocesses on a real 2-worker LocalCluster; every wait is bounded and every process this
test starts is killed by its id at the end.
"""

from __future__ import annotations

import contextlib
import json
import os
import random
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_dataset_common import write_tiny  # noqa: E402

from scopetwin.sim.datasets.store import MANIFEST, SAMPLES, load_plan, verify  # noqa: E402
from scopetwin.sim.datasets.store import generate as generate_in_process  # noqa: E402

pytestmark = [pytest.mark.mitsuba, pytest.mark.slow]
ROOT = Path(__file__).resolve().parents[2]
COUNT = 8


def _start(cfg: Path, out: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT), "PYTHONFAULTHANDLER": "1"}  # SIGABRT prints every thread's stack
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
            "--workers",
            "2",
            "--quiet",
        ],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )


def _communicate(proc: subprocess.Popen, timeout: float) -> str:
    """The output of a signalled run; if it has not ended within ``timeout``, fail with where each of its threads
    waits (faulthandler's dump on SIGABRT) and its process tree."""
    try:
        return proc.communicate(timeout=timeout)[0].decode()
    except subprocess.TimeoutExpired:
        tree = []
        for child in psutil.Process(proc.pid).children(recursive=True):
            with contextlib.suppress(psutil.Error):
                tree.append(f"{child.pid} {child.status()} {' '.join(child.cmdline())[:160]}")
        os.kill(proc.pid, signal.SIGABRT)
        try:
            dump = proc.communicate(timeout=20)[0].decode()
        except subprocess.TimeoutExpired:
            dump = "(no dump within 20 s)"
        raise AssertionError(
            f"still running {timeout} s after the signal; children:\n" + "\n".join(tree) + "\n" + dump[-12000:]
        ) from None


def _finished(out: Path) -> int:
    path = out / MANIFEST
    return len(path.read_text().splitlines()) if path.exists() else 0


def _wait(cond, timeout: float, what: str) -> None:
    t0 = time.monotonic()
    while not cond():
        if time.monotonic() - t0 > timeout:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(0.05)


def _workers(proc: subprocess.Popen) -> list[psutil.Process]:
    """The Dask worker processes (spawned children running distributed's worker), not helper processes."""
    out = []
    for child in psutil.Process(proc.pid).children(recursive=True):
        try:
            cmd = " ".join(child.cmdline())
        except psutil.Error:
            continue
        if "spawn_main" in cmd and "resource_tracker" not in cmd:
            out.append(child)
    return out


def _cleanup(proc: subprocess.Popen, family: list[psutil.Process]) -> None:
    for p in [*family, psutil.Process(proc.pid) if proc.poll() is None else None]:
        if p is None:
            continue
        try:
            p.kill()
        except psutil.Error:
            pass
    proc.wait(timeout=30)


@pytest.mark.parametrize("victim", ["client", "worker"])
def test_kill_resume_verify(tmp_path, victim):
    cfg = write_tiny(tmp_path, count=COUNT)
    out = tmp_path / "set"
    rng = random.Random(victim)
    proc = _start(cfg, out)
    family: list[psutil.Process] = []
    try:
        _wait(lambda: len(_workers(proc)) >= 2 or proc.poll() is not None, 120, "two workers")
        assert proc.poll() is None, "the generator stopped early: " + proc.stdout.read().decode()[-2000:]
        family = list(psutil.Process(proc.pid).children(recursive=True))
        target = rng.randint(1, 3)
        _wait(lambda: _finished(out) >= target or proc.poll() is not None, 180, f"{target} finished samples")
        time.sleep(rng.uniform(0.0, 0.8))  # a random moment, most likely inside a sample
        assert proc.poll() is None, "the generator finished before it could be killed: make the set larger"
        if victim == "client":
            os.kill(proc.pid, signal.SIGKILL)
            proc.wait(timeout=30)
            # the orphaned workers notice their parent is gone and exit by themselves
            _wait(
                lambda: not any(p.is_running() and p.status() != psutil.STATUS_ZOMBIE for p in family),
                60,
                "the orphaned workers to exit",
            )
            assert verify(out)["complete"] < COUNT
        else:
            worker = _workers(proc)[0]
            worker.send_signal(signal.SIGKILL)
            # the nanny restarts the worker and the scheduler reruns its task: the run still finishes
            assert proc.wait(timeout=240) == 0, proc.stdout.read().decode()[-2000:]
    finally:
        _cleanup(proc, family)
    generate_in_process(load_plan(out), out, workers=0, progress=False)  # `dataset resume`
    rep = verify(out)
    assert rep["ok"], json.dumps(rep)
    assert rep["complete"] == COUNT and rep["duplicates"] == [] and rep["corrupt"] == []
    assert not [p.name for p in (out / SAMPLES).iterdir() if p.name.startswith(".")]
    assert not [p for p in out.rglob("*.part*")]
    indices = [json.loads(line)["index"] for line in (out / MANIFEST).read_text().splitlines()]
    assert sorted(indices) == list(range(COUNT))


@pytest.mark.parametrize(
    ("sig", "group"),
    [(signal.SIGINT, True), (signal.SIGTERM, True), (signal.SIGHUP, True), (signal.SIGTERM, False)],
    ids=["ctrl-c-to-the-group", "sigterm-to-the-group", "sighup-to-the-group", "sigterm-to-the-client"],
)
def test_signal_stops_cleanly_with_every_sample_listed(tmp_path, sig, group):
    """Ctrl-C (SIGINT to the whole process group, as a terminal sends it), SIGTERM (`timeout`, a batch system;
    `kill PID`), SIGHUP (a dropped session): one line, exit 128 + n, no worker traceback, every sample listed."""
    cfg = write_tiny(tmp_path, count=COUNT)
    out = tmp_path / "set"
    proc = _start(cfg, out)
    family: list[psutil.Process] = []
    try:
        _wait(lambda: len(_workers(proc)) >= 2 or proc.poll() is not None, 120, "two workers")
        family = list(psutil.Process(proc.pid).children(recursive=True))
        _wait(lambda: _finished(out) >= 2 or proc.poll() is not None, 180, "2 finished samples")
        time.sleep(random.Random(int(sig)).uniform(0.0, 0.5))
        assert proc.poll() is None, "the generator finished before it could be signalled: make the set larger"
        (os.killpg if group else os.kill)(proc.pid, sig)
        output = _communicate(proc, 60)
        _wait(
            lambda: not any(p.is_running() and p.status() != psutil.STATUS_ZOMBIE for p in family),
            60,
            "the workers to exit",
        )
    finally:
        _cleanup(proc, family)
    assert proc.returncode == 128 + sig, output
    assert output == f"scopetwin: interrupted by {signal.Signals(sig).name}\n"  # --quiet: nothing else
    rep = verify(out)
    assert rep["unlisted"] == [] and rep["temporary"] == [] and rep["corrupt"] == [] and rep["duplicates"] == []
    assert rep["in_use_by"] is None and rep["complete"] >= 2  # (all of them when the last ones were in flight)
    rows = [json.loads(line) for line in (out / MANIFEST).read_text().splitlines()]
    made = [r for r in rows if r["status"] == "written"]
    # the embedded cluster's workers speak TLS (no other local user can submit work to them)
    assert made and all(r["pid"] not in (proc.pid, None) and r["worker"].startswith("tls://") for r in made)
    generate_in_process(load_plan(out), out, workers=0, progress=False)  # `dataset resume`
    assert verify(out)["ok"]


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGHUP])
def test_signal_while_the_cluster_starts_is_one_line_and_leaves_no_folder(tmp_path, sig):
    """Ctrl-C / SIGHUP to the group while the worker processes start: no traceback from a half-started cluster."""
    cfg = write_tiny(tmp_path, count=COUNT)
    out = tmp_path / "set"
    proc = _start(cfg, out)
    family: list[psutil.Process] = []
    try:
        _wait(lambda: len(_workers(proc)) >= 1 or proc.poll() is not None, 120, "a starting worker")
        family = list(psutil.Process(proc.pid).children(recursive=True))
        os.killpg(proc.pid, sig)
        output = _communicate(proc, 60)
    finally:
        _cleanup(proc, family)
    assert proc.returncode == 128 + sig, output
    assert output == f"scopetwin: interrupted by {signal.Signals(sig).name}\n"
    if out.exists():  # the signal came after the first sample: then it is listed
        rep = verify(out)
        assert rep["unlisted"] == [] and rep["temporary"] == [] and rep["complete"] >= 1, rep
