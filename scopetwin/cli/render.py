"""``scopetwin render SETUP --out DIR`` and ``scopetwin presets`` (docs/contract.md, "Command line";
:mod:`scopetwin.sim.measurement`).

The render's memory and time are estimated before anything is written (:func:`scopetwin.scenes.limits.check_render`).
A ``--surface`` must cover the substrate (or ``--extrapolate``) with heights within ±10 mm, checked before the
render; a render that is not finite or carries no signal is refused and nothing is written. The output is staged
beside ``--out``; staging folders that killed runs left there are removed first.
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scopetwin.cli.options import SEED, SPP, conventions, finite_float
from scopetwin.scenes.errors import ScopetwinError

if TYPE_CHECKING:
    from scopetwin.sim.measurement import StagedOutput

log = logging.getLogger(__name__)


def cmd_render(args: argparse.Namespace) -> dict[str, Any]:
    """Render one setup to EXR with its truth; returns ``{"image", "truth", "spp", "seconds"}`` — for a setup with a
    ``[fringes]`` display, every frame of its sequence and ``fringes.json`` (:func:`_render_fringes`)."""
    from scopetwin.scenes.limits import check_render
    from scopetwin.sim.measurement import StagedOutput, load_measurement, render_measurement, write_measurement

    setup, heights = load_measurement(args.setup, args.surface, args.spp, args.seed, args.noise, args.extrapolate)
    if setup.fringes is not None:
        return _render_fringes(args, setup, heights)
    cam = setup.camera_model
    renderer = "analytic" if args.renderer == "analytic" else "setup"
    check_render(cam.nx, cam.ny, setup.render.spp, f"render {setup.name}", renderer)  # before anything is written
    stage = StagedOutput(Path(args.out))
    log.info(
        "rendering %s (%s scene): %d x %d px, %d spp, seed %d, noise %s, %s renderer",
        setup.name,
        setup.scene,
        cam.nx,
        cam.ny,
        setup.render.spp,
        setup.render.seed,
        "on" if setup.render.noise else "off",
        args.renderer,
    )
    try:
        image, seconds = render_measurement(
            setup, heights, setup.render.spp, setup.render.seed, setup.render.noise, args.renderer
        )
        names = write_measurement(stage, "", setup, heights, image, setup.render.spp, setup.render.seed, args.renderer)
        second = _second_position(args, setup, heights, stage)
        moved = stage.commit()
    except BaseException:
        stage.discard()
        raise
    result = {
        "image": str(moved[names["image"]]),
        "truth": str(moved[names["truth"]]),
        "spp": setup.render.spp,
        "seconds": seconds,
    }
    if second is not None:
        shift, names2, seconds2 = second
        result.update(
            shifted_image=str(moved[names2["image"]]),
            shifted_truth=str(moved[names2["truth"]]),
            pattern_shift_mm=shift,
            seconds=seconds + seconds2,
        )
    print(f"rendered {setup.name} ({setup.scene}) at {setup.render.spp} spp in {seconds:.2f} s -> {args.out}")
    return result


def _render_fringes(args: argparse.Namespace, setup: Any, heights: Any) -> dict[str, Any]:
    """A ``[fringes]`` setup: every frame of its sequence rendered (:func:`scopetwin.sim.fringes.render_fringes`) and
    written with ``fringes.json`` (:func:`scopetwin.sim.fringes.write_fringes`); returns ``{"images": [...],
    "fringes", "surface", "frames", "spp", "seconds", "seconds_per_frame"}``. With ``--pattern-shift`` or the setup's
    ``[pattern_stage]`` the sequence at the second display position too (seed + 1), its files prefixed ``shifted_``
    (``shifted_fringes.json``), listed as ``shifted_images``, ``shifted_fringes``, ``pattern_shift_mm``."""
    from scopetwin.scenes.limits import check_render
    from scopetwin.scenes.pattern_stage import stage_shift
    from scopetwin.sim.fringes import render_fringes, render_second_fringes, write_fringes
    from scopetwin.sim.measurement import StagedOutput

    if args.renderer != "mitsuba":
        raise ScopetwinError(f"{setup.name} shows fringes: only the Mitsuba renderer renders a fringe display")
    shift = None
    if args.pattern_shift is not None or setup.pattern_stage is not None:
        shift = stage_shift(setup, args.pattern_shift)  # a zero or non-finite shift refused before the render
    cam = setup.camera_model
    frames = len(setup.fringe_sequence or ())
    positions = 1 if shift is None else 2
    check_render(
        cam.nx,
        cam.ny,
        setup.render.spp * frames * positions,
        f"render {setup.name}, {frames * positions} fringe frames",
    )
    stage = StagedOutput(Path(args.out))
    log.info(
        "rendering %s (%s scene, %d fringe frames): %d x %d px, %d spp, seed %d, noise %s",
        setup.name,
        setup.scene,
        frames,
        cam.nx,
        cam.ny,
        setup.render.spp,
        setup.render.seed,
        "on" if setup.render.noise else "off",
    )
    try:
        measurement = render_fringes(setup, heights, setup.render.spp, setup.render.seed, setup.render.noise)
        names = write_fringes(stage, measurement)
        names2 = None
        if shift is not None:
            log.info("rendering the second display position, %+g mm along the display's normal", shift)
            spp, seed, noise = setup.render.spp, setup.render.seed, setup.render.noise
            measurement2 = render_second_fringes(setup, heights, spp, seed, noise, shift)
            names2 = write_fringes(stage, measurement2, "shifted_")
        moved = stage.commit()
    except BaseException:
        stage.discard()
        raise
    seconds = float(sum(measurement.seconds_per_frame))
    second: dict[str, Any] = {}
    if names2 is not None:
        seconds += float(sum(measurement2.seconds_per_frame))
        second = {
            "shifted_images": [str(moved[n]) for n in names2["images"]],
            "shifted_fringes": str(moved[names2["fringes"]]),
            "pattern_shift_mm": shift,
        }
    print(
        f"rendered {setup.name} ({setup.scene}): {frames * positions} fringe frames"
        f"{'' if shift is None else f' (two display positions, {shift:+g} mm)'} at {setup.render.spp} spp in "
        f"{seconds:.2f} s ({seconds / (frames * positions):.2f} s a frame) -> {args.out}"
    )
    return {
        "images": [str(moved[n]) for n in names["images"]],
        "fringes": str(moved[names["fringes"]]),
        "surface": None if names["surface"] is None else str(moved[names["surface"]]),
        "frames": [frame.to_dict() for frame in measurement.frames],
        "spp": setup.render.spp,
        "seconds": seconds,
        "seconds_per_frame": list(measurement.seconds_per_frame),
        **second,
    }


def _second_position(
    args: argparse.Namespace, setup: Any, heights: Any, stage: StagedOutput
) -> tuple[float, dict[str, str], float] | None:
    """The second image of a pattern stage (``--pattern-shift`` or the setup's ``[pattern_stage]``), staged as
    ``shifted_*``; None when neither asks for it."""
    if args.pattern_shift is None and setup.pattern_stage is None:
        return None
    from scopetwin.scenes.pattern_stage import stage_shift
    from scopetwin.sim.measurement import render_second_position, write_measurement

    if setup.scene != "deflectometry":
        raise ScopetwinError(f"--pattern-shift applies to deflectometry setups; {setup.name} is a {setup.scene} scene")
    shift = stage_shift(setup, args.pattern_shift)
    spp, seed = setup.render.spp, setup.render.seed
    log.info("rendering the second pattern position, %+g mm along the pattern's normal", shift)
    moved, image, seconds = render_second_position(setup, heights, spp, seed, setup.render.noise, args.renderer, shift)
    names = write_measurement(stage, "shifted_", moved, heights, image, spp, (seed + 1) % 2**32, args.renderer)
    return shift, names, seconds


def cmd_presets(args: argparse.Namespace) -> dict[str, Any]:
    """List the setup presets (name, section, description); returns ``{"presets": [...]}``."""
    from scopetwin.scenes.setup import preset_info

    info = preset_info()
    width = max(len(p["name"]) for p in info)
    for p in info:
        print(f"{p['name']:<{width}}  {p['section']:<8} {p['description']}")
    return {"presets": info}


def register(subparsers: Any) -> None:
    """Add ``render`` and ``presets`` to the ``scopetwin`` sub-command parsers."""
    help_ = "render one setup (preset name or TOML path) to EXR with its truth"
    p = subparsers.add_parser(
        "render",
        help=help_,
        description=help_,
        **conventions(
            "scopetwin render thesis-1.10-deflectometry --out r2 --spp 16 --pattern-shift 30 --json r2.json",
            "scopetwin render thesis-1.10-fringes --out f1 --spp 16 --noise --json f1.json",
        ),
    )
    p.set_defaults(func=cmd_render, outputs=[("out", "dir"), ("json", "file")], estimate="render")
    p.add_argument("--json", metavar="PATH", help="write machine-readable results here")
    p.add_argument("setup", help="preset name (see: scopetwin presets) or TOML path")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument(
        "--surface",
        help="height-map EXR replacing the preset's generated surface (it must cover the substrate; |z| <= 10 mm)",
    )
    p.add_argument(
        "--extrapolate",
        action="store_true",
        help="accept a --surface smaller than the substrate (continued beyond its edges with its edge values)",
    )
    p.add_argument("--spp", type=SPP, help="samples per pixel, >= 1 (default: the setup's)")
    p.add_argument("--seed", type=SEED, help="random seed, >= 0 (default: the setup's)")
    p.add_argument(
        "--noise", action=argparse.BooleanOptionalAction, default=None, help="apply the EMVA 1288 sensor model"
    )
    p.add_argument(
        "--renderer",
        choices=("mitsuba", "analytic"),
        default="mitsuba",
        help="Mitsuba (default) or the float64 analytic reference (slow)",
    )
    p.add_argument(
        "--pattern-shift",
        type=finite_float(-500.0, 500.0),
        metavar="MM",
        help="also render the second image of a pattern stage, the pattern moved MM along its normal, as "
        "shifted_image.exr (default: the setup's [pattern_stage] shift_mm, where it has one)",
    )

    help_ = "list the setup presets"
    p = subparsers.add_parser(
        "presets",
        help=help_,
        description=help_,
        **conventions("scopetwin presets", "scopetwin presets --json presets.json"),
    )
    p.set_defaults(func=cmd_presets)
    p.add_argument("--json", metavar="PATH", help="write machine-readable results here")
