"""GRIN speed benchmark: rays/s through a rod (Dr.Jit float32/64, numpy float64) and image time.

Run: ``PYTHONPATH=. python benchmarks/grin_speed.py [--rays N] [--spp 64] [--repeat 5] [--noise-spp 25]``. Prints
figures; asserts nothing. The rod is the §8.3.2 first rod (L = 3.58 mm, GrinTech profile, 36 RKN steps of 0.1 mm);
the image is the §8.3.2 objective imaging the 25 µm grid onto a 1392 x 1040 window at 64 spp (float32 path, 4 RKN
steps per rod).

The machine may be shared, so every rate is given as best and median of ``--repeat`` runs, next to a reference
kernel measured in the same loop (a ``dr.while_loop`` of 36 iterations doing as many float32 FMAs per ray as one
RKN step has operations, in 8 independent chains, i.e. throughput-bound): the ratio rod/reference moves much less
with the load than the rates. For the image, a breakdown at ``--spp`` / 8 scaled to ``--spp``: the render as
:func:`render_image` does it (the planes met in a known order, intersected directly), the same without the rods' RKN
loops (straight lines instead: pupil sensor, sampler, film and the interface logic), and the render that asks
Mitsuba's ray intersection at every plane (``sequential=False``, the slower general path: the same image, bit for
bit). Then the image itself at ``--spp``, each followed by the reference kernel.

Noise (fewer paths for the same noise): on a ``--noise-width`` x ``--noise-height`` window at the
objective's centre, the per-pixel noise of the independent sampler at ``--spp`` and of the multi-jittered one at
``--noise-spp``, each from two renders with different seeds (RMS of their difference / sqrt 2: needs no
reference image), and the time of the whole image at ``--noise-spp`` multi-jittered.
"""

from __future__ import annotations

import argparse
import functools
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


def _parse() -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--rays", type=int, default=4_000_000)
    ap.add_argument("--numpy-rays", type=int, default=500_000)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--width", type=int, default=1392)
    ap.add_argument("--height", type=int, default=1040)
    ap.add_argument("--image-repeat", type=int, default=2)
    ap.add_argument("--no-image", action="store_true")
    ap.add_argument("--noise-spp", type=int, default=25, help="multi-jittered spp compared with --spp independent")
    ap.add_argument("--noise-width", type=int, default=348)
    ap.add_argument("--noise-height", type=int, default=260)
    ap.add_argument("--no-noise", action="store_true")
    return ap.parse_args()


