"""``scopetwin rig RIG.toml info|move|position|acquire|live|mda|mm-config|serve`` (docs/contract.md, 'Rig files').

:func:`register` adds the ``rig`` command to an argparse subparsers object; each
action's handler returns a JSON-ready dict (written by the main CLI when
``--json PATH`` is given) and prints a short human-readable line:

* ``info`` — the rig's devices, their drivers, ports and limits (travel, velocity, focus range,
  maximum current, exposure range, sensor, bit depths);
* ``move NAME VALUE`` — move a stage (mm) or focus drive (µm); JSON ``{"device", "position_mm"}``
  or ``{"device", "position_um"}`` after the move;
* ``position NAME`` — the same JSON without moving;
* ``acquire OUT`` — frames from a camera with a light on (fixed or automatic exposure), written
  to ``OUT`` as they come, plus ``manifest.json`` and ``preview.png`` (the last frame); one warning
  line when no frame carries signal;
* ``live OUT`` — frames from a deflectometry camera with the pattern light on, each reconstructed as it comes
  (:func:`scopetwin.instrument.live_reconstruction.live_reconstruction`, the realtime stream of
  :mod:`scopetwin.recon.stream`): a height map per frame (every ``--every``-th) and ``manifest.json`` listing
  every frame's time, absolute height and uncertainty, seconds and frames per second so far;
* ``mda SEQUENCE --camera NAME --out PATH`` — a useq MDA sequence through pymmcore-plus
  (:func:`scopetwin.instrument.micromanager.run_mda`) into OME-TIFF or OME-Zarr, with a progress bar; the plan is
  sized in closed form and checked against the rig's limits before anything moves (one line naming the event and
  the limit, exit 2, nothing written); the JSON records what the devices reported for every plane;
* ``mm-config --out X.cfg`` — the rig's Micro-Manager configuration (pymmcore-plus Python devices that a plain
  ``UniMMCore`` loads; :func:`scopetwin.instrument.micromanager.config_text`);
* ``serve`` — the rig's devices through python-microscope's device server on 127.0.0.1, to clients that sign with
  its key (``--hmac-key-file``, or a new one in a private file it prints).

The rig is opened with :func:`scopetwin.instrument.rig.open_rig`, so lights are off again on every exit.
A device that stops answering during ``move``, ``acquire`` or ``mda`` (its port gone, no answer in time, garbage)
ends the command with one line naming it and what is known of its state ("light 'halogen' may still be on"),
every other device in its safe state and, for ``acquire`` and ``mda``, the frames already taken kept and named;
exit status 3 (:data:`scopetwin.instrument.errors.EXIT_DEVICE_LOST`).
SIGINT, SIGTERM and SIGHUP during ``acquire``, ``live`` or ``mda`` end the command cleanly: lights off,
shutters closed, every frame on disk listed in the manifest (the OME file closed with the planes
acquired so far); the main CLI prints the line naming the signal and exits 128 + n. ``serve`` ends
on SIGINT or SIGTERM with one line and exit 0, as ``scopetwin emulate`` does.

A device on an ``emu://`` port talks to an emulator that lives in this process only: every command
starts fresh emulators, so ``move`` then ``position`` in two commands reads the emulator's start
position. ``scopetwin emulate KIND`` runs one in its own process that keeps its state; put the port
it prints in the rig file.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from scopetwin.cli.options import conventions, finite_float, int_range, positive_float, positive_int
from scopetwin.instrument.devices import FocusDrive, Stage
from scopetwin.instrument.errors import DeviceLost, RigError
from scopetwin.instrument.rig import Rig, open_rig, read_rig_toml
from scopetwin.shipped import rig_names

log = logging.getLogger(__name__)

EMU_NOTE = (
    "note: devices on emu:// ports talk to emulators inside this one command; each command starts them "
    "fresh (a move is not seen by the next command). For state that lasts, run 'scopetwin emulate KIND' "
    "and put the port it prints in the rig file."
)
OME_SUFFIXES = (".ome.tif", ".ome.tiff", ".ome.zarr")
LOCALHOSTS = ("127.0.0.1", "localhost")
#: Most frames one ``acquire`` takes (a frame file each; far beyond a calibration series).
MAX_FRAMES = 100_000


@contextlib.contextmanager
def _kept(describe: Callable[[], str]) -> Iterator[None]:
    """A device that stopped answering (exit 3): its one line also says what the command kept on disk."""
    try:
        yield
    except DeviceLost as exc:
        raise exc.with_note(describe()) from exc.__cause__


@contextlib.contextmanager
def _thread_errors_logged() -> Iterator[None]:
    """An error that ends a library's worker thread (pymmcore-plus's sequence acquisition when a device stops
    answering) is logged at debug level, not printed as a traceback: the device's own error ends the command."""
    previous = threading.excepthook

    def hook(info: threading.ExceptHookArgs) -> None:
        name = info.thread.name if info.thread is not None else "?"
        log.debug("thread %s ended: %s: %s", name, info.exc_type.__name__, info.exc_value)

    threading.excepthook = hook
    try:
        yield
    finally:
        threading.excepthook = previous


