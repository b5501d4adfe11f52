"""The ``fringes`` study: markers against phase-shifted fringes on the same surfaces (thesis §1.10 setup, §1.2-§1.4).

The marker method (thesis §1.4-§1.8: one image of the §1.6.3 marker pattern, the markers' centroids) and
phase-measuring deflectometry (the same geometry with a display in the pattern plane showing the phase-shifted fringes
of the ``thesis-1.10-fringes`` preset: K = 24 frames, every pixel's display point decoded) measure the same surfaces:
the hard families of :mod:`scopetwin.sim.families` (``glass``, ``cut``, ``steep``, ``features``; seeds fixed before
any result was seen, those of ``benchmarks/hard_families.py``) and the §1.10 surface with a 1.5 mm wide, 2 µm deep
dimple (:func:`scopetwin.sim.families.dimple_spec`). Both are rendered by Mitsuba at 16 spp with the EMVA 1288
sensor noise and reconstructed with their absolute height from the frame criterion (§1.4) and from two positions of
the pattern / display moved along its normal by the setup's ``[pattern_stage]`` (§1.3), both by the one strategy,
:func:`scopetwin.recon.strategy.reconstruct` (the setup chooses the method: a fringe setup's stack goes to
``reconstruct_fringe_images``).

Per family, method and number of positions: failures, the shape error (ROI RMS after removing the ROI mean), the
absolute error (ROI mean), each within 2 of its reported standard uncertainty u (coverage), the dimple's depth share
(:func:`scopetwin.sim.families.dimple_depth`), the acquisition time (frames x exposure; the exposure of each method
from the sensor model, :func:`scopetwin.sim.measurement.sensor_exposure` / :func:`scopetwin.sim.fringes.
render_fringes`: the image peak fills the sensor's ``fill_fraction`` of the full well) and the reconstruction's
seconds.

``scopetwin study fringes`` (default, :data:`DEFAULT`): two seeds per hard family and the dimple on the §1.10 camera
binned 2 x 2 (680 x 512 px of 9.3 µm, the same field of view), a few minutes on 2 cores. ``scopetwin study
fringes-full`` (:data:`FULL`): six seeds per hard family and the dimple on the full 1360 x 1024 camera.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from scopetwin.sim.studies.context import StudyContext, StudyResult, error_text, failed
from scopetwin.sim.studies.tables import Table, jsonable

MARKER_PRESET = "thesis-1.10-deflectometry"
FRINGE_PRESET = "thesis-1.10-fringes"
#: The hard families and the named dimple case.
FAMILIES = ("glass", "cut", "steep", "features", "dimple")
#: The pattern stage's second position, mm along N_z (as the ``second-measurement`` study).
SHIFT_MM = 40.0
#: The dimple: FWHM and depth (:func:`scopetwin.sim.families.dimple_spec`).
DIMPLE_WIDTH_MM = 1.5
DIMPLE_DEPTH_UM = 2.0
#: The §1.10 camera binned 2 x 2: the same sensor area and field of view with a quarter of the pixels.
BINNED_CAMERA: dict[str, Any] = {"pixels": [680, 512], "pixel_pitch": 0.0093}


@dataclass(frozen=True)
class FringeStudyConfig:
    """What one run of the study measures.

    Attributes
    ----------
    seeds : tuple of int
        Surface seeds of each hard family (the render and noise seeds follow from them).
    camera : dict
        ``[camera]`` overrides of both setups ({} : the §1.10 camera).
    shift_mm : float or None
        The ``[pattern_stage]`` shift, mm along N_z; None: one position only (frame criterion).
    spp : int
        Samples per pixel of every render.
    families : tuple of str
        Which of :data:`FAMILIES`.
    """

    seeds: tuple[int, ...] = (9100, 9101)
    camera: dict[str, Any] | None = None
    shift_mm: float | None = SHIFT_MM
    spp: int = 16
    families: tuple[str, ...] = FAMILIES


#: ``scopetwin study fringes``: 2 seeds per hard family and the dimple, the 2 x 2 binned camera.
DEFAULT = FringeStudyConfig(camera=BINNED_CAMERA)
#: ``scopetwin study fringes-full``: 6 seeds per hard family and the dimple, the full camera.
FULL = FringeStudyConfig(seeds=(9100, 9101, 9102, 9103, 9104, 9105), camera={})


def surface_spec(family: str, seed: int) -> dict[str, Any]:
    """The ``substrate.surface`` table of one surface: a hard family's (drawn from ``seed``) or the dimple."""
    from scopetwin.sim.families import HARD, dimple_spec, family_spec

    if family == "dimple":
        return dimple_spec(depth_um=DIMPLE_DEPTH_UM, width_mm=DIMPLE_WIDTH_MM)
    if family not in HARD:
        raise ValueError(f"unknown family {family!r} (known: {', '.join(FAMILIES)})")
    return family_spec(family, seed)


