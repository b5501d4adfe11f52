"""The speed table: every path with a speed goal, beside a reference workload timed in the same run.

Run: ``.venv/bin/python benchmarks/speed_table.py [--full] [--rows 1 2 9] [--json PATH]`` (``make bench``,
``make bench-full``); ``--calibrate`` records the reference on a quiet machine in ``benchmarks/speed_reference.json``;
``--reprint PATH`` prints a table written by ``--json`` again, with the quiet reference recorded now.

The machine may be shared (2 cores, other jobs), so a bare time misleads. Right before and right after each row the
script times a fixed, deterministic numpy workload — the *reference*: Cholesky factorisations and products of a seeded
600 x 600 SPD matrix on one BLAS thread (threadpoolctl), in place in preallocated buffers (:func:`reference`), about
0.15-0.5 s — and prints for each row

* ``seconds``: the row's time as measured (the minimum over repeats where a repeat is cheap; for the CLI rows the
  figure the command reports, see each row),
* ``quiet est.``: beside it, ``seconds x (reference on a quiet machine / reference now)``, the quiet reference read
  from ``benchmarks/speed_reference.json`` (``--calibrate`` writes it: the minimum wall time of 30 reference runs, or
  their minimum CPU time where the machine was busy throughout; "—" without it),
* ``ref s``: the reference's time, the mean of the runs before and after the row,
* ``busy``: the reference's wall / CPU time, how much the load slowed it (1 on a quiet machine),
* ``row/ref``: seconds / ref s, which moves much less with the load than either,
* ``goal`` and ``1st round``: the row's goal and the figure first measured for it (:data:`TABLE`),
* ``status``: the quiet estimate (the seconds where there is none) against the goal, and the seconds' verdict in
  brackets where it differs.

The reference is single-threaded numpy while some rows use both cores (Mitsuba, Dr.Jit), so the estimate is a
correction for the load, not an exact one. Nothing here passes or fails.

Rows (``*``: only with ``--full``):

1. ``recon.strategy.solve`` with the default :class:`ReconstructionConfig` (uncertainty included) on the markers of
   the §1.10 frame (``thesis-1.10-deflectometry``, its §1.9 surface, 16 spp, EMVA sensor noise, render seed 1; the
   frame is rendered once and cached in ``--cache``); markers found once, the per-setup precomputation outside: each
   run a first frame on a fresh Reconstructor (beside it, the same Reconstructor solving again, which starts on the
   basis scale it chose: what a next frame with that scale gets; and what limits the row: the first frame without the
   posterior, with and without the scale choice on the data).
2. The same with the bias step (:func:`centroid_bias_step` as the Reconstructor's bias).
3. Detection + realtime reconstruction per frame (as ``benchmarks/reconstruct_speed.py``:
   :meth:`ReconstructionConfig.realtime`, ``find_markers_for`` + ``solve``), minimum over repeats; beside it the
   stream of 30 frames (``recon.stream.reconstruct_stream``) per frame, its stages one after the other and
   overlapped (frame k+1's markers searched in a worker process while frame k is solved; goal: one frame period).
4. ``scopetwin reconstruct`` of that frame (a subprocess; the JSON's ``seconds``), the process's wall time beside it
   (goal :data:`CLI_WALL_GOAL_S`) and their difference: the interpreter's start, the imports and the exit; then the
   next frame of a rig (render seed 2) with ``--previous`` that frame's JSON (the evidence searched from its prior),
   and with ``--hold`` too (its scale and prior held).
5. ``scopetwin reconstruct`` of glass-like surfaces (:data:`GLASS`), 3 seeds, median of the JSONs' ``seconds``; the
   median process wall time beside it.
6. ``scopetwin run`` (a subprocess): wall time; its ``summary.json``'s detect + reconstruct step beside it.
7. * ``scopetwin study thesis`` (a subprocess): wall time.
8. * ``scopetwin reconstruct --method inverse`` of the row-1 frame: the JSON's ``seconds`` (the wall time beside it).
9. Mitsuba render of the §1.10 frame at 16 spp (``benchmarks/render_speed.py``'s bowed surface, warm, minimum).
10. GRIN image 1392 x 1040 at 64 spp (``benchmarks/grin_speed.py``'s §8.3.2 objective and grid target, warm).
11. * ``make lint`` + ``make test`` (subprocesses): wall times.
12. The fringe method (:func:`scopetwin.recon.strategy.reconstruct_fringe_images`: decode, dense slopes,
    integration, the frame criterion's start-height loop, the uncertainty) on the ``thesis-1.10-fringes`` preset's 24
    frames of 1360 x 1024 px (its §1.9 surface, 16 spp, EMVA sensor noise, render seed 1; rendered once and cached in
    ``--cache`` with :func:`scopetwin.sim.fringes.save_fringes`), minimum over repeats; the decode alone beside it.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import platform
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

PRESET = "thesis-1.10-deflectometry"
FRINGE_PRESET = "thesis-1.10-fringes"
ROOT = Path(__file__).resolve().parent.parent
REFERENCE_FILE = Path(__file__).resolve().parent / "speed_reference.json"
SCOPETWIN = [sys.executable, "-m", "scopetwin"]
#: The repository's package folders (setup.py maps them onto ``scopetwin.*``).
PACKAGE_FOLDERS = ("scopetwin", "scenes", "recon", "calib", "sim", "instrument")


def uncompiled_modules() -> list[str]:
    """The project's modules without bytecode as new as their source: where the environment writes none
    (``PYTHONDONTWRITEBYTECODE``; the editable install writes none either), every process that imports them compiles
    them again, and the CLI rows time that too (``make setup`` compiles them, as installing the wheel does)."""
    import importlib.util

    stale = []
    for folder in PACKAGE_FOLDERS:
        for src in sorted((ROOT / folder).rglob("*.py")):
            pyc = Path(importlib.util.cache_from_source(str(src)))
            if not pyc.is_file() or pyc.stat().st_mtime < src.stat().st_mtime:
                stale.append(str(src.relative_to(ROOT)))
    return stale


#: The glass-like surface of row 5 (``[substrate.surface]`` of the §1.10 preset), like float glass (power-law
#: waviness at 8-80 mm, a bow, 20-100 nm of micro-waviness at 1-8 mm, PV 14-60 µm, slopes 2.5-8 mrad): a power law
#: f^-4 flat below f = 1/40 mm — on the 57 mm substrate its longest wavelengths make the bow —, a 3 mm Gaussian
#: roll-off, 30 µm PV, 30 nm RMS of flat-spectrum micro-waviness at 1-8 mm. Seeds 1-3 give maximum slopes of 3.0, 2.9
#: and 2.8 mrad. (A rougher choice — f^-3 flat below 1/80 mm, 2 mm roll-off, 50 nm, slopes 3.0-4.7 mrad — made seed 1's
#: start-height loop fail to converge after 223 s on a busy machine: an accuracy question, not a speed
#: row.)
GLASS: dict[str, Any] = {
    "kind": "psd",
    "spectrum": "power",
    "correlation_length": 40.0,
    "psd_exponent": 4.0,
    "psd_rolloff_mm": 3.0,
    "range_um": 30.0,
    "broadband_rms_nm": 30.0,
    "broadband_wavelength_mm": 8.0,
    "broadband_min_wavelength_mm": 1.0,
}
GLASS_SEEDS = (1, 2, 3)


@dataclass(frozen=True)
class Goal:
    """One row of the speed table as plain numbers, seconds: the goal (``<=``), the first round's figure
    (a range as (low, high), None where there is none) and the figure before the speed work."""

    path: str
    goal_s: float | None
    first_round_s: tuple[float, float] | None
    filed_s: tuple[float, float] | None
    full_only: bool = False


#: The paths with a speed goal: the goal, the first speed round's figure and the figure before the speed work.
TABLE: dict[str, Goal] = {
    "1": Goal("default reconstruction of one frame, with its uncertainty", 0.150, (0.145, 0.145), (4.1, 4.1)),
    "2": Goal("the same with the bias step", 0.300, (0.9, 1.15), (5.3, 5.3)),
    "3": Goal("detection + realtime reconstruction", 0.033, (0.030, 0.030), (0.041, 0.041)),
    "4": Goal("CLI reconstruct, the thesis's kind, sensor noise (JSON seconds)", 0.5, None, (7.2, 7.2)),
    "5": Goal("CLI reconstruct, glass-like, sensor noise (median of 3)", 1.0, None, (10.0, 27.0)),
    "6": Goal("scopetwin run (wall)", 8.0, (12.0, 12.0), (32.8, 32.8)),
    "7": Goal("scopetwin study thesis (wall)", 60.0, (55.0, 55.0), (103.0, 103.0), full_only=True),
    "8": Goal("inverse reconstruction, one image (JSON seconds)", 20.0, None, (80.0, 250.0), full_only=True),
    "9": Goal("Mitsuba render of the §1.10 frame at 16 spp", 0.15, (0.29, 0.29), (0.36, 0.36)),
    "10": Goal("GRIN image 1392 x 1040 at 64 spp", 5.0, (10.6, 10.6), (10.6, 10.6)),
    # the goal is make test's alone (<= 5 min), on its sub-row
    "11": Goal("make lint + make test (wall)", None, (185.0, 185.0), (754.0, 754.0), full_only=True),
    "12": Goal("fringe reconstruction, 24 frames of 1360 x 1024", 2.0, None, (57.0, 64.0)),
}  # fmt: skip


# -- the reference workload ------------------------------------------------------------------------------------------
REFERENCE_N = 600
REFERENCE_ROUNDS = 20
_SPD: list[NDArray[np.float64]] = []
#: The reference's two buffers, allocated once: the factor (Fortran order, factorised in place) and the product.
_BUFFERS: list[NDArray[np.float64]] = []


def _spd() -> NDArray[np.float64]:
    if not _SPD:
        a = np.random.default_rng(26).standard_normal((REFERENCE_N, REFERENCE_N))
        _SPD.append(a @ a.T + REFERENCE_N * np.eye(REFERENCE_N))
    return _SPD[0]


def _buffers() -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    if not _BUFFERS:
        _BUFFERS.extend([np.empty((REFERENCE_N, REFERENCE_N), order="F"), np.empty((REFERENCE_N, REFERENCE_N))])
    return _BUFFERS[0], _BUFFERS[1]


def reference() -> tuple[float, float]:
    """Wall and CPU seconds of the reference workload: ``REFERENCE_ROUNDS`` x (Cholesky of the seeded 600 x 600 SPD
    matrix and the product L L^T), on one BLAS thread.

    The workload is single-threaded, so its CPU time hardly moves with the load while its wall time does: wall / CPU is
    how much the machine slowed it down (1 on a quiet machine).

    Nothing is allocated while it is timed: the factor is computed in place in a preallocated buffer
    (``scipy.linalg.cholesky(overwrite_a=True)``) and the product written into another. An allocating version
    (``np.linalg.cholesky``, ``low @ low.T``) timed the C library's allocator as well: glibc hands the 3 MB blocks
    back to the system after each round until the process has once freed a larger block, so in a fresh process
    (``--calibrate``) every round faulted its pages in again (~160 000 page faults per 11 runs) and took ~20 % longer
    than after a row had run — the quiet reference then read slow and the quiet estimates high.
    """
    import scipy.linalg as sla
    from threadpoolctl import threadpool_limits

    spd = _spd()
    work, prod = _buffers()
    with threadpool_limits(limits=1, user_api="blas"):
        t0, c0 = time.perf_counter(), time.process_time()
        acc = 0.0
        for _ in range(REFERENCE_ROUNDS):
            np.copyto(work, spd)
            low = sla.cholesky(work, lower=True, overwrite_a=True, check_finite=False)  # in place: work is F-ordered
            np.matmul(low, low.T, out=prod)
            acc += float(np.trace(prod))
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
    if not np.isfinite(acc):  # pragma: no cover - the result is used, so the work is done
        raise RuntimeError("reference workload produced a non-finite value")
    return dt, dc


#: Above this wall / CPU ratio of the reference the machine is busy: --calibrate takes the CPU time as the quiet figure.
QUIET_RATIO = 1.1


def load_quiet_reference(path: Path = REFERENCE_FILE) -> dict[str, Any] | None:
    """The quiet machine's reference record (``--calibrate``), or None."""
    if not path.exists():
        return None
    data: dict[str, Any] = json.loads(path.read_text())
    return data


