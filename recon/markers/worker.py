"""The marker search (thesis §1.5) of one frame at a time in a worker process, beside the caller's own work.

:class:`MarkerWorker` runs :func:`scopetwin.recon.markers.find_markers_for` in a process of its own, so that a live
loop can reconstruct frame k (:mod:`scopetwin.recon.stream`) while frame k+1's markers are searched. A process, not a
thread: the search is hundreds of numpy, OpenCV and KD-tree calls on arrays of a few hundred to a few hundred thousand
elements, and the interpreter's lock is held between and around them (on the §1.10 frame, 2 cores, a worker thread
beside the realtime solve gained nothing: 20 ms + 23 ms took 43 ms a frame side by side, as one after the other).

The frame goes to the worker through shared memory, the markers come back pickled: they are those that
:func:`find_markers_for` gives in the caller's process, bit for bit (the same code on the same pixels).
"""

from __future__ import annotations

import contextlib
import pickle
import signal
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from scopetwin.recon.markers.centroid_search import MarkerError
from scopetwin.recon.markers.identification import Markers, find_markers_for

if TYPE_CHECKING:
    from multiprocessing.connection import Connection
    from multiprocessing.process import BaseProcess
    from multiprocessing.shared_memory import SharedMemory

    from scopetwin.scenes.setup import Setup

#: Name of the worker process.
WORKER_NAME = "scopetwin-markers"

#: Seconds :meth:`MarkerWorker.close` waits for the idle worker to end before it is terminated.
JOIN_S = 10.0

#: Image kinds the worker takes (numpy ``dtype.kind``: bool, integers, floats); others are searched in the caller's
#: process, where :func:`find_markers_for` refuses them with its own error.
_SHARED_KINDS = "biuf"


class Pending(Protocol):
    """One frame's marker search: :meth:`result` waits for its markers or raises its error."""

    def result(self) -> Markers:
        """The frame's markers; the search's error raised."""
        ...


@dataclass
class Searched:
    """A marker search that has ended: its markers, or the error to raise when they are asked for.

    ``source_error``: the error is the frame source's (no frame came), not the search's.
    """

    markers: Markers | None = None
    error: Exception | None = None
    source_error: bool = False

    def result(self) -> Markers:
        """The markers, or the error raised."""
        if self.error is not None:
            raise self.error
        assert self.markers is not None
        return self.markers


def search_now(image: NDArray[Any], setup: Setup, options: dict[str, Any]) -> Searched:
    """``find_markers_for(image, setup, **options)`` in this thread, its error kept to be raised later."""
    try:
        return Searched(find_markers_for(image, setup, **options))
    except Exception as err:
        return Searched(error=err)


def _serve(conn: Connection, setup: Setup, options: dict[str, Any]) -> None:
    """The worker process: one frame at a time, (shared memory name, shape, dtype) in, ``(markers, error)`` out.

    Ends on None or when the caller's end of the pipe closes. Ctrl-C reaches the whole process group: the worker
    ignores it and the caller, which receives it too, ends the worker.
    """
    from multiprocessing import shared_memory

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    shm: SharedMemory | None = None
    try:
        while (job := _receive_job(conn)) is not None:
            name, shape, dtype = job
            if shm is None or shm.name != name:
                if shm is not None:
                    shm.close()
                shm = shared_memory.SharedMemory(name)
            conn.send(_answer(np.ndarray(shape, np.dtype(dtype), buffer=shm.buf), setup, options))
    finally:
        if shm is not None:
            with contextlib.suppress(BufferError):  # a frame still held by an error's traceback
                shm.close()


def _receive_job(conn: Connection) -> Any:
    """The next job, or None when asked to end or when the caller's end is gone."""
    try:
        return conn.recv()
    except (EOFError, OSError):
        return None


