"""GRIN speed benchmark (issue 7): rays/s through a rod (Dr.Jit float32 / float64, numpy float64) and image time.

Run: ``PYTHONPATH=. python benchmarks/grin_speed.py [--rays N] [--spp 64] [--repeat 5]``. Prints figures; asserts
nothing. The rod is the §8.3.2 first rod (L = 3.58 mm, GrinTech profile, 36 RKN steps of 0.1 mm); the image is the
§8.3.2 objective imaging the 25 µm grid onto a 1392 x 1040 window at 64 spp (float32 path, 4 RKN steps per rod).

The machine may be shared, so every rate is given as best and median of ``--repeat`` runs, next to a reference
kernel measured in the same loop (a ``dr.while_loop`` of 36 iterations doing as many float32 FMAs per ray as one
RKN step has operations, in 8 independent chains, i.e. throughput-bound): the ratio rod/reference moves much less
with the load than the rates. For the image, the time without the rods' RKN loops (straight lines instead: Mitsuba's
intersections, the pupil sensor, the film) is printed beside the full time.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np

#: Arithmetic operations in one RKN step (:func:`scopetwin.scenes.grin.rkn.rkn_step`, the one numpy and Dr.Jit run)
#: with the polynomial profile
#: (counted from the formulas: 2 profile evaluations of 9, 3 r² of 3, the updates and the OPL).
OPS_PER_STEP = 96


def _timed(fn: Callable[[], Any], sync: Callable[[], None]) -> float:
    t0 = time.perf_counter()
    fn()
    sync()
    return time.perf_counter() - t0


def _stats(n: float, ts: list[float]) -> tuple[float, float]:
    return n / min(ts), n / statistics.median(ts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rays", type=int, default=4_000_000)
    ap.add_argument("--numpy-rays", type=int, default=500_000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--width", type=int, default=1392)
    ap.add_argument("--height", type=int, default=1040)
    ap.add_argument("--image-repeat", type=int, default=2)
    ap.add_argument("--no-image", action="store_true")
    args = ap.parse_args()

    import drjit as dr

    from scopetwin.scenes.grin import load_grin_setup
    from scopetwin.scenes.grin.analysis import analyse
    from scopetwin.scenes.grin.profiles import PolynomialProfile
    from scopetwin.scenes.grin.rkn import rkn_rod
    from scopetwin.scenes.grin.targets import target
    from scopetwin.scenes.mitsuba import grin

    prof = PolynomialProfile()
    length, steps = 3.58, 36
    rng = np.random.default_rng(1)
    n = args.rays
    x, y = rng.uniform(-0.6, 0.6, (2, n))
    tx, ty = rng.uniform(-0.2, 0.2, (2, n))
    tz = np.sqrt(prof.index(x * x + y * y) ** 2 - tx * tx - ty * ty)

    def reference(a: Any) -> Callable[[], Any]:
        def run() -> Any:
            def body(i: Any, *c: Any) -> tuple[Any, ...]:
                c = list(c)
                for k in range(OPS_PER_STEP // 8):
                    for j in range(8):
                        c[j] = dr.fma(c[j], 0.9999, 1e-4 * (k + 1))
                return (i + 1, *c)

            out = dr.while_loop(
                (dr.zeros(dr.llvm.UInt32, n), *[a + 0.01 * j for j in range(8)]), lambda i, *c: i < steps, body
            )
            dr.eval(*out)

        return run

    configs = [
        ("float32", dr.llvm.Float, 1),
        ("float32", dr.llvm.Float, 2),
        ("float64", dr.llvm.Float64, 1),
        ("float64", dr.llvm.Float64, 2),
    ]
    arrays = {}
    for label, F, _ in configs:
        arrays[label] = [F(a) for a in (x, y, tx, ty, tz)]
        dr.eval(*arrays[label])
    ref_fn = reference(arrays["float32"][0])
    ref_fn()
    times: dict[str, list[float]] = {"reference": []}
    runs = {}
    for label, _, il in configs:
        key = f"{label} interleave={il}"
        arrs = arrays[label]
        runs[key] = lambda arrs=arrs, il=il: dr.eval(*grin.rkn_rod_dr(*arrs, prof, length, steps, 1.0, interleave=il))
        runs[key]()
        dr.sync_thread()
        times[key] = []
    for _ in range(args.repeat):  # alternate, so that every figure sees the same load
        times["reference"].append(_timed(ref_fn, dr.sync_thread))
        for key, fn in runs.items():
            times[key].append(_timed(fn, dr.sync_thread))
    ref_best, ref_med = _stats(n, times["reference"])
    print(
        f"reference FMA kernel ({OPS_PER_STEP} float32 FMAs x {steps}, 8 chains): best {ref_best:.3e} "
        f"median {ref_med:.3e} ray-equivalents/s"
    )
    for key in runs:
        best, med = _stats(n, times[key])
        print(
            f"Dr.Jit {key}: best {best:.3e} median {med:.3e} rays/s through the rod ({steps} steps, {n} rays); "
            f"rod/reference {med / ref_med:.2f} (medians)"
        )
    m = args.numpy_rays
    tnp = [
        _timed(lambda: rkn_rod(x[:m], y[:m], tx[:m], ty[:m], tz[:m], prof, length, steps, 1.0), lambda: None)
        for _ in range(max(1, args.repeat // 2))
    ]
    np_best, np_med = _stats(m, tnp)
    print(f"numpy float64: best {np_best:.3e} median {np_med:.3e} rays/s ({m} rays)")
    for key in runs:
        print(f"ratio Dr.Jit {key} / numpy (medians): {_stats(n, times[key])[1] / np_med:.1f}x")
    if args.no_image:
        return

    from scopetwin.scenes.mitsuba.variant import choose

    variant = choose("mono")
    setup = load_grin_setup("thesis-8.3.2-grin-realized")
    rep = analyse(setup, samples=24)
    stack = setup.stack(image_distance=rep.image_distance_mm)
    tgt = target("grid-25")
    centre = setup.array.axes()[0]
    paths = args.width * args.height * args.spp
    grin.render_image(
        setup, stack, tgt, spp=1, width=64, height=48, center=centre, variant=variant
    )  # compile (cached kernels)
    # where the time goes: the same render with the rods' RKN loops replaced by straight lines (Mitsuba
    # intersections, pupil sampling, film and the interface logic remain), at --spp / 8, scaled to --spp
    spp_b = max(1, args.spp // 8)
    rkn = grin.rkn_rod_dr

    def straight(
        x: Any,
        y: Any,
        tx: Any,
        ty: Any,
        tz: Any,
        profile: Any,
        length: float,
        steps: int,
        radius: float,
        active: Any = True,
        interleave: int = 1,
    ) -> tuple[Any, ...]:
        s_ = length / tz
        return x + s_ * tx, y + s_ * ty, tx, ty, s_ * profile.n0, dr.mask_t(type(x))(active)

    part = {}
    for label, fn in (("full", rkn), ("no RKN", straight)):
        grin.rkn_rod_dr = fn
        grin.render_image(setup, stack, tgt, spp=1, width=64, height=48, center=centre, variant=variant)
        part[label] = (
            min(
                _timed(
                    lambda: grin.render_image(
                        setup,
                        stack,
                        tgt,
                        spp=spp_b,
                        width=args.width,
                        height=args.height,
                        center=centre,
                        variant=variant,
                    ),
                    lambda: None,
                )
                for _ in range(2)
            )
            * args.spp
            / spp_b
        )
    grin.rkn_rod_dr = rkn
    print(
        f"breakdown at {spp_b} spp scaled to {args.spp}: full {part['full']:.2f} s, without the RKN loops "
        f"{part['no RKN']:.2f} s (Mitsuba intersections + sampling + film), RKN share "
        f"{part['full'] - part['no RKN']:.2f} s"
    )
    tim = []
    for _ in range(args.image_repeat):
        t0 = time.perf_counter()
        img = grin.render_image(
            setup, stack, tgt, spp=args.spp, width=args.width, height=args.height, center=centre, variant=variant
        )
        tim.append(time.perf_counter() - t0)
        ref_t = _timed(ref_fn, dr.sync_thread)
        print(
            f"image {args.width}x{args.height} at {args.spp} spp: {tim[-1]:.2f} s ({paths / tim[-1]:.3e} paths/s, "
            f"mean {img.mean():.4g}); reference kernel right after: {n / ref_t:.3e}/s "
            f"(x{ref_med / (n / ref_t):.2f} slower than its median above)"
        )
    print(f"image best {min(tim):.2f} s, median {statistics.median(tim):.2f} s")


if __name__ == "__main__":
    main()
