"""Speed of marker detection + indexing on full 1360x1024 frames (target: <= 20 ms per frame).

Renders the §1.10 deflectometry setup (Mitsuba, 16 spp) and the §2.8.1 angular calibration view, adds
EMVA sensor noise, and times :func:`scopetwin.recon.markers.find_markers` (centroid search, filtering, grid
identification, indexing) per frame, with the setup-derived hint and region prepared once per setup
(as a measurement loop would). Prints the minimum and median over repeated runs and the stage split; then the
same for a strongly bent substrate (the §1.10 setup, 3 mm / 60 µm surface, seed 2), where the flood reaches a few
markers and the grid's topology (:func:`index_lattice`) numbers them, and the speed table's reference workload timed
before and after (``benchmarks/speed_table.py``), to compare runs on a shared machine.

Usage::

    PYTHONPATH=. python benchmarks/markers_speed.py [--repeat 50] [--analytic]

``--analytic`` renders with the numpy reference renderer instead of Mitsuba (slow: minutes).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

from scopetwin.recon.markers import (
    centroids,
    expected_axes,
    filter_spots,
    find_markers,
    find_markers_for,
    fourier_axes,
    index_grid,
    index_lattice,
    index_range,
    nearest_spacing,
    orient_axes,
    reference_axes,
    region_for_setup,
)
from scopetwin.scenes.setup import Setup, load_setup

sys.path.insert(0, str(Path(__file__).resolve().parent))
from speed_table import reference  # noqa: E402


def render(setup: Setup, heights, analytic: bool) -> np.ndarray:
    if analytic:
        from scopetwin.scenes.analytic import render as render_analytic

        return render_analytic(setup, heights, spp=4, seed=0)
    from scopetwin.scenes.mitsuba.render import render_setup

    return render_setup(setup, heights, spp=16, seed=0)


def noisy(setup: Setup, image: np.ndarray, seed: int = 0) -> np.ndarray:
    sensor = setup.sensor.sensor()
    exposure = sensor.exposure_for(float(image.max()), setup.sensor.photons_per_unit_s, 0.7)
    return sensor.capture(image, setup.sensor.photons_per_unit_s, exposure, rng=seed)


def timed(func, repeat: int) -> tuple[float, float]:
    func()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        func()
        times.append(time.perf_counter() - t0)
    return 1e3 * min(times), 1e3 * float(np.median(times))


def stages(image: np.ndarray, setup: Setup, repeat: int) -> dict[str, float]:
    """Minimum time (ms) of each stage of find_markers."""
    layout = setup.marker_pattern.layout
    region = region_for_setup(setup)
    hint = expected_axes(setup)
    spots = centroids(image)
    filt = filter_spots(spots, image.shape, region=region)
    keep = np.flatnonzero(filt.keep)
    pts = spots.centroids[keep]
    ref = int(np.flatnonzero(keep == filt.reference)[0])

    def grid() -> np.ndarray:
        if layout == "calibration":
            return reference_axes(pts, ref, setup.scene != "target")
        return orient_axes(fourier_axes(image, pts[ref], nearest_spacing(pts)), hint)

    axes = grid()
    return {
        "centroids": timed(lambda: centroids(image), repeat)[0],
        "filter": timed(lambda: filter_spots(spots, image.shape, region=region), repeat)[0],
        "grid axes": timed(grid, repeat)[0],
        "indexing": timed(lambda: index_grid(pts, ref, axes), repeat)[0],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=50)
    parser.add_argument("--analytic", action="store_true", help="render with the numpy reference renderer")
    args = parser.parse_args()
    from scopetwin.sim.surfaces import surface_for

    ref0 = reference()[0]

    print(f"{'frame':<34} {'markers':>7} {'min ms':>8} {'median ms':>10}   stages (min ms)")
    for name in ("thesis-1.10-deflectometry", "thesis-2.8.1-angular"):
        setup = load_setup(name)
        heights = surface_for(setup) if setup.scene == "deflectometry" else None
        clean = render(setup, heights, args.analytic)
        region = region_for_setup(setup)
        hint = expected_axes(setup)
        irange = index_range(setup)
        for label, image in (("noise-free", clean), ("EMVA 12-bit", noisy(setup, clean))):

            def run(image=image, setup=setup, region=region, hint=hint, irange=irange):
                return find_markers(
                    image,
                    setup.marker_pattern.layout,
                    hint=hint,
                    mirrored=setup.scene != "target",
                    region=region,
                    index_range=irange,
                )

            found = run()
            best, med = timed(run, args.repeat)
            st = stages(image, setup, max(5, args.repeat // 5))
            split = ", ".join(f"{k} {v:.1f}" for k, v in st.items())
            print(f"{name + ' ' + label:<34} {len(found):>7} {best:>8.1f} {med:>10.1f}   {split}")
    print("target: <= 20 ms per 1360x1024 frame (detection + indexing)")
    bent(args.analytic, max(3, args.repeat // 10))
    print(f"reference workload (speed_table.reference): {0.5 * (ref0 + reference()[0]):.4f} s, before and after")


#: The strongly bent substrate of :func:`bent`: 3 mm correlation length, 60 µm, seed 2.
BENT = {"substrate": {"surface": {"correlation_length": 3.0, "range_um": 60.0, "seed": 2}}}


def bent(analytic: bool, repeat: int) -> None:
    """Detection on the strongly bent substrate (:data:`BENT`, EMVA noise): the whole search and its topological
    indexing (:func:`index_lattice` over every spot) alone."""
    from scopetwin.sim.surfaces import surface_for

    setup = load_setup("thesis-1.10-deflectometry", BENT)
    image = noisy(setup, render(setup, surface_for(setup), analytic))
    found = find_markers_for(image, setup)
    best, med = timed(lambda: find_markers_for(image, setup), repeat)
    spots = found.spots
    ref = int(np.argmin(np.linalg.norm(spots.centroids - found.centroids[np.all(found.ij == 0, axis=1)][0], axis=1)))
    lattice = timed(lambda: index_lattice(spots.centroids, ref, found.axes), repeat)[0]
    name = "3 mm / 60 µm seed 2 EMVA 12-bit"
    print(f"{name:<34} {len(found):>7} {best:>8.1f} {med:>10.1f}   indexing: {found.indexing}, lattice {lattice:.1f}")


if __name__ == "__main__":
    main()