def _answer(image: NDArray[Any], setup: Setup, options: dict[str, Any]) -> tuple[Markers | None, Exception | None]:
    """The worker's answer for one frame: its markers, or its error as one that pickles."""
    done = search_now(image, setup, options)
    err = done.error
    if err is None:
        return done.markers, None
    err.__traceback__ = None  # the frame in shared memory is not held by it
    err.add_note("(raised in the marker search's worker process)")
    try:
        pickle.dumps(err)
    except Exception:
        return None, MarkerError(f"{type(err).__name__}: {err} (in the marker search's worker process)")
    return None, err


class MarkerWorker:
    """A worker process that searches the markers of one frame at a time (:func:`find_markers_for`).

    :meth:`start` hands a frame over (its pixels copied into a shared slot, a few bytes down a pipe) and returns the
    pending search; its ``result()`` waits for the markers (or raises the search's error, as
    :func:`find_markers_for` would have). One search at a time: the caller collects each before it starts the next.
    The slot grows when a larger frame comes. :meth:`close` (or leaving a ``with`` block) ends the worker.

    Parameters
    ----------
    setup : Setup
        The setup of every frame.
    **options
        Options of :func:`find_markers_for` (picklable).

    Notes
    -----
    The worker is a fresh interpreter ("spawn": no threads or locks copied from this one), ~1-2 s before it answers
    the first frame. As with any ``multiprocessing`` start by "spawn", a script that uses it keeps its top-level work
    under ``if __name__ == "__main__":`` (the worker imports the script's module).
    """

    def __init__(self, setup: Setup, **options: Any) -> None:
        import multiprocessing

        self.setup, self.options = setup, options
        ctx = multiprocessing.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc: BaseProcess = ctx.Process(target=_serve, args=(child, setup, options), name=WORKER_NAME)
        self._proc.daemon = True
        self._proc.start()
        child.close()
        self._shm: SharedMemory | None = None
        self._in_flight = False

    def __enter__(self) -> MarkerWorker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _slot(self, nbytes: int) -> SharedMemory:
        """The shared slot, at least ``nbytes`` large."""
        from multiprocessing import shared_memory

        if self._shm is None or self._shm.size < nbytes:
            self._release_slot()
            self._shm = shared_memory.SharedMemory(create=True, size=max(nbytes, 1))
        return self._shm

    def _release_slot(self) -> None:
        if self._shm is not None:
            self._shm.close()
            self._shm.unlink()
            self._shm = None

    def start(self, image: NDArray[Any]) -> Pending:
        """Start the search of ``image``'s markers in the worker; the pending search.

        An image the worker cannot take (not an array of numbers) is searched here, so that it fails with
        :func:`find_markers_for`'s own error.
        """
        if self._in_flight:
            raise RuntimeError("the previous frame's markers were not collected")
        frame = np.asarray(image) if isinstance(image, np.ndarray) else None
        if frame is None or frame.dtype.kind not in _SHARED_KINDS:
            return search_now(image, self.setup, self.options)
        shm = self._slot(frame.nbytes)
        np.copyto(np.ndarray(frame.shape, frame.dtype, buffer=shm.buf), frame)
        try:
            self._conn.send((shm.name, frame.shape, frame.dtype.str))
        except OSError as err:
            return Searched(error=MarkerError(f"the marker search's worker process ended ({err})"))
        self._in_flight = True
        return self

    def result(self) -> Markers:
        """The markers of the search under way (waits for them), or its error raised."""
        try:
            markers, error = self._conn.recv()
        except (EOFError, OSError) as err:
            self._proc.join(JOIN_S)
            raise MarkerError(f"the marker search's worker process ended (exit code {self._proc.exitcode})") from err
        self._in_flight = False
        return Searched(markers, error).result()

    def close(self) -> None:
        """End the worker (terminated where a search is under way or it does not end) and free the slot."""
        try:
            if not self._in_flight:
                self._conn.send(None)
                self._proc.join(JOIN_S)
        except (OSError, ValueError):
            pass
        finally:
            if self._proc.is_alive():
                self._proc.terminate()
                self._proc.join()
            self._conn.close()
            self._release_slot()