def _reference_kernel(a: Any, n: int, steps: int) -> Callable[[], Any]:
    """The reference: a ``dr.while_loop`` of ``steps`` iterations of OPS_PER_STEP float32 FMAs in 8 chains."""
    import drjit as dr

    def run() -> Any:
        def body(i: Any, *chains: Any) -> tuple[Any, ...]:
            c = list(chains)
            for k in range(OPS_PER_STEP // 8):
                for j in range(8):
                    c[j] = dr.fma(c[j], 0.9999, 1e-4 * (k + 1))
            return (i + 1, *c)

        out = dr.while_loop(
            (dr.zeros(dr.llvm.UInt32, n), *[a + 0.01 * j for j in range(8)]), lambda i, *c: i < steps, body
        )
        dr.eval(*out)

    return run


def _through_rod(arrs: list[Any], prof: Any, length: float, steps: int, interleave: int) -> None:
    """The rays ``arrs`` through one rod by :func:`scopetwin.scenes.mitsuba.grin.rkn_rod_dr`, evaluated."""
    import drjit as dr

    from scopetwin.scenes.mitsuba import grin

    x, y, tx, ty, tz = arrs
    dr.eval(*grin.rkn_rod_dr(x, y, tx, ty, tz, prof, length, steps, 1.0, interleave=interleave))


def rod_rates(args: argparse.Namespace) -> tuple[Callable[[], Any], float]:
    """Rays/s through the §8.3.2 first rod (Dr.Jit float32/64, interleaved or not; numpy) beside the reference.

    Returns the reference kernel and its median rate (ray-equivalents/s), for the image figures.
    """
    import drjit as dr

    from scopetwin.scenes.grin.profiles import PolynomialProfile
    from scopetwin.scenes.grin.rkn import rkn_rod

    prof = PolynomialProfile()
    length, steps = 3.58, 36
    rng = np.random.default_rng(1)
    n = args.rays
    x, y = rng.uniform(-0.6, 0.6, (2, n))
    tx, ty = rng.uniform(-0.2, 0.2, (2, n))
    tz = np.sqrt(prof.index(x * x + y * y) ** 2 - tx * tx - ty * ty)
    configs: list[tuple[str, Any, int]] = [("float32", dr.llvm.Float, 1), ("float32", dr.llvm.Float, 2)]
    configs += [("float64", dr.llvm.Float64, 1), ("float64", dr.llvm.Float64, 2)]
    arrays = {}
    for label, F, _ in configs:
        arrays[label] = [F(a) for a in (x, y, tx, ty, tz)]
        dr.eval(*arrays[label])
    ref_fn = _reference_kernel(arrays["float32"][0], n, steps)
    ref_fn()
    times: dict[str, list[float]] = {"reference": []}
    runs: dict[str, Callable[[], Any]] = {}
    for label, _, il in configs:
        key = f"{label} interleave={il}"
        runs[key] = functools.partial(_through_rod, arrays[label], prof, length, steps, il)
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
    return ref_fn, ref_med


class _Image:
    """The §8.3.2 objective, its stack and the grid target; :meth:`render` renders a window at its first axis."""

    def __init__(self) -> None:
        from scopetwin.scenes.grin import load_grin_setup
        from scopetwin.scenes.grin.analysis import analyse
        from scopetwin.scenes.grin.targets import target
        from scopetwin.scenes.mitsuba.variant import choose

        self.variant = choose("mono")
        self.setup = load_grin_setup("thesis-8.3.2-grin-realized")
        self.stack = self.setup.stack(image_distance=analyse(self.setup, samples=24).image_distance_mm)
        self.target = target("grid-25")
        self.centre = self.setup.array.axes()[0]

    def render(self, spp: int, width: int, height: int, **kw: Any) -> Any:
        from scopetwin.scenes.mitsuba import grin

        return grin.render_image(
            self.setup, self.stack, self.target, spp=spp, width=width, height=height, center=self.centre,
            variant=self.variant, **kw,
        )  # fmt: skip

    def timed(self, spp: int, width: int, height: int, runs: int = 2, **kw: Any) -> float:
        """The minimum time of ``runs`` renders, after one small render that compiles (the kernels are cached)."""
        self.render(1, 64, 48, **kw)
        return min(_timed(lambda: self.render(spp, width, height, **kw), lambda: None) for _ in range(runs))


def _straight(
    x: Any, y: Any, tx: Any, ty: Any, tz: Any, profile: Any, length: float, steps: int, radius: float,
    active: Any = True, interleave: int = 1,
) -> tuple[Any, ...]:  # fmt: skip
    """Stand-in for ``rkn_rod_dr``: straight lines through the rod (the breakdown without the RKN loops)."""
    import drjit as dr

    s_ = length / tz
    return x + s_ * tx, y + s_ * ty, tx, ty, s_ * profile.n0, dr.mask_t(type(x))(active)


def breakdown(args: argparse.Namespace, im: _Image) -> None:
    """Where the image's time goes, at ``--spp`` / 8 scaled to ``--spp``."""
    from scopetwin.scenes.mitsuba import grin

    spp_b = max(1, args.spp // 8)
    scale = args.spp / spp_b
    size = (args.width, args.height)
    part = {"full": im.timed(spp_b, *size) * scale}
    rkn = grin.rkn_rod_dr
    grin.rkn_rod_dr = _straight
    try:
        part["no RKN"] = im.timed(spp_b, *size) * scale
    finally:
        grin.rkn_rod_dr = rkn
    part["Mitsuba intersections"] = im.timed(spp_b, *size, runs=1, sequential=False) * scale
    print(
        f"breakdown at {spp_b} spp scaled to {args.spp}: full {part['full']:.2f} s, without the RKN loops "
        f"{part['no RKN']:.2f} s (sampling, pupil sensor, interface logic, film), RKN share "
        f"{part['full'] - part['no RKN']:.2f} s; with Mitsuba's ray intersection at every plane (the general path, "
        f"the same image) {part['Mitsuba intersections']:.2f} s, x{part['Mitsuba intersections'] / part['full']:.1f}"
    )


def image_figures(args: argparse.Namespace, ref_fn: Callable[[], Any], ref_med: float) -> None:
    """The image at ``--spp``, each render followed by the reference kernel."""
    import drjit as dr

    im = _Image()
    breakdown(args, im)
    paths = args.width * args.height * args.spp
    tim = []
    for _ in range(args.image_repeat):
        t0 = time.perf_counter()
        img = im.render(args.spp, args.width, args.height)
        tim.append(time.perf_counter() - t0)
        ref_rate = args.rays / _timed(ref_fn, dr.sync_thread)
        print(
            f"image {args.width}x{args.height} at {args.spp} spp: {tim[-1]:.2f} s ({paths / tim[-1]:.3e} paths/s, "
            f"mean {img.mean():.4g}); reference kernel right after: {ref_rate:.3e}/s "
            f"(x{ref_med / ref_rate:.2f} slower than its median above)"
        )
    print(f"image best {min(tim):.2f} s, median {statistics.median(tim):.2f} s")
    if not args.no_noise:
        noise_figures(args, im)


def pixel_noise(im: _Image, spp: int, width: int, height: int, sampler: str) -> tuple[float, float]:
    """Per-pixel noise (RMS of the difference of two seeds / sqrt 2) and mean of a window at ``spp``."""
    a, b = (im.render(spp, width, height, seed=seed, sampler=sampler) for seed in (11, 12))
    return float(np.sqrt(np.mean((a.astype(np.float64) - b) ** 2) / 2)), float(a.mean())


def noise_figures(args: argparse.Namespace, im: _Image) -> None:
    """Noise of ``--spp`` independent against ``--noise-spp`` multi-jittered, and the whole image at the latter."""
    size = (args.noise_width, args.noise_height)
    n_ind, m_ind = pixel_noise(im, args.spp, *size, "independent")
    n_mj, m_mj = pixel_noise(im, args.noise_spp, *size, "multijitter")
    print(
        f"noise on a {size[0]}x{size[1]} window: independent {args.spp} spp {n_ind:.3e} (mean {m_ind:.4g}), "
        f"multijitter {args.noise_spp} spp {n_mj:.3e} (mean {m_mj:.4g}): ratio {n_mj / n_ind:.2f}"
    )
    t = im.timed(args.noise_spp, args.width, args.height, sampler="multijitter")
    print(
        f"image {args.width}x{args.height} at {args.noise_spp} spp multijitter (noise x{n_mj / n_ind:.2f} that of "
        f"{args.spp} independent spp): {t:.2f} s"
    )


def main() -> None:
    args = _parse()
    ref_fn, ref_med = rod_rates(args)
    if not args.no_image:
        image_figures(args, ref_fn, ref_med)


if __name__ == "__main__":
    main()
