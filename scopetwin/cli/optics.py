"""``scopetwin optics ...``: the four-channel unit (thesis ch. 3-5), GRIN objectives (ch. 7-8), scan-time models.

``register(subparsers)`` adds the ``optics`` command to an argparse sub-parser set:

* ``optics cmu [--setup PRESET] [--splitter-maps NAME=EXR ...] [--stop] [--json PATH] [--out DIR] [--spp N]``
  -- the compact microscope unit (:mod:`scopetwin.sim.cmu_unit`): the §5.1.2 checks, per channel the refocused image
  distance, magnification (Table 5.1), RMS spots, astigmatism and wavefront PSF, the 4x4 excitation crosstalk,
  printed beside the thesis; with ``--out`` the Siemens star and the dummy cells rendered through each channel and
  measured (Tables 5.1-5.4).
* ``optics cmu --budget [--snr S] [--raster COLUMNS ROWS] [--plot PNG] [--json PATH] [--out DIR [--spp N]
  [--window PX] [--density RHO|implied]]`` -- the photon budget per channel beside the thesis's exposures, the lasers
  of §5.2.3, the time per field and per slide against a sequential microscope (:mod:`scopetwin.sim.cmu_budget`); with
  ``--out`` the dummy cells at the budget's photon counts and the thesis's exposures.
* ``optics grin PRESET [--json PATH] [--spots PNG] [--image TARGET --out EXR] [--profile TOML]
  [--sensitivity] [--spp N] [--width W --height H]`` -- paraxial data, NA, Airy radius, RMS spots,
  printed beside the thesis's Zemax figures; spot diagrams; an image of a §8.5 target with a PNG preview beside
  it. Before the analysis the render is estimated (:func:`scopetwin.scenes.limits.check_render`); before anything is
  printed, a window that misses the image of every objective of an array is refused
  (:func:`scopetwin.scenes.grin.setup.check_image_window`: it would render black).
* ``optics scan [...]`` -- T_I, T_M, T_N, eq. 7.1/7.2, the s^1.5 scaling law, N (eq. 8.1), N_max (eq. 8.2), d_L,max
  (:mod:`scopetwin.sim.scan_time`).

Errors the user can cause are :class:`scopetwin.scenes.errors.ScopetwinError` (exit code 2 in :mod:`scopetwin.cli`).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from scopetwin.cli.options import SEED, SIDE_PX, SPP, conventions, finite_float, positive_float, positive_int
from scopetwin.scenes.errors import ScopetwinError

#: Upper bound of the lengths ``optics scan`` takes (mm): 10 m, far beyond any substrate of the thesis.
MAX_LENGTH_MM = 1.0e4
#: Upper bound of the objective counts ``optics scan`` takes.
MAX_OBJECTIVES = 100_000


def register(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``optics`` (with ``grin`` and ``scan``) to ``subparsers``; returns the ``optics`` parser."""
    h = "the four-channel unit, GRIN objectives (spots, target images) and scan-time models (thesis Parts II, III)"
    optics = subparsers.add_parser(
        "optics",
        help=h,
        description=h,
        **conventions("scopetwin optics cmu", "scopetwin optics grin thesis-8.3.2-grin-realized --spots spots.png"),
    )
    sub = optics.add_subparsers(dest="optics_command", required=True)
    register_cmu(sub)
    h = "analyse a GRIN objective preset, draw its spot diagrams, render a target image (thesis §7.5.2, §8.3)"
    g = sub.add_parser(
        "grin",
        help=h,
        description=h,
        **conventions(
            "scopetwin optics grin thesis-8.3.2-grin-realized --spots spots.png --sensitivity",
            "scopetwin optics grin thesis-7.5.2-grin-egfp --image dots-25 --out egfp.exr --spp 16",
        ),
    )
    g.add_argument("preset", help="preset name (thesis-8.3.2-grin-realized, ...) or TOML path")
    g.add_argument("--json", type=Path, help="write the results as JSON")
    g.add_argument("--spots", type=Path, help="write spot diagrams (axis, 0.7 field, edge) as PNG")
    g.add_argument("--image", metavar="TARGET", help="render a §8.5 target: dots-25, grid-25, grid-12.5, lines-8")
    g.add_argument("--out", type=Path, help="EXR path for --image (a PNG preview is written beside it)")
    g.add_argument("--profile", type=Path, help="TOML with [rod1.profile] / [rod2.profile] overrides (sech allowed)")
    g.add_argument("--sensitivity", action="store_true", help="print the layout readings' effect")
    g.add_argument("--spp", type=SPP, default=16, help="samples per pixel for --image, >= 1 (default 16)")
    g.add_argument("--width", type=SIDE_PX, help="image width in pixels, >= 1 (default: the camera's)")
    g.add_argument("--height", type=SIDE_PX, help="image height in pixels, >= 1 (default: the camera's)")
    g.add_argument(
        "--target-offset",
        type=finite_float(),
        nargs=2,
        default=(0.0, 0.0),
        metavar=("X", "Y"),
        help="shift the target pattern from the axis (mm)",
    )
    g.add_argument("--seed", type=SEED, default=0, help="sampler seed for --image, >= 0")
    g.set_defaults(func=cmd_grin, outputs=[("json", "file"), ("spots", "file"), ("out", "file")])
    h = "scan-time models (thesis §7.2-7.4) and the objective count (§8.2.2)"
    s = sub.add_parser(
        "scan",
        help=h,
        description=h,
        **conventions("scopetwin optics scan", "scopetwin optics scan --n 4 --n-y 2 --json scan.json"),
    )
    pos, count = positive_float(MAX_LENGTH_MM), positive_int(MAX_OBJECTIVES)
    s.add_argument("--width", type=pos, default=75.0, help="substrate width W (mm)")
    s.add_argument("--height", type=pos, default=25.0, help="substrate height H (mm)")
    s.add_argument("--d-w", type=pos, default=0.4, help="spot distance d_w (mm)")
    s.add_argument("--d-h", type=pos, default=0.4, help="spot distance d_h (mm)")
    s.add_argument("--exposure-s", type=positive_float(), default=0.1, help="exposure time τ_e (s)")
    s.add_argument("--velocity", type=positive_float(), default=10.0, help="stage velocity v (mm/s)")
    s.add_argument("--w-fov", type=pos, default=0.4, help="field-of-view width w_FOV (mm)")
    s.add_argument("--v-scan", type=positive_float(), default=1.0, help="scan velocity (mm/s)")
    s.add_argument("--n", type=count, default=1, help="objectives N side by side (§7.3)")
    s.add_argument("--n-y", type=count, default=1, help="rows of objectives N_y (eq. 7.2)")
    s.add_argument("--lens-diameter", type=pos, default=2.0, help="lens diameter D_L (mm)")
    s.add_argument("--sensor-side", type=pos, default=4.28, help="sensor minimum side S (mm, §8.2.2)")
    s.add_argument("--magnification", type=positive_float(), default=4.29, help="magnification m (§8.2.2)")
    s.add_argument("--fov", type=pos, default=0.4, help="field of view (mm, §8.2.2)")
    s.add_argument("--spacing", type=pos, default=2.25, help="axis spacing d_L (mm, §8.2.2)")
    s.add_argument("--json", type=Path, help="write the results as JSON")
    s.set_defaults(func=cmd_scan)
    return optics


