"""Acquisition routines that take a rig and never ask which world is behind it.

* :func:`deflectometry_capture` — pattern light on, exposure chosen for ~70 % of
  the ADC range (thesis §1.11: a well-exposed, unsaturated marker image), one frame.
* :func:`two_position_capture` — the deflectometry frame with the pattern at two positions along its normal, moved
  by a stage (thesis §1.3: the second image resolves the height-normal ambiguity), the same exposure for both.
* :func:`calibration_capture` — frames of a calibration target (thesis §2.2) at a chosen exposure.
* :func:`simultaneous_capture` — the four channels exposed together on the
  global trigger, each light on for exactly its camera's exposure (thesis §4.3.2).
* :func:`tile_scan` — a stage grid, the focus set from a focus map at every tile
  (no focus search, thesis §1.1 / §6), each frame written as it arrives.

Every frame is written atomically (OpenEXR via :func:`scopetwin.scenes.io.write_image`)
the moment it is grabbed, with a ``manifest.json`` rewritten atomically after
each frame; SIGINT, SIGTERM and SIGHUP are held while a frame and its manifest
entry are written (:func:`scopetwin.instrument.interrupts.deferred_signals`), so a failure
or a signal leaves every finished frame readable on disk and listed in the
manifest, never one without the other. Lights are switched off on every exit
path (and :func:`scopetwin.instrument.open_rig` does it again). :class:`FrameWriter` also
keeps a PNG preview of the latest frame beside the frames, and records each
frame's signal above the black level (``signal_dn``), so a caller can tell an
acquisition that saw nothing (:func:`dark_frames`).
"""

from __future__ import annotations

import contextlib
import json
import signal
from collections.abc import Callable, Iterator, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from scopetwin.instrument.devices import CameraDevice, LightSource, TriggerMode, TriggerType
from scopetwin.instrument.errors import InstrumentError, OutOfRangeError, RigError
from scopetwin.instrument.interrupts import deferred_signals
from scopetwin.instrument.rig import Rig
from scopetwin.scenes.io import atomic_path, write_image, write_json_atomic

FocusMap = Callable[[float, float], float]


def sharpness(frame: NDArray, black_level_dn: float = 0.0) -> float:
    """Normalised band-pass energy: ``var(G_1 * I - G_4 * I) / mean(I)^2`` (dimensionless).

    A difference of Gaussians (sigma 1 and 4 px) keeps the structure scales that
    defocus removes first while suppressing pixel noise; dividing by the squared
    mean makes it independent of exposure. Higher is sharper.
    """
    img = np.asarray(frame, dtype=np.float64) - float(black_level_dn)
    band = ndimage.gaussian_filter(img, 1.0) - ndimage.gaussian_filter(img, 4.0)
    mean = img.mean()
    return float(band.var() / mean**2) if mean > 0 else 0.0


PREVIEW_NAME = "preview.png"
SIGNAL_PERCENTILE = 99.5
DARK_FRACTION = 0.01


def signal_dn(frame: NDArray, black_level_dn: float = 0.0) -> float:
    """The frame's bright end above the black level: the 99.5th percentile grey value minus the black level (DN)."""
    return float(np.percentile(np.asarray(frame, dtype=np.float64), SIGNAL_PERCENTILE)) - float(black_level_dn)


def dark_frames(signals_dn: Sequence[float], black_level_dn: float, saturation_dn: float) -> bool:
    """Whether every frame lacks signal: each :func:`signal_dn` below 1 % of the range above the black level.

    Sensor noise alone (read noise and dark current of a few DN) stays well below that threshold
    (41 DN for a 12-bit camera), so an acquisition with the light off or unseen is told apart from a
    dim one.
    """
    limit = DARK_FRACTION * (float(saturation_dn) - float(black_level_dn))
    return bool(signals_dn) and all(s < limit for s in signals_dn)


