"""A stream of deflectometry frames reconstructed one after another: a rig's live loop (thesis §1.5, §1.4).

Each frame passes two stages: its markers found, filtered and indexed (§1.5,
:func:`scopetwin.recon.markers.find_markers_for`), then the nested iteration on them (§1.4,
:func:`scopetwin.recon.strategy.solve`; by default the fixed-scale :meth:`ReconstructionConfig.realtime`
configuration, built once for the setup). :func:`reconstruct_stream` overlaps the stages of consecutive frames:
while frame k is solved in the caller's thread, the markers of frame k+1 are searched in a worker process
(:class:`scopetwin.recon.markers.worker.MarkerWorker`; a process, not a thread: that module says why).

The results are those of the stages run one after the other in the caller's thread (``overlap=False``): the same
frames, the same markers (computed by the same code on the same pixels), the same reconstructor, solved in the same
order. Where the configuration reads the posterior (§1.4 with :mod:`scopetwin.recon.posterior`), each frame's
evidence maximisation starts from the prior the frame before chose (``warm_start``). A live loop that must go on
past a frame that fails (``keep_going``) receives that frame's :class:`FrameFailure` in its place.
"""

from __future__ import annotations

from collections.abc import Callable, Generator, Iterable, Iterator
from typing import Any, Literal, NamedTuple, Protocol, overload

from numpy.typing import NDArray

from scopetwin.recon.config import ReconstructionConfig
from scopetwin.recon.markers.worker import WORKER_NAME, MarkerWorker, Pending, Searched, search_now
from scopetwin.recon.parallel import available_cpus as _cpus
from scopetwin.recon.policy import DEFAULT_POLICY, ReconstructionPolicy
from scopetwin.recon.posterior import prior_from_dict
from scopetwin.recon.reconstruct import MarkerObservations, ReconstructionResult, Reconstructor
from scopetwin.recon.strategy import ImageReconstruction, solve
from scopetwin.scenes.setup import Setup

__all__ = ["WORKER_NAME", "FrameFailure", "reconstruct_stream"]


class FrameFailure(NamedTuple):
    """A frame whose marker search (§1.5) or reconstruction (§1.4) failed, in its place in a ``keep_going`` stream;
    ``error`` is what the marker search or the nested iteration raised (a :class:`~scopetwin.recon.markers.
    MarkerError` or :class:`~scopetwin.recon.errors.ReconstructionError` as a rule)."""

    error: Exception


class _Here:
    """The marker search run at once in the calling thread (the stages one after the other)."""

    def __init__(self, setup: Setup, options: dict[str, Any]) -> None:
        self.setup, self.options = setup, options

    def start(self, image: NDArray[Any]) -> Pending:
        """The frame's markers, searched now (an error kept to be raised at its frame, as the worker's)."""
        return search_now(image, self.setup, self.options)

    def close(self) -> None:
        """Nothing to end."""


class _Stage(Protocol):
    """Where the marker search runs: :meth:`start` one frame's, :meth:`close` at the end of the stream."""

    def start(self, image: NDArray[Any]) -> Pending: ...

    def close(self) -> None: ...


def _next_frame(frames: Iterator[NDArray[Any]], stage: _Stage) -> Pending | None:
    """The next frame drawn in the calling thread and its marker search started; None at the end.

    An error of the frame source is returned as an ended search, so that it is raised at its own frame, after the
    results of the frames before it.
    """
    try:
        image = next(frames)
    except StopIteration:
        return None
    except Exception as err:
        return Searched(error=err, source_error=True)
    return stage.start(image)


def _warm(rec: Reconstructor, result: ReconstructionResult) -> None:
    """The prior this frame's posterior chose by evidence becomes the next frame's start (none: left as it is)."""
    if result.uncertainty is not None:
        rec.evidence_start = prior_from_dict(result.uncertainty.hyper)


def _frames(
    frames: Iterable[NDArray[Any]],
    make_stage: Callable[[], _Stage],
    rec: Reconstructor,
    policy: ReconstructionPolicy,
    warm_start: bool = True,
    keep_going: bool = False,
) -> Generator[ImageReconstruction | FrameFailure, None, None]:
    """Frame k solved here while frame k+1's markers are searched by the stage; each result in order.

    The stage is made when the first frame is asked for and closed when the stream ends, however it ends. With
    ``keep_going`` a frame's marker-search or reconstruction error is yielded as its :class:`FrameFailure` and the
    stream goes on; an error of the frame source ends it either way.
    """
    stage = make_stage()
    try:
        source = iter(frames)
        pending = _next_frame(source, stage)
        while pending is not None:
            if isinstance(pending, Searched) and pending.source_error:
                pending.result()  # the frame source failed: raised, the stream ends
            try:
                found = pending.result()  # frame k's detection error is raised here, at frame k
            except Exception as err:
                if not keep_going:
                    raise
                pending = _next_frame(source, stage)
                yield FrameFailure(err)
                continue
            pending = _next_frame(source, stage)
            try:
                result = solve(rec, MarkerObservations(found.ij, found.centroids), policy)
            except Exception as err:
                if not keep_going:
                    raise
                yield FrameFailure(err)
                continue
            if warm_start:
                _warm(rec, result)
            yield ImageReconstruction(found, result, rec)
    finally:
        stage.close()