# -- optics grin ----------------------------------------------------------------------------------
def _fmt(v: Any, nd: int = 3) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "-"
    return f"{v:.{nd}f}"


def _comparison_rows(rep: Any) -> list[tuple[str, Any, Any]]:
    seed = rep.seed
    return [
        ("magnification", rep.magnification, seed.get("magnification")),
        ("object NA", rep.na_object, seed.get("na_object")),
        ("RMS spot, axis (µm)", rep.rms_spot_um["axis"], seed.get("rms_axis_um")),
        ("RMS spot, edge (µm)", rep.rms_spot_um["edge"], seed.get("rms_edge_um")),
        ("Airy radius (µm)", rep.airy_um, seed.get("airy_um")),
        ("image distance (mm)", rep.image_distance_mm, seed.get("image_distance")),
        ("object distance (mm)", rep.object_distance_mm, seed.get("object_distance")),
    ]


def print_report(rep: Any, setup: Any) -> None:
    """Print ours beside the thesis's Zemax figures, and the layout reading used."""
    lay = setup.layout
    print(f"{setup.section} {setup.name}: {setup.description}")
    print(
        f"layout: substrate1 {lay.substrate1_side}, substrate2 {lay.substrate2_side}, object distance "
        f"{'includes' if setup.object.distance_includes_cover else 'excludes'} the {setup.object.cover_thickness} mm "
        f"cover glass, rod coefficients at "
        f"{setup.rod1.profile.wavelength_ref_nm or setup.wavelength_nm} nm (design {setup.wavelength_nm} nm)"
    )
    print(f"{'quantity':24s} {'ours':>10s} {'thesis':>10s} {'diff':>8s}")
    for label, ours, theirs in _comparison_rows(rep):
        diff = (
            "-"
            if theirs is None or (isinstance(theirs, float) and math.isnan(theirs)) or not theirs
            else f"{100 * (ours - theirs) / theirs:+.1f}%"
        )
        print(f"{label:24s} {_fmt(ours):>10s} {_fmt(theirs):>10s} {diff:>8s}")
    print(
        f"EFL {rep.efl_mm:.4f} mm, paraxial image distance {rep.paraxial_image_distance_mm:.3f} mm, real "
        f"magnification {rep.magnification_real:.3f}, image NA {rep.na_image:.4f}"
    )
    if rep.rms_spot_at_seed_plane_um:
        print(
            f"RMS at the thesis's image distance: axis {rep.rms_spot_at_seed_plane_um['axis']:.3f} µm, "
            f"edge {rep.rms_spot_at_seed_plane_um['edge']:.3f} µm"
        )
    print(f"OPD rms (waves): axis {rep.opd_rms_waves['axis']:.3f}, edge {rep.opd_rms_waves['edge']:.3f}")
    for key, r in rep.rods.items():
        print(
            f"{key}: L {r['length_mm']:.3f} mm, g {r['g_per_mm']:.5f}/mm, pitch {r['pitch_mm']:.3f} mm "
            f"({r['pitch_fraction']:.4f} P), EFL {r['efl_mm']:.4f} mm, "
            f"working distance {r['working_distance_mm']:.4f} mm"
        )


