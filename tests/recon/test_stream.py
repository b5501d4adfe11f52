"""The realtime stream (recon.stream): overlapped stages give the sequential results, errors arrive at their frame,
and the worker process ends with the stream however it ends."""

from __future__ import annotations

import multiprocessing
import pickle
from collections.abc import Iterator

import numpy as np
import pytest

import scopetwin.recon.stream as stream_module
from scopetwin.recon.errors import TooFewMarkersError
from scopetwin.recon.markers import MarkerError, ReferenceTieError, find_markers_for
from scopetwin.recon.strategy import ImageReconstruction
from scopetwin.recon.stream import WORKER_NAME, FrameFailure, reconstruct_stream
from scopetwin.scenes.setup import Setup, load_setup
from scopetwin.sim.surfaces import surface_for


@pytest.fixture(scope="module")
def frames() -> tuple[Setup, list[np.ndarray]]:
    """Three frames of the §1.10 setup on a camera of a quarter of its pixels: one analytic render, sensor noise of
    three seeds."""
    from scopetwin.scenes.analytic import render

    setup = load_setup("thesis-1.10-deflectometry", {"camera": {"pixels": [340, 256], "pixel_pitch": 0.0186}})
    clean = render(setup, surface_for(setup), spp=2, seed=1)
    sensor = setup.sensor.sensor()
    exposure = sensor.exposure_for(float(clean.max()), setup.sensor.photons_per_unit_s, 0.7)
    return setup, [sensor.capture(clean, setup.sensor.photons_per_unit_s, exposure, rng=s) for s in range(3)]


def _workers() -> list[multiprocessing.process.BaseProcess]:
    return [p for p in multiprocessing.active_children() if p.name == WORKER_NAME]


class _Source:
    """Frames drawn one by one, counted; ``fail``: raised in place of frame ``at``."""

    def __init__(self, images: list[np.ndarray], at: int = -1, fail: BaseException | None = None) -> None:
        self.images, self.at, self.fail, self.drawn = images, at, fail, 0

    def __iter__(self) -> Iterator[np.ndarray]:
        for k, image in enumerate(self.images):
            if k == self.at and self.fail is not None:
                raise self.fail
            self.drawn += 1
            yield image


def _few_markers(setup: Setup, image: np.ndarray) -> np.ndarray:
    """The frame with only the markers within 2.6 spacings of the reference left: found, but too few to solve."""
    m = find_markers_for(image, setup)
    ref = m.centroids[np.all(m.ij == 0, axis=1)][0]
    rows, cols = np.mgrid[: image.shape[0], : image.shape[1]]
    out = image.copy()
    far = np.hypot(cols + 0.5 - ref[0], rows + 0.5 - ref[1]) > 2.6 * np.linalg.norm(m.axes, axis=1).max()
    out[far] = np.median(image)
    return out


def test_overlapped_stream_gives_the_sequential_results(frames) -> None:
    setup, images = frames
    xx, yy = np.meshgrid(np.linspace(-12.0, 12.0, 25), np.linspace(-23.0, 23.0, 47))
    seq = list(reconstruct_stream(images, setup, overlap=False))
    ovl = list(reconstruct_stream(images, setup, overlap=True))
    assert len(seq) == len(ovl) == 3
    for a, b in zip(seq, ovl, strict=True):
        np.testing.assert_array_equal(a.markers.ij, b.markers.ij)
        np.testing.assert_array_equal(a.markers.centroids, b.markers.centroids)
        assert a.result.converged and b.result.converged
        np.testing.assert_allclose(b.result.surface.height(xx, yy), a.result.surface.height(xx, yy), rtol=0, atol=1e-12)
    # the frames differ (their noise), so the order is checked too
    assert not np.array_equal(ovl[0].markers.centroids, ovl[1].markers.centroids)
    assert not _workers()


@pytest.mark.parametrize("overlap", [True, False])
def test_an_error_in_a_frames_marker_search_is_raised_at_that_frame(frames, overlap: bool) -> None:
    setup, images = frames
    source = _Source([images[0], images[1], np.zeros_like(images[0]), images[2]])
    stream = reconstruct_stream(source, setup, overlap=overlap)
    got = [next(stream), next(stream)]
    for g, image in zip(got, images[:2], strict=True):
        np.testing.assert_array_equal(g.markers.centroids, find_markers_for(image, setup).centroids)
    with pytest.raises(MarkerError, match="blank"):
        next(stream)
    assert source.drawn == 3  # frame 3 was never drawn
    with pytest.raises(StopIteration):  # the stream ends at its first error
        next(stream)
    assert not _workers()


@pytest.mark.parametrize("overlap", [True, False])
def test_an_error_in_a_frames_reconstruction_is_raised_at_that_frame(frames, overlap: bool) -> None:
    setup, images = frames
    stream = reconstruct_stream([images[0], _few_markers(setup, images[1]), images[2]], setup, overlap=overlap)
    assert next(stream).result.converged
    with pytest.raises(TooFewMarkersError):
        next(stream)  # frame 2's markers were being searched meanwhile: dropped, the worker ended
    assert not _workers()


