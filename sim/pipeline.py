"""The end-to-end job of ``scopetwin run``: simulate, render, calibrate, reconstruct, compare, report.

1. a §1.9 random surface on the §1.10 substrate (40 µm range);
2. Mitsuba renders, sensor noise on: the target on the holding frame and the pattern in a flat mirror
   (the two calibration images of §2.7) and the measurement image of the bent substrate (§1.10);
3. calibration of the setup from the two calibration images (``calib``, §2.7);
4. marker detection (``recon.markers``) and reconstruction (``recon.reconstruct``, §1.4) with the
   calibrated and with the ideal setup, centroid-bias correction on, and the reconstruction from the exact marker
   images (the method's own floor); steps 3 and 4 on two threads (:func:`_calibrate_and_reconstruct`);
5. comparison with the truth over the region of interest — absolute height (ROI mean error), shape
   (RMS after removing the ROI mean), RMS and maximum — beside the thesis's §1.10 / Table 2.7 figures;
6. a report folder: ``report.md``, EXR height and error maps, PNG plots, the focus map, ``summary.json``.

The caller stages ``out_dir`` atomically; this module only writes into it.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap

if TYPE_CHECKING:
    from scopetwin.recon.focusmap import FocusMap
    from scopetwin.recon.markers import Markers
    from scopetwin.recon.posterior import Prior
    from scopetwin.recon.reconstruct import MarkerObservations, ReconstructionResult
    from scopetwin.recon.substrate import Substrate2D

log = logging.getLogger(__name__)

MEASUREMENT = "thesis-1.10-deflectometry"
TARGET = "thesis-2.8.3-substrate"
MIRROR = "thesis-2.8.3-mirror"

#: The thesis's figures (§1.10 height distribution 2, §2.8.4 Table 2.7), µm.
SEED = {"ideal": {"roi_rms_um": 0.091, "roi_max_um": 0.357}, "calibrated": {"roi_rms_um": 0.414, "roi_max_um": 1.162}}


def render_with_noise(setup: Setup, heights: HeightMap | None, spp: int, seed: int) -> NDArray[np.float32]:
    """Mitsuba render plus the EMVA sensor model (:func:`scopetwin.sim.measurement.apply_sensor`), as float32."""
    from scopetwin.scenes.mitsuba.render import render_setup
    from scopetwin.sim.measurement import apply_sensor

    image = render_setup(setup, heights, spp=spp, seed=seed)
    return np.asarray(apply_sensor(setup, image, seed), dtype=np.float32)


def roi_errors(
    surface_height: Callable[[NDArray[Any], NDArray[Any]], NDArray[Any]], truth: HeightMap, sub: Any, step: float = 0.2
) -> dict[str, float]:
    """Errors of a reconstruction against the truth: ROI absolute/shape/RMS/max and whole-substrate RMS/max, µm."""
    xs = np.linspace(-0.5 * sub.size_x, 0.5 * sub.size_x, int(round(sub.size_x / step)) + 1)
    ys = np.linspace(-0.5 * sub.size_y, 0.5 * sub.size_y, int(round(sub.size_y / step)) + 1)
    xx, yy = np.meshgrid(xs, ys)
    err = (surface_height(xx, yy) - truth.height(xx, yy)) * 1e3
    roi = np.abs(yy) < 0.5 * sub.roi_length
    e = err[roi]
    return {
        "roi_absolute_um": float(e.mean()),
        "roi_shape_um": float(e.std()),
        "roi_rms_um": float(np.sqrt(np.mean(e**2))),
        "roi_max_um": float(np.abs(e).max()),
        "all_rms_um": float(np.sqrt(np.mean(err**2))),
        "all_max_um": float(np.abs(err).max()),
    }


def _plots(
    out: Path, image: NDArray[Any], found: Any, truth: HeightMap, results: dict[str, Any], sub: Any
) -> list[str]:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure  # the object API: no pyplot state, no GUI backend

    names = []
    ext = [-0.5 * sub.size_x, 0.5 * sub.size_x, -0.5 * sub.size_y, 0.5 * sub.size_y]
    xx, yy = np.meshgrid(np.linspace(ext[0], ext[1], 126), np.linspace(ext[2], ext[3], 286))
    fig = Figure(figsize=(4 + 4 * len(results), 6))  # fixed margins: a layout engine would double the drawing time
    FigureCanvasAgg(fig)
    fig.subplots_adjust(left=0.05, right=0.97, top=0.94, bottom=0.08, wspace=0.3)
    axes = fig.subplots(1, 1 + len(results))
    im = axes[0].imshow(truth.height(xx, yy) * 1e3, origin="lower", extent=ext, cmap="viridis")
    axes[0].set_title("truth height, µm")
    fig.colorbar(im, ax=axes[0])
    for ax, (name, r) in zip(axes[1:], results.items(), strict=True):
        im = ax.imshow(r["result"].surface.height(xx, yy) * 1e3, origin="lower", extent=ext, cmap="viridis")
        ax.set_title(f"reconstructed ({name}), µm")
        fig.colorbar(im, ax=ax)
    for ax in axes:
        ax.axhline(-0.5 * sub.roi_length, color="w", lw=0.8)
        ax.axhline(0.5 * sub.roi_length, color="w", lw=0.8)
        ax.set_xlabel("x, mm")
    _save_png(fig, out / "height.png", 90)
    names.append("height.png")

    fig = Figure(figsize=(4.5 * len(results), 6))
    FigureCanvasAgg(fig)
    fig.subplots_adjust(left=0.08, right=0.95, top=0.94, bottom=0.05, wspace=0.35)
    axes = fig.subplots(1, len(results), squeeze=False)
    roi = np.abs(yy) < 0.5 * sub.roi_length
    for ax, (name, r) in zip(axes[0], results.items(), strict=True):
        err = np.where(roi, (r["result"].surface.height(xx, yy) - truth.height(xx, yy)) * 1e3, np.nan)
        im = ax.imshow(err, origin="lower", extent=ext, cmap="RdBu_r")
        ax.set_title(f"error in the ROI ({name}), µm")
        fig.colorbar(im, ax=ax)
    _save_png(fig, out / "error.png", 90)
    names.append("error.png")

    fig = Figure(figsize=(10, 7.5))
    FigureCanvasAgg(fig)
    fig.subplots_adjust(left=0.06, right=0.98, top=0.95, bottom=0.05)
    ax = fig.subplots()
    ax.imshow(image, cmap="gray", vmax=float(np.percentile(image, 99.9)))
    ax.plot(found.centroids[:, 0] - 0.5, found.centroids[:, 1] - 0.5, "r+", ms=4, mew=0.6)
    ref = np.flatnonzero((found.ij[:, 0] == 0) & (found.ij[:, 1] == 0))
    if len(ref):
        ax.plot(*(found.centroids[ref[0]] - 0.5), "co", mfc="none", ms=12)
    ax.set_title(f"measurement image with {len(found.ij)} indexed markers (cyan: reference)")
    _save_png(fig, out / "markers.png", 80)
    names.append("markers.png")

    fig = Figure(figsize=(11, 4))
    FigureCanvasAgg(fig)
    fig.subplots_adjust(left=0.07, right=0.98, top=0.95, bottom=0.13, wspace=0.25)
    axes = fig.subplots(1, 2)
    for name, r in results.items():
        hist = r["result"].history
        axes[0].semilogy(range(1, len(hist) + 1), [max(abs(s.criterion_um), 1e-6) for s in hist], "o-", label=name)
        changes = [c for s in hist for c in s.inner_rms_change_um]
        axes[1].semilogy(range(1, len(changes) + 1), changes, ".-", label=name)
    axes[0].set_xlabel("outer iteration (start height)")
    axes[0].set_ylabel("|criterion|, µm")
    axes[1].set_xlabel("inner iteration (all outer runs)")
    axes[1].set_ylabel("RMS height change, µm")
    for ax in axes:
        ax.legend()
        ax.grid(True, which="both", alpha=0.3)
    _save_png(fig, out / "convergence.png", 90)
    names.append("convergence.png")
    return names


def _save_png(fig: Any, path: Path, dpi: int) -> None:
    """``fig`` as a PNG at ``path``, written atomically (beside it, then renamed over it)."""
    from scopetwin.scenes.io import atomic_path

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi)


def _import_plotting() -> None:
    """Import what :func:`_plots` needs (~0.3 s), on a thread of its own while the renders run."""
    import matplotlib.backends.backend_agg  # noqa: F401
    import matplotlib.figure  # noqa: F401


def run_setups(
    setup_name: str | None, surface_path: str | Path | None, over: dict[str, Any]
) -> tuple[Setup, Setup, Setup]:
    """The measurement setup and the two calibration setups (target on the frame, pattern in a flat mirror).

    Default: the §1.10 preset and the §2.8.3 calibration presets. With ``setup_name`` (a preset name or TOML),
    the measurement is that setup and both calibration scenes take its camera (the mirror scene also its pattern
    and substrate), so the calibration describes the user's rig. ``surface_path`` (a height-map EXR of the
    contract) replaces the substrate's surface; it must cover the substrate.
    """
    from scopetwin.scenes.io import read_heightmap
    from scopetwin.scenes.setup import load_setup

    over = json.loads(json.dumps(over))
    if surface_path is not None:
        path = Path(surface_path)
        over.setdefault("substrate", {})["surface"] = {"kind": "file", "path": str(path.resolve())}
    setup = load_setup(setup_name or MEASUREMENT, over)
    if setup.scene != "deflectometry" or setup.substrate is None:
        raise ScopetwinError(f"setup {setup_name} is a {setup.scene!r} scene; run needs a deflectometry setup")
    if surface_path is not None:
        hm = read_heightmap(surface_path)
        sx, sy = setup.substrate.size
        tol = 1e-6
        if (
            hm.x_min > -0.5 * sx + tol
            or hm.x_max < 0.5 * sx - tol
            or hm.y_min > -0.5 * sy + tol
            or hm.y_max < 0.5 * sy - tol
        ):
            raise ScopetwinError(
                f"--surface {surface_path}: the height map covers x {hm.x_min:g}..{hm.x_max:g}, y {hm.y_min:g}.."
                f"{hm.y_max:g} mm but the substrate is {sx:g} x {sy:g} mm (centred): it must cover it"
            )
    render_over: dict[str, Any] = {"render": dict(over.get("render", {}))}
    if setup_name is None:
        return setup, load_setup(TARGET, render_over), load_setup(MIRROR, render_over)
    return (setup, *calibration_setups(setup, render_over))


def calibration_setups(setup: Setup, over: dict[str, Any] | None = None) -> tuple[Setup, Setup]:
    """The two calibration scenes of a deflectometry setup (thesis §2.7): the §2.8.3 target on the holding frame seen
    by the setup's camera, and the setup's pattern (or display) seen in a flat mirror on the frame by that camera
    (with the setup's substrate); ``over`` (e.g. ``{"render": {...}}``) overrides both."""
    from scopetwin.scenes.setup import load_setup

    if setup.substrate is None:
        raise ScopetwinError(f"setup {setup.name} is a {setup.scene!r} scene; its calibration needs a substrate")
    base = dict(over or {})
    camera = setup.camera.model_dump(exclude_none=True)
    target = load_setup(TARGET, {**base, "camera": camera})
    mirror = load_setup(
        MIRROR,
        {
            **base,
            "camera": camera,
            "pattern": setup.pattern.model_dump(exclude_none=True) if setup.pattern is not None else {},
            "substrate": setup.substrate.model_dump(exclude_none=True),
        },
    )
    return target, mirror


def surface_description(setup: Setup) -> str:
    """One line naming the substrate surface of a setup (family and parameters, or the file)."""
    if setup.substrate is None:
        return "no substrate"
    s = setup.substrate.surface
    bb = f", broadband {s.broadband_rms_nm:g} nm RMS" if s.broadband_rms_nm > 0 else ""
    if s.kind == "file":
        return f"height map {s.path}"
    if s.kind == "random":
        return (
            f"§1.9 generator, {s.range_um:g} µm range, Gaussian low-pass sigma {s.correlation_length:g} mm{bb}, "
            f"seed {s.seed}"
        )
    if s.kind == "psd":
        model = "K-correlation (ABC)" if s.spectrum == "abc" else "power law"
        return (
            f"PSD surface ({model}, B {s.correlation_length:g} mm, C {s.psd_exponent:g}, roll-off "
            f"{s.psd_rolloff_mm:g} mm), {s.range_um:g} µm range{bb}, seed {s.seed}"
        )
    return f"analytic {s.kind}, {s.range_um:g} µm range"


def run_pipeline(
    out_dir: Path,
    spp: int | None,
    seed: int | None,
    progress: bool,
    setup: str | None = None,
    surface: str | Path | None = None,
) -> dict[str, Any]:
    """Simulate, render, calibrate, reconstruct and compare; write the report folder into ``out_dir``.

    Parameters
    ----------
    out_dir : Path
        Folder to write into (created; the caller stages it atomically). Each file is written atomically too, and
        a folder that is a symbolic link is refused.
    spp : int, optional
        Samples per pixel of the renders (default: the setups' own).
    seed : int, optional
        Seed of the surface and of the renders (default: the preset's surface seed, render seed 0).
    progress : bool
        Show a progress bar.
    setup : str, optional
        Measurement setup (preset name or TOML; default the §1.10 preset), see :func:`run_setups`.
    surface : path, optional
        Height-map EXR of the substrate (default: the setup's own surface).

    Returns
    -------
    dict
        The summary (also written to ``summary.json``).
    """
    from scopetwin.recon.reconstruct import single_thread_blas

    with single_thread_blas():  # small dense problems: threaded BLAS only costs (recon.reconstruct)
        return _run(Path(out_dir), spp, seed, progress, setup, surface)


class _Steps:
    """The progress bar over the seven steps of a run and the seconds each timed step took (``timings_s``)."""

    def __init__(self, progress: bool) -> None:
        from tqdm import tqdm

        self.timings: dict[str, float] = {}
        self.bar = tqdm(total=7, desc="scopetwin run", unit="step", disable=not progress)
        self.t = time.perf_counter()

    def record(self, name: str, seconds: float) -> None:
        """Step ``name`` took ``seconds`` (run beside others): record it, advance the bar."""
        self.timings[name] = seconds
        self.bar.update(1)
        self.bar.set_postfix_str(name)
        self.t = time.perf_counter()

    def tick(self, name: str) -> None:
        """Step ``name`` is done: record its time, advance the bar."""
        self.timings[name] = time.perf_counter() - self.t
        self.bar.update(1)
        self.bar.set_postfix_str(name)
        self.t = time.perf_counter()


class _Worker:
    """One daemon thread that runs the calls given to :meth:`submit` in order, each result a :class:`Future`.

    A daemon, so that an interrupted run ends at once (the caller discards its staging folder) instead of waiting
    for the call under way; :meth:`stop` cancels the calls not yet started.
    """

    def __init__(self) -> None:
        self._calls: queue.SimpleQueue[tuple[Future[Any], Callable[..., Any], tuple[Any, ...]] | None] = (
            queue.SimpleQueue()
        )
        self._stopped = threading.Event()
        threading.Thread(target=self._work, name="scopetwin-run", daemon=True).start()

    def submit(self, fn: Callable[..., Any], *args: Any) -> Future[Any]:
        """``fn(*args)`` after the calls submitted before it."""
        fut: Future[Any] = Future()
        self._calls.put((fut, fn, args))
        return fut

    def stop(self) -> None:
        """The thread ends after the call under way; the calls not yet started are cancelled."""
        self._stopped.set()
        self._calls.put_nowait(None)

    def _work(self) -> None:
        while (item := self._calls.get()) is not None:
            fut, fn, args = item
            if self._stopped.is_set():
                fut.cancel()
                continue
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                fut.set_result(fn(*args))
            except BaseException as exc:  # handed to the caller through the future
                fut.set_exception(exc)


def _calibrate_and_reconstruct(
    image: NDArray[Any],
    setup: Setup,
    target: tuple[Setup, NDArray[Any]],
    mirror: tuple[Setup, NDArray[Any]],
    heights: HeightMap,
    out: Path,
    steps: _Steps,
) -> tuple[Setup | None, str, Markers, dict[str, Any], tuple[ReconstructionResult, dict[str, float]]]:
    """Steps 3-5 on two threads: the calibration and the reconstruction with the calibrated setup here, the
    reconstruction with the ideal setup and the truth reference beside them (:class:`_Worker`).

    The work is numpy and LAPACK on one BLAS thread each (:func:`run_pipeline`), which release the interpreter lock, so
    the two chains share the two cores of a small machine. The results are those of the steps run one after the
    other: the calibrated reconstruction waits for the ideal one's prior as its evidence start
    (:func:`_detect_and_reconstruct`). ``steps`` records each step's own seconds (they overlap).

    Returns the calibrated setup (None where the calibration failed), the report's calibration note, the markers
    found with the ideal setup, the results per setup name and the truth reference with its errors.
    """
    from scopetwin.recon.substrate import Substrate2D

    sub = Substrate2D.from_setup(setup)
    worker = _Worker()
    try:
        ideal = worker.submit(_timed, _reconstruct_one, image, "ideal", setup, out, heights, sub, None, None)
        truth = worker.submit(_timed, _truth_reference, setup, heights, sub)
        (calibrated, note), t_cal = _timed(_calibrate, target[0], mirror[0], target[1], mirror[1], out)
        steps.record("calibrate", t_cal)
        (found, r_ideal), t_ideal = ideal.result()
        prior, scale = _next_start(r_ideal["result"])
        (_, r_cal), t_rec = _timed(
            _reconstruct_one, image, "calibrated", calibrated or setup, out, heights, sub, prior, scale
        )
        steps.record("detect + reconstruct", t_ideal + t_rec)
        exact, t_truth = truth.result()
        steps.record("truth reference", t_truth)
    finally:
        worker.stop()
    return calibrated, note, found, {"ideal": r_ideal, "calibrated": r_cal}, exact


def _timed(fn: Callable[..., Any], *args: Any) -> tuple[Any, float]:
    """``fn(*args)`` and its seconds."""
    t0 = time.perf_counter()
    return fn(*args), time.perf_counter() - t0


def _run(
    out_dir: Path,
    spp: int | None,
    seed: int | None,
    progress: bool,
    setup_name: str | None,
    surface_file: str | Path | None,
) -> dict[str, Any]:
    from scopetwin.recon.reconstruct import MarkerObservations
    from scopetwin.recon.substrate import Substrate2D
    from scopetwin.scenes.io import write_json_atomic, write_text_atomic
    from scopetwin.sim.measurement import _refuse_link

    out = Path(out_dir)
    _refuse_link(out)  # a folder of its own: a link to another folder is not written through
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    threading.Thread(target=_import_plotting, name="scopetwin-imports", daemon=True).start()
    steps = _Steps(progress)
    setup, target_setup, mirror_setup, heights = _surface_and_setups(spp, seed, setup_name, surface_file)
    sub = Substrate2D.from_setup(setup)
    r_spp, r_seed = setup.render.spp, setup.render.seed
    steps.tick("surface")
    img_target = render_with_noise(target_setup, None, r_spp, r_seed + 1)
    img_mirror = render_with_noise(mirror_setup, None, r_spp, r_seed + 2)
    steps.tick("render calibration images")
    image = render_with_noise(setup, heights, r_spp, r_seed)
    steps.tick("render measurement")
    calibrated, calibration_note, found, results, (res_exact, exact_err) = _calibrate_and_reconstruct(
        image, setup, (target_setup, img_target), (mirror_setup, img_mirror), heights, out, steps
    )
    obs = MarkerObservations(found.ij, found.centroids)
    images = {
        "measurement.exr": (image, setup),
        "calib-target.exr": (img_target, target_setup),
        "calib-mirror.exr": (img_mirror, mirror_setup),
    }
    files = _write_files(out, heights, images, calibrated is not None, results)
    fm = _write_focus_map(out, results, sub)
    files += ["focusmap.csv"] + _plots(out, image, found, heights, results, sub)
    summary = _summary(setup, len(obs.ij), calibration_note, results, (res_exact, exact_err), fm)
    summary.update({"focus_map": fm.summary(), "timings_s": steps.timings, "files": files})
    if calibrated is not None:
        summary["calibration_deviation"] = _calibration_deviation(setup, calibrated)
    summary["seconds"] = time.perf_counter() - t_start
    write_text_atomic(out / "report.md", _report(summary))
    write_json_atomic(out / "summary.json", summary)
    steps.bar.update(1)
    steps.bar.close()
    return summary


def _surface_and_setups(
    spp: int | None, seed: int | None, setup_name: str | None, surface_file: str | Path | None
) -> tuple[Setup, Setup, Setup, HeightMap]:
    """The measurement and calibration setups (:func:`run_setups`, noise on) and the substrate's true surface."""
    from scopetwin.sim.surfaces import surface_for

    over: dict[str, Any] = {"render": {"noise": True}}
    if spp is not None:
        over["render"]["spp"] = spp
    if seed is not None:
        over["render"]["seed"] = seed
        over["substrate"] = {"surface": {"seed": seed}}
    setup, target_setup, mirror_setup = run_setups(setup_name, surface_file, over)
    heights = surface_for(setup)
    assert heights is not None
    return setup, target_setup, mirror_setup, heights


def _calibrate(
    target_setup: Setup, mirror_setup: Setup, img_target: NDArray[Any], img_mirror: NDArray[Any], out: Path
) -> tuple[Setup | None, str]:
    """Setup calibration of §2.7 from the two calibration images (calib/, bias-corrected); writes its TOML.

    Returns the calibrated setup (None where the calibration is unavailable or failed) and the report's note.
    """
    try:
        from scopetwin.calib.setup_calibration import calibrate_setup_from_images
        from scopetwin.scenes.io import write_text_atomic

        cal = calibrate_setup_from_images(
            img_target,
            img_mirror,
            target_setup,
            mirror_setup,
            comment="scopetwin run: setup calibrated as in thesis §2.7",
        )
        write_text_atomic(out / "calibrated-setup.toml", cal.toml)
    except (ImportError, ScopetwinError) as exc:
        log.warning("setup calibration failed; the 'calibrated' row uses the ideal setup", exc_info=True)
        return None, f"UNAVAILABLE ({type(exc).__name__}: {exc}); the 'calibrated' row uses the ideal setup"
    return cal.setup, "calib/ (§2.7: target on the frame + pattern in a flat mirror, bias-corrected)"


def _detect_and_reconstruct(
    image: NDArray[Any], setups: dict[str, Setup], out: Path, heights: HeightMap, sub: Substrate2D
) -> tuple[Markers, MarkerObservations, dict[str, Any]]:
    """The measurement image reconstructed with each setup by the one strategy (:mod:`scopetwin.recon.strategy`:
    markers found with that setup, a tied reference marker decided, every fallback), as ``scopetwin reconstruct``
    does.

    Returns the markers found with the ideal setup, their observations and per setup name ``{"result", "seconds",
    "errors"}`` (:func:`roi_errors` against the truth ``heights``); a history that is not accepted goes to
    ``out/<name>-history.json``. The same image's later reconstructions start where the first one ended, as
    ``scopetwin.reconstruct(previous=)`` does: their search on its basis scale, their posterior's evidence
    maximisation from its prior (``evidence_start``, one start instead of two cold ones).
    """
    from scopetwin.recon.reconstruct import MarkerObservations

    results: dict[str, Any] = {}
    found: Markers | None = None
    prior: Prior | None = None
    scale: float | None = None
    for name, s in setups.items():
        markers, results[name] = _reconstruct_one(image, name, s, out, heights, sub, prior, scale)
        if prior is None:
            prior, scale = _next_start(results[name]["result"])
        found = markers if found is None or name == "ideal" else found
    assert found is not None
    return found, MarkerObservations(found.ij, found.centroids), results


def _next_start(res: ReconstructionResult) -> tuple[Prior | None, float | None]:
    """Where the same image's next reconstruction starts: ``res``'s prior and the basis scale it ended on (None, None
    without an uncertainty)."""
    from scopetwin.recon.posterior import prior_from_dict

    if res.uncertainty is None:
        return None, None
    return prior_from_dict(res.uncertainty.hyper), float(res.surface.basis.sigma[0])


def _reconstruct_one(
    image: NDArray[Any],
    name: str,
    setup: Setup,
    out: Path,
    heights: HeightMap,
    sub: Substrate2D,
    prior: Prior | None,
    scale: float | None,
) -> tuple[Markers, dict[str, Any]]:
    """The image reconstructed with one setup (:func:`scopetwin.recon.strategy.reconstruct`; its search started on
    the basis scale ``scale``, its evidence from ``prior``, where given): the markers found and ``{"result",
    "seconds", "errors"}``; a history that is not accepted goes to ``out/<name>-history.json``."""
    from scopetwin.recon.config import ReconstructionConfig
    from scopetwin.recon.strategy import reconstruct

    t0 = time.perf_counter()
    config = ReconstructionConfig().starting_at(scale)
    done = reconstruct(image, setup, config=config, history_path=out / f"{name}-history.json", evidence_start=prior)
    markers, res = done.markers, done.result
    seconds = time.perf_counter() - t0
    return markers, {"result": res, "seconds": seconds, "errors": roi_errors(res.surface.height, heights, sub)}


def _truth_reference(
    setup: Setup, heights: HeightMap, sub: Substrate2D
) -> tuple[ReconstructionResult, dict[str, float]]:
    """Reconstruction from the exact marker images with the ideal setup and its errors (the method's own floor)."""
    from scopetwin.recon.reconstruct import MarkerObservations, Reconstructor
    from scopetwin.recon.strategy import solve
    from scopetwin.sim.truth import marker_truth

    truth = marker_truth(setup, heights)
    exact = MarkerObservations(truth.ij[truth.visible], truth.center_px[truth.visible])
    res_exact = solve(Reconstructor.from_setup(setup), exact)
    return res_exact, roi_errors(res_exact.surface.height, heights, sub)


def _write_files(
    out: Path,
    heights: HeightMap,
    images: dict[str, tuple[NDArray[Any], Setup]],
    calibrated: bool,
    results: dict[str, Any],
) -> list[str]:
    """The truth, the images (each with its setup in the header), each reconstruction's heights and error maps."""
    from scopetwin.scenes.io import write_heightmap, write_image

    write_heightmap(out / "truth-heights.exr", heights)
    for name, (image, setup) in images.items():
        write_image(out / name, image, setup.to_json())
    files = ["truth-heights.exr", *images]
    if calibrated:
        files.append("calibrated-setup.toml")
    nx, ny = heights.z.shape[1] // 2, heights.z.shape[0] // 2
    for name, r in results.items():
        hm = r["result"].heightmap(nx, ny)
        measured = r["result"].measured_mask(nx, ny)
        write_heightmap(out / f"heights-{name}.exr", hm, r["result"].std_heightmap(nx, ny), measured)
        err = HeightMap(
            hm.z - heights.height(*np.meshgrid(hm.x_nodes, hm.y_nodes)), hm.x_min, hm.x_max, hm.y_min, hm.y_max
        )
        write_heightmap(out / f"error-{name}.exr", err, measured=measured)
        files += [f"heights-{name}.exr", f"error-{name}.exr"]
    return files


def _write_focus_map(out: Path, results: dict[str, Any], sub: Substrate2D) -> FocusMap:
    """The focus map over the ROI from the calibrated reconstruction and its uncertainty; writes focusmap.csv."""
    from scopetwin.recon.focusmap import focus_map
    from scopetwin.scenes.io import write_text_atomic

    cal_res = results["calibrated"]["result"]
    cal_std = cal_res.std_heightmap()
    fm = focus_map(
        cal_res.surface.height,
        sub.x_range,
        (-0.5 * sub.roi_length, 0.5 * sub.roi_length),
        height_std=cal_std.height if cal_std is not None else None,
    )
    write_text_atomic(out / "focusmap.csv", fm.to_csv())
    return fm


def _summary(
    setup: Setup,
    markers: int,
    calibration_note: str,
    results: dict[str, Any],
    exact: tuple[ReconstructionResult, dict[str, float]],
    fm: FocusMap,
) -> dict[str, Any]:
    """The summary up to the focus map (the caller adds it, the timings, the files and the calibration deviation)."""
    surface = setup.substrate.surface if setup.substrate is not None else None
    if surface is None:
        raise ScopetwinError(f"setup {setup.name} has no substrate surface to compare with")
    res_exact, exact_err = exact
    return {
        "setup": setup.name,
        "surface": {
            "kind": surface.kind,
            "description": surface_description(setup),
            "range_um": surface.range_um,
            "correlation_length_mm": surface.correlation_length,
            "seed": surface.seed,
            "broadband_rms_nm": surface.broadband_rms_nm,
        },
        "spp": setup.render.spp,
        "render_seed": setup.render.seed,
        "markers": int(markers),
        "calibration": calibration_note,
        "reconstructions": {name: _reconstruction_summary(r) for name, r in results.items()},
        "exact_markers": {
            **exact_err,
            "outer_iterations": res_exact.outer_iterations,
            "roi_coverage": res_exact.roi_coverage(),
            **({"uncertainty": res_exact.uncertainty.summary()} if res_exact.uncertainty is not None else {}),
        },
    }


def _reconstruction_summary(r: dict[str, Any]) -> dict[str, Any]:
    """One reconstruction's entry of ``summary["reconstructions"]``: errors, iterations, time, uncertainty, history."""
    res = r["result"]
    return {
        **r["errors"],
        "outer_iterations": res.outer_iterations,
        "inner_iterations": res.inner_iterations,
        "delta_h_max_um": res.delta_h_max_um,
        "seconds": r["seconds"],
        "sigma_mm": res.surface.basis.sigma[0],
        "roi_coverage": res.roi_coverage(),
        **({"uncertainty": res.uncertainty.summary()} if res.uncertainty is not None else {}),
        "history": res.history_dicts(),
    }


def _calibration_deviation(setup: Setup, calibrated: Setup) -> dict[str, Any]:
    """Calibrated minus ideal camera and pattern poses (the report's "Calibration deviation" section)."""
    cam_i, cam_c = setup.camera_model, calibrated.camera_model
    pat_i, pat_c = setup.marker_pattern.frame, calibrated.marker_pattern.frame
    return {
        "camera_r_c_mm": (cam_c.center - cam_i.center).tolist(),
        "camera_b_mm": cam_c.b - cam_i.b,
        "camera_n_z": (cam_c.frame.nz - cam_i.frame.nz).tolist(),
        "pattern_r_c_mm": (pat_c.origin - pat_i.origin).tolist(),
        "pattern_n_z": (pat_c.nz - pat_i.nz).tolist(),
    }


_OVERLAP = "(calibrate, detect + reconstruct and truth reference run on two threads: their seconds overlap.)"


def _deviation_lines(s: dict[str, Any]) -> list[str]:
    """The report's "Calibration deviation" section (none without a calibration)."""
    if "calibration_deviation" not in s:
        return []
    d = s["calibration_deviation"]
    return [
        "## Calibration deviation from the ideal setup",
        "",
        f"- camera r_c: {np.round(d['camera_r_c_mm'], 5).tolist()} mm, b: {d['camera_b_mm']:+.2e} mm, "
        f"N_z: {np.round(d['camera_n_z'], 7).tolist()}",
        f"- pattern r_c: {np.round(d['pattern_r_c_mm'], 5).tolist()} mm, N_z: {np.round(d['pattern_n_z'], 7).tolist()}",
        "",
    ]


def _report(s: dict[str, Any]) -> str:
    rec = s["reconstructions"]
    ex = s["exact_markers"]
    surf = s["surface"]
    lines = [
        "# scopetwin run: deflectometric reconstruction end to end",
        "",
        f"Setup: {s['setup']}. Surface: {surf['description']}. Renders: Mitsuba, {s['spp']} spp, "
        "sensor noise on. "
        f"{s['markers']} markers detected and indexed in the measurement image.",
        "",
        f"Calibration: {s['calibration']}.",
        "",
        "Reconstruction: Gaussian shifted basis (sigma 12 mm, ridge-regularised, plane terms), centroid-bias "
        "correction in the inner loop, start height by a secant root search on the frame criterion "
        "(both frame maxima at the frame position); the frame maxima and the uncertainties from the Gaussian-"
        "process reading of the fit (recon.posterior: prior chosen by evidence).",
        "",
        "## ROI errors beside the thesis (µm)",
        "",
        "u: one standard uncertainty as reported by the reconstruction (no truth used).",
        "",
        "ROI covered: the share of the ROI within two marker spacings (3 mm) of a marker; the height maps leave the "
        "rest NaN (channel Z_measured).",
        "",
        "| reconstruction | ROI RMS | ROI max | absolute (ROI mean) | u(absolute) | shape (RMS - mean) | u(shape) "
        "| whole RMS | outer | inner | ROI covered | thesis ROI RMS | thesis ROI max |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

    def covered(r: dict[str, Any]) -> str:
        c = r.get("roi_coverage")
        return "" if c is None else f"{100.0 * c:.0f} %"

    def u_cells(r: dict[str, Any]) -> tuple[str, str]:
        u = r.get("uncertainty")
        return (f"{u['absolute_um']:.4f}", f"{u['shape_um']:.4f}") if u else ("", "")

    for name in ("ideal", "calibrated"):
        r = rec[name]
        sd = SEED[name]
        ua, us = u_cells(r)
        lines.append(
            f"| {name} setup | {r['roi_rms_um']:.4f} | {r['roi_max_um']:.4f} | {r['roi_absolute_um']:+.4f} | {ua} "
            f"| {r['roi_shape_um']:.4f} | {us} | {r['all_rms_um']:.3f} | {r['outer_iterations']} | "
            f"{r['inner_iterations']} | {covered(r)} | {sd['roi_rms_um']} | {sd['roi_max_um']} |"
        )
    ua, us = u_cells(ex)
    lines.append(
        f"| exact marker images, ideal setup | {ex['roi_rms_um']:.4f} | {ex['roi_max_um']:.4f} | "
        f"{ex['roi_absolute_um']:+.4f} | {ua} | {ex['roi_shape_um']:.4f} | {us} | {ex['all_rms_um']:.3f} | "
        f"{ex['outer_iterations']} | | {covered(ex)} | | |"
    )
    lines += ["", "Thesis figures: §1.10 height distribution 2 (ideal) and §2.8.4 Table 2.7 (calibrated).", ""]
    lines += _deviation_lines(s)
    fm = s["focus_map"]
    lines += [
        "## Focus map",
        "",
        f"{fm['fields']} fields over the ROI (10x / NA 0.45 objective, depth of field "
        f"{fm['depth_of_field_um']:.2f} µm); focus range {fm['focus_range_um']:.1f} µm = "
        f"{fm['height_range_over_dof']:.0f} depths of field; {fm['fields_in_focus']} fields lie wholly within "
        "the depth of field"
        + (
            f"; {fm['fields_interval_leaves_dof']} fields' 95 % height interval leaves it (largest height "
            f"uncertainty {fm['std_max_um']:.3f} µm)"
            if "fields_interval_leaves_dof" in fm
            else ""
        )
        + ". Table: focusmap.csv.",
        "",
        "## Timings (s)",
        "",
    ]
    lines += [f"- {k}: {v:.2f}" for k, v in s["timings_s"].items()] + ["", _OVERLAP]
    lines += ["", f"Total {s['seconds']:.1f} s.", "", "Files: " + ", ".join(s["files"]), ""]
    return "\n".join(lines)
