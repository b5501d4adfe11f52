"""Render speed of the §1.10 deflectometry frame: Mitsuba vs the float64 numpy analytic renderer.

Renders the thesis's §1.10 setup (1360 x 1024 px, 33 x 33 markers, 25.2 x 57 mm substrate)
with a smooth 40 µm bow, warm (kernels compiled, scene loaded), and prints seconds per
frame and camera rays per second at several spp (``render_setup``: every pixel of the live window; beside it
Mitsuba's render loop over the live window and over the image); then times
:func:`scopetwin.scenes.analytic.render` on a window of the image, extrapolates to a full frame per ray, and prints
the ratio. ``--centroids N`` compares the marker centroids of the marked render (``render_marked``: only the pixels
that can see a marker traced) with those of the render of every pixel over N seeds each.
Targets: <= 0.5 s per frame at 16 spp on 2 cores, >= 50x the numpy reference.
Prints figures only; nothing here passes or fails.

Usage: ``PYTHONPATH=. python benchmarks/render_speed.py [--spp 4 16 64] [--repeats 3] [--window 96] [--centroids 8]``
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from scopetwin.scenes.setup import load_setup
from scopetwin.scenes.surface import HeightMap

PRESET = "thesis-1.10-deflectometry"


def bowed_heights(range_um: float = 40.0) -> HeightMap:
    """A smooth bow of ``range_um`` peak-to-valley over the 25.2 x 57 mm substrate (256 x 512 nodes)."""

    def bow(x, y):
        return (x / 12.6) ** 2 * 0.3 + (y / 28.5) ** 2 + 0.15 * (x / 12.6) * (y / 28.5)

    x = np.linspace(-12.6, 12.6, 256)
    y = np.linspace(-28.5, 28.5, 512)
    z = bow(*np.meshgrid(x, y))
    scale = range_um * 1e-3 / (z.max() - z.min())
    return HeightMap.from_function(lambda xx, yy: -scale * (bow(xx, yy) - z.min()), -12.6, 12.6, -28.5, 28.5)


def time_mitsuba(setup, heights, spp_list: list[int], repeats: int, variant: str) -> dict[int, dict[str, float]]:
    import drjit as dr

    from scopetwin.scenes.mitsuba.render import live_window, load_scene, render_setup, render_window

    window = live_window(setup, heights)
    nx, ny = setup.camera.pixels
    window_px = nx * ny if window is None else (window[1] - window[0]) * (window[3] - window[2])
    t0 = time.perf_counter()
    scene = load_scene(setup, heights, window, variant)
    load_s = time.perf_counter() - t0
    traced_px = _marked_pixels(setup, scene)
    print(
        f"live window {window}: {window_px / (nx * ny):.0%} of the pixels can see light; {traced_px / window_px:.0%} "
        f"of those can see a marker and are traced ({traced_px / (nx * ny):.0%} of the image)"
    )
    print(f"scene load (texture, mesh, plugins; first call): {load_s:.2f} s")
    out = {}
    for spp in spp_list:
        t0 = time.perf_counter()
        render_setup(setup, heights, spp=spp, seed=0, variant=variant)  # compiles (or loads from the kernel cache)
        dr.sync_thread()
        first = time.perf_counter() - t0
        wall, cpu = [], []
        for k in range(repeats):
            t0, c0 = time.perf_counter(), time.process_time()
            render_setup(setup, heights, spp=spp, seed=k + 1, variant=variant)
            dr.sync_thread()
            wall.append(time.perf_counter() - t0)
            cpu.append(time.process_time() - c0)
        best = min(wall)
        rays = traced_px * spp
        out[spp] = {
            "seconds": best,
            "median_seconds": float(np.median(wall)),
            "cpu_seconds": min(cpu),
            "first_seconds": first,
            "rays_per_s": rays / best,
        }
        print(
            f"mitsuba {spp:4d} spp: {best:6.3f} s/frame (median {np.median(wall):.3f}, cpu {min(cpu):.3f} s, "
            f"first {first:.2f} s), {rays / best / 1e6:6.1f} M traced camera rays/s"
        )
    if window is not None and 16 in spp_list:
        for label, win, px in (("every pixel of the live window", window, window_px), ("every pixel", None, nx * ny)):
            render_window(setup, heights, spp=16, seed=0, window=win, variant=variant)  # load + compile
            dr.sync_thread()
            wall = []
            for k in range(repeats):
                t0 = time.perf_counter()
                render_window(setup, heights, spp=16, seed=k + 1, window=win, variant=variant)
                dr.sync_thread()
                wall.append(time.perf_counter() - t0)
            print(
                f"mitsuba   16 spp, {label} traced (Mitsuba's render loop): {min(wall):6.3f} s/frame, "
                f"{px * 16 / min(wall) / 1e6:6.1f} M camera rays/s"
            )
            out["window_16" if win is not None else "uncropped_16"] = {"seconds": min(wall)}
    return out


def _marked_pixels(setup, scene) -> int:
    """How many pixels of the scene's window the marked render traces (those whose rays can meet a marker)."""
    from scopetwin.scenes.mitsuba.lit import lit_pixels
    from scopetwin.scenes.mitsuba.scene import TEXEL

    width, height = (int(v) for v in scene.sensors()[0].film().crop_size())
    ms = scene.integrator().geometry(scene)
    return len(lit_pixels(ms, scene, setup.marker_pattern, TEXEL, width, height))


