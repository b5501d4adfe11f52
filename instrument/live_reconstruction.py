"""Live reconstruction on a rig: frames grabbed with the pattern light on, each reconstructed as it comes (thesis §1.4,
§1.5, §1.11).

:func:`live_reconstruction` switches the pattern light on, sets the exposure (~70 % of the ADC range, §1.11, or the
one given), grabs frames from the rig's camera and reconstructs them through the realtime stream
(:func:`scopetwin.recon.stream.reconstruct_stream`: frame k+1's markers searched in a worker process while frame k is
solved), with ``ReconstructionConfig.realtime(posterior="correct")`` by default, so every frame has its absolute
height corrected by the posterior frame criterion and its uncertainty, the posterior warm-started from the frame
before. Each frame's height map is written atomically (:func:`scopetwin.scenes.io.write_heightmap`: ``Z`` in mm,
``Z_std``, ``Z_measured``, as ``scopetwin reconstruct`` writes it) and listed in ``manifest.json``, rewritten
atomically after each frame; SIGINT, SIGTERM and SIGHUP wait while a map and its manifest entry are written
(:func:`scopetwin.instrument.interrupts.deferred_signals`). A frame that fails to reconstruct is listed with its
one-line error and the loop goes on. On every exit (the end, an error, a signal) the stream is closed (its worker
process ended), then the lights go off, then the manifest records how the run ended.

The setup of the frames: the one given, or the setup a simulated deflectometry camera renders
(:class:`scopetwin.instrument.simulated.renderers.DeflectometryRenderer`, e.g. ``rigs/sim-deflectometry.toml``).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.instrument.acquisition import FrameWriter, _error_text, _run, choose_exposure
from scopetwin.instrument.devices import CameraDevice
from scopetwin.instrument.errors import InstrumentError, OutOfRangeError, RigError
from scopetwin.instrument.interrupts import deferred_signals
from scopetwin.instrument.rig import Rig
from scopetwin.recon.config import ReconstructionConfig
from scopetwin.recon.policy import DEFAULT_POLICY, ReconstructionPolicy
from scopetwin.recon.reconstruct import ReconstructionResult, Reconstructor
from scopetwin.recon.strategy import ImageReconstruction
from scopetwin.recon.stream import FrameFailure, reconstruct_stream
from scopetwin.scenes.io import write_heightmap
from scopetwin.scenes.setup import Setup, load_setup

#: Name of the manifest written beside the height maps.
MANIFEST_NAME = "manifest.json"


def rig_setup(rig: Rig, camera: str | None = None, setup: str | Path | Setup | None = None) -> Setup:
    """The deflectometry setup of the rig's camera frames: ``setup`` (preset name, TOML path or Setup), else the one
    a simulated deflectometry camera renders.

    Raises
    ------
    RigError
        No setup given and the camera renders none (not a deflectometry rig), a setup that is not a deflectometry
        setup, or one whose camera has other pixels than the rig's camera delivers.
    """
    cam = rig.camera(camera)
    if setup is None:
        rendered = getattr(getattr(cam, "renderer", None), "setup", None)
        if not isinstance(rendered, Setup):
            raise RigError(
                f"rig {rig.name!r}: camera {cam.name!r} is not a deflectometry camera (it renders no deflectometry "
                "setup); give the setup of its frames (--setup PRESET|TOML)"
            )
        found = rendered
    else:
        found = setup if isinstance(setup, Setup) else load_setup(setup)
    if found.scene != "deflectometry" or found.substrate is None:
        raise RigError(f"rig {rig.name!r}: setup {found.name!r} is a {found.scene!r} scene, not a deflectometry setup")
    model = found.camera_model
    shape = _frame_shape(cam)
    if shape != (model.ny, model.nx):
        raise RigError(
            f"rig {rig.name!r}: camera {cam.name!r} delivers {shape[1]} x {shape[0]} px frames but setup "
            f"{found.name!r} has {model.nx} x {model.ny} px"
        )
    return found


def _frame_shape(cam: CameraDevice) -> tuple[int, int]:
    """(rows, cols) of the camera's frames: its region of interest, binned."""
    roi, binning = cam.roi, max(int(cam.binning), 1)
    return int(roi.rows) // binning, int(roi.cols) // binning


@dataclass
class _Arrival:
    """When one frame came from the camera: wall-clock time (UTC) and the monotonic clock, s."""

    wall: datetime
    monotonic: float