def _frames_kept(out: str) -> str:
    """``12 frame(s) already taken kept in OUT, listed in OUT/manifest.json`` (or that none was taken)."""
    manifest = Path(out) / "manifest.json"
    try:
        n = len(json.loads(manifest.read_text())["frames"])
    except (OSError, ValueError, KeyError, TypeError):
        n = 0
    return f"{n} frame(s) already taken kept in {out}, listed in {manifest}" if n else "no frame was taken"


def _planes_kept(out: str, acquired: int | None = None, planned: int | None = None) -> str:
    """Where the planes acquired before a device stopped answering are, and how many of the plan's (or that none
    was written: the writer removes a file or store without a plane)."""
    files = _ome_files(Path(out))
    if not files:
        return "no plane was written"
    if acquired is None or planned is None:
        return f"the planes acquired so far kept in {', '.join(files)}"
    text = f"{acquired} of {planned} plane(s) kept in {', '.join(files)}"
    if acquired < planned:
        missing = planned - acquired
        text += f" (each file declares only the planes it holds; the {missing} plane(s) never acquired are not in them)"
    return text


def _position(rig: Rig, name: str) -> dict[str, Any]:
    device = rig[name]
    if isinstance(device, Stage):
        return {"device": name, "position_mm": device.position_mm}
    if isinstance(device, FocusDrive):
        return {"device": name, "position_um": device.position_um}
    raise RigError(f"device {name!r} is a {device.kind}: only stages and focus drives have a position")


def _span(values: list[float], unit: str) -> str:
    return f"{values[0]:g}..{values[1]:g} {unit}"


def limits_text(device: dict[str, Any]) -> str:
    """The limits of one device's :meth:`~scopetwin.instrument.devices.Device.describe` entry, as one short phrase."""
    parts = []
    if "travel_mm" in device:
        parts.append(f"travel {_span(device['travel_mm'], 'mm')}")
    if "max_velocity_mm_s" in device:
        parts.append(f"max {device['max_velocity_mm_s']:g} mm/s")
    if "range_um" in device:
        parts.append(f"range {_span(device['range_um'], 'um')}")
    if "model" in device and device.get("kind") == "focus":
        parts.append(f"model {device['model']}")
    if "max_current_ma" in device:
        parts.append(f"max {device['max_current_ma']:g} mA")
    if "exposure_s" in device:
        parts.append(f"exposure {_span(device['exposure_s'], 's')}")
    if "sensor_shape" in device:
        rows, cols = device["sensor_shape"]
        parts.append(f"{cols}x{rows} px")
    if "pixel_size_um" in device:
        magnification = float(device.get("magnification", 1.0))
        behind = f" behind {magnification:g}x" if magnification != 1.0 else ""
        parts.append(f"{device['pixel_size_um']:g} um pixels{behind}")
    if "bit_depths" in device:
        parts.append("bits " + "/".join(str(b) for b in device["bit_depths"]))
    if "n_camera_lines" in device:
        parts.append(f"{device['n_camera_lines']} camera lines")
    return ", ".join(parts)