def cmd_grin(args: argparse.Namespace) -> dict[str, Any]:
    """Handler of ``optics grin``: the analysis (plus spots, image, sensitivity); returns the JSON-ready result."""
    from scopetwin.scenes.grin import load_grin_setup, profile_override
    from scopetwin.scenes.grin.analysis import analyse, sensitivity
    from scopetwin.scenes.grin.setup import check_image_window
    from scopetwin.scenes.grin.targets import target
    from scopetwin.scenes.io import write_image
    from scopetwin.scenes.limits import check_render
    from scopetwin.sim.figures import write_spots
    from scopetwin.sim.measurement import write_preview

    setup = load_grin_setup(args.preset)
    if args.profile is not None:
        setup = profile_override(setup, args.profile)
    if args.image is not None and args.out is None:
        raise ScopetwinError("--image needs --out PATH.exr")
    tgt = None
    width = setup.camera.width_px if args.width is None else args.width
    height = setup.camera.height_px if args.height is None else args.height
    centre = (0.0, 0.0) if setup.array.nx * setup.array.ny > 1 else setup.array.axes()[0]
    if args.image is not None:
        tgt = target(args.image, tuple(args.target_offset))
        tgt.check_field(setup.object.field_radius)
        check_render(width, height, args.spp, f"GRIN image of {args.preset}", "grin")
    rep = analyse(setup)
    if tgt is not None:  # before anything is printed or written: a window between the lenses renders black
        reach = math.hypot(*tgt.offset) + 0.5 * tgt.diameter
        check_image_window(setup, width, height, centre, rep.magnification, reach)
    print_report(rep, setup)
    result = rep.to_json()
    if args.sensitivity:
        rows = sensitivity(setup)
        print(f"\n{'reading':40s} {'m_par':>6s} {'d_par':>7s} {'d_best':>7s} {'NA':>6s} {'rms0':>7s} {'rms1':>7s}")
        for r in rows:
            print(
                f"{r['reading']:40s} {r['magnification_paraxial']:6.3f} {r['paraxial_image_distance_mm']:7.3f} "
                f"{r['image_distance_mm']:7.3f} {r['na_object']:6.3f} {r['rms_axis_um']:7.3f} "
                f"{r['rms_edge_um']:7.3f}"
            )
        result["sensitivity"] = rows
    stack = setup.stack(image_distance=rep.image_distance_mm)
    if rep.stop_radius_mm is not None:
        stack = stack.with_stop_radius(rep.stop_radius_mm)
    if args.spots is not None:
        write_spots(args.spots, setup, stack, rep.image_distance_mm, rep.na_object)
        result["spots"] = str(args.spots)
    if tgt is not None:
        from scopetwin.scenes.mitsuba.grin import render_image

        t0 = time.perf_counter()
        img = render_image(setup, stack, tgt, spp=args.spp, width=width, height=height, center=centre, seed=args.seed)
        seconds = time.perf_counter() - t0
        write_image(
            args.out,
            img,
            setup.to_json(),
            {"seed": "000_a2b7d38b4750eb48", "section": setup.section, "spp": args.spp, "target": tgt.name},
            image_distance_mm=float(rep.image_distance_mm),
            pixel_um=float(setup.camera.pixel_um),
        )
        preview = args.out.with_suffix(".png" if args.out.suffix.lower() != ".png" else ".preview.png")
        write_preview(preview, img)
        print(
            f"image of {tgt.name}: {img.shape[1]}x{img.shape[0]} px, {args.spp} spp, {seconds:.2f} s -> {args.out} "
            f"(preview {preview})"
        )
        result["image"] = str(args.out)
        result["preview"] = str(preview)
        result["seconds"] = seconds
    return json.loads(json.dumps(result, default=float))


