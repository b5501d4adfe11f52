"""A rig's next frames with the first frame's scale and prior held (``scopetwin.reconstruct(previous=, hold=True)``)
against the same frames searched from them (``previous=`` alone): accuracy, calibration and time.

Run: ``.venv/bin/python benchmarks/held_prior.py [--seeds 1 2] [--frames 4]`` (about 3 minutes on one core).

Truth from elsewhere: for each family of ``scopetwin study coverage`` (:data:`scopetwin.sim.studies.coverage.
FAMILIES`: §1.9 Gaussian, with broadband content, PSD, glass-like, cut, steep and locally featured sheets) and each
seed, one surface on the §1.10 setup, its exact marker-centre images (:func:`scopetwin.sim.truth.marker_truth`) plus
independent Gaussian centroid noise of 0.005 px per frame (noise seeds fixed before any run: [seed, frame, 97]). The
first frame is reconstructed alone; each later frame twice, from the first's result: its scale and prior as starts
(``Reconstructor.evidence_start``, the scale re-chosen) and held (``Reconstructor.held_prior``, no scale choice).
Printed per family: the share of frames whose absolute height error lies within 2 u (u: the frame's own reported
standard uncertainty) and whose shape error lies within 2 u_shape, for both; how often the held prior was read as it
is; the median seconds of a frame. Nothing here passes or fails.
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any

import numpy as np

from scopetwin.recon.config import ReconstructionConfig
from scopetwin.recon.policy import DEFAULT_POLICY
from scopetwin.recon.posterior import prior_from_dict
from scopetwin.recon.reconstruct import MarkerObservations, Reconstructor, single_thread_blas
from scopetwin.recon.strategy import solve
from scopetwin.recon.substrate import Substrate2D
from scopetwin.recon.uncertainty import HeldPrior
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.setup import load_setup
from scopetwin.sim.families import family_spec
from scopetwin.sim.pipeline import roi_errors
from scopetwin.sim.studies.coverage import FAMILIES
from scopetwin.sim.surfaces import surface_for
from scopetwin.sim.truth import marker_truth

NOISE_PX = 0.005


def _frame(truth: Any, seed: int, frame: int) -> MarkerObservations:
    vis = truth.visible
    rng = np.random.default_rng([seed, frame, 97])
    return MarkerObservations(truth.ij[vis], truth.center_px[vis] + NOISE_PX * rng.standard_normal((int(vis.sum()), 2)))


def _solve(setup: Any, obs: MarkerObservations, scale: float | None, held: HeldPrior | None, hold: bool) -> tuple:
    rec = Reconstructor.from_setup(setup, ReconstructionConfig().starting_at(scale))
    rec.evidence_start, rec.held_prior = (held.hyper if held else None), (held if hold else None)
    policy = DEFAULT_POLICY.with_changes(rechoose_scale=False) if hold else DEFAULT_POLICY
    t0 = time.perf_counter()
    with single_thread_blas():
        res = solve(rec, obs, policy)
    return res, time.perf_counter() - t0


def surface_rows(family: str, seed: int, frames: int) -> list[dict[str, Any]]:
    """The later frames of one surface, each searched from and held from the first frame's result."""
    setup = load_setup("thesis-1.10-deflectometry", {"substrate": {"surface": family_spec(family, seed)}})
    heights = surface_for(setup)
    truth = marker_truth(setup, heights)
    sub = Substrate2D.from_setup(setup)
    try:
        first, _ = _solve(setup, _frame(truth, seed, 0), None, None, False)
    except ScopetwinError as exc:
        print(f"  {family} seed {seed}: the first frame failed ({type(exc).__name__})", flush=True)
        return []
    if first.uncertainty is None:
        return []
    u = first.uncertainty
    prior, scale = HeldPrior(prior_from_dict(u.hyper), u.prior_z), float(first.surface.basis.sigma[0])
    rows = []
    for k in range(1, frames):
        obs = _frame(truth, seed, k)
        for hold in (False, True):
            row: dict[str, Any] = {"family": family, "seed": seed, "frame": k, "hold": hold}
            try:
                res, seconds = _solve(setup, obs, scale, prior, hold)
            except ScopetwinError as exc:
                rows.append({**row, "error": type(exc).__name__})
                continue
            u = res.uncertainty
            e = roi_errors(res.surface.height, heights, sub)
            rows.append(
                {
                    **row,
                    "seconds": seconds,
                    "abs_ok": u is not None and abs(e["roi_absolute_um"]) <= 2 * u.absolute_um,
                    "shape_ok": u is not None and e["roi_shape_um"] <= 2 * u.shape_um,
                    "held": any(s.startswith("prior held") for s in res.strategy),
                }
            )
    return rows


def _share(rows: list[dict[str, Any]], key: str) -> str:
    good = [r for r in rows if "error" not in r]
    return f"{100.0 * sum(r[key] for r in good) / len(good):5.1f}" if good else "    —"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--frames", type=int, default=4, help="frames per surface, the first included")
    ap.add_argument("--families", nargs="+", choices=FAMILIES, default=list(FAMILIES))
    args = ap.parse_args()
    rows = []
    for family in args.families:
        for seed in args.seeds:
            rows += surface_rows(family, seed, args.frames)
    print(
        f"{'family':18s} {'frames':>6s} | searched: {'abs 2u %':>8s} {'shape 2u %':>10s} {'s':>6s} | held: "
        f"{'abs 2u %':>8s} {'shape 2u %':>10s} {'s':>6s} {'as is %':>7s} {'failed':>6s}"
    )
    for family in [*args.families, "all"]:
        mine = [r for r in rows if family == "all" or r["family"] == family]
        cols = []
        for hold in (False, True):
            part = [r for r in mine if r["hold"] is hold]
            secs = [r["seconds"] for r in part if "error" not in r]
            med = f"{statistics.median(secs):6.3f}" if secs else "     —"
            cols.append((part, f"{_share(part, 'abs_ok'):>8s} {_share(part, 'shape_ok'):>10s} {med}"))
        held = cols[1][0]
        failed = sum("error" in r for r in held)
        print(
            f"{family:18s} {len(cols[0][0]):6d} | searched: {cols[0][1]} | held: {cols[1][1]} "
            f"{_share(held, 'held'):>7s} {failed:6d}"
        )


if __name__ == "__main__":
    main()
