"""Dataset throughput: deflectometry samples per minute with 1 and 2 local Dask workers, and the
parallel efficiency rate(2) / (2 rate(1)).

Uses the first example config (``examples/datasets/01-deflectometry-small.toml``: the §1.10 setup at half the
thesis's sensor resolution, noise on) unless ``--config`` names another. Each worker is warmed up first (imports,
Dr.Jit kernel compilation) on a throw-away sample, so the figures are steady-state rates; the cluster start-up time
is printed separately. Target: efficiency >= 85 %.

    PYTHONPATH=. python benchmarks/dataset_throughput.py [--samples 8] [--config CFG] [--workers 1 2]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

from scopetwin.sim.datasets.config import load_config
from scopetwin.sim.datasets.plan import Plan
from scopetwin.sim.datasets.runner import dask_client
from scopetwin.sim.datasets.store import generate, generate_sample

ROOT = Path(__file__).resolve().parents[1]


def rate(plan: Plan, n_workers: int, samples: int, scratch: Path) -> tuple[float, float]:
    """Steady-state samples per minute on ``n_workers`` local workers, and the cluster start-up seconds."""
    t0 = time.perf_counter()
    with dask_client(None, n_workers) as client:
        client.wait_for_workers(n_workers)
        startup = time.perf_counter() - t0
        warm = scratch / f"warm-{n_workers}"
        workers = list(client.scheduler_info()["workers"])
        futs = [
            client.submit(generate_sample, plan.to_json(), 10_000 + k, str(warm), 1, workers=[w], pure=False)
            for k, w in enumerate(workers)
        ]
        client.gather(futs)
        out = scratch / f"run-{n_workers}"
        t1 = time.perf_counter()
        generate(plan, out, threads=1, indices=range(samples), progress=False, client=client)
        seconds = time.perf_counter() - t1
    return 60.0 * samples / seconds, startup


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "examples" / "datasets" / "01-deflectometry-small.toml"))
    ap.add_argument("--samples", type=int, default=8, help="samples per measurement")
    ap.add_argument("--workers", type=int, nargs="*", default=[1, 2])
    args = ap.parse_args()
    cfg = load_config(args.config, count=max(args.samples, 10_000 + max(args.workers)))
    plan = Plan.build(cfg, indices=range(args.samples))
    scratch = Path(tempfile.mkdtemp(prefix="scopetwin-throughput-"))
    try:
        rates = {}
        for n in args.workers:
            r, startup = rate(plan, n, args.samples, scratch)
            rates[n] = r
            print(
                f"{n} worker(s): {r:6.2f} samples/min ({60.0 / r * n:.2f} s per sample per worker; "
                f"cluster start-up {startup:.1f} s)",
                flush=True,
            )
        if 1 in rates:
            for n, r in rates.items():
                if n > 1:
                    print(f"parallel efficiency with {n} workers: {100.0 * r / (n * rates[1]):.1f} % (target >= 85 %)")
    finally:
        shutil.rmtree(scratch, ignore_errors=True)


if __name__ == "__main__":
    main()