def study_setups(family: str, seed: int, camera: dict[str, Any] | None, shift_mm: float | None) -> tuple[Any, Any]:
    """The marker setup and the fringe setup of one surface: the same geometry, substrate, camera and pattern stage."""
    from scopetwin.scenes.setup import load_setup

    over: dict[str, Any] = {"substrate": {"surface": surface_spec(family, seed)}}
    if camera:
        over["camera"] = dict(camera)
    if shift_mm is not None:
        over["pattern_stage"] = {"shift_mm": float(shift_mm)}
    return load_setup(MARKER_PRESET, over), load_setup(FRINGE_PRESET, over)


def _errors(row: dict[str, Any], height: Any, heights: Any, setup: Any, u_abs: Any, u_shape: Any) -> None:
    """ROI errors, uncertainties and (dimple) depth share into ``row``, µm."""
    from scopetwin.recon.substrate import Substrate2D
    from scopetwin.sim.families import dimple_depth
    from scopetwin.sim.pipeline import roi_errors

    errs = roi_errors(height, heights, Substrate2D.from_setup(setup))
    row.update(
        absolute_um=errs["roi_absolute_um"],
        shape_um=errs["roi_shape_um"],
        u_abs_um=None if u_abs is None else float(u_abs),
        u_shape_um=None if u_shape is None else float(u_shape),
    )
    if row["family"] == "dimple":
        row["depth_share"] = dimple_depth(height) / dimple_depth(heights.height)


def fringes_task(
    family: str,
    seed: int,
    camera: dict[str, Any] | None = None,
    shift_mm: float | None = SHIFT_MM,
    spp: int = 16,
) -> list[dict[str, Any]]:
    """Render one surface with markers and with fringes (at both positions with ``shift_mm``) and reconstruct each.

    Returns one row per method and number of positions: ``family``, ``seed``, ``method`` ("markers" / "fringes"),
    ``positions`` (1, 2), ``frames`` (images acquired), ``exposure_s``, ``acquisition_s`` (frames x exposure),
    and either ``error`` (the reconstruction's one-line error) or ``seconds`` (reconstruction), ``absolute_um``,
    ``shape_um``, ``u_abs_um``, ``u_shape_um`` (µm) and, for the dimple, ``depth_share``.
    """
    from scopetwin.recon.strategy import reconstruct
    from scopetwin.scenes.errors import ScopetwinError
    from scopetwin.scenes.mitsuba.render import render_setup
    from scopetwin.scenes.pattern_stage import shift_pattern
    from scopetwin.sim.fringes import render_fringes
    from scopetwin.sim.measurement import apply_sensor, check_rendered, sensor_exposure
    from scopetwin.sim.surfaces import surface_for

    marker_setup, fringe_setup = study_setups(family, seed, camera, shift_mm)
    heights = surface_for(marker_setup)
    assert heights is not None
    positions = (1,) if shift_mm is None else (1, 2)
    # the marker images: the render, its exposure, the sensor (as render_measurement, with the exposure kept)
    marker_images, marker_exposure = [], []
    fringe_stacks, fringe_exposure = [], []
    for p in positions:
        ms = marker_setup if p == 1 else shift_pattern(marker_setup, float(shift_mm))  # type: ignore[arg-type]
        clean = check_rendered(render_setup(ms, heights, spp=spp, seed=seed + p - 1), f"the render of {ms.name}")
        marker_exposure.append(sensor_exposure(ms, clean))
        marker_images.append(apply_sensor(ms, clean, seed + p - 1))
        fs = fringe_setup if p == 1 else shift_pattern(fringe_setup, float(shift_mm))  # type: ignore[arg-type]
        m = render_fringes(fs, heights, spp, seed + p - 1, True)
        fringe_stacks.append(m.images)
        assert m.exposure_s is not None
        fringe_exposure.append(m.exposure_s)
    k_frames = len(fringe_setup.fringe_sequence)
    rows = []
    for method in ("markers", "fringes"):
        for n in positions:
            exposures = (marker_exposure if method == "markers" else fringe_exposure)[:n]
            frames = 1 if method == "markers" else k_frames
            row: dict[str, Any] = {
                "family": family,
                "seed": seed,
                "method": method,
                "positions": n,
                "frames": frames * n,
                "exposure_s": float(exposures[0]),
                "acquisition_s": float(frames * sum(exposures)),
            }
            t0 = time.perf_counter()
            try:
                images, stage_setup = (
                    (marker_images, marker_setup) if method == "markers" else (fringe_stacks, fringe_setup)
                )
                # the one strategy: it chooses the method by the setup (markers, or the fringe sequence)
                done = reconstruct(images[0], stage_setup, second=None if n == 1 else (images[1], None))
                height, u_abs, u_shape = done.height_at, done.uncertainty.absolute_um, done.uncertainty.shape_um
            except ScopetwinError as exc:
                rows.append({**row, "error": f"{type(exc).__name__}: {str(exc).splitlines()[0][:200]}"})
                continue
            row["seconds"] = time.perf_counter() - t0
            _errors(row, height, heights, marker_setup, u_abs, u_shape)
            rows.append(row)
    return rows