def test_an_error_of_the_frame_source_is_raised_at_its_frame(frames) -> None:
    setup, images = frames
    source = _Source(images, at=1, fail=TimeoutError("no frame"))
    stream = reconstruct_stream(source, setup, overlap=True)
    assert next(stream).result.converged
    with pytest.raises(TimeoutError, match="no frame"):
        next(stream)
    assert not _workers()


def test_the_stream_stops_cleanly_on_close_and_on_keyboard_interrupt(frames) -> None:
    setup, images = frames
    stream = reconstruct_stream(images, setup, overlap=True)
    next(stream)  # frame 1's marker search is under way now
    assert len(_workers()) == 1
    stream.close()
    assert not _workers()
    source = _Source(images, at=2, fail=KeyboardInterrupt())
    with pytest.raises(KeyboardInterrupt):
        for _ in reconstruct_stream(source, setup, overlap=True):
            pass
    assert source.drawn == 2 and not _workers()
    reconstruct_stream(images, setup, overlap=True).close()  # never started: no worker at all
    assert not _workers()


def test_a_worker_that_died_is_an_error_at_the_next_frame(frames) -> None:
    setup, images = frames
    stream = reconstruct_stream(images, setup, overlap=True)
    next(stream)
    (worker,) = _workers()
    worker.kill()
    worker.join()
    with pytest.raises(MarkerError, match="worker process ended"):
        next(stream)  # frame 1, or frame 2 where frame 1's markers had come back before the worker died
        next(stream)
    assert not _workers()


def test_a_tied_reference_pickles_with_its_candidates() -> None:
    """The worker process hands errors back pickled: a tie keeps its candidates."""
    err = pickle.loads(pickle.dumps(ReferenceTieError(np.array([3, 7]), "two equally large candidates")))
    assert isinstance(err, ReferenceTieError) and str(err) == "two equally large candidates"
    np.testing.assert_array_equal(err.candidates, [3, 7])


def test_the_stages_overlap_by_default_only_with_two_cpus(frames, monkeypatch) -> None:
    setup, images = frames
    monkeypatch.setattr(stream_module, "_cpus", lambda: 1)
    stream = reconstruct_stream(images, setup)
    next(stream)
    assert not _workers()
    stream.close()
    monkeypatch.setattr(stream_module, "_cpus", lambda: 2)
    stream = reconstruct_stream(images, setup)
    next(stream)
    assert len(_workers()) == 1
    stream.close()
    assert not _workers()


@pytest.mark.parametrize("overlap", [True, False])
def test_keep_going_yields_a_failed_frame_in_its_place_and_goes_on(frames, overlap: bool) -> None:
    """A blank frame (marker search) and a frame with too few markers (reconstruction) each come back as their
    FrameFailure; the frames after them are reconstructed as without the failures."""
    setup, images = frames
    source = [images[0], np.zeros_like(images[0]), _few_markers(setup, images[1]), images[2]]
    got = list(reconstruct_stream(source, setup, overlap=overlap, keep_going=True))
    assert [type(g).__name__ for g in got] == [
        "ImageReconstruction",
        "FrameFailure",
        "FrameFailure",
        "ImageReconstruction",
    ]
    assert isinstance(got[1], FrameFailure) and isinstance(got[1].error, MarkerError)
    assert isinstance(got[2], FrameFailure) and isinstance(got[2].error, TooFewMarkersError)
    alone = next(iter(reconstruct_stream([images[2]], setup, overlap=False)))
    last = got[3]
    assert isinstance(last, ImageReconstruction) and last.result.converged
    np.testing.assert_array_equal(last.markers.centroids, alone.markers.centroids)
    assert not _workers()


def test_a_frame_source_error_ends_a_keep_going_stream(frames) -> None:
    setup, images = frames
    stream = reconstruct_stream(_Source(images, at=1, fail=TimeoutError("no frame")), setup, keep_going=True)
    assert isinstance(next(stream), ImageReconstruction)
    with pytest.raises(TimeoutError, match="no frame"):
        next(stream)
    assert not _workers()


def test_each_frames_posterior_starts_from_the_prior_of_the_frame_before(frames) -> None:
    """With the posterior on, frame k+1's evidence maximisation starts from frame k's chosen prior; the warm-started
    frame's uncertainty agrees with a cold start's within 20 % (the same frame, the same evidence maximum)."""
    from scopetwin.recon.config import ReconstructionConfig
    from scopetwin.recon.posterior import Prior, prior_from_dict
    from scopetwin.recon.reconstruct import Reconstructor

    setup, images = frames
    rec = Reconstructor.from_setup(setup, ReconstructionConfig.realtime(posterior="report"))
    seen: list[Prior | None] = []
    results = []
    for done in reconstruct_stream(images[:2], setup, rec, overlap=False):
        seen.append(rec.evidence_start)
        results.append(done.result)
    first, second = (r.uncertainty for r in results)
    assert first is not None and second is not None
    assert seen[0] == prior_from_dict(first.hyper) and seen[1] == prior_from_dict(second.hyper)
    rec_cold = Reconstructor.from_setup(setup, ReconstructionConfig.realtime(posterior="report"))
    alone = next(iter(reconstruct_stream(images[1:2], setup, rec_cold, overlap=False))).result.uncertainty
    assert alone is not None
    assert second.absolute_um == pytest.approx(alone.absolute_um, rel=0.2)
    assert second.shape_um == pytest.approx(alone.shape_um, rel=0.2)