def cmd_info(args: argparse.Namespace) -> dict[str, Any]:
    """List the rig's devices, drivers, ports and limits (opens and initialises them: a connection check)."""
    with open_rig(args.rig) as rig:
        info = rig.describe()
        emulated = rig.emulated_ports()
    for d in info["devices"]:
        port = f"  [{d['port']}]" if "port" in d else ""
        print(f"{d['name']:<12} {d['kind']:<8} {d['driver']:<11} {limits_text(d)}{port}")
    if emulated:
        print(EMU_NOTE)
    info["emulated_ports"] = sorted(emulated)
    return info


def cmd_move(args: argparse.Namespace) -> dict[str, Any]:
    """Move a stage (mm) or the focus drive (µm) to an absolute position."""
    with open_rig(args.rig) as rig:
        device = rig[args.name]
        if isinstance(device, Stage):
            device.move_absolute(args.value)
        elif isinstance(device, FocusDrive):
            device.move_absolute_um(args.value)
        else:
            raise RigError(f"device {args.name!r} is a {device.kind}: only stages and focus drives move")
        result = _position(rig, args.name)
    print(" ".join(f"{k}={v}" for k, v in result.items()))
    return result


def cmd_position(args: argparse.Namespace) -> dict[str, Any]:
    """Report a stage's (mm) or the focus drive's (µm) position."""
    with open_rig(args.rig) as rig:
        result = _position(rig, args.name)
    print(" ".join(f"{k}={v}" for k, v in result.items()))
    return result


def _camera_pixels(rig_path: str, camera: str | None) -> int:
    """Pixels of a frame of ``camera`` (default: the rig's first camera), from the rig TOML alone; 0 if unknown."""
    try:
        tables = read_rig_toml(rig_path).get("devices", {})
        cams = [(n, t) for n, t in tables.items() if isinstance(t, dict) and t.get("kind") == "camera"]
        table = next(t for n, t in cams if camera is None or n == camera)
        rows, cols = table.get("sensor_shape", [1024, 1360])
        return int(rows) * int(cols)
    except (OSError, ValueError, TypeError, StopIteration, AttributeError):
        return 0


def estimate_acquire(args: argparse.Namespace) -> dict[str, int]:
    """Bytes ``acquire`` writes at most: each frame a float32 EXR (uncompressed bound) plus its share of the preview."""
    return {"out": int(args.frames) * _camera_pixels(args.rig, args.camera) * 5}


def mda_size(rig_path: str, camera: str | None, sequence: Any) -> Any:
    """The plan's planes, bytes and least duration in closed form (:func:`scopetwin.instrument.mdaplan.plan_size`),
    from the rig TOML alone: frames 16 bits per pixel (12-bit cameras deliver uint16)."""
    from scopetwin.instrument.devices import Range
    from scopetwin.instrument.mdaplan import PlanLimits, load_sequence, plan_size

    try:
        tables = read_rig_toml(rig_path).get("devices", {})
        table = next(t for n, t in tables.items() if t.get("kind") == "camera" and camera in (None, n))
        rows, cols = (int(v) for v in table.get("sensor_shape", [1024, 1360]))
        pixel_um = float(table.get("pixel_size_um", 6.45)) / float(table.get("magnification", 1.0))
    except (OSError, ValueError, TypeError, StopIteration, AttributeError):
        rows, cols, pixel_um = 0, 0, 1.0
    limits = PlanLimits(None, None, None, Range(0.0, 0.0, "ms"), frame_shape=(rows, cols), pixel_size_um=pixel_um)
    return plan_size(load_sequence(sequence), limits)


def estimate_mda(args: argparse.Namespace) -> dict[str, int]:
    """Bytes ``mda`` writes, in closed form (never by enumerating the events)."""
    return {"out": mda_size(args.rig, args.camera, args.sequence).bytes}


