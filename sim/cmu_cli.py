"""``scopetwin optics cmu``: the four-channel microscope unit (seed ch. 3-5), analysed and rendered.

``register_cmu(optics_subparsers)`` adds ``cmu`` to the ``optics`` command's sub-parsers:

    optics cmu [--setup PRESET] [--splitter-maps NAME=EXR ...] [--stop] [--json PATH] [--out DIR] [--spp N]

Prints, beside the seed: the §5.1.2 checks (perfect mirror, beam splitter 3 perpendicular and at 45°, with and
without the 4 mm stop), per channel the refocused image distance, magnification (Table 5.1), RMS spots, the
astigmatism and the wavefront PSF; the 4x4 excitation crosstalk. With ``--out`` it renders the Siemens star and
the dummy cells through each channel (Mitsuba, spectral), writes EXR files and measures magnification, resolution,
offset and tilt from the star images with :mod:`calib.channels` (Tables 5.1-5.4).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from scenes.errors import ScopetwinError

SEED_TABLE_5_1 = {"blue": 9.82, "green": 9.92, "red": 9.95, "nir": 10.0}
SEED_TABLE_5_2_UM = {"blue": 2.20, "green": 2.53, "red": 2.70, "nir": "< 1"}
SEED_TABLE_5_3_PX = {"blue": (-18, -225), "green": (35, -95), "red": (-138, -610)}
SEED_TABLE_5_4_DEG = {"blue": 0.13, "green": -0.01, "red": 0.07}
SEED_5_1_2 = {
    "mirror_magnification": 10.0,
    "bs3_perpendicular_magnification": 9.90,
    "bs3_45_rms_um": 43.499,
    "bs3_45_stop_rms_um": 8.826,
}


def register_cmu(optics_subparsers: Any) -> argparse.ArgumentParser:
    """Add ``cmu`` to the ``optics`` sub-parsers; returns its parser."""
    p = optics_subparsers.add_parser(
        "cmu", help="four-channel microscope unit (seed ch. 3-5): spots, PSF, magnification, Siemens star, crosstalk"
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
    p.add_argument("--out", type=Path, help="render star and cell images per channel into this folder")
    p.add_argument("--spp", type=int, default=16, help="samples per pixel for --out (default 16)")
    p.add_argument("--no-cells", action="store_true", help="with --out: skip the dummy-cell images")
    p.set_defaults(func=cmd_cmu)
    return p


def _maps(items: list[str]) -> dict[str, Any]:
    from scenes.io import read_heightmap

    out = {}
    for item in items:
        name, sep, path = item.partition("=")
        if not sep or not name or not path:
            raise ScopetwinError(f"--splitter-maps expects NAME=PATH.exr, got {item!r}")
        out[name] = read_heightmap(path)
    return out


def section_5_1_2(setup: Any, maps: dict[str, Any]) -> dict[str, float]:
    """The §5.1.2 Zemax checks: perfect mirror and beam splitter 3 perpendicular; beam splitter 3 at 45° (the red
    channel: 770DCXR in reflection, flat mirror) without and with the 4 mm stop."""
    from scenes.cmu.analysis import analyse, channel_optics, perpendicular_optics
    from scenes.cmu.plates import plate_heightmap

    bs3 = maps.get("770DCXR") or plate_heightmap(setup.splitters["770DCXR"], setup.plate)
    mirror = analyse(setup, perpendicular_optics(setup, None))
    perp = analyse(setup, perpendicular_optics(setup, bs3))
    r45 = analyse(setup, channel_optics(setup, "red", maps))
    r45s = analyse(setup, channel_optics(setup, "red", maps, stop=True))
    return {
        "mirror_magnification": mirror.magnification,
        "mirror_rms_um": mirror.rms_spot_um["1.0"],
        "bs3_perpendicular_magnification": perp.magnification,
        "bs3_perpendicular_rms_um": perp.rms_spot_um["1.0"],
        "bs3_45_rms_um": r45.rms_spot_um["1.0"],
        "bs3_45_stop_rms_um": r45s.rms_spot_um["1.0"],
        "stop_transmitted_fraction": r45s.transmitted_fraction,
    }


def channel_table(setup: Any, maps: dict[str, Any], stop: bool) -> dict[str, dict[str, Any]]:
    """Per channel: refocus, magnification, spots, astigmatism, wavefront PSF (axis and corner)."""
    from scenes.cmu.analysis import airy_radius_um, analyse, channel_optics, field_points, wavefront_psf

    out = {}
    for ch in setup.channels:
        opt = channel_optics(setup, ch, maps, stop=stop)
        res = analyse(setup, opt)
        psf_axis = wavefront_psf(
            opt, 0.0, 0.0, defocus=res.image_distance_mm - opt.tube.f, object_magnification=res.magnification
        )
        corner = field_points(setup)["1.0"]
        psf_edge = wavefront_psf(
            opt, *corner, defocus=res.image_distance_mm - opt.tube.f, object_magnification=res.magnification
        )
        nyquist_um = setup.camera.pixel_um / res.magnification  # half period at the pixel Nyquist limit
        out[ch] = {
            "magnification": res.magnification,
            "magnification_xy": list(res.magnification_xy),
            "rms_spot_um": {
                "axis": res.rms_spot_um["0.0"],
                "0.7": res.rms_spot_um["0.7"],
                "edge": res.rms_spot_um["1.0"],
            },
            "delta_x_um": max(psf_axis["delta_x_um"], nyquist_um),
            "delta_x_optics_um": psf_axis["delta_x_um"],
            "image_distance_mm": res.image_distance_mm,
            "astigmatism_mm": res.astigmatism_mm,
            "strehl": {"axis": psf_axis["strehl"], "edge": psf_edge["strehl"]},
            "wavefront_rms_waves": {"axis": psf_axis["wavefront_rms_waves"], "edge": psf_edge["wavefront_rms_waves"]},
            "ee80_radius_um": {"axis": psf_axis["ee80_radius_um"], "edge": psf_edge["ee80_radius_um"]},
            "airy_um": airy_radius_um(opt),
            "wavelength_nm": opt.wavelength_nm,
        }
    return out


def render_and_measure(
    setup: Any, maps: dict[str, Any], table: dict[str, Any], out: Path, spp: int, stop: bool, cells: bool
) -> dict[str, Any]:
    """Render star (and cells) per channel at its refocused distance, write EXR, measure with calib.channels."""
    from calib.channels import measure_channel, relative_pose
    from scenes.io import write_image
    from scenes.mitsuba.cmu import CameraPose, render_channel, unit_scene

    scene = unit_scene(setup, maps)
    meas, files = {}, {}
    for ch in setup.channels:
        pose = CameraPose(table[ch]["image_distance_mm"])
        t0 = time.perf_counter()
        img = render_channel(setup, ch, pose, "star", spp=spp, stop=stop, scene=scene)
        secs = time.perf_counter() - t0
        path = out / f"star_{ch}.exr"
        write_image(
            path,
            img,
            setup.to_json(),
            {"seed": "000_a2b7d38b4750eb48", "section": "§5.2.2", "spp": spp, "channel": ch},
            image_distance_mm=float(pose.image_distance),
        )
        files[f"star_{ch}"] = str(path)
        meas[ch] = measure_channel(
            img,
            setup.camera.pixel_um,
            setup.target.frame_side * 1e3,
            setup.target.star_radius * 1e3,
            setup.target.spokes,
        )
        print(f"rendered star, {ch}: {img.shape[1]}x{img.shape[0]} px, {spp} spp, {secs:.1f} s -> {path}")
        if cells:
            cimg = render_channel(setup, ch, pose, "cells", spp=spp, stop=stop, scene=scene)
            cpath = out / f"cells_{ch}.exr"
            write_image(
                cpath,
                cimg,
                setup.to_json(),
                {"seed": "000_a2b7d38b4750eb48", "section": "§5.1.2", "spp": spp, "channel": ch},
            )
            files[f"cells_{ch}"] = str(cpath)
    ref = meas.get("nir")
    result = {}
    for ch, m in meas.items():
        entry = {
            "magnification": m.magnification,
            "delta_x_um": m.delta_x_um,
            "r_min_um": m.r_min_um,
            "resolved_to_limit": m.resolved_to_limit,
            "frame_center_px": list(m.frame.center),
        }
        if ref is not None and ch != "nir":
            entry |= relative_pose(m, ref, setup.camera.pixel_um)
        result[ch] = entry
    return {"measured": result, "files": files}


def _fmt(v: Any, nd: int = 2) -> str:
    return v if isinstance(v, str) else f"{v:.{nd}f}"


def cmd_cmu(args: argparse.Namespace) -> int:
    """Handler of ``optics cmu``."""
    from scenes.cmu import spectra
    from scenes.cmu.layout import load_cmu_setup
    from scenes.io import write_json_atomic

    setup = load_cmu_setup(args.setup)
    maps = _maps(args.splitter_maps)
    unknown = set(maps) - set(setup.splitters) - set(setup.mirrors)
    if unknown:
        raise ScopetwinError(
            f"--splitter-maps: unknown element(s) {', '.join(sorted(unknown))} "
            f"(known: {', '.join([*setup.splitters, *setup.mirrors])})"
        )
    if args.spp < 1:
        raise ScopetwinError(f"--spp must be >= 1, got {args.spp}")
    s512 = section_5_1_2(setup, maps)
    print("§5.1.2 (perfect lenses f = 16.45 / 164.5 mm, 20 mm beam)        ours      seed")
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
    table = channel_table(setup, maps, args.stop)
    print("\nchannel  b (mm)   m (ours)  m (T5.1)  dx optics (µm)  dx (T5.2)  RMS axis/edge (µm)  astig (mm)  Strehl")
    for ch, r in table.items():
        print(
            f"{ch:7s} {r['image_distance_mm']:8.3f} {r['magnification']:9.3f} {SEED_TABLE_5_1[ch]:9.2f} "
            f"{r['delta_x_optics_um']:14.2f} {_fmt(SEED_TABLE_5_2_UM[ch]):>10s} "
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
        "seed": SEED_5_1_2,
        "excitation_crosstalk": x.tolist(),
        "emission_crosstalk": spectra.emission_crosstalk().tolist(),
        "channel_signal_matrix": spectra.channel_signal_matrix().tolist(),
        "crosstalk_order": list(spectra.CHANNELS),
    }
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        rm = render_and_measure(setup, maps, table, args.out, args.spp, args.stop, not args.no_cells)
        print("\nfrom the rendered Siemens-star images (calib.channels):")
        print("channel  m (img)  m (T5.1)  dx (µm)  dx (T5.2)  offset px (x, y)  T5.3 px      tilt (°)  T5.4")
        for ch, r in rm["measured"].items():
            off = (
                "reference" if ch == "nir" else f"({r.get('offset_x_px', 0.0):6.1f}, {r.get('offset_y_px', 0.0):6.1f})"
            )
            seed_off = str(SEED_TABLE_5_3_PX.get(ch, "reference"))
            print(
                f"{ch:7s} {r['magnification']:8.3f} {SEED_TABLE_5_1[ch]:9.2f} {r['delta_x_um']:8.2f} "
                f"{_fmt(SEED_TABLE_5_2_UM[ch]):>10s}  {off:17s} {seed_off:12s} "
                f"{r.get('tilt_deg', 0.0):8.3f}  {SEED_TABLE_5_4_DEG.get(ch, '-')}"
            )
        result |= rm
        for ch in table:
            table[ch]["delta_x_um"] = rm["measured"][ch]["delta_x_um"]
    if args.json is not None:
        write_json_atomic(args.json, _jsonable(result))
    return 0


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {k: _jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.generic):
        return v.item()
    return v