# -- optics scan ----------------------------------------------------------------------------------
def cmd_scan(args: argparse.Namespace) -> dict[str, Any]:
    """Handler of ``optics scan``: the §7.2-7.4 scan times and the §8.2.2 objective count."""
    from scopetwin.sim import scan_time as tp

    classic = tp.classic_time(args.width, args.height, args.d_w, args.d_h, args.exposure_s, args.velocity)
    t_n = tp.scan_time(args.width, args.height, args.w_fov, args.v_scan, args.n)
    t_par = tp.scan_time_parallel(args.lens_diameter, args.w_fov, args.height, args.v_scan, args.n_y)
    geo = tp.demonstrator_geometry(args.sensor_side, args.lens_diameter, args.magnification, args.fov, args.spacing)
    print(f"§7.2 classic: T_I = {classic['t_i_s']:.1f} s, T_M = {classic['t_m_s']:.1f} s, T = {classic['t_s']:.1f} s")
    print(
        f"§7.3 scanning with N = {args.n}: T_N = {t_n:.1f} s; eq. 7.2 (N_y = {args.n_y}): T = {t_par:.1f} s, "
        f"N_scans = {tp.scans_needed(args.lens_diameter, args.w_fov):.2f}"
    )
    print("§7.4 scaling: T ~ s^1.5 when N_y ~ 1/s (eq. 7.6): s = 1/4 -> T/8")
    print(
        f"§8.2.2: N_max = {geo['n_max']}, d_L,max = {geo['d_l_max_mm']:.3f} mm, N at d_L = {args.spacing} mm: "
        f"{geo['n_at_d_l']}  (the thesis: N_max = 2, d_L,max = 2.848 mm)"
    )
    return {
        "classic": classic,
        "t_n_s": t_n,
        "t_parallel_s": t_par,
        "n_scans": tp.scans_needed(args.lens_diameter, args.w_fov),
        **geo,
    }