def calibrate(runs: int, path: Path) -> dict[str, Any]:
    """Time the reference ``runs`` times (after one warm-up) and write the record.

    ``reference_s``, the quiet machine's reference, is the minimum wall time; where even that is more than
    :data:`QUIET_RATIO` x the minimum CPU time, the machine was busy throughout and the minimum CPU time stands for it
    (a single-threaded workload's wall time on a quiet machine; ``basis`` says which was taken).
    """
    from threadpoolctl import threadpool_info

    load_start = os.getloadavg()[0]
    reference()
    walls, cpus = [], []
    for _ in range(runs):
        w, c = reference()
        walls.append(w)
        cpus.append(c)
        time.sleep(0.05)
    busy = min(walls) > QUIET_RATIO * min(cpus)
    record = {
        "reference_s": min(cpus) if busy else min(walls),
        "basis": "minimum CPU time (the machine was busy)" if busy else "minimum wall time",
        "wall_min_s": min(walls),
        "wall_median_s": statistics.median(walls),
        "cpu_min_s": min(cpus),
        "runs": runs,
        "load_average": load_start,
        "load_average_end": os.getloadavg()[0],
        "cpus": os.cpu_count(),
        "machine": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "blas": [
            {k: info.get(k) for k in ("internal_api", "version", "architecture")}
            for info in threadpool_info()
            if info.get("user_api") == "blas"
        ],
        "date": datetime.now(UTC).isoformat(timespec="seconds"),
        "workload": f"{REFERENCE_ROUNDS} x (cholesky, L L^T) of a seeded {REFERENCE_N}^2 SPD matrix, 1 thread, "
        "in place in preallocated buffers",
        "method": f"benchmarks/speed_table.py --calibrate: one warm-up run, then {runs} runs 50 ms apart; "
        f"reference_s is their {'minimum CPU time' if busy else 'minimum wall time'}; load average (1 min) "
        f"{load_start:.2f} before, load_average_end after",
    }
    path.write_text(json.dumps(record, indent=2) + "\n")
    return record