def _within(err: Any, u: Any) -> Any:
    """Share (%) of |err| <= 2 u; a missing u counts as outside."""
    e = np.abs(np.asarray(err, dtype=np.float64))
    uu = np.array([np.inf if v is None else v for v in u], dtype=np.float64)
    return float(np.mean(e <= 2.0 * np.where(np.isfinite(uu), uu, -1.0)) * 100)


def fringes_table(rows: list[dict[str, Any]], title: str) -> Table:
    """Per family, method and positions: failures, shape and absolute errors, 2u coverage, dimple depth share,
    acquisition time and reconstruction seconds (``rows`` may hold failed reconstructions: counted, not measured)."""
    cells = []
    fams = [f for f in FAMILIES if any(r["family"] == f for r in rows)]
    for fam in fams:
        for method in ("markers", "fringes"):
            for n in (1, 2):
                mine = [r for r in rows if r["family"] == fam and r["method"] == method and r["positions"] == n]
                if not mine:
                    continue
                ok = [r for r in mine if "error" not in r]
                sh = np.array([r["shape_um"] for r in ok]) if ok else np.full(1, np.nan)
                ab = np.abs([r["absolute_um"] for r in ok]) if ok else np.full(1, np.nan)
                depth = [r["depth_share"] for r in ok if "depth_share" in r]
                cells.append(
                    [
                        fam,
                        method,
                        "frame criterion" if n == 1 else "two positions",
                        len(mine),
                        len(mine) - len(ok),
                        float(np.median(sh)),
                        float(np.max(sh)),
                        float(np.median(ab)),
                        float(np.max(ab)),
                        _within([r["absolute_um"] for r in ok], [r["u_abs_um"] for r in ok]) if ok else None,
                        _within([r["shape_um"] for r in ok], [r["u_shape_um"] for r in ok]) if ok else None,
                        float(np.median(depth) * 100) if depth else None,
                        int(mine[0]["frames"]),
                        float(np.median([r["acquisition_s"] for r in mine]) * 1e3),
                        float(np.median([r["seconds"] for r in ok])) if ok else None,
                    ]
                )
    return Table(
        title,
        columns=[
            "family",
            "method",
            "absolute height",
            "surfaces",
            "failed",
            "shape median (µm)",
            "shape max (µm)",
            "|abs| median (µm)",
            "|abs| max (µm)",
            "|abs| <= 2 u (%)",
            "shape <= 2 u (%)",
            "dimple depth (%)",
            "frames",
            "acquisition (ms)",
            "reconstruction median (s)",
        ],
        cells=cells,
        note="shape: ROI RMS of the error after removing its ROI mean; abs: the ROI mean error; u: the reported "
        "standard uncertainty; dimple depth: the reconstructed depth of the 1.5 mm / 2 µm dimple against a 4 mm "
        "ring as a share of the true; acquisition: frames x exposure (the sensor model's exposure filling "
        "fill_fraction of the full well at the peak), camera readout and display settling not counted.",
    )