# -- optics cmu ----------------------------------------------------------------------------------
def register_cmu(optics_subparsers: Any) -> argparse.ArgumentParser:
    """Add ``cmu`` to the ``optics`` sub-parsers; returns its parser."""
    h = (
        "the four-channel microscope unit (thesis ch. 3-5): spots, PSF, magnification, Siemens star, crosstalk; "
        "--budget: photon budget per channel, the lasers of §5.2.3, time per field and per slide (ch. 6)"
    )
    p = optics_subparsers.add_parser(
        "cmu",
        help=h,
        description=h,
        **conventions(
            "scopetwin optics cmu --stop --out cmu --spp 16 --json cmu.json",
            "scopetwin optics cmu --budget --plot budget.png --out budget-cells --spp 8",
        ),
    )
    p.add_argument("--setup", default="thesis-cmu", help="preset name or TOML (default thesis-cmu)")
    p.add_argument(
        "--splitter-maps",
        nargs="+",
        default=[],
        metavar="NAME=EXR",
        help="replace a splitter's modelled surface by a height-map EXR (plate-local mm), e.g. 770DCXR=bs3.exr",
    )
    p.add_argument("--stop", action="store_true", help="put the 4 mm aperture in front of every tube lens")
    p.add_argument("--json", type=Path, help="write the results as JSON")
    p.add_argument(
        "--out", type=Path, help="render star and cell images per channel into this folder (EXR + PNG preview)"
    )
    p.add_argument("--spp", type=SPP, default=16, help="samples per pixel for --out, >= 1 (default 16)")
    p.add_argument("--no-cells", action="store_true", help="with --out: skip the dummy-cell images")
    _budget_options(p)
    p.set_defaults(func=cmd_cmu, outputs=[("json", "file"), ("out", "dir"), ("plot", "file")])
    return p


def _density(text: str) -> float | str:
    """``--density``: molecules/µm² (> 0) or the word ``implied``."""
    if text == "implied":
        return text
    return positive_float(1e12)(text)


def _budget_options(p: argparse.ArgumentParser) -> None:
    """``--budget`` and its options: photon budget, lasers, time per field (:mod:`scopetwin.sim.cmu_budget`)."""
    p.add_argument(
        "--budget",
        action="store_true",
        help="instead of the ray analyses: the photon budget per channel, the lasers of §5.2.3 and the time per field "
        "and per slide against a sequential microscope; with --out, the dummy cells at the budget's photon counts",
    )
    p.add_argument("--snr", type=positive_float(1e4), default=10.0, help="with --budget: the SNR an image must reach")
    p.add_argument("--plot", type=Path, help="with --budget: write the exposures and field times as a PNG")
    p.add_argument(
        "--raster",
        type=positive_int(100_000),
        nargs=2,
        default=(80, 25),
        metavar=("COLUMNS", "ROWS"),
        help="with --budget: the slide's fields (default 80 x 25 = 2000)",
    )
    p.add_argument(
        "--density",
        type=_density,
        help="with --budget --out: labelled molecules per µm² of the nuclei, or 'implied' (each channel the density "
        "its thesis exposure implies; default: the one the blue channel's 80 ms implies, for all)",
    )
    p.add_argument(
        "--window", type=SIDE_PX, default=256, help="with --budget --out: side of the centred window, px (default 256)"
    )


def _maps(items: list[str]) -> dict[str, Any]:
    from scopetwin.scenes.io import read_heightmap

    out = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise ScopetwinError(f"--splitter-maps expects NAME=PATH.exr, got {item!r}")
        out[name] = read_heightmap(path)
    return out


def _fmt_seed(v: Any, nd: int = 2) -> str:
    """A thesis figure: a number to ``nd`` decimals, or its text (e.g. "< 1")."""
    return v if isinstance(v, str) else f"{v:.{nd}f}"


