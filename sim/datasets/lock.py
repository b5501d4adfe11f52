"""One run at a time on a dataset folder: an exclusive lock on ``DIR/.scopetwin.lock`` (:mod:`scopetwin.sim.datasets`).

``dataset generate`` and ``resume`` rewrite the manifest and tidy temporary sample folders when they start, so two
runs on one folder would undo each other's bookkeeping. The run that holds the lock writes its host, pid, command
and start time into the lock file; a second run is refused at once with one line naming the holder. The lock is the
operating system's own file lock, taken through the cross-platform ``filelock`` package
(:func:`filelock.lock_descriptor`: ``flock`` on POSIX, ``LockFileEx`` on byte 0 on Windows), so the system
releases it when the holder exits, however it exits (a SIGKILL included), and a lock is never stale: a lock file
whose lock is free is simply taken over. Locks work on local file systems and on NFS (Linux emulates ``flock`` there
with POSIX record locks). The holder's line is written after byte 0, which Windows' lock keeps others from reading.

The lock file is never reached through a symbolic link: a link (or anything but a plain file) planted at
``DIR/.scopetwin.lock`` is refused (checked with :func:`os.lstat`, and opened with ``O_NOFOLLOW`` where the platform
has it), so a run cannot be made to truncate and write a file elsewhere.
"""

from __future__ import annotations

import errno
import json
import os
import socket
import stat
import sys
import time
from datetime import UTC, datetime
from pathlib import Path
from types import TracebackType
from typing import Any

from scopetwin.sim.datasets.config import DatasetError

LOCK_FILE = ".scopetwin.lock"

#: Flags of every open of the lock file: never through a symbolic link, never blocking on a planted FIFO, binary.
_OPEN_FLAGS = getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_BINARY", 0)
#: Where the holder's line starts: Windows locks byte 0, which other processes then cannot read.
_HOLDER_OFFSET = 1


class LockPathError(DatasetError):
    """The lock path is a symbolic link or not a plain file: refused rather than followed."""


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


def _open(path: Path, flags: int) -> int:
    """Open the lock file ``path`` without following a symbolic link; refuse anything but a plain file.

    Raises
    ------
    LockPathError
        ``path`` is a symbolic link or not a plain file.
    OSError
        It cannot be opened (FileNotFoundError when it does not exist and ``flags`` has no ``O_CREAT``).
    """
    refused = LockPathError(
        f"{path} is a symbolic link or not a plain file; a dataset lock file is never followed through a link: "
        "remove it and run again"
    )
    try:
        before = os.lstat(path)
    except FileNotFoundError:
        if not flags & os.O_CREAT:
            raise
    else:
        if not stat.S_ISREG(before.st_mode):
            raise refused
    try:
        fd = os.open(path, flags | _OPEN_FLAGS, 0o666)
    except OSError as exc:  # a link swapped in after the check: O_NOFOLLOW refuses it (ELOOP; EMLINK on FreeBSD)
        if exc.errno in (errno.ELOOP, errno.EMLINK) or os.path.islink(path):
            raise refused from None
        raise
    if not stat.S_ISREG(os.fstat(fd).st_mode):  # swapped in after the check, where there is no O_NOFOLLOW
        os.close(fd)
        raise refused
    return fd


def _try_lock(fd: int) -> bool:
    """Take the exclusive lock of ``fd`` without waiting; False when another open file holds it."""
    from filelock import lock_descriptor

    return lock_descriptor(fd, blocking=False)


def _read_holder(fd: int) -> dict[str, Any]:
    text = b""
    for offset in (0, _HOLDER_OFFSET):  # byte 0 is unreadable to others while Windows' lock holds it
        try:
            os.lseek(fd, offset, os.SEEK_SET)
            text = os.read(fd, 1 << 16)
            break
        except OSError:
            continue
    try:
        data = json.loads(text.decode() or "{}")
    except ValueError:
        return {}
    return data if isinstance(data, dict) else {}


def holder(root: str | Path) -> dict[str, Any] | None:
    """Who holds the lock of dataset folder ``root`` (the lock file's contents), or None when nobody does.

    The peek takes the lock for an instant when it is free, so :meth:`DatasetLock.acquire` tries again briefly.
    """
    from filelock import unlock_descriptor

    path = Path(root) / LOCK_FILE
    fd = -1
    for mode in (os.O_RDWR, os.O_RDONLY):  # NFS grants an exclusive lock only to a descriptor open for writing
        try:
            fd = _open(path, mode)
            break
        except PermissionError:
            continue
        except (OSError, DatasetError):
            return None
    if fd < 0:
        return None
    try:
        for attempt in range(5):  # another peek holds it for an instant: try again briefly before naming a holder
            try:
                if _try_lock(fd):
                    unlock_descriptor(fd)
                    return None
            except OSError:
                return None
            if attempt < 4:
                time.sleep(0.01)
        return _read_holder(fd)
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
        """Take the lock without waiting and write this run's host and pid into the lock file.

        Raises
        ------
        DatasetBusy
            Another live run holds it.
        LockPathError
            ``DIR/.scopetwin.lock`` is a symbolic link or not a plain file.
        """
        fd = _open(self.path, os.O_RDWR | os.O_CREAT)
        try:
            for attempt in range(5):  # a `holder()` peek holds the lock for microseconds: try again briefly
                if _try_lock(fd):
                    break
                if attempt == 4:
                    info = _read_holder(fd)
                    raise DatasetBusy(self.root, info)
                time.sleep(0.05)
            me = {
                "host": socket.gethostname(),
                "pid": os.getpid(),
                "command": self.command,
                "started_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            }
            os.ftruncate(fd, 0)
            os.lseek(fd, 0, os.SEEK_SET)
            os.write(fd, ("\n" * _HOLDER_OFFSET + json.dumps(me) + "\n").encode())
        except BaseException:
            os.close(fd)
            raise
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
