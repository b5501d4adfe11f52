"""``scopetwin optics ...``: GRIN objectives (seed ch. 7-8) and the scan-time models (§7.2-7.4, §8.2.2).

``register(subparsers)`` adds the ``optics`` command to an argparse sub-parser set:

* ``optics grin PRESET [--json PATH] [--spots PNG] [--image TARGET --out EXR] [--profile TOML]
  [--sensitivity] [--spp N] [--width W --height H]`` -- paraxial data, NA, Airy radius, RMS spots,
  printed beside the seed's Zemax figures; spot diagrams; an image of a §8.5 target.
* ``optics scan [...]`` -- T_I, T_M, T_N, eq. 7.1/7.2, the s^1.5 scaling law, N (eq. 8.1), N_max (eq. 8.2), d_L,max.

Errors the user can cause are :class:`scenes.errors.ScopetwinError` (exit code 2 in ``sim.cli``).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

from scenes.errors import ScopetwinError
from scenes.io import atomic_path, write_image, write_json_atomic


def register(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``optics`` (with ``grin`` and ``scan``) to ``subparsers``; returns the ``optics`` parser."""
    optics = subparsers.add_parser("optics", help="GRIN objectives, spot diagrams, target images, scan-time models")
    sub = optics.add_subparsers(dest="optics_command", required=True)
    from sim.cmu_cli import register_cmu

    register_cmu(sub)
    g = sub.add_parser("grin", help="analyse/render a GRIN objective preset (seed §7.5.2, §8.3)")
    g.add_argument("preset", help="preset name (thesis-8.3.2-grin-realized, ...) or TOML path")
    g.add_argument("--json", type=Path, help="write the results as JSON")
    g.add_argument("--spots", type=Path, help="write spot diagrams (axis, 0.7 field, edge) as PNG")
    g.add_argument("--image", metavar="TARGET", help="render a §8.5 target: dots-25, grid-25, grid-12.5, lines-8")
    g.add_argument("--out", type=Path, help="EXR path for --image")
    g.add_argument("--profile", type=Path, help="TOML with [rod1.profile] / [rod2.profile] overrides (sech allowed)")
    g.add_argument("--sensitivity", action="store_true", help="print the layout readings' effect")
    g.add_argument("--spp", type=int, default=16, help="samples per pixel for --image (default 16)")
    g.add_argument("--width", type=int, help="image width in pixels (default: the camera's)")
    g.add_argument("--height", type=int, help="image height in pixels (default: the camera's)")
    g.add_argument(
        "--target-offset",
        type=float,
        nargs=2,
        default=(0.0, 0.0),
        metavar=("X", "Y"),
        help="shift the target pattern from the axis (mm)",
    )
    g.add_argument("--seed", type=int, default=0, help="sampler seed for --image")
    g.set_defaults(func=cmd_grin)
    s = sub.add_parser("scan", help="scan-time models (§7.2-7.4) and objective count (§8.2.2)")
    s.add_argument("--width", type=float, default=75.0, help="substrate width W (mm)")
    s.add_argument("--height", type=float, default=25.0, help="substrate height H (mm)")
    s.add_argument("--d-w", type=float, default=0.4, help="spot distance d_w (mm)")
    s.add_argument("--d-h", type=float, default=0.4, help="spot distance d_h (mm)")
    s.add_argument("--exposure-s", type=float, default=0.1, help="exposure time τ_e (s)")
    s.add_argument("--velocity", type=float, default=10.0, help="stage velocity v (mm/s)")
    s.add_argument("--w-fov", type=float, default=0.4, help="field-of-view width w_FOV (mm)")
    s.add_argument("--v-scan", type=float, default=1.0, help="scan velocity (mm/s)")
    s.add_argument("--n", type=int, default=1, help="objectives N side by side (§7.3)")
    s.add_argument("--n-y", type=int, default=1, help="rows of objectives N_y (eq. 7.2)")
    s.add_argument("--lens-diameter", type=float, default=2.0, help="lens diameter D_L (mm)")
    s.add_argument("--sensor-side", type=float, default=4.28, help="sensor minimum side S (mm, §8.2.2)")
    s.add_argument("--magnification", type=float, default=4.29, help="magnification m (§8.2.2)")
    s.add_argument("--fov", type=float, default=0.4, help="field of view (mm, §8.2.2)")
    s.add_argument("--spacing", type=float, default=2.25, help="axis spacing d_L (mm, §8.2.2)")
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
    """Print ours beside the seed's Zemax figures, and the layout reading used."""
    lay = setup.layout
    print(f"{setup.section} {setup.name}: {setup.description}")
    print(
        f"layout: substrate1 {lay.substrate1_side}, substrate2 {lay.substrate2_side}, object distance "
        f"{'includes' if setup.object.distance_includes_cover else 'excludes'} the {setup.object.cover_thickness} mm "
        f"cover glass, rod coefficients at "
        f"{setup.rod1.profile.wavelength_ref_nm or setup.wavelength_nm} nm (design {setup.wavelength_nm} nm)"
    )
    print(f"{'quantity':24s} {'ours':>10s} {'seed':>10s} {'diff':>8s}")
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
            f"RMS at the seed's image distance: axis {rep.rms_spot_at_seed_plane_um['axis']:.3f} µm, "
            f"edge {rep.rms_spot_at_seed_plane_um['edge']:.3f} µm"
        )
    print(f"OPD rms (waves): axis {rep.opd_rms_waves['axis']:.3f}, edge {rep.opd_rms_waves['edge']:.3f}")
    for key, r in rep.rods.items():
        print(
            f"{key}: L {r['length_mm']:.3f} mm, g {r['g_per_mm']:.5f}/mm, pitch {r['pitch_mm']:.3f} mm "
            f"({r['pitch_fraction']:.4f} P), EFL {r['efl_mm']:.4f} mm, "
            f"working distance {r['working_distance_mm']:.4f} mm"
        )


