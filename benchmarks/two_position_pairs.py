"""The two-position fit residual of true and of mismatched image pairs: the figure behind
:attr:`scopetwin.recon.two_positions.TwoPositionConfig.max_excess_urad`.

Run: ``.venv/bin/python benchmarks/two_position_pairs.py [--families thesis,glass] [--seeds 9100,9101,9102]
[--spp 16]`` (the default, 2 families x 3 seeds: about 3 minutes on 2 cores; ``--families cut,steep,features``
about 4 more).

Each surface (the thesis's kind, :func:`scopetwin.sim.families.thesis_spec` ``gauss+broadband``; glass-like,
:func:`scopetwin.sim.families.glass_spec`, with its 20-100 nm of micro-waviness; or any family of
:func:`scopetwin.sim.families.family_spec`) is rendered on the §1.10 setup with the pattern at its position and moved
40 mm along its normal, by Mitsuba at ``--spp`` samples per pixel with the EMVA 1288 sensor noise
(:func:`scopetwin.sim.measurement.render_measurement`, :func:`~scopetwin.sim.measurement.render_second_position`).
Each image 1 is reconstructed (:func:`scopetwin.recon.strategy.reconstruct_pair`, the pair check turned off)
with its own second image (a true pair), with the second image of the next seed of its family (a mismatched pair:
another surface of the same kind), and, for the first seed, with its own second image but a 30 mm shift given.
Printed per pair: the RMS gradient residual of the joint fit of both images' markers, the residual standard deviation
of each image's markers fitted alone, the excess the joint fit adds to it (:func:`scopetwin.recon.two_positions.
pair_excess`; µrad), the ratio of the first two, the markers of both images, the basis scale, the two-position
height's distance from the frame criterion's and its uncertainty; then the largest true-pair and the smallest
mismatched excess.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

FAMILIES = ("thesis", "glass")
SEEDS = (9100, 9101, 9102)
SHIFT_MM = 40.0
#: The shift given for a true pair in one row per family: the second image taken 40 mm away, reconstructed as 30 mm.
WRONG_SHIFT_MM = 30.0
PRESET = "thesis-1.10-deflectometry"


def spec_for(family: str, seed: int) -> dict[str, Any]:
    """The ``substrate.surface`` table of one surface."""
    from scopetwin.sim.families import family_spec, thesis_spec

    if family == "thesis":
        return thesis_spec("gauss+broadband", seed)
    return family_spec(family, seed)  # glass, cut, steep, features


def images(family: str, seed: int, spp: int) -> tuple[Any, Any, Any]:
    """The setup and both rendered images of one surface."""
    from scopetwin.scenes.setup import load_setup
    from scopetwin.sim.measurement import render_measurement, render_second_position
    from scopetwin.sim.surfaces import surface_for

    over = {"substrate": {"surface": spec_for(family, seed)}, "pattern_stage": {"shift_mm": SHIFT_MM}}
    setup = load_setup(PRESET, over)
    heights = surface_for(setup)
    image, _ = render_measurement(setup, heights, spp, seed, True)
    _, image2, _ = render_second_position(setup, heights, spp, seed, True, "mitsuba", SHIFT_MM)
    return setup, image, image2


def pair(setup: Any, image: Any, image2: Any, shift_mm: float = SHIFT_MM) -> dict[str, Any]:
    """Reconstruct one pair (the pattern shift given as ``shift_mm``) with the residual check off; its residuals and
    height."""
    from scopetwin.recon.strategy import reconstruct_pair
    from scopetwin.recon.two_positions import TwoPositionConfig
    from scopetwin.scenes.errors import ScopetwinError

    t0 = time.perf_counter()
    try:
        done = reconstruct_pair(image, image2, setup, shift_mm, tp=TwoPositionConfig(max_excess_urad=np.inf))
    except ScopetwinError as exc:
        return {"error": f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"}
    est = done.result.estimate
    return {
        "seconds": time.perf_counter() - t0,
        "residual_urad": est.residual_urad,
        "separate_urad": est.separate_urad,
        "excess_urad": est.excess_urad,
        "markers": est.markers,
        "pair_minus_frame_um": None if est.frame_um is None else est.pair_um - est.frame_um,
        "pair_std_um": est.pair_std_um,
        "sigma_mm": est.sigma_mm,
    }


def line(kind: str, family: str, seed: int, second: int, r: dict[str, Any]) -> str:
    head = f"| {kind:10s} | {family:6s} | {seed} | {second} |"
    if "error" in r:
        return f"{head} FAILED: {r['error']} |"
    dh = "—" if r["pair_minus_frame_um"] is None else f"{r['pair_minus_frame_um']:+.3f}"
    return (
        f"{head} {r['residual_urad']:8.2f} | {r['separate_urad']:.2f} | {r['excess_urad']:.2f} | "
        f"{r['residual_urad'] / r['separate_urad']:.2f} | "
        f"{r['markers'][0]} + {r['markers'][1]} | {r['sigma_mm']:g} | {dh} | {r['pair_std_um']:.3f} | "
        f"{r['seconds']:.1f} |"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--seeds", default=",".join(map(str, SEEDS)))
    ap.add_argument("--spp", type=int, default=16)
    args = ap.parse_args()
    families = args.families.split(",")
    seeds = [int(s) for s in args.seeds.split(",")]
    print(
        "| pair | family | image 1 seed | second image seed | joint residual µrad | each alone µrad | excess µrad | "
        "ratio | markers | basis mm | pair - frame µm | u µm | s |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    true_r: list[float] = []
    wrong_r: list[float] = []  # the excess, µrad
    for fam in families:
        rendered = {s: images(fam, s, args.spp) for s in seeds}
        for k, s in enumerate(seeds):
            setup, image, image2 = rendered[s]
            r = pair(setup, image, image2)
            print(line("true", fam, s, s, r), flush=True)
            if "error" not in r:
                true_r.append(r["excess_urad"])
            if k == 0:
                r = pair(setup, image, image2, WRONG_SHIFT_MM)
                print(line(f"shift {WRONG_SHIFT_MM:g}", fam, s, s, r), flush=True)
            other = seeds[(k + 1) % len(seeds)]
            if other != s:
                r = pair(setup, image, rendered[other][2])
                print(line("mismatched", fam, s, other, r), flush=True)
                if "error" not in r:
                    wrong_r.append(r["excess_urad"])
    print()
    if true_r:
        print(f"true pairs: largest excess {max(true_r):.2f} µrad ({len(true_r)} pairs)")
    if wrong_r:
        print(f"mismatched pairs: smallest excess {min(wrong_r):.2f} µrad ({len(wrong_r)} pairs)")


if __name__ == "__main__":
    main()