def cmd_cmu(args: argparse.Namespace) -> dict[str, Any]:
    """Handler of ``optics cmu``: the unit's analyses (and renders with ``--out``); returns the JSON-ready result."""
    from scopetwin.scenes.cmu import spectra
    from scopetwin.scenes.cmu.layout import load_cmu_setup
    from scopetwin.scenes.io import read_image
    from scopetwin.sim import cmu_unit
    from scopetwin.sim.measurement import write_preview

    _check_budget_args(args)
    if args.budget:
        return _cmd_budget(args, load_cmu_setup(args.setup))
    setup = load_cmu_setup(args.setup)
    maps = _maps(args.splitter_maps)
    unknown = set(maps) - set(setup.splitters) - set(setup.mirrors)
    if unknown:
        raise ScopetwinError(
            f"--splitter-maps: unknown element(s) {', '.join(sorted(unknown))} "
            f"(known: {', '.join([*setup.splitters, *setup.mirrors])})"
        )
    if args.out is not None:  # the renders' estimate before any work (and before the folder is made)
        from scopetwin.scenes.limits import check_render

        cam = setup.camera
        check_render(cam.width_px, cam.height_px, args.spp, f"optics cmu --out at {args.spp} spp", "cmu")
    s512 = cmu_unit.section_5_1_2(setup, maps)
    print("§5.1.2 (perfect lenses f = 16.45 / 164.5 mm, 20 mm beam)        ours    thesis")
    print(f"  perfect mirror, perpendicular: magnification          {s512['mirror_magnification']:8.3f}  10")
    print(
        f"  beam splitter 3 perpendicular, refocused: magnification {s512['bs3_perpendicular_magnification']:6.3f}"
        f"  9.90"
    )
    print(f"  beam splitter 3 at 45°: RMS spot at the outer bound (µm) {s512['bs3_45_rms_um']:6.3f}  43.499")
    print(
        f"  ... with the 4 mm stop (µm)                            {s512['bs3_45_stop_rms_um']:6.3f}  8.826"
        f"   (light through the stop: {100 * s512['stop_transmitted_fraction']:.1f} %)"
    )
    table = cmu_unit.channel_table(setup, maps, args.stop)
    print("\nchannel  b (mm)   m (ours)  m (T5.1)  dx optics (µm)  dx (T5.2)  RMS axis/edge (µm)  astig (mm)  Strehl")
    for ch, r in table.items():
        print(
            f"{ch:7s} {r['image_distance_mm']:8.3f} {r['magnification']:9.3f} {cmu_unit.SEED_TABLE_5_1[ch]:9.2f} "
            f"{r['delta_x_optics_um']:14.2f} {_fmt_seed(cmu_unit.SEED_TABLE_5_2_UM[ch]):>10s} "
            f"{r['rms_spot_um']['axis']:8.2f}/{r['rms_spot_um']['edge']:<8.2f} {r['astigmatism_mm']:11.3f} "
            f"{r['strehl']['axis']:7.3f}"
        )
    x = spectra.excitation_crosstalk()
    print("\nexcitation crosstalk X[source, fluorophore] (relative to each fluorophore's own source):")
    names = [spectra.CHANNEL_FLUOROPHORE[c] for c in spectra.CHANNELS]
    print("source \\ " + " ".join(f"{n:>9s}" for n in names))
    for c, row in zip(spectra.CHANNELS, x, strict=True):
        print(f"{c:9s} " + " ".join(f"{v:9.2e}" for v in row))
    result: dict[str, Any] = {
        "channels": table,
        "section_5_1_2": s512,
        "seed": cmu_unit.SEED_5_1_2,
        **cmu_unit.crosstalk(),
    }
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        rm = cmu_unit.render_and_measure(setup, maps, table, args.out, args.spp, args.stop, not args.no_cells)
        _print_measured(rm["measured"])
        result |= rm
        previews = {}
        for name, path in rm["files"].items():
            exr = Path(path)
            previews[name] = str(exr.with_suffix(".png"))
            write_preview(exr.with_suffix(".png"), read_image(exr)[0])
        result["previews"] = previews
        print(f"EXR images and PNG previews of {len(previews)} renders -> {args.out}")
        for ch in table:
            table[ch]["delta_x_um"] = rm["measured"][ch]["delta_x_um"]
    return _jsonable(result)


