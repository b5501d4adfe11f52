"""``scopetwin rig RIG.toml info|move|position|acquire`` (DESIGN.md, 'Rig files').

:func:`register` adds the ``rig`` command to an argparse subparsers object; each
action's handler returns a JSON-ready dict (written by the main CLI when
``--json PATH`` is given) and prints a short human-readable line:

* ``info`` — the rig's devices, their drivers and limits;
* ``move NAME VALUE`` — move a stage (mm) or focus drive (µm); JSON ``{"device", "position_mm"}``
  or ``{"device", "position_um"}`` after the move;
* ``position NAME`` — the same JSON without moving;
* ``acquire OUT`` — frames from a camera with a light on (fixed or automatic exposure), written
  to ``OUT`` as they come, plus ``manifest.json``.

The rig is opened with :func:`instrument.rig.open_rig`, so lights are off again on every exit.
"""

from __future__ import annotations

import argparse
from typing import Any

from instrument.devices import FocusDrive, Stage
from instrument.errors import RigError
from instrument.rig import Rig, open_rig


def _position(rig: Rig, name: str) -> dict[str, Any]:
    device = rig[name]
    if isinstance(device, Stage):
        return {"device": name, "position_mm": device.position_mm}
    if isinstance(device, FocusDrive):
        return {"device": name, "position_um": device.position_um}
    raise RigError(f"device {name!r} is a {device.kind}: only stages and focus drives have a position")


def cmd_info(args: argparse.Namespace) -> dict[str, Any]:
    """List the rig's devices (opens and initialises them: a connection check)."""
    with open_rig(args.rig) as rig:
        info = rig.describe()
    for d in info["devices"]:
        print(f"{d['name']:<12} {d['kind']:<8} {d['driver']}")
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


def cmd_acquire(args: argparse.Namespace) -> dict[str, Any]:
    """Acquire frames with a light on; each frame is on disk as soon as it is grabbed."""
    from instrument.acquisition import calibration_capture

    with open_rig(args.rig) as rig:
        paths = calibration_capture(
            rig, args.out, n_frames=args.frames, camera=args.camera, light=args.light, exposure_s=args.exposure_s
        )
        exposure = rig.camera(args.camera).exposure_s
    print(f"wrote {len(paths)} frame(s) to {args.out}")
    return {"frames": [str(p) for p in paths], "exposure_s": exposure, "manifest": f"{args.out}/manifest.json"}


def register(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``rig RIG.toml info|move|position|acquire`` to an argparse subparsers object."""
    parser = subparsers.add_parser(
        "rig",
        help="open a rig config (simulated or hardware), list devices, move, acquire",
        description="open a rig config (simulated or hardware), list devices, move, acquire",
    )
    parser.add_argument("rig", help="rig TOML file (see rigs/)")
    actions = parser.add_subparsers(dest="rig_action", required=True)

    def add(name: str, func: Any, help_: str) -> argparse.ArgumentParser:
        p = actions.add_parser(name, help=help_, description=help_)
        p.set_defaults(func=func)
        p.add_argument("--json", metavar="PATH", help="write machine-readable results here")
        return p

    add("info", cmd_info, "list the devices, their drivers and limits")
    p = add("move", cmd_move, "move a stage (mm) or the focus drive (um) to an absolute position")
    p.add_argument("name", help="device name in the rig")
    p.add_argument("value", type=float, help="target: mm for a stage, um for a focus drive")
    p = add("position", cmd_position, "report a stage's (mm) or the focus drive's (um) position")
    p.add_argument("name", help="device name in the rig")
    p = add("acquire", cmd_acquire, "grab frames with a light on, each written as it arrives")
    p.add_argument("out", help="output folder")
    p.add_argument("--camera", help="camera name (default: the first)")
    p.add_argument("--light", help="light name (default: the first)")
    p.add_argument("--exposure-s", type=float, help="exposure time (default: automatic, ~70%% of the range)")
    p.add_argument("--frames", type=int, default=1, help="number of frames")
    return parser