# -- rows ------------------------------------------------------------------------------------------------------------
@dataclass
class Measured:
    """What a row measured: its seconds, sub-figures (label, seconds, goal or None) and a note."""

    seconds: float
    extras: list[tuple[str, float, float | None]] = field(default_factory=list)
    note: str = ""


def repeat_min(fn: Callable[[], Any], min_runs: int = 2, max_runs: int = 15, budget_s: float = 3.0) -> list[float]:
    """Run ``fn`` at least ``min_runs`` times, more while the total stays under ``budget_s``; the seconds of each."""
    times: list[float] = []
    while len(times) < max_runs:
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
        if len(times) >= min_runs and sum(times) + times[-1] > budget_s:
            break
    return times


class Context:
    """Shared inputs: the cache folder, the §1.10 setup, its frame (rendered once) and the markers found on it."""

    def __init__(self, cache: Path, fresh: bool) -> None:
        from scopetwin.scenes.setup import load_setup

        self.cache = cache
        self.fresh = fresh
        cache.mkdir(parents=True, exist_ok=True)
        self.work = Path(tempfile.mkdtemp(prefix="speed-table-", dir=cache))
        self.setup = load_setup(PRESET)
        self._frame: Path | None = None
        self._glass: list[Path] = []

    def render_cached(self, setup: Any, seed: int, tag: str) -> Path:
        """``render_with_noise(setup, surface_for(setup), 16, seed)`` (sensor noise on) as an EXR in the cache,
        rendered once per setup (the setup's JSON is in the file name's hash)."""
        from scopetwin.scenes.io import write_image
        from scopetwin.sim.pipeline import render_with_noise
        from scopetwin.sim.surfaces import surface_for

        key = hashlib.sha256(f"{setup.to_json()}|16|{seed}".encode()).hexdigest()[:16]
        path = self.cache / f"{tag}-16spp-seed{seed}-{key}.exr"
        if self.fresh or not path.exists():
            t0 = time.perf_counter()
            image = render_with_noise(setup, surface_for(setup), 16, seed)
            tmp = path.with_suffix(".partial.exr")
            write_image(tmp, image)
            tmp.replace(path)
            print(f"  (rendered {path.name} in {time.perf_counter() - t0:.1f} s)", flush=True)
        return path

    @property
    def frame(self) -> Path:
        """The §1.10 frame: its own §1.9 surface, 16 spp, sensor noise, render seed 1."""
        if self._frame is None:
            self._frame = self.render_cached(self.setup, 1, "frame-1.10")
        return self._frame

    def glass_frames(self) -> list[Path]:
        """Row 5's frames: the §1.10 setup with the :data:`GLASS` surface of each seed, render seed = surface seed."""
        from scopetwin.scenes.setup import load_setup

        if not self._glass:
            for seed in GLASS_SEEDS:
                setup = load_setup(PRESET, {"substrate": {"surface": {**GLASS, "seed": seed}}})
                self._glass.append(self.render_cached(setup, seed, "frame-glass"))
        return self._glass

    @property
    def fringes(self) -> Path:
        """Row 12's measurement: ``thesis-1.10-fringes``, its own §1.9 surface, 16 spp, sensor noise, render seed 1
        (a folder written by :func:`scopetwin.sim.fringes.save_fringes`, rendered once)."""
        from scopetwin.scenes.setup import load_setup
        from scopetwin.sim.fringes import render_fringes, save_fringes
        from scopetwin.sim.surfaces import surface_for

        setup = load_setup(FRINGE_PRESET)
        key = hashlib.sha256(f"{setup.to_json()}|16|1".encode()).hexdigest()[:16]
        path = self.cache / f"fringes-1.10-16spp-seed1-{key}"
        if self.fresh or not (path / "fringes.json").exists():
            t0 = time.perf_counter()
            if path.exists():
                shutil.rmtree(path)
            save_fringes(render_fringes(setup, surface_for(setup), 16, 1, True), path)
            print(f"  (rendered {path.name} in {time.perf_counter() - t0:.1f} s)", flush=True)
        return path

    def image(self) -> NDArray[np.float32]:
        from scopetwin.scenes.io import read_image

        return read_image(self.frame)[0]