def _print_measured(measured: dict[str, dict[str, Any]]) -> None:
    """The Siemens-star measurements of ``optics cmu --out`` beside Tables 5.1-5.4."""
    from scopetwin.sim import cmu_unit

    print("\nfrom the rendered Siemens-star images (calib.channels):")
    print("channel  m (img)  m (T5.1)  dx (µm)  dx (T5.2)  offset px (x, y)  T5.3 px      tilt (°)  T5.4")
    for ch, r in measured.items():
        off = "reference" if ch == "nir" else f"({r.get('offset_x_px', 0.0):6.1f}, {r.get('offset_y_px', 0.0):6.1f})"
        seed_off = str(cmu_unit.SEED_TABLE_5_3_PX.get(ch, "reference"))
        print(
            f"{ch:7s} {r['magnification']:8.3f} {cmu_unit.SEED_TABLE_5_1[ch]:9.2f} {r['delta_x_um']:8.2f} "
            f"{_fmt_seed(cmu_unit.SEED_TABLE_5_2_UM[ch]):>10s}  {off:17s} {seed_off:12s} "
            f"{r.get('tilt_deg', 0.0):8.3f}  {cmu_unit.SEED_TABLE_5_4_DEG.get(ch, '-')}"
        )


def _check_budget_args(args: argparse.Namespace) -> None:
    """Refuse the options of the ray analyses with ``--budget``, and the budget's without it."""
    if args.budget:
        used = [
            o
            for o, v in (("--splitter-maps", args.splitter_maps), ("--stop", args.stop), ("--no-cells", args.no_cells))
            if v
        ]
        if used:
            raise ScopetwinError(
                f"{', '.join(used)}: not with --budget (the budget renders the cells of the model unit)"
            )
        return
    given = [o for o, v in (("--plot", args.plot), ("--density", args.density)) if v is not None]
    given += [
        o
        for o, v, d in (
            ("--snr", args.snr, 10.0),
            ("--raster", tuple(args.raster), (80, 25)),
            ("--window", args.window, 256),
        )
        if v != d
    ]
    if given:
        raise ScopetwinError(f"{', '.join(given)}: only with --budget")


def _cmd_budget(args: argparse.Namespace, setup: Any) -> dict[str, Any]:
    """``optics cmu --budget``: the three tables (and the plot, and the cells at the budget's photon counts)."""
    from scopetwin.sim import cmu_budget
    from scopetwin.sim.field_time import TimingModel

    if args.out is not None:
        from scopetwin.scenes.limits import check_render

        side = min(args.window, setup.camera.width_px, setup.camera.height_px)
        check_render(side, side, args.spp * len(setup.channels), f"optics cmu --budget --out at {args.spp} spp", "cmu")
    result = cmu_budget.report(args.snr, TimingModel(columns=args.raster[0], rows=args.raster[1]))
    print("\n".join(cmu_budget.format_report(result)))
    if args.plot is not None:
        result["plot"] = str(cmu_budget.write_plot(result, args.plot))
        print(f"plot -> {args.plot}")
    if args.out is not None:
        rows = cmu_budget.render_cells(
            setup, args.out, args.snr, density=args.density, spp=args.spp, window_px=args.window
        )
        print()
        print("\n".join(cmu_budget.render_lines(rows)))
        print(f"EXR images (DN) and PNG previews of {len(rows)} channels -> {args.out}")
        result["cells"] = rows
    return _jsonable(result)


def _jsonable(v: Any) -> Any:
    """Numpy scalars as Python numbers, tuples as lists (the ``optics cmu`` JSON)."""
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    return v
