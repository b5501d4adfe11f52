"""The reconstruction on bent glass it was not designed on: rendered images of the hard families, one table per family.

Run: ``.venv/bin/python benchmarks/hard_families.py [--families cut,glass] [--seeds 9100,9101] [--spp 16]
[--intersection offset]``
(the default, 4 families x 6 seeds and the dimple case: about 10 minutes on 2 cores).

Each surface of :mod:`scopetwin.sim.families` (``glass``, ``cut``, ``steep``, ``features``; seeds 9100-9105, fixed
before any tuning) is rendered on the §1.10 setup by Mitsuba at ``--spp`` samples per pixel with the EMVA sensor
noise (render and noise seed = the surface seed) and reconstructed with the defaults of :func:`scopetwin.reconstruct`,
exactly as a camera frame would be. Printed per image: the outcome (or the one-line error), seconds, the absolute
error (ROI mean) and the shape error (ROI RMS about it) in µm with each one's distance in reported standard
uncertainties, and the share of the ROI within two marker spacings of a marker (``roi_coverage``); per family:
failures, the median shape and absolute errors, how many lie within 2 u, how many absolute errors are within 1 µm
and the least ROI coverage. ``--intersection offset`` starts the rays on the plane of the fit's offset term
(:attr:`~scopetwin.recon.config.ReconstructionConfig.intersection_start`) instead of the default, the current
surface. The ``dimple`` row is :func:`scopetwin.sim.families.dimple_spec` (the §1.10 surface with a 3 mm wide,
2 µm deep dimple): the depth reconstructed at its centre, relative to a 4 mm ring around it, as a share of the true one.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import time  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

FAMILIES = ("glass", "cut", "steep", "features")
SEEDS = (9100, 9101, 9102, 9103, 9104, 9105)


def one(family: str, seed: int, spp: int, intersection: str = "surface") -> dict[str, Any]:
    """Render and reconstruct one surface; errors and uncertainties in µm."""
    import scopetwin
    from scopetwin.recon.config import ReconstructionConfig
    from scopetwin.recon.strategy import reconstruct
    from scopetwin.recon.substrate import Substrate2D
    from scopetwin.scenes.errors import ScopetwinError
    from scopetwin.sim.families import dimple_depth, dimple_spec, family_spec
    from scopetwin.sim.pipeline import roi_errors

    spec = dimple_spec() if family == "dimple" else family_spec(family, seed)
    setup = scopetwin.load_setup("thesis-1.10-deflectometry", {"substrate": {"surface": spec}})
    m = scopetwin.render(setup, spp=spp, seed=seed)
    row: dict[str, Any] = {"family": family, "seed": seed}
    t0 = time.perf_counter()
    try:
        if intersection == ReconstructionConfig().intersection_start:  # the front door's defaults
            res = scopetwin.reconstruct(m.image, setup).result
        else:
            res = reconstruct(m.image, setup, config=ReconstructionConfig(intersection_start=intersection)).result
    except ScopetwinError as exc:
        return {**row, "error": f"{type(exc).__name__}: {str(exc).splitlines()[0][:160]}"}
    row["seconds"] = time.perf_counter() - t0
    assert m.heights is not None
    row.update(roi_errors(res.surface.height, m.heights, Substrate2D.from_setup(setup)))
    assert res.uncertainty is not None
    row["u_abs_um"], row["u_shape_um"] = res.uncertainty.absolute_um, res.uncertainty.shape_um
    row["coverage"] = res.roi_coverage()
    if family == "dimple":
        row["depth_share"] = dimple_depth(res.height_at) / dimple_depth(m.heights.height)
    return row


def line(r: dict[str, Any]) -> str:
    head = f"{r['family']:9s} {r['seed']:5d}"
    if "error" in r:
        return f"{head}  FAILED  {r['error']}"
    a, s, ua, us = r["roi_absolute_um"], r["roi_shape_um"], r["u_abs_um"], r["u_shape_um"]
    text = (
        f"{head}  {r['seconds']:5.1f} s  absolute {a:+8.3f} µm ({abs(a) / ua:4.1f} u)  "
        f"shape {s:6.3f} µm ({s / us:4.1f} u)  ROI covered {100 * r['coverage']:.0f} %"
    )
    return text + (f"  dimple depth {100 * r['depth_share']:.0f} %" if "depth_share" in r else "")


def table(rows: list[dict[str, Any]]) -> str:
    out = [
        "| family | images | failed | shape median µm | |absolute| median µm | within 2 u (abs, shape) | "
        "|absolute| <= 1 µm | ROI covered (least) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for fam in dict.fromkeys(r["family"] for r in rows):
        rs = [r for r in rows if r["family"] == fam]
        ok = [r for r in rs if "error" not in r]
        if ok:
            a = np.abs([r["roi_absolute_um"] for r in ok])
            sh = np.array([r["roi_shape_um"] for r in ok])
            in_a = int(np.sum(a <= 2 * np.array([r["u_abs_um"] for r in ok])))
            in_s = int(np.sum(sh <= 2 * np.array([r["u_shape_um"] for r in ok])))
            cover = min(r["coverage"] for r in ok)
            cells = (
                f"{np.median(sh):.3f} | {np.median(a):.3f} | {in_a}, {in_s} of {len(ok)} | {int(np.sum(a <= 1))} | "
                f"{100 * cover:.0f} %"
            )
        else:
            cells = "— | — | — | 0 | —"
        out.append(f"| {fam} | {len(rs)} | {len(rs) - len(ok)} | {cells} |")
    return "\n".join(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--seeds", default=",".join(map(str, SEEDS)))
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--no-dimple", action="store_true")
    ap.add_argument(
        "--intersection",
        choices=("surface", "offset"),
        default="surface",
        help="the rays' start plane on the current surface (ReconstructionConfig.intersection_start)",
    )
    args = ap.parse_args()
    jobs = [(f, int(s)) for f in args.families.split(",") for s in args.seeds.split(",")]
    if not args.no_dimple:
        jobs.append(("dimple", 1))
    rows = []
    for fam, seed in jobs:
        rows.append(one(fam, seed, args.spp, args.intersection))
        print(line(rows[-1]), flush=True)
    print()
    print(table(rows))


if __name__ == "__main__":
    main()