def _solve_rows(ctx: Context, bias: bool) -> Measured:
    """Rows 1 and 2: a first frame of the setup, each run on a fresh :class:`Reconstructor` (built before the timing:
    the per-setup precomputation). A Reconstructor keeps the basis scale its last solve chose, so a second solve on
    the same one starts on that scale (a next frame's ``starting_at``): that figure is printed beside it."""
    from scopetwin.recon.config import ReconstructionConfig
    from scopetwin.recon.markers import find_markers_for
    from scopetwin.recon.reconstruct import MarkerObservations, Reconstructor, centroid_bias_step
    from scopetwin.recon.strategy import solve

    image = ctx.image()
    found = find_markers_for(image, ctx.setup)
    obs = MarkerObservations(found.ij, found.centroids)

    def fresh() -> Any:
        return Reconstructor.from_setup(
            ctx.setup, ReconstructionConfig(), centroid_bias_step(ctx.setup) if bias else None
        )

    t0 = time.perf_counter()
    recs = [fresh()]
    t_setup = time.perf_counter() - t0
    recs += [fresh() for _ in range(FIRST_FRAME_RUNS - 1)]
    result: list[Any] = []
    times = repeat_min(
        lambda: result.append(solve(recs[len(result)], obs)), min_runs=2, max_runs=len(recs), budget_s=4.0
    )
    res = result[-1]
    again = repeat_min(lambda: solve(recs[0], obs), min_runs=2, max_runs=5, budget_s=2.0)
    u = res.uncertainty
    note = (
        f"{len(obs.ij)} markers, {res.outer_iterations} outer / {res.inner_iterations} inner iterations, "
        f"{len(times)} runs (median {statistics.median(times):.3f} s), per-setup {t_setup:.2f} s"
        + (f", u(abs) {u.absolute_um:.3f} µm" if u is not None else ", NO uncertainty")
    )
    extras: list[tuple[str, float, float | None]] = [
        ("  the same Reconstructor again (its scale kept)", min(again), None)
    ]
    if not bias:
        extras += _warm_next_frame(ctx, recs[0], res)
        extras += _without_posterior(ctx, obs)
    return Measured(min(times), extras=extras, note=note)


def _without_posterior(ctx: Context, obs: Any) -> list[tuple[str, float, float | None]]:
    """What limits row 1: the same first frame without its uncertainty (``posterior="off"``), with the scale chosen
    on the data and without (``rechoose_scale`` off: the fits alone), each on a fresh Reconstructor. The first is the
    least a faster posterior alone could bring the row to."""
    from scopetwin.recon.config import ReconstructionConfig
    from scopetwin.recon.policy import DEFAULT_POLICY
    from scopetwin.recon.reconstruct import Reconstructor
    from scopetwin.recon.strategy import solve

    cfg = ReconstructionConfig(posterior="off")

    def first_frames(policy: Any) -> float:
        recs = iter([Reconstructor.from_setup(ctx.setup, cfg) for _ in range(FIRST_FRAME_RUNS)])
        return min(
            repeat_min(lambda: solve(next(recs), obs, policy), min_runs=2, max_runs=FIRST_FRAME_RUNS, budget_s=2)
        )

    return [
        ("  without the posterior (the fits, the scale choice)", first_frames(DEFAULT_POLICY), None),
        (
            "  without the posterior and the scale choice",
            first_frames(DEFAULT_POLICY.with_changes(rechoose_scale=False)),
            None,
        ),
    ]


#: Most first-frame runs of rows 1 and 2 (each on its own Reconstructor, built before the timing).
FIRST_FRAME_RUNS = 8