def cmd_acquire(args: argparse.Namespace) -> dict[str, Any]:
    """Acquire frames with a light on; each frame is on disk (and in the manifest) as soon as it is grabbed."""
    from scopetwin.instrument.acquisition import PREVIEW_NAME, calibration_capture, dark_frames

    if (args.pattern_stage is None) != (args.pattern_shift is None):
        raise RigError("--pattern-stage and --pattern-shift go together (the stage and how far it moves, mm)")
    extra: dict[str, Any] = {}
    with _kept(lambda: _frames_kept(args.out)), open_rig(args.rig) as rig:
        cam = rig.camera(args.camera)
        if args.exposure_s is not None:
            cam.limits.exposure_s.check(args.exposure_s, f"--exposure-s of camera {cam.name!r}")
        if args.pattern_stage is not None:
            paths, positions = _two_positions(rig, args)
            extra = {"pattern_stage_mm": positions, "pattern_shift_mm": positions[1] - positions[0]}
        else:
            paths = calibration_capture(
                rig, args.out, n_frames=args.frames, camera=args.camera, light=args.light, exposure_s=args.exposure_s
            )
        exposure = cam.exposure_s
        black, saturation = cam.black_level_dn, cam.saturation_dn
        lamp = rig.light(args.light)
        unseen = cam.driver_name() == "sim" and lamp.driver_name() != "sim" and lamp.name not in rig.emulated_ports()
    manifest_path = Path(args.out) / "manifest.json"
    signals = [float(f["signal_dn"]) for f in json.loads(manifest_path.read_text())["frames"]]
    dark = dark_frames(signals, black, saturation)
    print(f"wrote {len(paths)} frame(s) to {args.out} (preview: {Path(args.out) / PREVIEW_NAME})")
    if dark:
        why = (
            f"a simulated camera cannot see light {lamp.name!r} on a real port (only simulated and emu:// lights)"
            if unseen
            else "is the light on, and can the camera see it?"
        )
        log.warning(
            "the frames carry no signal (brightest at %.1f DN above the black level, under 1 %% of the %g DN "
            "range): %s",
            max(signals),
            saturation - black,
            why,
        )
    return {
        "frames": [str(p) for p in paths],
        "exposure_s": exposure,
        "manifest": str(manifest_path),
        "preview": str(Path(args.out) / PREVIEW_NAME),
        "signal_dn": signals,
        "dark": dark,
        **extra,
    }