def _plot(ctx: StudyContext, rows: list[dict[str, Any]]) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2), constrained_layout=True)
    for (method, n), marker in zip(
        [("markers", 1), ("markers", 2), ("fringes", 1), ("fringes", 2)], ("o", "s", "^", "D"), strict=True
    ):
        rs = [r for r in rows if r["method"] == method and r["positions"] == n and "error" not in r]
        label = f"{method}, {'frame criterion' if n == 1 else 'two positions'}"
        axes[0].scatter([r["acquisition_s"] * 1e3 for r in rs], [r["shape_um"] for r in rs], marker=marker, s=16)
        axes[1].scatter(
            [r["u_abs_um"] or np.nan for r in rs], np.abs([r["absolute_um"] for r in rs]), marker=marker, s=16
        )
        axes[0].scatter([], [], marker=marker, label=label)
    axes[0].set(xscale="log", yscale="log", xlabel="acquisition time (ms)", ylabel="shape error, ROI RMS (µm)")
    axes[1].set(xscale="log", yscale="log", xlabel="reported u_abs (µm)", ylabel="|absolute error| (µm)")
    axes[1].axline((1e-3, 2e-3), (1.0, 2.0), color="k", ls="--", lw=0.8, label="2 u")
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=7)
    fig.savefig(ctx.out / "fringes.png", dpi=100)
    plt.close(fig)
    return "fringes.png"


def fringes(ctx: StudyContext, config: FringeStudyConfig = DEFAULT) -> StudyResult:
    """Markers against fringes over the hard families and the dimple (module docstring)."""
    seeds = {fam: (1,) if fam == "dimple" else config.seeds for fam in config.families}
    args = [(fam, s, config.camera, config.shift_mm, config.spp) for fam in config.families for s in seeds[fam]]
    results = ctx.map(fringes_task, args, "fringes: render + reconstruct")
    notes = [f"surface failed: {error_text(r)}" for r in results if failed(r)]
    rows = [row for r in results if not failed(r) for row in r]
    notes += [
        f"{r['family']} seed {r['seed']}, {r['method']} ({r['positions']}): {r['error']}" for r in rows if "error" in r
    ]
    cam = config.camera or {}
    camera = (
        f"{cam['pixels'][0]} x {cam['pixels'][1]} px of {cam['pixel_pitch'] * 1e3:g} µm"
        if "pixels" in cam
        else "the §1.10 camera (1360 x 1024 px of 4.65 µm)"
    )
    table = fringes_table(rows, f"Markers against fringes ({len(args)} surfaces; {camera}; Mitsuba {config.spp} spp)")
    plots = [_plot(ctx, rows)] if rows else []
    stage = "" if config.shift_mm is None else f", and from two positions {config.shift_mm:+g} mm along N_z"
    return StudyResult(
        "Study: markers against phase-shifted fringes",
        "The marker method (one image of the §1.6.3 pattern) and phase-measuring deflectometry (a display in the "
        "pattern plane, 4-step fringes of 64, 8 and 1 mm in x and y: 24 frames) on the same surfaces — the hard "
        f"families (seeds {', '.join(map(str, config.seeds))}) and the 1.5 mm / 2 µm dimple — rendered with "
        f"EMVA 1288 sensor noise on {camera}; absolute height from the frame criterion (thesis §1.4){stage} "
        "(§1.3).",
        [table],
        plots,
        {"rows": jsonable(rows), "config": jsonable(config.__dict__)},
        notes,
    )


def fringes_full(ctx: StudyContext) -> StudyResult:
    """The study on the full camera with six seeds per hard family (:data:`FULL`)."""
    return fringes(ctx, FULL)
