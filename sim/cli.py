"""The ``scopetwin`` command line (DESIGN.md, "Command line").

Every command that produces results accepts ``--json PATH``; bad input gives
one line ``scopetwin: error: ...`` on stderr and exit code 2, and leaves no
partial output behind.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from scenes.errors import ScopetwinError
from scenes.io import write_json_atomic

EXIT_BAD_INPUT = 2


class StagedOutput:
    """Collects output files in a hidden staging folder and moves them into ``out`` only on success."""

    def __init__(self, out: Path) -> None:
        self.out = out
        out.parent.mkdir(parents=True, exist_ok=True)
        self.stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))

    def path(self, name: str) -> Path:
        return self.stage / name

    def commit(self) -> dict[str, Path]:
        self.out.mkdir(parents=True, exist_ok=True)
        moved = {}
        for f in sorted(self.stage.iterdir()):
            dest = self.out / f.name
            f.replace(dest)
            moved[f.name] = dest
        self.stage.rmdir()
        return moved

    def discard(self) -> None:
        shutil.rmtree(self.stage, ignore_errors=True)


def _provenance(seed: int, spp: int, renderer: str) -> dict[str, Any]:
    import importlib.metadata as md

    versions = {}
    for pkg in ("scopetwin", "mitsuba", "drjit", "numpy"):
        try:
            versions[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            versions[pkg] = "unknown"
    return {"seed": seed, "spp": spp, "renderer": renderer, "versions": versions}


def _preview(path: Path, image: np.ndarray) -> None:
    import cv2

    top = float(np.percentile(image, 99.9)) or 1.0
    img8 = np.clip(255.0 * (np.clip(image / top, 0, 1) ** (1 / 2.2)), 0, 255).astype(np.uint8)
    if not cv2.imwrite(str(path), img8):
        raise ScopetwinError(f"could not write the preview {path}")


def render_measurement(setup, heights, spp: int, seed: int, noise: bool, renderer: str = "mitsuba"):
    """Render one setup (and optionally apply the sensor model); returns (image, seconds)."""
    t0 = time.perf_counter()
    if renderer == "analytic":
        from scenes.analytic import render

        image = render(setup, heights, spp=spp, seed=seed)
    else:
        from scenes.mitsuba.render import render_setup

        image = render_setup(setup, heights, spp=spp, seed=seed)
    if noise:
        sensor = setup.sensor.sensor()
        exposure = setup.sensor.exposure_s
        if exposure is None:
            peak = float(image.max())
            if peak <= 0:
                raise ScopetwinError("the rendered image is black: cannot choose an exposure for the noise model")
            exposure = sensor.exposure_for(peak, setup.sensor.photons_per_unit_s, setup.sensor.fill_fraction)
        image = sensor.capture(image, setup.sensor.photons_per_unit_s, exposure, rng=seed)
    return image, time.perf_counter() - t0


def write_measurement(
    stage: StagedOutput, prefix: str, setup, heights, image, spp: int, seed: int, renderer: str
) -> dict[str, str]:
    """Write image EXR, truth JSON (and height map), preview PNG into the staging folder."""
    from scenes.io import write_heightmap, write_image
    from sim.truth import marker_truth

    names = {"image": f"{prefix}image.exr", "truth": f"{prefix}truth.json", "preview": f"{prefix}preview.png"}
    write_image(stage.path(names["image"]), image, setup.to_json(), _provenance(seed, spp, renderer))
    truth: dict[str, Any] = {"setup": setup.name, "scene": setup.scene, "surface": None}
    if heights is not None:
        names["surface"] = f"{prefix}surface.exr"
        write_heightmap(stage.path(names["surface"]), heights)
        truth["surface"] = names["surface"]
    truth["markers"] = marker_truth(setup, heights).as_records()
    write_json_atomic(stage.path(names["truth"]), truth)
    _preview(stage.path(names["preview"]), image)
    return names


def _load(setup_arg: str, surface: str | None, spp: int | None, seed: int | None, noise: bool | None):
    from scenes.io import read_heightmap
    from scenes.setup import load_setup
    from sim.surfaces import surface_for

    overrides: dict[str, Any] = {}
    render_over = {k: v for k, v in (("spp", spp), ("seed", seed), ("noise", noise)) if v is not None}
    if render_over:
        overrides["render"] = render_over
    setup = load_setup(setup_arg, overrides)
    if surface is not None:
        if setup.scene != "deflectometry":
            raise ScopetwinError(f"--surface applies to deflectometry setups; {setup.name} is a {setup.scene} scene")
        heights = read_heightmap(surface)
    else:
        heights = surface_for(setup)
    return setup, heights


def cmd_render(args: argparse.Namespace) -> dict[str, Any]:
    setup, heights = _load(args.setup, args.surface, args.spp, args.seed, args.noise)
    stage = StagedOutput(Path(args.out))
    try:
        image, seconds = render_measurement(
            setup, heights, setup.render.spp, setup.render.seed, setup.render.noise, args.renderer
        )
        names = write_measurement(stage, "", setup, heights, image, setup.render.spp, setup.render.seed, args.renderer)
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
    print(f"rendered {setup.name} ({setup.scene}) at {setup.render.spp} spp in {seconds:.2f} s -> {args.out}")
    return result


def cmd_presets(args: argparse.Namespace) -> dict[str, Any]:
    from scenes.setup import preset_info

    info = preset_info()
    width = max(len(p["name"]) for p in info)
    for p in info:
        print(f"{p['name']:<{width}}  {p['section']:<8} {p['description']}")
    return {"presets": info}


def cmd_run(args: argparse.Namespace) -> dict[str, Any]:
    """The main job on the embedded default (issue 5): simulate, render, calibrate, reconstruct, compare.

    Generates a §1.9 surface, renders the two calibration images and the measurement image (noise on)
    with Mitsuba, calibrates the setup, reconstructs with the calibrated and with the ideal setup,
    compares with the truth and writes a report folder (report.md, EXR maps, PNG plots). The folder
    appears only when everything succeeded.
    """
    from sim.pipeline import run_pipeline

    out = Path(args.out)
    stage = StagedOutput(out)
    try:
        summary = run_pipeline(stage.stage, args.spp, args.seed, progress=not args.quiet)
        stage.commit()
    except BaseException:
        stage.discard()
        raise
    print(f"wrote the report to {out / 'report.md'}")
    return {"report": str(out / "report.md"), **summary}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="scopetwin",
        description="Physically based testbed: deflectometry, one-shot calibration, the four-channel and GRIN "
        "microscopes, and the instruments that drive them.",
    )
    sub = parser.add_subparsers(dest="command", required=True)

    def add(name: str, func: Callable[[argparse.Namespace], dict[str, Any]], help_: str) -> argparse.ArgumentParser:
        p = sub.add_parser(name, help=help_, description=help_)
        p.set_defaults(func=func)
        p.add_argument("--json", metavar="PATH", help="write machine-readable results here")
        return p

    p = add("render", cmd_render, "render one setup (preset name or TOML path) to EXR with its truth")
    p.add_argument("setup", help="preset name (see `scopetwin presets`) or TOML path")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--surface", help="height-map EXR replacing the preset's generated surface")
    p.add_argument("--spp", type=int, help="samples per pixel")
    p.add_argument("--seed", type=int, help="random seed")
    p.add_argument(
        "--noise", action=argparse.BooleanOptionalAction, default=None, help="apply the EMVA 1288 sensor model"
    )
    p.add_argument(
        "--renderer",
        choices=("mitsuba", "analytic"),
        default="mitsuba",
        help="Mitsuba (default) or the float64 analytic reference (slow)",
    )

    add("presets", cmd_presets, "list the setup presets")

    p = add("run", cmd_run, "the main job on the embedded default: simulate, render, calibrate, reconstruct, compare")
    p.add_argument("--out", default="scopetwin-run", help="report folder (default: scopetwin-run)")
    p.add_argument("--spp", type=int, help="samples per pixel")
    p.add_argument("--seed", type=int, help="random seed")
    p.add_argument("--quiet", action="store_true", help="no progress bar")

    from calib.cli import register as register_calib
    from instrument.cli import register as register_rig
    from recon.markers_cli import register as register_markers
    from recon.reconstruct_cli import register as register_reconstruct
    from sim import dataset_cli, optics_cli, study_cli

    register_markers(sub)
    register_reconstruct(sub)
    register_calib(sub)
    optics_cli.register(sub)
    register_rig(sub)
    dataset_cli.register(sub)
    study_cli.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        result = args.func(args)
        # Commands return their results as a dict (written here for --json) or an exit code
        # (sub-command modules that write their own JSON).
        if isinstance(result, int):
            return result
        if getattr(args, "json", None):
            write_json_atomic(args.json, result)
    except ScopetwinError as exc:
        print(f"scopetwin: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("scopetwin: interrupted", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
