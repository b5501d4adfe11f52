"""Benchmark: the four-channel unit (thesis ch. 5) - analyses, full-frame spectral renders, Siemens-star tables.

Run: PYTHONPATH=. python benchmarks/cmu_channels.py [--spp 16] [--out /tmp/cmu]
Prints ours beside the thesis (§5.1.2, Tables 5.1-5.4), render times and the 4x4 crosstalk, and a sensitivity of
the 45° spot to the two readings the thesis leaves open (the bow's range definition, the beam diameter).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--out", type=Path, default=Path("/tmp/cmu_bench"))
    args = ap.parse_args()
    from scopetwin.cli import main as scopetwin
    from scopetwin.scenes.cmu.analysis import analyse, channel_optics
    from scopetwin.scenes.cmu.layout import load_cmu_setup

    t0 = time.perf_counter()
    scopetwin(["optics", "cmu", "--json", str(args.out / "cmu.json"), "--out", str(args.out), "--spp", str(args.spp)])
    print(
        f"\noptics cmu with renders ({args.spp} spp, 1392x1040 px, 4 channels x star + cells): "
        f"{time.perf_counter() - t0:.1f} s"
    )
    s = load_cmu_setup()
    print("\nsensitivity of the 45° RMS spot at the outer bound (red channel, beam splitter 3):")
    for label, over in (
        ("preset (20 mm beam, range over the whole plate)", {}),
        ("beam 14.81 mm (2 f NA, NA 0.45)", {"objective": {"beam_diameter": 2 * 16.45 * 0.45}}),
        (
            "range read over a 25.5 mm circle",
            {"splitters": {"770DCXR": {"bow_range_um": 10.2 * ((12.75**2 + 18**2) / 12.75**2)}}},
        ),
    ):
        ss = load_cmu_setup("thesis-cmu", over)
        r = analyse(ss, channel_optics(ss, "red"))
        rs = analyse(ss, channel_optics(ss, "red", stop=True))
        print(
            f"  {label:50s} {r.rms_spot_um['1.0']:7.2f} µm, with stop {rs.rms_spot_um['1.0']:6.2f} µm "
            f"(seed 43.499 / 8.826), m {r.magnification:.3f}"
        )
    t1 = time.perf_counter()
    for _ in range(3):
        analyse(s, channel_optics(s, "blue"))
    print(f"\nnumpy analysis of one channel: {(time.perf_counter() - t1) / 3:.2f} s")
    _ = np


if __name__ == "__main__":
    main()
