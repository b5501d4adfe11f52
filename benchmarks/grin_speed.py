"""GRIN speed benchmark (issue 7): rays/s through a rod (Dr.Jit float32 / float64, numpy float64) and image time.

Run: ``PYTHONPATH=. python benchmarks/grin_speed.py [--rays N] [--spp 64]``. Prints figures; asserts nothing.
The rod is the §8.3.2 first rod (L = 3.58 mm, GrinTech profile, 36 RKN steps of 0.1 mm); the image is the
§8.3.2 objective imaging the 25 µm grid onto a 1392 x 1040 window at 64 spp (float32 path, 0.3 mm RKN steps).
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rays", type=int, default=4_000_000)
    ap.add_argument("--numpy-rays", type=int, default=500_000)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--width", type=int, default=1392)
    ap.add_argument("--height", type=int, default=1040)
    args = ap.parse_args()

    import drjit as dr

    from scenes.grin import load_grin_setup
    from scenes.grin.analysis import analyse
    from scenes.grin.profiles import PolynomialProfile
    from scenes.grin.rkn import rkn_rod
    from scenes.grin.targets import target
    from scenes.mitsuba import grin

    prof = PolynomialProfile()
    length, steps = 3.58, 36
    rng = np.random.default_rng(1)
    n = args.rays
    x, y = rng.uniform(-0.6, 0.6, (2, n))
    tx, ty = rng.uniform(-0.2, 0.2, (2, n))
    tz = np.sqrt(prof.index(x * x + y * y) ** 2 - tx * tx - ty * ty)
    rates = {}
    for label, F in (("float32", dr.llvm.Float), ("float64", dr.llvm.Float64)):
        arrs = [F(a) for a in (x, y, tx, ty, tz)]
        dr.eval(*arrs)
        for _ in range(3):
            t0 = time.perf_counter()
            out = grin.rkn_rod_dr(*arrs, prof, length, steps, 1.0)
            dr.eval(*out)
            dr.sync_thread()
            dt = time.perf_counter() - t0
        rates[label] = n / dt
        print(f"Dr.Jit {label}: {n / dt:.3e} rays/s through the rod ({steps} steps, {dt:.3f} s for {n} rays)")
    m = args.numpy_rays
    t0 = time.perf_counter()
    rkn_rod(x[:m], y[:m], tx[:m], ty[:m], tz[:m], prof, length, steps, 1.0)
    dt = time.perf_counter() - t0
    rates["numpy"] = m / dt
    print(f"numpy float64: {m / dt:.3e} rays/s ({dt:.3f} s for {m} rays)")
    print(f"ratio Dr.Jit float32 / numpy: {rates['float32'] / rates['numpy']:.1f}x, "
          f"float64 / numpy: {rates['float64'] / rates['numpy']:.1f}x")

    setup = load_grin_setup("thesis-8.3.2-grin-realized")
    rep = analyse(setup, samples=24)
    stack = setup.stack(image_distance=rep.image_distance_mm)
    tgt = target("grid-25")
    centre = setup.array.axes()[0]
    grin.render_image(setup, stack, tgt, spp=1, width=64, height=48, center=centre)  # compile (cached kernels)
    t0 = time.perf_counter()
    img = grin.render_image(setup, stack, tgt, spp=args.spp, width=args.width, height=args.height, center=centre)
    dt = time.perf_counter() - t0
    paths = args.width * args.height * args.spp
    print(f"image {args.width}x{args.height} at {args.spp} spp: {dt:.2f} s "
          f"({paths / dt:.3e} paths/s, mean {img.mean():.4g})")


if __name__ == "__main__":
    main()