def write_spots(path: Path, setup: Any, stack: Any, image_distance: float, na: float) -> None:
    """Spot diagrams at field 0, 0.7, 1 on the best-focus plane, PNG written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from scenes.grin.analysis import FIELDS, bundle, rms_radius

    fig, axes = plt.subplots(1, len(FIELDS), figsize=(4 * len(FIELDS), 4))
    for ax, f in zip(axes, FIELDS, strict=True):
        b = bundle(stack, f * setup.object.field_radius, na)
        x, y = b.spot(image_distance)
        cx, cy = x.mean(), y.mean()
        ax.plot((x - cx) * 1e3, (y - cy) * 1e3, ".", ms=1.5)
        ax.set_aspect("equal")
        ax.set_title(
            f"field {f:.1f} ({f * setup.object.field_radius * 1e3:.0f} µm): RMS {rms_radius(x, y) * 1e3:.2f} µm"
        )
        ax.set_xlabel("x (µm)")
        ax.set_ylabel("y (µm)")
    fig.suptitle(f"{setup.section} spot diagrams, image plane {image_distance:.3f} mm")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def cmd_grin(args: argparse.Namespace) -> int:
    """Handler of ``optics grin``."""
    from scenes.grin import load_grin_setup, profile_override
    from scenes.grin.analysis import analyse, sensitivity
    from scenes.grin.targets import target

    setup = load_grin_setup(args.preset)
    if args.profile is not None:
        setup = profile_override(setup, args.profile)
    if args.image is not None and args.out is None:
        raise ScopetwinError("--image needs --out PATH.exr")
    tgt = None
    if args.image is not None:
        tgt = target(args.image, tuple(args.target_offset))
        tgt.check_field(setup.object.field_radius)
    rep = analyse(setup)
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
        from scenes.mitsuba.grin import render_image

        t0 = time.perf_counter()
        centre = (0.0, 0.0) if setup.array.nx * setup.array.ny > 1 else setup.array.axes()[0]
        img = render_image(
            setup, stack, tgt, spp=args.spp, width=args.width, height=args.height, center=centre, seed=args.seed
        )
        seconds = time.perf_counter() - t0
        write_image(
            args.out,
            img,
            setup.to_json(),
            {"seed": "000_a2b7d38b4750eb48", "section": setup.section, "spp": args.spp, "target": tgt.name},
            image_distance_mm=float(rep.image_distance_mm),
            pixel_um=float(setup.camera.pixel_um),
        )
        print(f"image of {tgt.name}: {img.shape[1]}x{img.shape[0]} px, {args.spp} spp, {seconds:.2f} s -> {args.out}")
        result["image"] = str(args.out)
        result["seconds"] = seconds
    if args.json is not None:
        write_json_atomic(args.json, json.loads(json.dumps(result, default=float)))
    return 0


# -- optics scan ----------------------------------------------------------------------------------
def cmd_scan(args: argparse.Namespace) -> int:
    """Handler of ``optics scan``: the §7.2-7.4 scan times and the §8.2.2 objective count."""
    from sim import throughput as tp

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
        f"{geo['n_at_d_l']}  (seed: N_max = 2, d_L,max = 2.848 mm)"
    )
    if args.json is not None:
        write_json_atomic(
            args.json,
            {
                "classic": classic,
                "t_n_s": t_n,
                "t_parallel_s": t_par,
                "n_scans": tp.scans_needed(args.lens_diameter, args.w_fov),
                **geo,
            },
        )
    return 0