def write_preview(path: str | Path, frame: NDArray, low: float | None = None, high: float | None = None) -> Path:
    """An 8-bit PNG of ``frame`` scaled linearly from ``low`` (black) to ``high`` (white), written atomically.

    Without bounds the frame's 0.5th and 99.5th percentiles are used. With the camera's black level and
    saturation as bounds a dark frame looks dark, as it should.
    """
    import cv2

    img = np.asarray(frame, dtype=np.float64)
    lo = float(np.percentile(img, 0.5)) if low is None else float(low)
    hi = float(np.percentile(img, 99.5)) if high is None else float(high)
    scaled = np.clip((img - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    ok, data = cv2.imencode(".png", np.rint(scaled * 255.0).astype(np.uint8))
    if not ok:  # pragma: no cover - OpenCV cannot fail on a valid 8-bit image
        raise InstrumentError(f"could not encode the preview {path}")
    dest = Path(path)
    try:
        with atomic_path(dest) as tmp:
            tmp.write_bytes(data.tobytes())
    except OSError as exc:
        raise InstrumentError(f"cannot write the preview {dest}: {exc.strerror or exc}") from None
    return dest


class FrameWriter:
    """Writes frames atomically, one file each, with a manifest rewritten after every frame.

    Parameters
    ----------
    directory : path
        Output folder (created; a symbolic link there is refused, not written through).
    meta : dict
        Run-level metadata stored in the manifest.
    display_range : (float, float), optional
        Grey values shown black and white in the PNG preview (default: each frame's own range).
    preview : bool
        Keep ``preview.png`` (the latest frame) beside the frames, rewritten by :meth:`finish`.
    """

    def __init__(
        self,
        directory: str | Path,
        meta: dict[str, Any] | None = None,
        *,
        display_range: tuple[float, float] | None = None,
        preview: bool = True,
    ) -> None:
        self.directory = Path(directory)
        if self.directory.is_symlink():
            raise RigError(f"{self.directory} is a symbolic link; scopetwin writes through no link it did not make")
        self.directory.mkdir(parents=True, exist_ok=True)
        self.manifest: dict[str, Any] = {"meta": dict(meta or {}), "frames": [], "complete": False, "error": None}
        self.display_range = display_range
        self.preview = preview
        self._last: NDArray | None = None

    def write(self, name: str, frame: NDArray, **info: Any) -> Path:
        """Write ``frame`` as ``name.exr`` and record ``info`` in the manifest.

        SIGINT, SIGTERM and SIGHUP wait until both are done: a frame on disk is in the manifest.
        """
        path = self.directory / f"{name}.exr"
        data = np.asarray(frame, dtype=np.float32)
        entry = {"name": name, "path": path.name, **_jsonable(info)}
        with deferred_signals():
            write_image(path, data, provenance={"frame": name, **_jsonable(info)})
            self.manifest["frames"].append(entry)
            self._flush()
        self._last = data
        return path

    def finish(self, error: BaseException | None = None) -> None:
        """Mark the run complete, or record the error that ended it; write the preview of the latest frame."""
        self.manifest["complete"] = error is None
        self.manifest["error"] = None if error is None else _error_text(error)
        with deferred_signals():
            self._flush()
            if self.preview and self._last is not None:
                low, high = self.display_range if self.display_range is not None else (None, None)
                write_preview(self.directory / PREVIEW_NAME, self._last, low, high)

    def _flush(self) -> None:
        write_json_atomic(self.directory / "manifest.json", self.manifest)


def _error_text(error: BaseException) -> str:
    """``Terminated: SIGTERM`` (the CLI's exception carries the signal number), ``KeyboardInterrupt: SIGINT``, or
    ``TypeName: message``."""
    signum = getattr(error, "signum", None)
    if signum is None and type(error) is KeyboardInterrupt:
        signum = signal.SIGINT
    if signum is not None:
        return f"{type(error).__name__}: {signal.Signals(int(signum)).name}"
    return f"{type(error).__name__}: {error}"


def _jsonable(info: dict[str, Any]) -> dict[str, Any]:
    return json.loads(json.dumps(info, default=float))


def _display_range(cam: CameraDevice) -> tuple[float, float]:
    return float(cam.black_level_dn), float(cam.saturation_dn)


@contextlib.contextmanager
def _run(writer: FrameWriter, rig: Rig) -> Iterator[None]:
    """Record success or failure in the manifest and switch all lights off on every exit.

    The lights go off first (a signal during the clean-up waits until it is done), then the manifest
    records how the run ended.
    """
    try:
        yield
    except BaseException as exc:
        with deferred_signals():
            rig.lights_off()
        writer.finish(exc)
        raise
    else:
        with deferred_signals():
            rig.lights_off()
        writer.finish()


def choose_exposure(
    camera: CameraDevice, target_fraction: float = 0.7, percentile: float = 99.5, max_iterations: int = 6
) -> float:
    """Set the exposure so the ``percentile`` grey value sits at ``target_fraction`` of the ADC range.

    Signal is linear in exposure above the black level, so each test frame gives
    the next exposure directly; a saturated frame halves it.
    """
    black = camera.black_level_dn
    full = camera.saturation_dn - black
    exposure = camera.exposure_s
    for _ in range(max_iterations):
        frame = camera.grab()
        level = float(np.percentile(frame, percentile)) - black
        if level >= 0.98 * full:
            exposure *= 0.4
        elif level <= 0:
            exposure *= 10.0
        else:
            ratio = target_fraction * full / level
            exposure *= ratio
            if abs(ratio - 1.0) < 0.05:
                break
        exposure = min(max(exposure, camera.limits.exposure_s.low), camera.limits.exposure_s.high)
        camera.set_exposure_s(exposure)
    return camera.exposure_s


def deflectometry_capture(
    rig: Rig, out_dir: str | Path, *, camera: str | None = None, light: str | None = None, target_fraction: float = 0.7
) -> Path:
    """Pattern light on, exposure for ~``target_fraction`` of the range, one frame on disk; light off.

    Returns the frame's path.
    """
    cam, lamp = rig.camera(camera), rig.light(light)
    writer = FrameWriter(
        out_dir, {"routine": "deflectometry", "rig": rig.name, "camera": cam.name}, display_range=_display_range(cam)
    )
    with _run(writer, rig):
        lamp.switch_on(lamp.current_range.high if lamp.current_ma == 0 else None)
        exposure = choose_exposure(cam, target_fraction)
        frame = cam.grab()
        lamp.switch_off()
        return writer.write(
            "deflectometry",
            frame,
            exposure_s=exposure,
            camera=cam.name,
            light=lamp.name,
            signal_dn=signal_dn(frame, cam.black_level_dn),
        )


def two_position_capture(
    rig: Rig,
    out_dir: str | Path,
    stage: str,
    shift_mm: float,
    *,
    camera: str | None = None,
    light: str | None = None,
    exposure_s: float | None = None,
    target_fraction: float = 0.7,
) -> tuple[list[Path], list[float]]:
    """The deflectometry frame at the pattern stage's position and ``shift_mm`` further (thesis §1.3), one exposure.

    Pattern light on, exposure chosen at the first position (or ``exposure_s``), frame ``deflectometry_1``; the
    stage moved by ``shift_mm`` (checked against its travel before anything is switched on), frame
    ``deflectometry_2``; the stage back at its first position, the light off. Each manifest entry records the stage's
    read-back position; their difference is the shift :mod:`scopetwin.recon.two_positions` takes.

    Returns
    -------
    paths : list of Path
        The two frames.
    positions_mm : list of float
        The stage's read-back position at each.
    """
    cam, lamp, axis = rig.camera(camera), rig.light(light), rig.stage(stage)
    start = axis.position_mm
    axis.travel.check(start + shift_mm, f"stage {axis.name!r} second position ({start} mm + {shift_mm} mm)")
    writer = FrameWriter(
        out_dir,
        {"routine": "two-position deflectometry", "rig": rig.name, "camera": cam.name, "pattern_stage": axis.name},
        display_range=_display_range(cam),
    )
    paths, positions = [], []
    with _run(writer, rig):
        lamp.switch_on(lamp.current_range.high if lamp.current_ma == 0 else None)
        if exposure_s is None:
            choose_exposure(cam, target_fraction)
        else:
            cam.set_exposure_s(exposure_s)
        for k, target in enumerate((start, start + shift_mm), start=1):
            axis.move_absolute(target)
            positions.append(axis.position_mm)
            frame = cam.grab()
            if not lamp.is_on:
                raise InstrumentError(f"light {lamp.name!r} went off during the acquisition (position {k})")
            paths.append(
                writer.write(
                    f"deflectometry_{k}",
                    frame,
                    exposure_s=cam.exposure_s,
                    pattern_stage_mm=positions[-1],
                    signal_dn=signal_dn(frame, cam.black_level_dn),
                )
            )
        axis.move_absolute(start)
    return paths, positions


def calibration_capture(
    rig: Rig,
    out_dir: str | Path,
    *,
    n_frames: int = 1,
    camera: str | None = None,
    light: str | None = None,
    exposure_s: float | None = None,
    target_fraction: float = 0.7,
) -> list[Path]:
    """Frames of a calibration target (light on, fixed or automatic exposure), written as they come.

    Each manifest entry has the frame's ``exposure_s`` and ``signal_dn`` (:func:`signal_dn`).

    Raises
    ------
    OutOfRangeError
        ``n_frames`` below 1 (nothing is opened or switched on).
    """
    if int(n_frames) != n_frames or n_frames < 1:
        raise OutOfRangeError(f"number of frames must be a positive integer, got {n_frames}")
    cam, lamp = rig.camera(camera), rig.light(light)
    writer = FrameWriter(
        out_dir, {"routine": "calibration", "rig": rig.name, "camera": cam.name}, display_range=_display_range(cam)
    )
    paths = []
    with _run(writer, rig):
        lamp.switch_on(lamp.current_range.high if lamp.current_ma == 0 else None)
        if exposure_s is None:
            choose_exposure(cam, target_fraction)
        else:
            cam.set_exposure_s(exposure_s)
        for i in range(int(n_frames)):
            frame = cam.grab()
            if not lamp.is_on:  # asked every frame: a light that stops answering (or goes off) ends the run
                raise InstrumentError(f"light {lamp.name!r} went off during the acquisition (frame {i})")
            paths.append(
                writer.write(
                    f"calibration_{i:03d}",
                    frame,
                    exposure_s=cam.exposure_s,
                    signal_dn=signal_dn(frame, cam.black_level_dn),
                )
            )
    return paths


def simultaneous_capture(
    rig: Rig,
    out_dir: str | Path,
    channels: dict[str, str],
    exposure_s: float,
    *,
    trigger: str | None = None,
    delay_s: float = 0.0,
) -> dict[str, Path]:
    """Expose several cameras at once on the global trigger, each with its light on for the exposure.

    Parameters
    ----------
    channels : dict
        Camera name -> light name (e.g. the four channels of the microscope unit).
    exposure_s : float
        Exposure of every camera; each light is on for exactly this long.
    delay_s : float
        Global trigger delay of cameras and lights (fine adjustment of synchrony, thesis §4.3.2).
    """
    board = rig.trigger(trigger)
    cams = {c: rig.camera(c) for c in channels}
    lamps = {c: rig.light(lamp) for c, lamp in channels.items()}
    writer = FrameWriter(out_dir, {"routine": "simultaneous", "rig": rig.name, "exposure_s": exposure_s})
    out: dict[str, Path] = {}
    with _run(writer, rig):
        try:
            for i, (name, cam) in enumerate(cams.items()):
                line = int(getattr(cam, "trigger_line", i))
                cam.set_exposure_s(exposure_s)
                cam.set_trigger(TriggerType.RISING_EDGE, TriggerMode.ONCE, 0.0)
                board.configure_camera_line(line, True, delay_s)
                lamps[name].configure(
                    use_duration=True,
                    duration_s=exposure_s,
                    listen_global_trigger=True,
                    global_trigger_delay_s=delay_s,
                    current_ma=lamps[name].current_ma or lamps[name].current_range.high,
                )
                cam.arm()
            board.fire()
            for name, cam in cams.items():
                out[name] = writer.write(
                    f"channel_{name}", cam.grab(), camera=name, light=lamps[name].name, exposure_s=exposure_s
                )
        finally:
            for i, (name, cam) in enumerate(cams.items()):
                with contextlib.suppress(InstrumentError):
                    cam.disarm()
                    cam.set_trigger(TriggerType.SOFTWARE)
                    board.configure_camera_line(int(getattr(cam, "trigger_line", i)), False, 0.0)
                    lamps[name].configure(listen_global_trigger=False, use_duration=False)
    return out


@dataclass
class TileResult:
    """One tile of a scan: where it was taken, at which focus, and its file."""

    index: tuple[int, int]
    x_mm: float
    y_mm: float
    focus_um: float
    path: str
    sharpness: float = field(default=0.0)


def grid(
    x_range_mm: tuple[float, float], y_range_mm: tuple[float, float], nx: int, ny: int
) -> list[tuple[int, int, float, float]]:
    """Serpentine stage grid: ``(ix, iy, x, y)`` with x reversing on every other row."""
    if nx < 1 or ny < 1:
        raise OutOfRangeError(f"tile grid needs nx, ny >= 1, got {nx} x {ny}")
    xs = np.linspace(x_range_mm[0], x_range_mm[1], nx) if nx > 1 else np.array([x_range_mm[0]])
    ys = np.linspace(y_range_mm[0], y_range_mm[1], ny) if ny > 1 else np.array([y_range_mm[0]])
    out: list[tuple[int, int, float, float]] = []
    for iy, y in enumerate(ys):
        order = range(nx) if iy % 2 == 0 else range(nx - 1, -1, -1)
        out.extend((ix, iy, float(xs[ix]), float(y)) for ix in order)
    return out


def tile_scan(
    rig: Rig,
    out_dir: str | Path,
    positions: Sequence[tuple[int, int, float, float]],
    *,
    focus_map: FocusMap | None = None,
    fixed_focus_um: float | None = None,
    camera: str | None = None,
    light: str | None = None,
    stage_x: str = "x",
    stage_y: str = "y",
    focus: str | None = None,
    exposure_s: float | None = None,
    on_tile: Callable[[TileResult], None] | None = None,
) -> list[TileResult]:
    """Scan a stage grid, setting the focus from ``focus_map(x_mm, y_mm) -> focus_um`` at every tile.

    With ``fixed_focus_um`` instead, the focus stays where it is set once (the
    comparison case). The light is on only while a frame is exposed. Each frame
    is on disk before the stage moves on.

    Raises
    ------
    OutOfRangeError
        Neither or both of ``focus_map`` and ``fixed_focus_um`` given; a focus-map value outside the drive's range.
    """
    if (focus_map is None) == (fixed_focus_um is None):
        raise OutOfRangeError("tile_scan needs exactly one of focus_map and fixed_focus_um")
    cam, lamp = rig.camera(camera), rig.light(light)
    sx, sy, drive = rig.stage(stage_x), rig.stage(stage_y), rig.focus(focus)
    writer = FrameWriter(
        out_dir,
        {
            "routine": "tile_scan",
            "rig": rig.name,
            "focus": "map" if focus_map is not None else f"fixed {fixed_focus_um} um",
        },
        display_range=_display_range(cam),
    )
    results: list[TileResult] = []
    with _run(writer, rig):
        if exposure_s is not None:
            cam.set_exposure_s(exposure_s)
        if fixed_focus_um is not None:
            drive.move_absolute_um(fixed_focus_um)
        if lamp.current_ma == 0:
            lamp.configure(current_ma=lamp.current_range.high)
        for ix, iy, x, y in positions:
            sx.move_absolute(x)
            sy.move_absolute(y)
            if focus_map is not None:
                drive.move_absolute_um(float(focus_map(x, y)))
            lamp.switch_on()
            try:
                frame = cam.grab()
            finally:
                lamp.switch_off()
            z = drive.position_um
            s = sharpness(frame, cam.black_level_dn)
            path = writer.write(
                f"tile_{iy:03d}_{ix:03d}", frame, x_mm=x, y_mm=y, focus_um=z, sharpness=s, exposure_s=cam.exposure_s
            )
            result = TileResult((ix, iy), x, y, z, str(path), s)
            results.append(result)
            if on_tile is not None:
                on_tile(result)
    return results


def results_json(results: Sequence[TileResult]) -> list[dict[str, Any]]:
    """Tile results as JSON-ready dicts."""
    return [_jsonable(asdict(r)) for r in results]


__all__ = [
    "FrameWriter",
    "LightSource",
    "TileResult",
    "calibration_capture",
    "choose_exposure",
    "dark_frames",
    "deflectometry_capture",
    "grid",
    "results_json",
    "sharpness",
    "signal_dn",
    "simultaneous_capture",
    "tile_scan",
    "two_position_capture",
    "write_preview",
]