def estimate_live(args: argparse.Namespace) -> dict[str, int]:
    """Bytes ``live`` writes at most with ``--frames``: each written map three float32 channels on 128 x 288 nodes
    (uncompressed bound) plus its manifest entry; without ``--frames``, one map (the run's length is unknown)."""
    maps = 1 if args.frames is None else -(-int(args.frames) // int(args.every))
    return {"out": maps * (128 * 288 * 3 * 4 + 4096)}


def cmd_live(args: argparse.Namespace) -> dict[str, Any]:
    """Reconstruct a deflectometry camera's frames live; each map and manifest entry on disk as the frame is done."""
    from scopetwin.instrument.live_reconstruction import live_reconstruction, rig_setup

    with _kept(lambda: _frames_kept(args.out)), open_rig(args.rig) as rig:
        setup = rig_setup(rig, args.camera, args.setup)  # checked before the light goes on
        lamp = rig.light(args.light)
        if args.exposure_s is not None:
            cam = rig.camera(args.camera)
            cam.limits.exposure_s.check(args.exposure_s, f"--exposure-s of camera {cam.name!r}")
        if args.frames is None and args.seconds is None:
            log.info("reconstructing live until interrupted (Ctrl-C keeps every map written)")
        summary = live_reconstruction(
            rig,
            args.out,
            setup,
            n_frames=args.frames,
            seconds=args.seconds,
            every=args.every,
            camera=args.camera,
            light=lamp.name,
            exposure_s=args.exposure_s,
        )
    height = summary["absolute_height_um"]
    last = "" if height is None else f"; last absolute height {height:+.3f} µm"
    if height is not None and summary["absolute_um"] is not None:
        last += f" (u = {summary['absolute_um']:.3f} µm)"
    fps = summary["fps"]
    print(
        f"reconstructed {summary['reconstructed']} of {summary['frames']} frame(s)"
        + (f" at {fps:.2f} frames/s" if fps is not None else "")
        + (f", {summary['failed']} failed" if summary["failed"] else "")
        + f"; {summary['maps_written']} map(s) in {args.out}, listed in {summary['manifest']}{last}"
    )
    return summary


def _two_positions(rig: Rig, args: argparse.Namespace) -> tuple[list[Path], list[float]]:
    """``acquire --pattern-stage NAME --pattern-shift MM``: one frame at the stage's position, one ``MM`` further
    (:func:`scopetwin.instrument.acquisition.two_position_capture`, thesis §1.3)."""
    from scopetwin.instrument.acquisition import two_position_capture

    return two_position_capture(
        rig,
        args.out,
        args.pattern_stage,
        args.pattern_shift,
        camera=args.camera,
        light=args.light,
        exposure_s=args.exposure_s,
    )


def _strip_ome_suffix(name: str) -> str:
    for suffix in OME_SUFFIXES:
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return name


def _ome_outputs(out: Path) -> list[Path]:
    """Where the OME writers put ``out``: the path itself, or for several positions of an OME-TIFF a folder
    named like it without the suffix holding one ``<stem>_pNNN.ome.tif`` per position (ome-writers' layout)."""
    return [out, out.parent / _strip_ome_suffix(out.name)] if out.name.lower().endswith((".tif", ".tiff")) else [out]


def _ome_files(out: Path) -> list[str]:
    if out.is_file() or (out.is_dir() and out.name.lower().endswith(".zarr")):
        return [str(out)]
    folder = _ome_outputs(out)[-1]
    return sorted(str(p) for p in folder.glob("*.ome.tif*")) if folder.is_dir() else []


def _quiet_pymmcore_plus() -> None:
    """pymmcore-plus logs to stderr (its adapter search, 'MDA Canceled'); errors that matter raise anyway."""
    import pymmcore_plus

    pymmcore_plus.configure_logging(stderr_level="CRITICAL")


def cmd_mda(args: argparse.Namespace) -> dict[str, Any]:
    """Run a useq MDA sequence (YAML/JSON, µm and ms) on the rig through pymmcore-plus into an OME file."""
    from tqdm import tqdm

    from scopetwin.cli.outputs import human_bytes
    from scopetwin.instrument.mdaplan import load_sequence

    out = Path(args.out)
    if not out.name.lower().endswith(OME_SUFFIXES):
        raise RigError(f"--out {args.out!r} must end in one of {', '.join(OME_SUFFIXES)}")
    for path in _ome_outputs(out):
        if path.exists() or path.is_symlink():  # a dangling link too: the OME writer would write through it
            raise RigError(f"--out {args.out!r}: {str(path)!r} exists already; choose a new path")
    sequence = load_sequence(args.sequence)
    size = mda_size(args.rig, args.camera, sequence)  # closed form: a 1e8-loop plan is sized at once
    if size.planes == 0 or next(iter(sequence), None) is None:  # useq's first event only: an empty plan has none
        raise RigError(f"MDA sequence {args.sequence!r} has no events: nothing to acquire")
    log.info("plan: %d plane(s), %s, at least %.3g s", size.planes, human_bytes(size.bytes), size.seconds)
    from scopetwin.instrument.micromanager import run_mda  # pymmcore-plus is imported only now

    _quiet_pymmcore_plus()
    bars: list[Any] = []  # the progress bar starts with the first plane: a refused plan prints its one line only
    acquired = [0]  # planes written, for the line after a device fault

    def progress(*_: Any) -> None:
        acquired[0] += 1
        if not bars:
            bars.append(tqdm(total=size.planes, desc="mda", unit="plane", file=sys.stderr, disable=args.quiet))
        bars[0].update(1)

    kept = _kept(lambda: _planes_kept(args.out, acquired[0], size.planes))
    with kept, _thread_errors_logged(), open_rig(args.rig) as rig:
        rig.camera(args.camera)  # a clear error for an unknown camera before the core loads
        try:
            result = run_mda(  # checked against the rig's limits before the first event: nothing written if refused
                rig, sequence, camera=args.camera, output=str(out), on_frame=progress, single_file=args.single_file
            )
        finally:
            for bar in bars:
                bar.close()
    files = _ome_files(out)
    where = str(out) if files == [str(out)] else str(_ome_outputs(out)[-1])  # several positions: a folder of TIFFs
    print(
        f"wrote {result['planes']} plane(s) to {where} ({len(files)} file(s)); pixel size "
        f"{result['pixel_size_um']:g} um, {result['bit_depth']} bit, channels {', '.join(result['channels']) or '-'}"
    )
    return {
        "planes": result["planes"],
        "path": where,
        "files": files,
        "pixel_size_um": result["pixel_size_um"],
        "bit_depth": result["bit_depth"],
        "channels": result["channels"],
        "estimate": result["estimate"],
        "frames": result["frames"],
    }


def cmd_mm_config(args: argparse.Namespace) -> dict[str, Any]:
    """Write the rig's Micro-Manager configuration file (Python devices a plain ``UniMMCore`` loads)."""
    from scopetwin.instrument.micromanager import config_text
    from scopetwin.instrument.rig import load_rig

    out = Path(args.out)
    if out.suffix.lower() != ".cfg":
        raise RigError(f"--out {args.out!r} must end in .cfg")
    rig = load_rig(args.rig)  # nothing is sent to a device: the configuration comes from the rig file
    try:
        text = config_text(rig, camera=args.camera, focus=args.focus, light=args.light)
    finally:
        rig.close()
    from scopetwin.scenes.io import write_text_atomic

    # a temporary file beside --out moved into place: never half-written, and a link at --out is replaced by the
    # file, never written through
    write_text_atomic(out, text)
    lines = [line for line in text.splitlines() if line and not line.startswith("# ")]
    devices = [line.split(",")[1] for line in lines if line.startswith("#py pyDevice,")]
    presets = [line.split(",")[2] for line in lines if line.startswith("#py ConfigGroup,")]
    print(f"wrote {out}: devices {', '.join(devices)}; Channel presets {', '.join(presets) or '-'}")
    return {"path": str(out), "devices": devices, "channel_presets": presets, "rig": rig.name}


def cmd_serve(args: argparse.Namespace) -> dict[str, Any]:
    """Serve the rig's devices through python-microscope's device server on 127.0.0.1 until SIGINT/SIGTERM.

    Clients must sign every message with the server's key (Pyro's HMAC, checked before anything is deserialised):
    ``--hmac-key-file`` names a key file (only its owner may read it), else a new key is written to a private
    temporary file, printed, and removed when the server stops.
    """
    import signal

    from scopetwin.instrument.interrupts import stop_on_signals
    from scopetwin.instrument.pymicroscope import (
        LOCALHOST,
        microscope_devices,
        new_key_file,
        read_key_file,
        remove_key_file,
        serve_devices,
    )

    if args.host not in LOCALHOSTS:
        raise RigError(f"--host {args.host!r} refused: the device server listens on {LOCALHOST} only")
    if args.hmac_key_file is not None:
        key, key_path, made = read_key_file(args.hmac_key_file), Path(args.hmac_key_file), False
    stop = threading.Event()
    with open_rig(args.rig) as rig, stop_on_signals(stop) as received:
        devices = microscope_devices(rig)
        if args.hmac_key_file is None:
            (key, key_path), made = new_key_file(), True
        try:

            def ready(uris: dict[str, str]) -> None:
                served = ", ".join(f"{name}={uri}" for name, uri in uris.items())
                print(f"serving {len(uris)} device(s) of rig {rig.name!r} on {LOCALHOST}: {served}", flush=True)
                print(f"clients sign with the key in {key_path} (only its owner can read it)", flush=True)

            uris = serve_devices(devices, key=key, port=args.port, stop=stop, ready=ready, serializer=args.serializer)
        finally:
            if made:
                remove_key_file(key_path)
        for device in devices.values():
            device.shutdown()
    why = signal.Signals(received[0]).name if received else "stop"
    print(f"serve: stopped on {why}", flush=True)
    return {"rig": rig.name, "host": LOCALHOST, "uris": uris, "key_file": str(key_path), "serializer": args.serializer}


def _add_motion_commands(add: Callable[..., argparse.ArgumentParser]) -> None:
    """``rig RIG info``, ``rig RIG move`` and ``rig RIG position``."""
    add(
        "info",
        cmd_info,
        "list the devices, their drivers, ports and limits (travel, velocity, focus range, maximum current, "
        "exposure range)",
        "scopetwin rig rigs/sim-cmu.toml info",
        "scopetwin rig rigs/emulated-hardware.toml info --json rig.json",
    )
    p = add(
        "move",
        cmd_move,
        "move a stage (mm) or the focus drive (um) to an absolute position",
        "scopetwin rig rigs/sim-cmu.toml move x 80",
        "scopetwin rig rigs/emulated-hardware.toml move focus 120",
    )
    p.add_argument("name", help="device name in the rig")
    p.add_argument("value", type=finite_float(), help="target: mm for a stage, um for a focus drive")
    p = add(
        "position",
        cmd_position,
        "report a stage's (mm) or the focus drive's (um) position",
        "scopetwin rig rigs/sim-cmu.toml position focus",
        "scopetwin rig rigs/emulated-hardware.toml position y --json y.json",
    )
    p.add_argument("name", help="device name in the rig")


def _add_live_command(add: Callable[..., argparse.ArgumentParser]) -> None:
    """``rig RIG live OUT``."""
    p = add(
        "live",
        cmd_live,
        "reconstruct a deflectometry camera's frames as they come (pattern light on; the next frame's markers searched "
        "while this one is solved): a height map per frame with its std and measured mask, manifest.json listing "
        "every frame; SIGINT/SIGTERM/SIGHUP switch the lights off and keep every map written",
        "scopetwin rig sim-deflectometry live live-maps --frames 5",
        "scopetwin rig rigs/sim-deflectometry.toml live live-maps --seconds 30 --every 10 --json live.json",
    )
    p.add_argument("out", help="output folder (heights_NNNNNN.exr, manifest.json)")
    p.set_defaults(outputs=[("out", "dir", "keep", "positional"), ("json", "file")], estimate=estimate_live)
    p.add_argument("--frames", type=positive_int(MAX_FRAMES), help="most frames (>= 1; default: no limit)")
    p.add_argument("--seconds", type=positive_float(), help="stop grabbing after this many seconds (default: no limit)")
    p.add_argument("--every", type=positive_int(MAX_FRAMES), default=1, help="write every K-th map (all are listed)")
    p.add_argument("--camera", help="camera name (default: the first)")
    p.add_argument("--light", help="the pattern's light (default: the first)")
    p.add_argument("--exposure-s", type=positive_float(), help="exposure time (default: automatic, ~70%% of the range)")
    p.add_argument(
        "--setup",
        help="the frames' (calibrated) deflectometry setup, preset name or TOML (default: the setup a simulated "
        "deflectometry camera renders)",
    )


def _add_mda_commands(add: Callable[..., argparse.ArgumentParser]) -> None:
    """``rig RIG mda`` and ``rig RIG mm-config``."""
    p = add(
        "mda",
        cmd_mda,
        "run a useq MDA sequence (YAML or JSON; um and ms) through pymmcore-plus into OME-TIFF or OME-Zarr; every "
        "light is a preset of config group Channel; Ctrl-C keeps the planes written",
        "scopetwin rig rigs/sim-cmu.toml mda examples/mda/2-positions-2-channels-z.json --camera cam_nir "
        "--out stack.ome.tif",
        "scopetwin rig rigs/sim-cmu.toml mda examples/mda/2-positions-2-channels-z.json --out stack.ome.zarr -q",
    )
    p.add_argument("sequence", help="MDA sequence file (.yaml or .json, useq-schema)")
    p.add_argument("--camera", help="camera name (default: the first)")
    p.add_argument("--out", required=True, help="output .ome.tif or .ome.zarr (several positions: one TIFF each)")
    p.add_argument("--single-file", action="store_true", help="OME-TIFF: all positions in one multi-series file")
    p.set_defaults(outputs=[("out", "path", "keep"), ("json", "file")], estimate=estimate_mda)
    p = add(
        "mm-config",
        cmd_mm_config,
        "write the rig's Micro-Manager configuration: pymmcore-plus Python devices ('#py' lines) that a plain "
        "UniMMCore, pymmcore-widgets or napari-micromanager load; a Channel preset per light, the pixel size",
        "scopetwin rig rigs/sim-cmu.toml mm-config --out sim-cmu.cfg",
        "scopetwin rig rigs/sim-cmu.toml mm-config --camera cam_nir --light deep_red --out nir.cfg",
    )
    p.add_argument("--out", required=True, help="the .cfg file to write")
    p.add_argument("--camera", help="the camera (device Camera; default: the first)")
    p.add_argument("--focus", help="the focus drive (device Z; default: the first)")
    p.add_argument("--light", help="the light selected at start (default: the first)")
    p.set_defaults(outputs=[("out", "file"), ("json", "file")])


def register(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``rig RIG.toml info|move|position|acquire|live|mda|mm-config|serve`` to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "rig",
        help="open a rig config (simulated or hardware): list devices, move, acquire, MDA, serve",
        description="Open a rig config (simulated or hardware): list devices and limits, move, acquire, run a "
        "Micro-Manager MDA into OME files, serve the devices to python-microscope clients. Devices on emu:// "
        "ports talk to emulators that live for one command only (each command starts them fresh); run "
        "'scopetwin emulate KIND' and put its port in the rig file to keep their state between commands.",
        **conventions("scopetwin rig rigs/sim-cmu.toml info", "scopetwin rig rigs/emulated-hardware.toml move x 80"),
    )
    parser.add_argument(
        "rig",
        help="rig TOML file, or the name of a rig shipped with scopetwin (" + ", ".join(rig_names()) + "; rigs/)",
    )
    actions = parser.add_subparsers(dest="rig_action", required=True)

    def add(name: str, func: Any, help_: str, *examples: str) -> argparse.ArgumentParser:
        p = actions.add_parser(
            name, help=help_, description=help_, prog=f"scopetwin rig RIG {name}", **conventions(*examples)
        )
        p.set_defaults(func=func)
        p.add_argument("--json", metavar="PATH", help="write machine-readable results here")
        return p

    _add_motion_commands(add)
    p = add(
        "acquire",
        cmd_acquire,
        "grab frames with a light on, each written as it arrives and listed in manifest.json; preview.png shows "
        "the last; SIGINT/SIGTERM/SIGHUP switch the lights off and keep every frame written",
        "scopetwin rig rigs/sim-cmu.toml acquire frames --camera cam_blue --light uv --frames 3",
        "scopetwin rig rigs/sim-deflectometry.toml acquire deflectometry-frame",
    )
    p.add_argument("out", help="output folder")
    p.set_defaults(outputs=[("out", "dir", "keep", "positional"), ("json", "file")], estimate=estimate_acquire)
    p.add_argument("--camera", help="camera name (default: the first)")
    p.add_argument("--light", help="light name (default: the first)")
    p.add_argument("--exposure-s", type=positive_float(), help="exposure time (default: automatic, ~70%% of the range)")
    p.add_argument("--frames", type=positive_int(MAX_FRAMES), default=1, help="number of frames (>= 1)")
    p.add_argument(
        "--pattern-stage",
        metavar="NAME",
        help="a stage that moves the pattern along its normal: one frame here and one --pattern-shift further "
        "(deflectometry_1.exr, deflectometry_2.exr; thesis §1.3), for reconstruct --second",
    )
    p.add_argument("--pattern-shift", type=finite_float(-500.0, 500.0), metavar="MM", help="with --pattern-stage, mm")
    _add_live_command(add)
    _add_mda_commands(add)
    p = add(
        "serve",
        cmd_serve,
        "serve the devices through python-microscope's device server (Pyro) on 127.0.0.1 until SIGINT/SIGTERM; "
        "clients sign every message with the printed key file (Pyro's HMAC), others are refused",
        "scopetwin rig rigs/sim-cmu.toml serve",
        "scopetwin rig rigs/emulated-hardware.toml serve --port 0",
    )
    p.add_argument("--port", type=int_range(0, 65535), default=8000, help="first port; one per device (0: free ports)")
    p.add_argument("--host", default=LOCALHOSTS[0], help="only 127.0.0.1 (or localhost) is accepted")
    p.add_argument(
        "--hmac-key-file",
        metavar="PATH",
        help="the key clients sign with (a file only its owner can read; default: a new key in a private "
        "temporary file, printed at start and removed at exit)",
    )
    p.add_argument(
        "--serializer",
        choices=("auto", "pickle"),
        default="auto",
        help="auto (default): lights and stages speak serpent, which cannot run code, cameras pickle (frames are "
        "numpy arrays); pickle: every device, as python-microscope's device server and Cockpit",
    )
    return parser