def _warm_next_frame(ctx: Context, rec: Any, first: Any) -> list[tuple[str, float, float | None]]:
    """The next frame of a live loop (the same surface, render seed 2) as ``scopetwin.reconstruct(previous=)`` reads
    it: its search started on the basis scale the first frame ended on, its posterior's evidence warm-started from
    the first frame's prior (``Reconstructor.evidence_start``); and with ``hold=True``: that scale kept (no scale
    choice) and that prior read as it is where plausible (``Reconstructor.held_prior``)."""
    from scopetwin.recon.markers import find_markers_for
    from scopetwin.recon.policy import DEFAULT_POLICY
    from scopetwin.recon.posterior import prior_from_dict
    from scopetwin.recon.reconstruct import MarkerObservations, Reconstructor
    from scopetwin.recon.strategy import solve
    from scopetwin.recon.uncertainty import HeldPrior
    from scopetwin.scenes.io import read_image

    image = read_image(ctx.render_cached(ctx.setup, 2, "frame-1.10"))[0]
    found = find_markers_for(image, ctx.setup)
    obs = MarkerObservations(found.ij, found.centroids)
    prior = prior_from_dict(first.uncertainty.hyper)
    held = DEFAULT_POLICY.with_changes(rechoose_scale=False)
    out: list[tuple[str, float, float | None]] = []
    for label, hold in (("as previous= (scale and prior)", False), ("both held, previous= and hold=True", True)):
        times = []
        for _ in range(5):  # a fresh Reconstructor each time: a reused one keeps the scale it ended on
            warm = Reconstructor.from_setup(ctx.setup, rec.config.starting_at(float(first.surface.basis.sigma[0])))
            warm.evidence_start, warm.held_prior = (
                prior,
                (HeldPrior(prior, first.uncertainty.prior_z) if hold else None),
            )
            policy = held if hold else DEFAULT_POLICY
            times += repeat_min(lambda w=warm, p=policy: solve(w, obs, p), min_runs=1, max_runs=1)
        out.append((f"  next frame, {label}", min(times), 0.15))
    return out


def row_default(ctx: Context) -> Measured:
    return _solve_rows(ctx, bias=False)


def row_bias(ctx: Context) -> Measured:
    return _solve_rows(ctx, bias=True)


def row_realtime(ctx: Context) -> Measured:
    """As ``benchmarks/reconstruct_speed.py``: detection + the realtime configuration's solve, per frame."""
    from scopetwin.recon.config import ReconstructionConfig
    from scopetwin.recon.markers import find_markers_for
    from scopetwin.recon.reconstruct import MarkerObservations, Reconstructor
    from scopetwin.recon.strategy import solve

    image = ctx.image()
    rec = Reconstructor.from_setup(ctx.setup, ReconstructionConfig.realtime())
    t_det: list[float] = []
    t_sol: list[float] = []

    def frame() -> None:
        t0 = time.perf_counter()
        found = find_markers_for(image, ctx.setup)
        t1 = time.perf_counter()
        solve(rec, MarkerObservations(found.ij, found.centroids))
        t_det.append(t1 - t0)
        t_sol.append(time.perf_counter() - t1)

    times = repeat_min(frame, min_runs=5, max_runs=30, budget_s=2.0)
    seq, ovl = _stream_per_frame(image, ctx.setup, rec)
    return Measured(
        min(times),
        extras=[
            ("  detection alone", min(t_det), None),
            ("  realtime solve alone", min(t_sol), None),
            (f"  stream of {STREAM_FRAMES} frames, sequential (per frame)", seq, None),
            (f"  stream of {STREAM_FRAMES} frames, overlapped (per frame)", ovl, TABLE["3"].goal_s),
        ],
        note=f"{len(times)} frames, median {statistics.median(times) * 1e3:.1f} ms; stream {1.0 / seq:.1f} fps "
        f"sequential, {1.0 / ovl:.1f} fps overlapped",
    )


#: Frames of row 3's stream figures (timed from the first frame's result to the last's).
STREAM_FRAMES = 30


def _stream_per_frame(image: NDArray[np.float32], setup: Any, rec: Any) -> tuple[float, float]:
    """Seconds per frame of ``recon.stream.reconstruct_stream`` on copies of the frame, its stages one after the other
    and overlapped (frame k+1's markers searched in the worker process while frame k is solved): the time from the
    first frame's result to the last's over :data:`STREAM_FRAMES` frames, so the worker's start (a fresh interpreter,
    1-2 s) and the first frame's search are not counted."""
    from scopetwin.recon.stream import reconstruct_stream

    out = []
    for overlap in (False, True):
        stamps = [
            time.perf_counter() for _ in reconstruct_stream([image] * (STREAM_FRAMES + 1), setup, rec, overlap=overlap)
        ]
        out.append((stamps[-1] - stamps[0]) / STREAM_FRAMES)
    return out[0], out[1]