@overload
def reconstruct_stream(
    frames: Iterable[NDArray[Any]],
    setup: Setup,
    reconstructor: Reconstructor | None = None,
    policy: ReconstructionPolicy = DEFAULT_POLICY,
    *,
    overlap: bool | None = None,
    warm_start: bool = True,
    keep_going: Literal[False] = False,
    **marker_options: Any,
) -> Generator[ImageReconstruction, None, None]: ...


@overload
def reconstruct_stream(
    frames: Iterable[NDArray[Any]],
    setup: Setup,
    reconstructor: Reconstructor | None = None,
    policy: ReconstructionPolicy = DEFAULT_POLICY,
    *,
    overlap: bool | None = None,
    warm_start: bool = True,
    keep_going: Literal[True],
    **marker_options: Any,
) -> Generator[ImageReconstruction | FrameFailure, None, None]: ...


def reconstruct_stream(
    frames: Iterable[NDArray[Any]],
    setup: Setup,
    reconstructor: Reconstructor | None = None,
    policy: ReconstructionPolicy = DEFAULT_POLICY,
    *,
    overlap: bool | None = None,
    warm_start: bool = True,
    keep_going: bool = False,
    **marker_options: Any,
) -> Generator[ImageReconstruction, None, None] | Generator[ImageReconstruction | FrameFailure, None, None]:
    """The frames' markers (§1.5) and surfaces (§1.4), in order, frame k+1's markers searched while frame k is solved.

    Parameters
    ----------
    frames : iterable of ndarray, (rows, cols)
        Camera images of one setup, e.g. :meth:`scopetwin.instrument.devices.CameraDevice.stream`. They are drawn in
        the caller's thread, one frame ahead: frame k+1 is drawn before frame k's result is delivered.
    setup : Setup
        The (calibrated) deflectometry setup of every frame.
    reconstructor : Reconstructor, optional
        The nested iteration's pieces for the setup, built once (default:
        ``Reconstructor.from_setup(setup, ReconstructionConfig.realtime())``, the fixed-scale configuration for
        one frame period, without the centroid-bias step). Its frames are solved one at a time, in order.
    policy : ReconstructionPolicy
        The fallbacks of :func:`scopetwin.recon.strategy.solve`; its ``lattice_below`` is the marker search's.
    overlap : bool, optional
        Search frame k+1's markers in a worker process while frame k is solved; False: one stage after the other
        in the caller's thread. The results are the same either way. Default: overlapped where this process may run
        on two CPUs or more (on one, the worker would only take turns with the solve).
    warm_start : bool
        Where the reconstructor's configuration reads the posterior (``posterior`` not ``"off"``), start each frame's
        evidence maximisation from the prior the frame before chose (:attr:`Reconstructor.evidence_start`; the
        frames of one setup share their prior's scales). Without a posterior this changes nothing.
    keep_going : bool
        A frame whose marker search or reconstruction fails is yielded as its :class:`FrameFailure` and the stream
        goes on with the next frame (a live loop); False: the error is raised at that frame and ends the stream.
    **marker_options
        Options of :func:`scopetwin.recon.markers.find_markers_for` (picklable: they go to the worker).

    Yields
    ------
    ImageReconstruction or FrameFailure
        Per frame, in the order of ``frames``: its markers, its reconstruction result and the reconstructor (with
        ``keep_going``, a failed frame's :class:`FrameFailure`).

    Raises
    ------
    scopetwin.recon.markers.MarkerError, scopetwin.recon.errors.ReconstructionError
        At the frame whose marker search or reconstruction failed (without ``keep_going``), after the results of the
        frames before it; the stream ends there (a tied reference marker,
        :class:`scopetwin.recon.markers.ReferenceTieError`, included: :func:`scopetwin.recon.strategy.reconstruct_image`
        decides those with several reconstructions). An error of the frame source is raised at the frame it failed to
        deliver, and ends the stream with or without ``keep_going``.

    Notes
    -----
    The worker process starts with the stream's first frame (a fresh interpreter, ~1-2 s before that frame's
    markers) and ends with the stream: closing it (``close()``, leaving a ``for`` loop over it, the end of the frames,
    an error, a KeyboardInterrupt in the loop or the stream) ends the worker (terminated where a search is under way)
    and frees the shared memory; nothing is left running. As with any ``multiprocessing`` start by "spawn", a script
    that runs a stream keeps its top-level work under ``if __name__ == "__main__":`` (the worker imports the script's
    module). Short streams run faster with ``overlap=False``.
    """
    rec = Reconstructor.from_setup(setup, ReconstructionConfig.realtime()) if reconstructor is None else reconstructor
    options = {"lattice_below": policy.lattice_below, **marker_options}
    worker = _cpus() >= 2 if overlap is None else overlap
    return _frames(
        frames,
        lambda: MarkerWorker(setup, **options) if worker else _Here(setup, options),
        rec,
        policy,
        warm_start,
        keep_going,
    )