def _grabbed(
    cam: CameraDevice,
    lamp_is_on: Callable[[], bool],
    arrivals: list[_Arrival],
    n_frames: int | None,
    seconds: float | None,
) -> Iterator[NDArray[Any]]:
    """Frames from ``cam`` until ``n_frames`` were grabbed or ``seconds`` have passed (None: no limit), each arrival
    recorded; a light that went off (or stops answering) ends the run."""
    start = time.monotonic()
    k = 0
    while (n_frames is None or k < n_frames) and (seconds is None or time.monotonic() - start < seconds):
        frame = cam.grab()
        arrivals.append(_Arrival(datetime.now(UTC), time.monotonic()))
        if not lamp_is_on():
            raise InstrumentError(f"the pattern light went off during the live reconstruction (frame {k})")
        k += 1
        yield frame


def _absolute_um(rec: Reconstructor, result: ReconstructionResult) -> float:
    """The absolute height: the surface's mean over the ROI (the thesis's absolute height, §1.4), µm."""
    surface = result.surface
    return 1e3 * (rec.roi_mean(surface.coef) + float(surface.offset))


def _map_name(index: int) -> str:
    return f"heights_{index:06d}.exr"


def live_reconstruction(
    rig: Rig,
    out_dir: str | Path,
    setup: Setup,
    *,
    n_frames: int | None = None,
    seconds: float | None = None,
    every: int = 1,
    camera: str | None = None,
    light: str | None = None,
    exposure_s: float | None = None,
    config: ReconstructionConfig | None = None,
    policy: ReconstructionPolicy = DEFAULT_POLICY,
    overlap: bool | None = None,
    on_frame: Callable[[dict[str, Any]], None] | None = None,
) -> dict[str, Any]:
    """Grab frames with the pattern light on and reconstruct each as it comes (thesis §1.4-§1.5); maps on disk.

    Parameters
    ----------
    rig : Rig
        An open rig with a camera that sees the pattern through the substrate and the pattern's light.
    out_dir : path
        Output folder: ``heights_NNNNNN.exr`` per written frame and ``manifest.json``.
    setup : Setup
        The (calibrated) deflectometry setup of the frames (:func:`rig_setup`).
    n_frames : int, optional
        Most frames (>= 1); None: no limit.
    seconds : float, optional
        Stop grabbing after this many seconds (> 0); None: no limit. Neither: until interrupted.
    every : int
        Write every ``every``-th frame's map (frames 0, every, 2 every, ...); every frame is listed.
    camera, light : str, optional
        Device names (default: the rig's first camera and light).
    exposure_s : float, optional
        Exposure, s (default: chosen for ~70 % of the ADC range, thesis §1.11).
    config : ReconstructionConfig, optional
        The nested iteration's configuration (default ``ReconstructionConfig.realtime(posterior="correct")``).
    policy : ReconstructionPolicy
        The fallbacks of :func:`scopetwin.recon.strategy.solve`.
    overlap : bool, optional
        Search the next frame's markers in a worker process (default: where two CPUs or more may run this process).
    on_frame : callable, optional
        Called with each frame's manifest entry once it is on disk.

    Returns
    -------
    dict
        The summary: frames listed, reconstructed, failed, maps written, frames per second, the last absolute height
        and its uncertainty, the exposure, the manifest's path.

    Raises
    ------
    OutOfRangeError
        ``n_frames`` below 1, ``seconds`` not positive, ``every`` below 1 (before the light goes on).
    """
    _check_limits(n_frames, seconds, every)
    cam, lamp = rig.camera(camera), rig.light(light)
    if exposure_s is not None:
        cam.limits.exposure_s.check(exposure_s, f"exposure of camera {cam.name!r}")
    cfg = ReconstructionConfig.realtime(posterior="correct") if config is None else config
    rec = Reconstructor.from_setup(setup, cfg)
    meta: dict[str, Any] = {"routine": "live reconstruction", "rig": rig.name, "camera": cam.name, "light": lamp.name}
    meta |= {"setup": setup.name, "every": int(every), "posterior": cfg.posterior}
    run = _LiveRun(FrameWriter(out_dir, meta, preview=False), Path(out_dir), int(every), rec)
    with _run(run.writer, rig):
        lamp.switch_on(lamp.current_range.high if lamp.current_ma == 0 else None)
        if exposure_s is None:
            choose_exposure(cam)
        else:
            cam.set_exposure_s(exposure_s)
        run.writer.manifest["meta"]["exposure_s"] = cam.exposure_s
        frames = _grabbed(cam, lambda: lamp.is_on, run.arrivals, n_frames, seconds)
        stream = reconstruct_stream(frames, setup, rec, policy, overlap=overlap, keep_going=True)
        with contextlib.closing(stream):  # the worker process ends here, however the loop ends
            for index, done in enumerate(stream):
                entry = run.record(index, done)
                if on_frame is not None:
                    on_frame(entry)
    return run.summary(setup)


