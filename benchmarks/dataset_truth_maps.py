"""What the per-pixel truth maps cost, and what reading a dataset costs.

1. Samples per minute on one core (in this process, one Dr.Jit thread) of ``examples/datasets/01-deflectometry-
   small.toml`` with and without the truth maps (``[dataset] maps``), in one run: the two configs alternate sample
   by sample (after a warm-up sample each: imports, Dr.Jit kernel compilation), so a load that changes during the
   run weighs on both alike. Beside it, the maps' own time per sample (trace + EXR write, the minimum of 3 runs each,
   wall and CPU) against the render's, and as a share of the median sample without maps: a figure the load moves
   less than the alternating totals. Target: the maps cost <= 15 % of a sample's time.
   Beside them, every lossless compression OpenEXR offers for the maps of that sample: write and decode time
   (minimum of 3) and size (``maps_compression`` chooses between Zstandard, the default, and ZIP).
2. Reader throughput: ``scopetwin.open_dataset`` reading every sample's image and maps (``.image``, ``.maps``)
   beside the raw reads of the same files (their bytes; and OpenEXR's own decode of every channel).

    PYTHONPATH=. python benchmarks/dataset_truth_maps.py [--samples 4] [--config CFG] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from scopetwin.sim.datasets.config import config_from_dict
from scopetwin.sim.datasets.plan import Plan
from scopetwin.sim.datasets.store import CONFIG_FILE, SAMPLES, generate_sample

ROOT = Path(__file__).resolve().parents[1]


def _plan(config: Path, maps: bool, count: int) -> Plan:
    import tomllib

    data = tomllib.loads(config.read_text())
    data["dataset"]["maps"] = maps
    data["dataset"]["count"] = count
    return Plan.build(config_from_dict(data, str(config), config.resolve().parent))


def _generation(config: Path, samples: int, scratch: Path) -> dict[str, float]:
    plans = {flag: _plan(config, flag, samples + 1) for flag in (False, True)}
    roots = {}
    for flag, plan in plans.items():
        roots[flag] = scratch / ("maps" if flag else "plain")
        (roots[flag] / SAMPLES).mkdir(parents=True)
        (roots[flag] / CONFIG_FILE).write_text(json.dumps(plan.to_json()))  # a dataset folder the reader opens
        generate_sample(plan.to_json(), samples, str(roots[flag]), 1)  # warm-up (not counted)
    seconds: dict[bool, list[float]] = {False: [], True: []}
    for i in range(samples):
        for flag in (False, True) if i % 2 == 0 else (True, False):
            t0 = time.perf_counter()
            generate_sample(plans[flag].to_json(), i, str(roots[flag]), 1)
            seconds[flag].append(time.perf_counter() - t0)
    plain, with_maps = sum(seconds[False]), sum(seconds[True])
    return {
        "samples": samples,
        "plain_samples_per_min": 60.0 * samples / plain,
        "maps_samples_per_min": 60.0 * samples / with_maps,
        "maps_cost_percent": 100.0 * (with_maps - plain) / plain,
        "plain_median_s": statistics.median(seconds[False]),
        "maps_median_s": statistics.median(seconds[True]),
        "root": str(roots[True]),
    }


def _maps_alone(config: Path, repeats: int = 3) -> dict[str, float]:
    """The maps' own time on one sample (trace, EXR write) beside the render of the same sample: the minimum of
    ``repeats`` runs each (warm), wall and CPU seconds."""
    from scopetwin.sim.datasets.maps import part1_maps, write_maps
    from scopetwin.sim.measurement import render_measurement
    from scopetwin.sim.surfaces import surface_for

    plan = _plan(config, True, 1)
    setup = plan.setup_of(0)
    heights = surface_for(setup)
    steps = {
        "render": lambda: render_measurement(setup, heights, setup.render.spp, 0, setup.render.noise),
        "maps_trace": lambda: part1_maps(setup, heights),
    }
    maps = part1_maps(setup, heights)
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        compression = plan.config.dataset.maps_compression
        steps["maps_write"] = lambda: write_maps(Path(tmp) / "maps.exr", maps, compression)
        for name, step in steps.items():
            step()  # warm-up
            wall, cpu = [], []
            for _ in range(repeats):
                t0, c0 = time.perf_counter(), time.process_time()
                step()
                wall.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
            out[f"{name}_s"], out[f"{name}_cpu_s"] = min(wall), min(cpu)
    return out


def _compressions(config: Path, repeats: int = 3) -> dict[str, dict[str, float]]:
    """Each lossless OpenEXR compression on one sample's maps (the channels :func:`write_maps` writes): write and
    decode seconds (minimum of ``repeats``), megabytes."""
    import OpenEXR

    from scopetwin.sim.datasets.maps import part1_maps
    from scopetwin.sim.surfaces import surface_for

    setup = _plan(config, True, 1).setup_of(0)
    chans: dict[str, object] = {}
    for name, arr in part1_maps(setup, surface_for(setup)).items():
        parts = [arr[..., k] for k in range(arr.shape[2])] if arr.ndim == 3 else [arr]
        for k, part in enumerate(parts):
            chans[f"{name}.{k}"] = np.ascontiguousarray(part, dtype=np.float32)
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / "maps.exr")
        for name in ("ZSTD", "ZIP", "ZIPS", "RLE", "PIZ", "HTJ2K32", "HTJ2K256", "NO"):
            header = {"compression": getattr(OpenEXR, f"{name}_COMPRESSION"), "type": OpenEXR.scanlineimage}
            write, read = [], []
            for _ in range(repeats):
                t0 = time.perf_counter()
                OpenEXR.File(header, dict(chans)).write(path)  # a copy: the binding replaces the dict's arrays
                write.append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                for chan in OpenEXR.File(path, separate_channels=True).channels().values():
                    _ = chan.pixels
                read.append(time.perf_counter() - t0)
            out[name] = {"write_s": min(write), "decode_s": min(read), "megabytes": Path(path).stat().st_size / 1e6}
    return out


def _reading(root: Path) -> dict[str, float]:
    import OpenEXR

    import scopetwin

    ds = scopetwin.open_dataset(root)
    files = [s.folder / name for s in ds for name in ("image.exr", "maps.exr")]
    nbytes = sum(f.stat().st_size for f in files)
    t0 = time.perf_counter()
    for f in files:
        f.read_bytes()
    raw = time.perf_counter() - t0
    t0 = time.perf_counter()
    for f in files:
        exr = OpenEXR.File(str(f), separate_channels=True)
        for chan in exr.channels().values():
            _ = chan.pixels
    decode = time.perf_counter() - t0
    t0 = time.perf_counter()
    for sample in scopetwin.open_dataset(root):  # a fresh reader: nothing cached
        _ = sample.image, sample.maps
    reader = time.perf_counter() - t0
    n = len(ds)
    return {
        "samples": n,
        "megabytes": nbytes / 1e6,
        "raw_read_samples_per_s": n / raw,
        "exr_decode_samples_per_s": n / decode,
        "reader_samples_per_s": n / reader,
        "reader_mb_per_s": nbytes / 1e6 / reader,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "examples" / "datasets" / "01-deflectometry-small.toml"))
    ap.add_argument("--samples", type=int, default=4)
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args()
    scratch = Path(tempfile.mkdtemp(prefix="scopetwin-maps-bench-"))
    try:
        gen = _generation(Path(args.config), args.samples, scratch)
        print(f"config {args.config}, {gen['samples']} samples each, one core, alternating")
        print(
            f"  without maps  {gen['plain_samples_per_min']:6.1f} samples/min  (median {gen['plain_median_s']:.2f} s)\n"
            f"  with maps     {gen['maps_samples_per_min']:6.1f} samples/min  (median {gen['maps_median_s']:.2f} s)\n"
            f"  maps cost     {gen['maps_cost_percent']:+5.1f} % of a sample's time (target <= 15 %)",
            flush=True,
        )
        alone = _maps_alone(Path(args.config))
        own = alone["maps_trace_s"] + alone["maps_write_s"]
        print(
            f"  one sample (minimum of 3, wall / CPU): render {alone['render_s']:.2f} / {alone['render_cpu_s']:.2f} s, "
            f"maps trace {alone['maps_trace_s']:.3f} / {alone['maps_trace_cpu_s']:.3f} s, "
            f"maps EXR write {alone['maps_write_s']:.3f} / {alone['maps_write_cpu_s']:.3f} s: "
            f"{100 * own / gen['plain_median_s']:.1f} % of the median sample without maps",
            flush=True,
        )
        comp = _compressions(Path(args.config))
        print("  maps.exr compressions (lossless; write / decode, minimum of 3):", flush=True)
        for name, c in comp.items():
            print(f"    {name:9s} {1e3 * c['write_s']:6.1f} / {1e3 * c['decode_s']:5.1f} ms  {c['megabytes']:5.2f} MB")
        read = _reading(Path(gen.pop("root")))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    print(
        f"reading {read['samples']} samples ({read['megabytes']:.1f} MB of image.exr + maps.exr):\n"
        f"  raw file reads    {read['raw_read_samples_per_s']:8.1f} samples/s\n"
        f"  OpenEXR decode    {read['exr_decode_samples_per_s']:8.1f} samples/s\n"
        f"  open_dataset      {read['reader_samples_per_s']:8.1f} samples/s ({read['reader_mb_per_s']:.0f} MB/s)"
    )
    if args.json:
        Path(args.json).write_text(
            json.dumps({"generation": gen, "one_sample": alone, "compressions": comp, "reading": read}, indent=2)
        )


if __name__ == "__main__":
    main()