def _spot_centroids(image: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    from scipy import ndimage

    return np.array(ndimage.center_of_mass(image.astype(np.float64), labels, np.arange(1, n + 1)))[:, ::-1] + 0.5


def centroid_check(setup, heights, renders: int, variant: str) -> dict[str, float]:
    """Marker centroids of the marked render (only the pixels that can see a marker traced) against Mitsuba's render
    of every pixel of the live window, ``renders`` seeds each at 16 spp: the RMS over the spots of the difference of
    their seed means, beside one render's Monte-Carlo scatter (the spread over seeds) and the largest single spot
    difference of the means."""
    from scipy import ndimage

    from scopetwin.scenes.mitsuba.render import live_window, render_marked, render_window

    window = live_window(setup, heights)
    r0, r1, c0, c1 = window if window is not None else (0, setup.camera_model.ny, 0, setup.camera_model.nx)
    every = []
    for k in range(renders):
        full = np.zeros((setup.camera_model.ny, setup.camera_model.nx), dtype=np.float32)
        full[r0:r1, c0:c1] = render_window(setup, heights, spp=16, seed=100 + k, window=window, variant=variant)
        every.append(full)
    marked = []
    for k in range(renders):
        full = np.zeros((setup.camera_model.ny, setup.camera_model.nx), dtype=np.float32)
        full[r0:r1, c0:c1] = render_marked(setup, heights, spp=16, seed=200 + k, window=window, variant=variant)
        marked.append(full)
    labels, n = ndimage.label(ndimage.binary_dilation(np.mean(every, axis=0) > 0, iterations=2))
    sums = np.array([ndimage.sum_labels(im, labels, np.arange(1, n + 1)) for im in [*every, *marked]])
    keep = sums.min(axis=0) > 1.0  # whole spots in every render (slivers at the ROI's edges left out)
    c_every = np.array([_spot_centroids(im, labels, n)[keep] for im in every])
    c_marked = np.array([_spot_centroids(im, labels, n)[keep] for im in marked])
    n = int(keep.sum())
    diff = np.linalg.norm(c_marked.mean(axis=0) - c_every.mean(axis=0), axis=1)
    scatter = float(np.sqrt(np.mean(np.sum(c_every.var(axis=0, ddof=1), axis=1))))
    out = {"spots": n, "rms_px": float(np.sqrt(np.mean(diff**2))), "max_px": float(diff.max()), "scatter_px": scatter}
    print(
        f"centroids, marked render vs every pixel ({renders} seeds each, 16 spp, {n} spots): mean shift "
        f"{out['rms_px']:.4f} px RMS, {out['max_px']:.4f} px at most; one render's Monte-Carlo scatter "
        f"{scatter:.4f} px RMS (the means' own noise: {scatter * np.sqrt(2 / renders):.4f} px)"
    )
    return out


def time_analytic(setup, heights, spp: int, window: int) -> dict[str, float]:
    from scopetwin.scenes.analytic import render

    nx, ny = setup.camera.pixels
    r0, c0 = ny // 2 - window // 2, nx // 2 - window // 2
    box = (r0, r0 + window, c0, c0 + window)
    render(setup, heights, spp=spp, seed=0, window=(r0, r0 + 8, c0, c0 + 8))  # warm caches
    t0, c0 = time.perf_counter(), time.process_time()
    render(setup, heights, spp=spp, seed=1, window=box)
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    rays = window * window * spp
    per_ray = dt / rays
    full = per_ray * nx * ny * spp
    print(
        f"numpy analytic (float64) {spp} spp on a {window}x{window} window: {dt:.2f} s (cpu {dc:.2f} s), "
        f"{1 / per_ray / 1e6:.3f} M rays/s -> {full:.1f} s per full frame (extrapolated)"
    )
    return {"seconds": full, "cpu_seconds": dc / rays * nx * ny * spp, "rays_per_s": 1 / per_ray, "window": window}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--spp", type=int, nargs="+", default=[4, 16, 64])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--window", type=int, default=96, help="side of the analytic renderer's window, px")
    ap.add_argument("--json", help="write the figures here")
    ap.add_argument(
        "--centroids", type=int, default=0, metavar="N", help="also compare marker centroids over N seeds (see below)"
    )
    args = ap.parse_args()

    from scopetwin.scenes.mitsuba.variant import choose

    variant = choose("mono")
    setup = load_setup(PRESET)
    heights = bowed_heights()
    z = heights.z
    print(
        f"{PRESET}: {setup.camera.pixels[0]}x{setup.camera.pixels[1]} px, bow {1e3 * (z.max() - z.min()):.1f} µm, "
        f"variant {variant}, {os.cpu_count()} cores, load average {os.getloadavg()[0]:.2f}"
    )
    mit = time_mitsuba(setup, heights, args.spp, args.repeats, variant)
    cen = centroid_check(setup, heights, args.centroids, variant) if args.centroids else None
    ref_spp = 16 if 16 in args.spp else args.spp[0]
    ana = time_analytic(setup, heights, ref_spp, args.window)
    # like for like: rays per second where rays are traced (Mitsuba culls pixels that see nothing, the numpy
    # figure is measured on a window of useful pixels), and whole frames with culling left to Mitsuba
    ratio = mit[ref_spp]["rays_per_s"] / ana["rays_per_s"]
    frame_ratio = ana["seconds"] / mit[ref_spp]["seconds"]
    cpu_ratio = ana["cpu_seconds"] / mit[ref_spp]["cpu_seconds"]
    print(
        f"speed-up at {ref_spp} spp: {ratio:.0f}x per traced ray (mitsuba {mit[ref_spp]['rays_per_s'] / 1e6:.1f} vs "
        f"numpy {ana['rays_per_s'] / 1e6:.3f} M rays/s); per frame {frame_ratio:.0f}x wall "
        f"({mit[ref_spp]['seconds']:.3f} s vs {ana['seconds']:.1f} s), {cpu_ratio:.0f}x CPU; "
        f"targets: <= 0.5 s at 16 spp, >= 50x"
    )
    if os.getloadavg()[0] > 0.8 * (os.cpu_count() or 1):
        print(
            "note: the machine is busy (load average above the core count): wall times are inflated; "
            "the CPU times divided by the core count estimate an idle machine's wall time"
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(
                {
                    "mitsuba": mit,
                    "analytic": ana,
                    "speedup": ratio,
                    "speedup_cpu": cpu_ratio,
                    "spp_ratio": ref_spp,
                    "centroids": cen,
                },
                fh,
                indent=2,
            )


if __name__ == "__main__":
    main()