def _check_limits(n_frames: int | None, seconds: float | None, every: int) -> None:
    """``n_frames`` >= 1, ``seconds`` > 0, ``every`` >= 1, or an :class:`OutOfRangeError` naming the one that is not."""
    if n_frames is not None and (int(n_frames) != n_frames or n_frames < 1):
        raise OutOfRangeError(f"number of frames must be a positive integer, got {n_frames}")
    if seconds is not None and not (np.isfinite(seconds) and seconds > 0):
        raise OutOfRangeError(f"seconds must be a positive number, got {seconds}")
    if int(every) != every or every < 1:
        raise OutOfRangeError(f"every must be a positive integer, got {every}")


@dataclass
class _LiveRun:
    """One live run's bookkeeping: the manifest's writer, the frames' arrivals, what came of them."""

    writer: FrameWriter
    directory: Path
    every: int
    rec: Reconstructor
    arrivals: list[_Arrival] = field(default_factory=list)
    counts: dict[str, int] = field(default_factory=lambda: {"reconstructed": 0, "failed": 0, "written": 0})
    last: dict[str, Any] = field(default_factory=dict)

    def record(self, index: int, done: ImageReconstruction | FrameFailure) -> dict[str, Any]:
        """Frame ``index``'s map (every ``every``-th) and manifest entry on disk together; the entry."""
        arrived = self.arrivals[index]
        entry: dict[str, Any] = {"index": index, "time": arrived.wall.isoformat()}
        entry["seconds"] = time.monotonic() - arrived.monotonic
        if isinstance(done, FrameFailure):
            self.counts["failed"] += 1
            entry |= {"path": None, "error": _error_text(done.error)}
        else:
            entry |= _solved(self.rec, done.result, len(done.markers.ij))
            self.counts["reconstructed"] += 1
        elapsed = time.monotonic() - self.arrivals[0].monotonic
        entry["fps"] = (index + 1) / elapsed if elapsed > 0 else None
        with deferred_signals():  # a map on disk is in the manifest
            if not isinstance(done, FrameFailure) and index % self.every == 0:
                path = self.directory / _map_name(index)
                _write_map(path, done.result, entry)
                entry["path"] = path.name
                self.counts["written"] += 1
            self.writer.manifest["frames"].append(entry)
            self.writer._flush()
        self.last = entry
        return entry

    def summary(self, setup: Setup) -> dict[str, Any]:
        """The run's summary (the command's ``--json``)."""
        span = self.arrivals[-1].monotonic - self.arrivals[0].monotonic if self.arrivals else 0.0
        return {
            "out": str(self.directory),
            "manifest": str(self.directory / MANIFEST_NAME),
            "frames": len(self.writer.manifest["frames"]),
            "reconstructed": self.counts["reconstructed"],
            "failed": self.counts["failed"],
            "maps_written": self.counts["written"],
            "fps": self.last.get("fps"),
            "exposure_s": self.writer.manifest["meta"]["exposure_s"],
            "setup": setup.name,
            "absolute_height_um": self.last.get("absolute_height_um"),
            "absolute_um": self.last.get("absolute_um"),
            "shape_um": self.last.get("shape_um"),
            "seconds_between_first_and_last_frame": span,
        }


def _solved(rec: Reconstructor, result: ReconstructionResult, markers: int) -> dict[str, Any]:
    """A reconstructed frame's manifest entry: absolute height (µm) and its standard uncertainty, the shape's."""
    u = result.uncertainty
    return {
        "path": None,
        "error": None,
        "markers": markers,
        "absolute_height_um": _absolute_um(rec, result),
        "absolute_um": None if u is None else u.absolute_um,
        "shape_um": None if u is None else u.shape_um,
        "start_height_um": result.history[-1].start_height_um,
        "delta_h_max_um": result.delta_h_max_um,
        "converged": result.converged,
    }


def _write_map(path: Path, result: ReconstructionResult, entry: dict[str, Any]) -> None:
    """The frame's height map, its std map and measured mask, as ``scopetwin reconstruct`` writes them (atomic)."""
    write_heightmap(
        path,
        result.heightmap(),
        result.std_heightmap(),
        result.measured_mask(),
        scopetwin_reconstruction=f"frame={entry['index']} time={entry['time']} "
        f"outer={result.outer_iterations} inner={result.inner_iterations}",
    )


__all__ = ["MANIFEST_NAME", "live_reconstruction", "rig_setup"]
