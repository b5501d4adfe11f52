"""Fringe render of the §1.10 setup: seconds per frame and the per-pixel phase noise of the rendered sequence.

Renders the ``thesis-1.10-fringes`` preset (1360 x 1024 px, the preset's 40 µm surface, 24 frames: 4 steps of
64, 8 and 1 mm fringes in x and y) with :func:`scopetwin.sim.fringes.render_fringes`, twice (the first compiles the
kernels), and prints the seconds of each frame of the second run and their median. Then decodes every period and
direction with the textbook 4-step formula and prints the phase error against the numpy truth ``pattern_xy``
(2 pi u / period, :func:`scopetwin.sim.datasets.maps.part1_maps`) on the pixels that see the display through the
ROI, 2 px from its edges: RMS, mean and 99.9th percentile (rad), and the RMS as display mm.
Prints figures only; nothing here passes or fails.

Usage: ``PYTHONPATH=. python benchmarks/fringe_render.py [--spp 16] [--seed 3] [--no-noise]``
"""

from __future__ import annotations

import argparse

import numpy as np
from scipy import ndimage

from scopetwin.scenes.setup import load_setup
from scopetwin.sim.datasets.maps import part1_maps
from scopetwin.sim.fringes import render_fringes
from scopetwin.sim.surfaces import surface_for


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spp", type=int, default=16)
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--no-noise", action="store_true", help="no sensor model")
    args = parser.parse_args()
    setup = load_setup("thesis-1.10-fringes")
    heights = surface_for(setup)
    render_fringes(setup, heights, spp=args.spp, seed=args.seed, noise=not args.no_noise)  # warm-up
    m = render_fringes(setup, heights, spp=args.spp, seed=args.seed, noise=not args.no_noise)
    sec = np.array(m.seconds_per_frame)
    print(f"{len(sec)} frames at {args.spp} spp, noise {'off' if args.no_noise else 'on'}")
    print(f"seconds per frame: median {np.median(sec):.3f}, min {sec.min():.3f}, max {sec.max():.3f}")
    maps = part1_maps(setup, heights)
    xy = maps["pattern_xy"].astype(np.float64)
    seen = maps["mask"] & maps["roi"] & np.isfinite(xy).all(axis=-1)
    interior = ndimage.binary_erosion(seen, np.ones((5, 5)))
    seq = m.sequence
    shifts = seq.shifts()
    print(f"{int(interior.sum())} pixels; phase error against 2 pi u / period at pattern_xy:")
    for axis, direction in enumerate("xy"):
        for p, period in enumerate(seq.periods_mm):
            stack = np.stack([m.images[seq.index(direction, p, k)] for k in range(seq.steps)]).astype(np.float64)
            phase = np.arctan2(-np.tensordot(np.sin(shifts), stack, 1), np.tensordot(np.cos(shifts), stack, 1))
            err = np.angle(np.exp(1j * (phase - 2 * np.pi * xy[..., axis] / period)))[interior]
            top, um = np.percentile(np.abs(err), 99.9), err.std() * period / (2 * np.pi) * 1e3
            print(
                f"  {direction} {period:5g} mm: RMS {err.std():.4f} rad, mean {err.mean():+.5f}, "
                f"99.9 % {top:.4f} rad; RMS {um:.2f} µm"
            )


if __name__ == "__main__":
    main()