def _cli(args: list[str], timeout: float) -> tuple[int, float, str]:
    """Run ``python -m scopetwin ARGS``; exit status, wall seconds, the last lines of stderr."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [*SCOPETWIN, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout, check=False
    )  # fmt: skip
    wall = time.perf_counter() - t0
    tail = " | ".join((proc.stderr or proc.stdout).strip().splitlines()[-2:])
    return proc.returncode, wall, tail


def _reconstruct_cli(ctx: Context, image: Path, name: str, extra: list[str], timeout: float) -> tuple[float, float]:
    """``scopetwin reconstruct IMAGE --setup PRESET``: (the JSON's seconds, or nan where it failed; the wall time)."""
    out, js = ctx.work / f"{name}.exr", ctx.work / f"{name}.json"
    rc, wall, tail = _cli(
        ["reconstruct", str(image), "--setup", PRESET, "--out", str(out), "--json", str(js), *extra], timeout
    )
    if rc != 0 or not js.exists():
        print(f"  ({name}: exit status {rc} after {wall:.1f} s: {tail})", flush=True)
        return float("nan"), wall
    return float(json.loads(js.read_text())["seconds"]), wall


#: The goal of the process's wall time of ``scopetwin reconstruct`` (row 4's sub-row), seconds.
CLI_WALL_GOAL_S = 1.0
#: Row 4's goal (its JSON's ``seconds``), for its sub-row of the next frame.
CLI_GOAL_S = 0.5


def _wall_extras(seconds: float, wall: float, goal: float | None) -> list[tuple[str, float, float | None]]:
    """The process's wall time beside the JSON's ``seconds``, and what lies outside them: the interpreter's start,
    the imports, the parsing and the exit."""
    return [
        ("  process wall time", wall, goal),
        ("  outside the JSON's seconds (start-up, imports, exit)", wall - seconds, None),
    ]


def row_cli_seed(ctx: Context) -> Measured:
    seconds, wall = _reconstruct_cli(ctx, ctx.frame, "cli-seed", [], 600)
    extras = _wall_extras(seconds, wall, CLI_WALL_GOAL_S)
    if np.isfinite(seconds):  # a rig's next frame (render seed 2), its prior searched from this frame's
        prior = ["--previous", str(ctx.work / "cli-seed.json")]
        frame2 = ctx.render_cached(ctx.setup, 2, "frame-1.10")
        nxt, nxt_wall = _reconstruct_cli(ctx, frame2, "cli-next", prior, 600)
        extras += [("  next frame, --previous (JSON seconds)", nxt, CLI_GOAL_S), ("    its wall time", nxt_wall, None)]
        held, held_wall = _reconstruct_cli(ctx, frame2, "cli-held", [*prior, "--hold"], 600)
        extras += [("  next frame, --previous --hold (JSON seconds)", held, CLI_GOAL_S)]
        extras += [("    its wall time", held_wall, None)]
    return Measured(seconds, extras=extras)


def row_cli_glass(ctx: Context) -> Measured:
    frames = ctx.glass_frames()  # rendered in PREPARE, before this row's first reference
    per_seed = [_reconstruct_cli(ctx, f, f"cli-glass-{s}", [], 900) for s, f in zip(GLASS_SEEDS, frames, strict=True)]
    ok = [s for s, _ in per_seed if np.isfinite(s)]
    note = "seeds " + ", ".join(
        f"{seed}: {s:.2f} s" if np.isfinite(s) else f"{seed}: FAILED after {w:.1f} s"
        for seed, (s, w) in zip(GLASS_SEEDS, per_seed, strict=True)
    )
    walls = [w for s, w in per_seed if np.isfinite(s)]
    extras = [("  process wall time (median)", statistics.median(walls), None)] if walls else []
    return Measured(statistics.median(ok) if ok else float("nan"), extras=extras, note=note)


def row_run(ctx: Context) -> Measured:
    out = ctx.work / "run"
    rc, wall, tail = _cli(["run", "--out", str(out), "-q"], 1800)
    if rc != 0:
        return Measured(float("nan"), note=f"exit status {rc} after {wall:.1f} s: {tail}")
    summary = json.loads((out / "summary.json").read_text())
    t = summary.get("timings_s", {})
    extras: list[tuple[str, float, float | None]] = [("  in-process (summary.json)", float(summary["seconds"]), None)]
    extras += [(f"  step: {k}", float(v), None) for k, v in t.items() if k in ("detect + reconstruct", "calibrate")]
    return Measured(wall, extras=extras)


def row_study(ctx: Context) -> Measured:
    rc, wall, tail = _cli(["study", "thesis", "--out", str(ctx.work / "study-thesis"), "-q"], 3600)
    return Measured(wall, note="" if rc == 0 else f"exit status {rc}: {tail}")


def row_inverse(ctx: Context) -> Measured:
    seconds, wall = _reconstruct_cli(ctx, ctx.frame, "cli-inverse", ["--method", "inverse"], 1800)
    return Measured(seconds, extras=_wall_extras(seconds, wall, None))


def row_render(ctx: Context) -> Measured:
    """``benchmarks/render_speed.py``'s figure at 16 spp: its bowed surface, warm, minimum over repeats."""
    import drjit as dr
    from render_speed import bowed_heights

    from scopetwin.scenes.mitsuba.render import render_setup
    from scopetwin.scenes.mitsuba.variant import choose

    variant = choose("mono")
    heights = bowed_heights()
    render_setup(ctx.setup, heights, spp=16, seed=0, variant=variant)  # scene load + compile
    dr.sync_thread()
    seeds = iter(range(1, 100))

    def one() -> None:
        render_setup(ctx.setup, heights, spp=16, seed=next(seeds), variant=variant)
        dr.sync_thread()

    times = repeat_min(one, min_runs=5, max_runs=10, budget_s=3.0)
    return Measured(min(times), note=f"{len(times)} renders, median {statistics.median(times):.3f} s, {variant}")


def row_grin(ctx: Context) -> Measured:
    """``benchmarks/grin_speed.py``'s image: the §8.3.2 objective imaging the 25 µm grid, 1392 x 1040, 64 spp."""
    from scopetwin.scenes.grin import load_grin_setup
    from scopetwin.scenes.grin.analysis import analyse
    from scopetwin.scenes.grin.targets import target
    from scopetwin.scenes.mitsuba import grin
    from scopetwin.scenes.mitsuba.variant import choose

    variant = choose("mono")
    setup = load_grin_setup("thesis-8.3.2-grin-realized")
    stack = setup.stack(image_distance=analyse(setup, samples=24).image_distance_mm)
    tgt, centre = target("grid-25"), setup.array.axes()[0]
    grin.render_image(setup, stack, tgt, spp=1, width=64, height=48, center=centre, variant=variant)  # compile

    def one(spp: int = 64, sampler: grin.Sampler = "independent") -> None:
        grin.render_image(
            setup, stack, tgt, spp=spp, width=1392, height=1040, center=centre, variant=variant, sampler=sampler
        )

    times = repeat_min(one, min_runs=1, max_runs=3, budget_s=8.0)
    # 25 multi-jittered spp have at most the noise of 64 independent ones (benchmarks/grin_speed.py)
    grin.render_image(
        setup, stack, tgt, spp=1, width=64, height=48, center=centre, variant=variant, sampler="multijitter"
    )
    mj = repeat_min(lambda: one(25, "multijitter"), min_runs=1, max_runs=3, budget_s=6.0)
    return Measured(
        min(times),
        extras=[("  the same noise: 25 spp multijitter", min(mj), 5.0)],
        note=f"{len(times)} image{'s' if len(times) > 1 else ''}",
    )


def row_fringes(ctx: Context) -> Measured:
    """Row 12: :func:`scopetwin.recon.strategy.reconstruct_fringe_images` on the cached preset measurement (read
    once, outside the timing), minimum over repeats; the decode of the same stack beside it."""
    from scopetwin.recon.fringes.frames import decode_stack
    from scopetwin.recon.strategy import reconstruct_fringe_images
    from scopetwin.sim.fringes import read_fringes

    m = read_fringes(ctx.fringes)
    done: list[Any] = []
    times = repeat_min(lambda: done.append(reconstruct_fringe_images(m.images, m.setup)), 2, 5, 8.0)
    decode = repeat_min(lambda: decode_stack(m.images, m.setup), 1, 5, 2.0)
    r = done[-1]
    s = r.summary()
    note = (
        f"{s['observations']} slopes, {s['outer_iterations']} outer / {s['inner_iterations']} inner iterations, "
        f"{len(times)} runs, u(abs) {r.uncertainty.absolute_um:.3f} µm, u(shape) {r.uncertainty.shape_um:.3f} µm"
    )
    return Measured(min(times), extras=[("  decode of the 24 frames", min(decode), None)], note=note)


def row_make(ctx: Context) -> Measured:
    walls = {}
    for target in ("lint", "test"):
        t0 = time.perf_counter()
        proc = subprocess.run(["make", target], cwd=ROOT, capture_output=True, text=True, check=False)
        walls[target] = time.perf_counter() - t0
        if proc.returncode != 0:
            print(f"  (make {target}: exit status {proc.returncode})", flush=True)
    return Measured(
        walls["lint"] + walls["test"],
        extras=[("  make lint", walls["lint"], None), ("  make test", walls["test"], 300.0)],
    )


ROWS: dict[str, Callable[[Context], Measured]] = {
    "1": row_default,
    "2": row_bias,
    "3": row_realtime,
    "4": row_cli_seed,
    "5": row_cli_glass,
    "6": row_run,
    "7": row_study,
    "8": row_inverse,
    "9": row_render,
    "10": row_grin,
    "11": row_make,
    "12": row_fringes,
}

#: What each row needs before its timing starts (renders to the cache), so that the reference brackets the row only.
PREPARE: dict[str, Callable[[Context], Any]] = {
    "1": lambda ctx: ctx.frame,
    "2": lambda ctx: ctx.frame,
    "3": lambda ctx: ctx.frame,
    "4": lambda ctx: ctx.frame,
    "5": lambda ctx: ctx.glass_frames(),
    "8": lambda ctx: ctx.frame,
    "12": lambda ctx: ctx.fringes,
}


# -- the table -------------------------------------------------------------------------------------------------------
def _fmt(x: float | None) -> str:
    """Seconds, three significant digits."""
    if x is None or not np.isfinite(x):
        return "—"
    return f"{x:.3g}" if x < 1000 else f"{x:.0f}"


def _range(r: tuple[float, float] | None) -> str:
    if r is None:
        return "—"
    return _fmt(r[0]) if r[0] == r[1] else f"{_fmt(r[0])}-{_fmt(r[1])}"


W = 58  # width of the path column

HEADER = (
    f"{'#':>3} {'path':<{W}} {'seconds':>8} {'quiet est.':>10} {'ref s':>6} {'busy':>5} {'row/ref':>8} {'goal':>8} "
    f"{'1st round':>9}  status"
)


def _verdict(seconds: float, goal: float) -> str:
    return "met" if seconds <= goal else "NOT met"


def line(
    key: str,
    label: str,
    seconds: float,
    ref: float,
    quiet: float | None,
    goal: float | None,
    first: str,
    busy: float | None = None,
) -> str:
    """One printed row (seconds throughout): the seconds as measured and their quiet estimate side by side;
    ``busy``: the reference's wall / CPU time. The status judges the estimate (the seconds where there is none) and
    says so where the seconds as measured would be judged otherwise."""
    ratio = seconds / ref if np.isfinite(seconds) else float("nan")
    est = seconds * quiet / ref if quiet is not None and np.isfinite(seconds) else None
    judged = est if est is not None else seconds
    status = "" if goal is None or not np.isfinite(judged) else _verdict(judged, goal)
    if status and est is not None and _verdict(seconds, goal) != status:
        status += f" (as measured: {_verdict(seconds, goal)})"
    b = f"{busy:5.2f}" if busy is not None else " " * 5
    return (
        f"{key:>3} {label[:W]:<{W}} {_fmt(seconds):>8} {_fmt(est):>10} {ref:6.3f} {b} {_fmt(ratio):>8} "
        f"{'<= ' + _fmt(goal) if goal is not None else '—':>8} {first:>9}  {status}"
    ).rstrip()


def print_row(row: dict[str, Any], quiet: float | None) -> None:
    """Print one measured row (a dict of :func:`run_rows`), its sub-rows and its note."""
    seconds = float("nan") if row["seconds"] is None else row["seconds"]
    first = _range(tuple(row["first_round_s"]) if row["first_round_s"] is not None else None)
    ref = row["reference_s"]
    cpu = row.get("reference_cpu_s")
    busy = ref / cpu if cpu else None
    print(line(row["row"], row["path"], seconds, ref, quiet, row["goal_s"], first, busy), flush=True)
    for extra in row["extras"]:
        print(line("", "  " + extra["label"], extra["seconds"], ref, quiet, extra["goal_s"], ""), flush=True)
    if row["note"]:
        print(f"{'':>3}   {row['note']}", flush=True)


def run_rows(keys: list[str], ctx: Context, quiet: float | None) -> list[dict[str, Any]]:
    """Measure the rows ``keys`` between two reference runs each; print each as it is done."""
    out = []
    print(HEADER, flush=True)
    for key in keys:
        goal = TABLE[key]
        if key in PREPARE:
            PREPARE[key](ctx)
        ref0, cpu0 = reference()
        try:
            m = ROWS[key](ctx)
        except Exception as exc:  # a path that fails is a row of the table, not the end of it
            m = Measured(float("nan"), note=f"FAILED: {type(exc).__name__}: {exc}")
        ref1, cpu1 = reference()
        ref = 0.5 * (ref0 + ref1)
        row = {
            "row": key,
            "path": goal.path,
            "seconds": m.seconds if np.isfinite(m.seconds) else None,
            "reference_s": ref,
            "reference_before_s": ref0,
            "reference_after_s": ref1,
            "reference_cpu_s": 0.5 * (cpu0 + cpu1),
            "ratio": m.seconds / ref if np.isfinite(m.seconds) else None,
            "quiet_estimate_s": m.seconds * quiet / ref if quiet is not None and np.isfinite(m.seconds) else None,
            "goal_s": goal.goal_s,
            "first_round_s": goal.first_round_s,
            "at_filing_s": goal.filed_s,
            "extras": [{"label": lab.strip(), "seconds": s, "goal_s": g} for lab, s, g in m.extras],
            "note": m.note,
        }
        print_row(row, quiet)
        out.append(row)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--full", action="store_true", help="also rows 7, 8, 11 (study thesis, inverse, make lint/test)")
    ap.add_argument("--rows", nargs="+", choices=list(TABLE), help="only these rows (default: all of the run's set)")
    ap.add_argument("--json", metavar="PATH", help="write the table here as JSON")
    ap.add_argument(
        "--cache",
        type=Path,
        default=Path(tempfile.gettempdir()) / "scopetwin-speed-table",
        help="folder of the cached renders and the CLI's outputs (default: TMPDIR/scopetwin-speed-table)",
    )
    ap.add_argument("--fresh", action="store_true", help="render the cached frames again")
    ap.add_argument(
        "--calibrate",
        action="store_true",
        help=f"time the reference only (minimum of --runs) and write it to {REFERENCE_FILE.name}: on a quiet machine",
    )
    ap.add_argument("--runs", type=int, default=30, help="reference runs of --calibrate")
    ap.add_argument(
        "--reprint", metavar="JSON", help="print a table written by --json again, with the quiet reference stored now"
    )
    args = ap.parse_args()

    load = os.getloadavg()[0]
    if args.calibrate:
        if load > 0.5:
            print(
                f"warning: load average {load:.2f}: the machine is not quiet; where even the fastest run is slowed, "
                "the reference's CPU time is recorded instead (a quiet machine is better)"
            )
        rec = calibrate(args.runs, REFERENCE_FILE)
        print(
            f"quiet reference {rec['reference_s']:.4f} s ({rec['basis']}; wall minimum {rec['wall_min_s']:.4f} s, "
            f"median {rec['wall_median_s']:.4f} s, CPU minimum {rec['cpu_min_s']:.4f} s of {rec['runs']} runs, "
            f"load average {rec['load_average']:.2f}) -> {REFERENCE_FILE}"
        )
        return

    keys = args.rows or [k for k, g in TABLE.items() if args.full or not g.full_only]
    stored = load_quiet_reference()
    quiet = float(stored["reference_s"]) if stored else None
    if args.reprint:
        table = json.loads(Path(args.reprint).read_text())
        print(f"{args.reprint}: load average {table['load_average_start']:.2f} at its start; quiet reference {quiet}")
        print(HEADER)
        for row in table["rows"]:
            print_row(row, quiet)
        return
    print(
        f"speed table: {os.cpu_count()} CPUs, load average {load:.2f}; reference = {REFERENCE_ROUNDS} x "
        f"(Cholesky, product) of a seeded {REFERENCE_N}^2 SPD matrix on one BLAS thread, timed before and "
        f"after each row; quiet reference "
        + (
            f"{quiet:.4f} s ({stored['date'] if stored else ''}, load {stored['load_average']:.2f})"
            if stored and quiet is not None
            else f"not recorded (run --calibrate on a quiet machine: {REFERENCE_FILE.name})"
        ),
        flush=True,
    )
    if stored and stored.get("machine") != platform.platform():
        print(
            f"note: the quiet reference was recorded on {stored.get('machine')}, this is {platform.platform()}: "
            "record it here (--calibrate on a quiet machine) before quoting the estimates",
            flush=True,
        )
    stale = uncompiled_modules()
    if stale and sys.dont_write_bytecode:
        print(
            f"note: {len(stale)} of the project's modules have no up-to-date bytecode and this environment writes none "
            "(PYTHONDONTWRITEBYTECODE): the CLI rows include compiling them in every process (make setup writes it)",
            flush=True,
        )
    reference()  # warm: the matrix, BLAS's first call
    ctx = Context(args.cache, args.fresh)
    t0 = time.perf_counter()
    try:
        rows = run_rows(keys, ctx, quiet)
    finally:
        shutil.rmtree(ctx.work, ignore_errors=True)  # the CLI's outputs; the cached renders stay
    print(f"(rows took {time.perf_counter() - t0:.0f} s; load average now {os.getloadavg()[0]:.2f})")
    if args.json:
        Path(args.json).write_text(
            json.dumps(
                {
                    "cpus": os.cpu_count(),
                    "load_average_start": load,
                    "load_average_end": os.getloadavg()[0],
                    "modules_without_bytecode": len(stale),
                    "quiet_reference": stored,
                    "glass_surface": GLASS,
                    "glass_seeds": list(GLASS_SEEDS),
                    "rows": rows,
                },
                indent=2,
            )
            + "\n"
        )


if __name__ == "__main__":
    main()
