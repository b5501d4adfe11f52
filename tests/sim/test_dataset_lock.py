"""The dataset folder lock through ``filelock``: one holder, released when it dies, never through a link.

The lock is taken with :func:`filelock.lock_descriptor` (``flock`` on POSIX, ``LockFileEx`` on Windows); a symbolic
link (or a FIFO) planted at ``DIR/.scopetwin.lock`` is refused rather than followed, whether it is there before the
check or swapped in after it (``O_NOFOLLOW``).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest

from scopetwin.sim.datasets import lock as lock_mod
from scopetwin.sim.datasets.config import DatasetError
from scopetwin.sim.datasets.lock import LOCK_FILE, DatasetBusy, DatasetLock, LockPathError, holder


def test_the_holder_line_is_readable_after_byte_zero(tmp_path):
    with DatasetLock(tmp_path, command="scopetwin dataset generate (test)"):
        raw = (tmp_path / LOCK_FILE).read_bytes()
        # byte 0 is what Windows' lock keeps others from reading: the holder's line starts after it
        assert raw[:1] == b"\n"
        me = json.loads(raw[1:])
        assert me["pid"] == os.getpid() and me["command"] == "scopetwin dataset generate (test)"
        assert holder(tmp_path) == me
    assert holder(tmp_path) is None


def test_a_symlink_at_the_lock_path_is_refused_and_its_target_untouched(tmp_path):
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    root = tmp_path / "set"
    root.mkdir()
    (root / LOCK_FILE).symlink_to(target)
    with pytest.raises(LockPathError, match=r"is a symbolic link or not a plain file") as info:
        DatasetLock(root).acquire()
    assert isinstance(info.value, DatasetError)  # the command line's one-line error, exit 2
    assert target.read_text() == "keep me"
    assert holder(root) is None  # a peek does not follow it either
    dangling = tmp_path / "other"
    dangling.mkdir()
    (dangling / LOCK_FILE).symlink_to(tmp_path / "nowhere")
    with pytest.raises(LockPathError):
        DatasetLock(dangling).acquire()
    assert not (tmp_path / "nowhere").exists()  # not created through the link


def test_a_link_swapped_in_after_the_check_is_refused_by_o_nofollow(tmp_path, monkeypatch):
    if not hasattr(os, "O_NOFOLLOW"):  # pragma: no cover - Windows: the lstat check alone
        pytest.skip("no O_NOFOLLOW on this platform")
    target = tmp_path / "precious.txt"
    target.write_text("keep me")
    root = tmp_path / "set"
    root.mkdir()
    (root / LOCK_FILE).symlink_to(target)
    real_lstat = os.lstat
    monkeypatch.setattr(lock_mod.os, "lstat", lambda p: real_lstat(target))  # the check saw a plain file
    with pytest.raises(LockPathError):
        DatasetLock(root).acquire()
    assert target.read_text() == "keep me"


def test_a_fifo_at_the_lock_path_is_refused_without_hanging(tmp_path):
    if not hasattr(os, "mkfifo"):  # pragma: no cover - Windows
        pytest.skip("no FIFOs on this platform")
    os.mkfifo(tmp_path / LOCK_FILE)
    with pytest.raises(LockPathError):
        DatasetLock(tmp_path).acquire()
    assert holder(tmp_path) is None


def test_a_lock_held_by_another_process_is_refused_and_freed_when_it_is_killed(tmp_path):
    script = textwrap.dedent(
        """
        import sys, time
        from scopetwin.sim.datasets.lock import DatasetLock

        DatasetLock(sys.argv[1], command="scopetwin dataset generate (other)").acquire()
        print("held", flush=True)
        time.sleep(60)
        """
    )
    proc = subprocess.Popen(
        [sys.executable, "-c", script, str(tmp_path)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert proc.stdout is not None and proc.stdout.readline() == "held\n", proc.stderr
        with pytest.raises(DatasetBusy, match=rf"in use by pid {proc.pid} on .*scopetwin dataset generate \(other\)"):
            DatasetLock(tmp_path).acquire()
        assert holder(tmp_path)["pid"] == proc.pid
    finally:
        proc.kill()
        proc.wait()
    assert holder(tmp_path) is None  # released by the system when the holder died: never stale
    with DatasetLock(tmp_path) as taken:
        assert taken.held and holder(tmp_path)["pid"] == os.getpid()
