"""One run at a time on a dataset folder: an exclusive ``flock`` on ``DIR/.scopetwin.lock``
(:mod:`scopetwin.sim.datasets`).

``dataset generate`` and ``resume`` rewrite the manifest and tidy temporary sample folders when they start, so two
runs on one folder would undo each other's bookkeeping. The run that holds the lock writes its host, pid, command
and start time into the lock file; a second run is refused at once with one line naming the holder. The kernel
releases the lock when the holder exits, however it exits (a SIGKILL included), so a lock is never stale: a lock
file whose lock is free is simply taken over. Locks work on local file systems and on NFS (Linux emulates
``flock`` there with POSIX record locks).
"""

from __future__ import annotations

import fcntl
import json
import os
import socket
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import Any

from scopetwin.sim.datasets.config import DatasetError

LOCK_FILE = ".scopetwin.lock"


class DatasetBusy(DatasetError):
    """Another live run holds the dataset folder's lock; ``holder`` is what it wrote into the lock file."""

    def __init__(self, root: Path, holder: dict[str, Any]) -> None:
        self.root = root
        self.holder = holder
        super().__init__(
            f"dataset folder {root} is in use by {describe_holder(holder)}; wait for it to finish or stop it"
        )


def describe_holder(holder: dict[str, Any]) -> str:
    """``pid 123 on host (scopetwin dataset generate ..., since 2026-...)`` from a lock file's contents."""
    if not holder.get("pid"):
        return "another run (it is starting; no details yet)"
    text = f"pid {holder['pid']} on {holder.get('host', '?')}"
    extra = [
        x for x in (holder.get("command"), f"since {holder['started_utc']}" if holder.get("started_utc") else "") if x
    ]
    return text + (f" ({', '.join(extra)})" if extra else "")


def _read_holder(fd: int) -> dict[str, Any]:
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        data = json.loads(os.read(fd, 1 << 16).decode() or "{}")
    except (OSError, ValueError):
        return {}
    return data if isinstance(data, dict) else {}


def holder(root: str | Path) -> dict[str, Any] | None:
    """Who holds the lock of dataset folder ``root`` (the lock file's contents), or None when nobody does."""
    path = Path(root) / LOCK_FILE
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return _read_holder(fd)
        except OSError:
            return None
        return None
    finally:
        os.close(fd)


class DatasetLock:
    """The exclusive lock of a dataset folder, held from :meth:`acquire` to :meth:`release` (a context manager).

    Raises
    ------
    DatasetBusy
        Another live run holds it (the message names its pid, host, command and start time).
    """

    def __init__(self, root: str | Path, command: str | None = None) -> None:
        self.root = Path(root)
        self.path = self.root / LOCK_FILE
        self.command = command if command is not None else " ".join(["scopetwin", *sys.argv[1:3]])
        self._fd: int | None = None

    def acquire(self) -> DatasetLock:
        """Take the lock without waiting and write this run's host and pid into the lock file."""
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            for attempt in range(5):  # a `holder()` peek holds a shared lock for microseconds: try again briefly
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if attempt == 4:
                        raise
                    time.sleep(0.05)
        except BlockingIOError:
            info = _read_holder(fd)
            os.close(fd)
            raise DatasetBusy(self.root, info) from None
        except BaseException:
            os.close(fd)
            raise
        me = {
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "command": self.command,
            "started_utc": datetime.now(UTC).isoformat(timespec="seconds"),
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, (json.dumps(me) + "\n").encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        """Give the lock up (the file stays; its contents name the last holder)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    @property
    def held(self) -> bool:
        """Whether this object holds the lock."""
        return self._fd is not None

    def __enter__(self) -> DatasetLock:
        return self.acquire()

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.release()
