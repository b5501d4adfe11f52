"""The posterior's evidence search against the evidence's maximum itself (speed not bought with accuracy).

Run: ``.venv/bin/python benchmarks/evidence_search.py [--only psd]`` (about 4 minutes on 2 cores).

The prior of every reconstruction's uncertainty is chosen by maximum evidence (:func:`scopetwin.recon.posterior.
fit_hyper`). L-BFGS-B stops short of that maximum along its flat directions, so the search a reconstruction uses is
compared here with the maximum found by the same search run to ``ftol`` 1e-12 and 400 iterations, on 17 surfaces
none of its settings were chosen on: the six PSD surfaces of the accuracy tests, the glass-like hash family of
``tests/recon/test_accuracy_glass.py`` and four §1.9 surfaces (seeds 21-24); exact marker images
(:func:`scopetwin.sim.truth.marker_truth`) plus 0.01 px (glass: 0.005 px) of centroid noise with fixed seeds. Printed
per surface and search: the absolute height's distance from the maximum's in units of its standard uncertainty,
the shape uncertainty relative to the maximum's, and the seconds of the evidence search, beside the maximum's own
(the same-run reference). Searches: ``default`` (the configuration's: coarse to fine, ``evidence_coarse_points``) and
``full`` (both starts on all ``evidence_points``, the search before it).
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import hashlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

import scopetwin.recon.posterior as posterior  # noqa: E402
from scopetwin.recon.config import ReconstructionConfig  # noqa: E402
from scopetwin.recon.reconstruct import MarkerObservations, Reconstructor  # noqa: E402
from scopetwin.recon.strategy import solve  # noqa: E402
from scopetwin.recon.substrate import Substrate2D  # noqa: E402
from scopetwin.scenes.errors import ScopetwinError  # noqa: E402
from scopetwin.scenes.setup import load_setup  # noqa: E402
from scopetwin.sim.families import glass_spec  # noqa: E402
from scopetwin.sim.pipeline import roi_errors  # noqa: E402
from scopetwin.sim.surfaces import surface_for  # noqa: E402
from scopetwin.sim.truth import marker_truth  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "recon"))
from psd_cases import PSD_CASES, psd_surface  # noqa: E402

PRESET = "thesis-1.10-deflectometry"
GLASS_SEEDS = tuple(
    int.from_bytes(hashlib.sha256(f"scopetwin glass-like {k}".encode()).digest()[:4], "little") for k in range(8)
)


def cases(only: str | None) -> list[tuple[str, Any, Any, float]]:
    """(name, setup, true heights, centroid noise px) of the family."""
    base = load_setup(PRESET)
    out: list[tuple[str, Any, Any, float]] = []
    if only in (None, "psd"):
        out += [(f"psd{c[-1]}", base, psd_surface(base, c), 0.01) for c in PSD_CASES]
    if only in (None, "glass"):
        for s in GLASS_SEEDS:
            setup = load_setup(PRESET, {"substrate": {"surface": glass_spec(s)}})
            out.append((f"glass{s}", setup, surface_for(setup), 0.005))
    if only in (None, "seed"):
        for s in (21, 22, 23, 24):
            setup = load_setup(PRESET, {"substrate": {"surface": {"seed": s}}})
            out.append((f"seed{s}", setup, surface_for(setup), 0.01))
    return out


def run(setup: Any, heights: Any, obs: MarkerObservations, config: ReconstructionConfig) -> dict[str, float] | str:
    """One solve: absolute error, uncertainties (µm) and the evidence search's seconds; the error's name if none."""
    spent: list[float] = []
    inner = posterior.fit_hyper

    def timed(*args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            spent.append(time.perf_counter() - t0)

    posterior.fit_hyper = timed  # type: ignore[assignment]
    try:
        res = solve(Reconstructor.from_setup(setup, config), obs)
    except ScopetwinError as exc:
        return type(exc).__name__
    finally:
        posterior.fit_hyper = inner  # type: ignore[assignment]
    assert res.uncertainty is not None
    e = roi_errors(res.surface.height, heights, Substrate2D.from_setup(setup))
    u = res.uncertainty
    return {"abs": e["roi_absolute_um"], "ua": u.absolute_um, "us": u.shape_um, "s": sum(spent)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", choices=["psd", "glass", "seed"], help="one kind of surface")
    args = ap.parse_args()
    default = ReconstructionConfig(prior="process")  # the Gaussian process's search, which these settings tune
    searches = {"default": default, "full": replace(default, evidence_coarse_points=0)}
    print(
        f"{'surface':17s} {'max: abs µm':>11s} {'u':>6s} {'s':>5s}   "
        + "   ".join(f"{k}: d/u  us/us*   s" for k in searches)
    )
    worst = dict.fromkeys(searches, 0.0)
    seconds = dict.fromkeys([*searches, "max"], 0.0)
    for name, setup, heights, noise in cases(args.only):
        truth = marker_truth(setup, heights)
        vis = truth.visible
        rng = np.random.default_rng([int.from_bytes(hashlib.sha256(name.encode()).digest()[:4], "little"), 7])
        obs = MarkerObservations(truth.ij[vis], truth.center_px[vis] + noise * rng.standard_normal((int(vis.sum()), 2)))
        saved = posterior.FTOL, posterior.MAXITER
        posterior.FTOL, posterior.MAXITER = 1e-12, 400
        try:
            best = run(setup, heights, obs, replace(default, evidence_coarse_points=0))
        finally:
            posterior.FTOL, posterior.MAXITER = saved
        if isinstance(best, str):
            print(f"{name:17s} {best}")
            continue
        seconds["max"] += best["s"]
        line = f"{name:17s} {best['abs']:+11.3f} {best['ua']:6.3f} {best['s']:5.2f}"
        for key, cfg in searches.items():
            r = run(setup, heights, obs, cfg)
            if isinstance(r, str):
                line += f"   {key}: {r}"
                continue
            d = (r["abs"] - best["abs"]) / best["ua"]
            worst[key] = max(worst[key], abs(d))
            seconds[key] += r["s"]
            line += f"   {key}: {d:+5.2f}  {r['us'] / best['us']:6.2f} {r['s']:5.2f}"
        print(line, flush=True)
    print(
        "worst |d|/u: "
        + ", ".join(f"{k} {v:.2f}" for k, v in worst.items())
        + "; evidence seconds in all: "
        + ", ".join(f"{k} {v:.1f}" for k, v in seconds.items())
    )


if __name__ == "__main__":
    main()
