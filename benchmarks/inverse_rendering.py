"""Inverse rendering vs the centroid method: shape and absolute error against Gauss-Newton steps and time.

For each case (a §1.9 surface) the §1.10 measurement is rendered with Mitsuba, reconstructed by the centroid
method and by inverse rendering started from it (``sim.studies.inverse.inverse_task``, the task of
``scopetwin study inverse``); every Gauss-Newton step's surface is compared with the truth. Beside them: the
Cramér-Rao bound of the pixel data on the shape (Fisher information J^T W J of the render with EMVA 1288 pixel
variances), the Bayesian (Van Trees) bound under the surface family's prior, and the B-spline's own
representation error of the true surface.

Run: ``.venv/bin/python benchmarks/inverse_rendering.py [--cases 12:40,5:40,3:60] [--kind random|psd] [--noise]
[--spp 16] [--config '{"levels": [[1, 4]]}'] [--json PATH]`` (one surface per case; minutes each on 2 cores).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    from scopetwin.sim.studies.inverse import inverse_task

    ap = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    ap.add_argument("--cases", default="12:40,5:40,3:60", help="correlation_mm:range_um,...")
    ap.add_argument("--kind", default="random", help="surface kind (random: §1.9 Gaussian; psd where available)")
    ap.add_argument("--seed", type=int, default=2)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--noise", action="store_true", help="apply the EMVA 1288 sensor model")
    ap.add_argument("--config", default="{}", help="InverseConfig fields as JSON")
    ap.add_argument("--json", help="write the rows here")
    args = ap.parse_args()
    rows = []
    print(
        "corr mm  range µm  centroid shape / abs µm  inverse shape / abs µm  CRB shape µm  Bayes bound µm"
        "  spline µm  inverse s  tilt removed: centroid / inverse µm"
    )
    for case in args.cases.split(","):
        corr, rng = (float(v) for v in case.split(":"))
        r = inverse_task(args.kind, corr, rng, args.seed, args.noise, args.spp, json.loads(args.config))
        rows.append(r)
        nan = float("nan")
        print(
            f"{corr:7.1f}  {rng:7.1f}  {r.get('centroid_shape_um', nan):10.4f} / {r.get('centroid_abs_um', nan):+.4f}"
            f"  {r.get('inverse_shape_um', nan):10.4f} / {r.get('inverse_abs_um', nan):+.4f}"
            f"  {r.get('crb_shape_um', nan):12.5f}  {r.get('bayes_bound_um', nan):14.5f}"
            f"  {r.get('spline_shape_um', nan):9.5f}"
            f"  {r.get('inverse_s', nan):9.1f}  u_shape {r.get('inverse_std_um', nan):.4f}"
            f"  {r.get('centroid_untilted_um', nan):.4f} / {r.get('inverse_untilted_um', nan):.4f}",
            flush=True,
        )
        for k in ("centroid_error", "inverse_error"):
            if k in r:
                print(f"    {k}: {r[k]}")
        for s in r.get("steps", []):
            print(
                f"    level {s['level']} step at {s['seconds']:7.1f} s: chi2/px {s['chi2']:.4g}, "
                f"shape {s['shape_um']:.4f} µm, absolute {s['abs_um']:+.4f} µm"
            )
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
