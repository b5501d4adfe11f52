"""The ``noise`` study: centroid and calibration error against the exposure (EMVA 1288 sensor model).

A few clean renders of the angular calibration view are captured many times by the sensor model at each exposure
(:func:`~scopetwin.sim.studies.tasks.calibration_view_task` with a fill). The noise draws separate the calibration's
bias
(the length of the mean error vector of the camera centre) from its scatter (the RMS of the error vectors about
their mean). The bias is known only to its standard error, scatter / sqrt(draws), and the
length of a mean vector reads about one standard error even where the true bias is 0; the scatter grows
~1/sqrt(fill) and more at the low fills (8 µm at 2 % of the full well, 1.6 µm at 20 %), so the low fills get more
draws (:data:`DRAW_WEIGHTS`): 64 at 2 % bring the standard error to ~1 µm.
"""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from scopetwin.sim.datasets.seeding import sample_seed
from scopetwin.sim.studies.context import StudyContext, StudyResult, error_text, failed, require
from scopetwin.sim.studies.tables import Table, group, jsonable, line_plot, mean, view_table
from scopetwin.sim.studies.tasks import CALIB_MODULES, calibration_dataset, calibration_view_task, sample_folders

FILLS = [0.02, 0.05, 0.1, 0.2, 0.4, 0.7, 0.95]
#: Noise draws per exposure, in units of ``replicates``: about the square of the scatter, relative to 20 %.
DRAW_WEIGHTS = {0.02: 8, 0.05: 4, 0.1: 2}
MASTER_SEED = 2013


def draws_per_fill(replicates: int) -> dict[float, int]:
    """The number of noise draws at each fill: ``replicates`` times its weight (:data:`DRAW_WEIGHTS`, else 1)."""
    return {f: replicates * DRAW_WEIGHTS.get(f, 1) for f in FILLS}


def bias_and_scatter(
    rows: list[dict[str, Any]], key: str = "corrected_r_c_vec_um"
) -> tuple[float | None, float | None]:
    """Bias |mean error vector| and scatter sqrt(trace of the covariance) of the error vectors ``key`` (µm).

    The bias carries its own standard error, scatter / sqrt(n); None where fewer than two draws have the key.
    """
    v = np.array([r[key] for r in rows if r.get(key) is not None], dtype=np.float64)
    if len(v) < 2:
        return None, None
    return float(np.linalg.norm(v.mean(axis=0))), float(np.sqrt(np.sum(v.var(axis=0, ddof=1))))


def floor_removed(bias: float | None, scatter: float | None, n: int) -> float | None:
    """The bias less its noise floor: sqrt(max(|m|^2 - scatter^2 / n, 0)).

    |m|^2 of the mean m of n error vectors overestimates the squared bias by trace(cov) / n = scatter^2 / n
    on average; this removes that part, so that a bias of 0 does not read as one standard error.
    """
    if bias is None or scatter is None or n < 2:
        return None
    return float(np.sqrt(max(bias * bias - scatter * scatter / n, 0.0)))


def failure_notes(rows: list[Any], good: list[dict[str, Any]]) -> list[str]:
    """One line per distinct failure: 'fill F: message (k of n draws)' (each listed once)."""
    notes = [f"sample failed: {m} ({k}x)" for m, k in Counter(error_text(r) for r in rows if failed(r)).items()]
    per_fill: dict[float, list[dict[str, Any]]] = {}
    for r in good:
        per_fill.setdefault(r["parameters"]["exposure_fill"], []).append(r)
    for fill, rs in sorted(per_fill.items()):
        counts = Counter(r[k] for r in rs for k in ("error", "raw_error", "corrected_error") if k in r)
        notes += [f"fill {fill:g}: {msg} ({k} of {len(rs)} draws)" for msg, k in counts.items()]
    return notes


def _noise_args(folders: list[str], draws: dict[float, int]) -> list[tuple[str, float, int]]:
    """Task arguments (render folder, fill, noise seed): draw k of a fill captures render k mod the renders."""
    return [
        (folders[k % len(folders)], fill, sample_seed(MASTER_SEED, k, f"noise:{fill:g}"))
        for fill in FILLS
        for k in range(draws[fill])
    ]


#: Per fill: ((bias, scatter) of the raw centroids, (bias, scatter) corrected), µm.
_BiasStats = dict[float, tuple[tuple[float | None, float | None], tuple[float | None, float | None]]]


def _bias_table(groups: dict[float, list[dict[str, Any]]]) -> tuple[Table, _BiasStats, dict[float, float | None]]:
    """The camera-centre bias and scatter table; per fill the (raw, corrected) (bias, scatter) and the bias's SE."""
    stats = {fill: (bias_and_scatter(g, "raw_r_c_vec_um"), bias_and_scatter(g)) for fill, g in groups.items()}
    cells = []
    se: dict[float, float | None] = {}
    for fill, g in groups.items():
        (raw_b, raw_s), (cor_b, cor_s) = stats[fill]
        n = sum(1 for r in g if r.get("corrected_r_c_vec_um") is not None)
        se[fill] = None if cor_s is None else cor_s / np.sqrt(max(n, 1))
        cells.append([fill, n, raw_b, raw_s, cor_b, cor_s, se[fill], floor_removed(cor_b, cor_s, n)])
    table = Table(
        "Camera-centre bias and scatter against the exposure",
        columns=[
            "full-well fill at the peak",
            "draws",
            "bias raw (µm)",
            "scatter raw (µm)",
            "bias corrected (µm)",
            "scatter corrected (µm)",
            "standard error of the bias (µm)",
            "bias less its noise floor (µm)",
        ],
        cells=cells,
        note="bias = |mean of the camera-centre error vectors| over the draws; scatter = RMS of the vectors about "
        "their mean (3-D); the bias is known to about its standard error, scatter / sqrt(draws), and reads about "
        "one standard error where the true bias is 0; 'less its noise floor' = sqrt(max(bias^2 - SE^2, 0)). "
        "Target: bias <= 2 µm.",
    )
    return table, stats, se


def _noise_plots(
    out: Path,
    groups: dict[float, list[dict[str, Any]]],
    stats: _BiasStats,
    se: dict[float, float | None],
    draws: dict[float, int],
) -> list[str]:
    """Write the centroid-error and the calibration bias/scatter plots against the fill; their file names."""
    x = list(groups)
    return [
        line_plot(
            out,
            "noise-centroids.png",
            x,
            {
                "raw": [mean(g, "raw_rms_px") for g in groups.values()],
                "bias-corrected": [mean(g, "corrected_rms_px") for g in groups.values()],
            },
            "fill of the full well at the peak (∝ exposure time)",
            "centroid RMS error (px)",
            "Centroid error vs exposure",
            logx=True,
            refs={"1/20 px": 0.05, "1/40 px": 0.025},
        ),
        line_plot(
            out,
            "noise-calibration.png",
            x,
            {
                "bias (µm)": [stats[f][1][0] for f in x],
                "standard error of the bias (µm)": [se[f] for f in x],
                "scatter (µm)": [stats[f][1][1] for f in x],
                "bias raw centroids (µm)": [stats[f][0][0] for f in x],
            },
            "fill of the full well at the peak",
            "camera-centre error (µm)",
            f"Calibration bias and scatter vs exposure ({min(draws.values())}-{max(draws.values())} draws each)",
            logx=True,
            refs={"2 µm target": 2.0},
        ),
    ]


def noise(ctx: StudyContext, spp: int = 16, replicates: int = 8, renders: int = 4) -> StudyResult:
    """Centroid and calibration error against the exposure (EMVA sensor model), angular calibration view.

    ``renders`` clean Mitsuba renders (``spp``) of the §2.8.1 angular view; each exposure captures them
    :func:`draws_per_fill` times in all (draw k: render k mod ``renders``), every draw with its own noise seed.

    Parameters
    ----------
    ctx : StudyContext
        Where the dataset is written and the tasks run.
    spp : int
        Mitsuba samples per pixel of the clean renders.
    replicates : int
        Noise draws per exposure at weight 1 (:data:`DRAW_WEIGHTS`).
    renders : int
        Clean renders the draws cycle through.

    Returns
    -------
    StudyResult
        The error and bias tables, the two plots, and per fill the corrected bias, scatter and standard error.
    """
    require("noise", CALIB_MODULES)
    draws = draws_per_fill(replicates)
    cfg = calibration_dataset({}, "thesis-2.8.1-angular", renders, MASTER_SEED, False, spp)
    folders = sample_folders(ctx.dataset(cfg, "samples-noise"))
    rows = ctx.map(calibration_view_task, _noise_args(folders, draws), "noise: calibrate")
    good = [r for r in rows if not failed(r)]
    notes = failure_notes(rows, good)
    groups = dict(sorted(group(good, "exposure_fill").items()))
    x = list(groups)
    t = view_table(
        "Centroid and calibration error against the exposure",
        groups,
        "full-well fill at the peak",
        f"Angular view of §2.8.1 (11x9 target), {len(folders)} Mitsuba renders at {spp} spp, EMVA 1288 sensor "
        f"(12 bit, 18 ke- full well, 10 e- dark noise); exposure set so the brightest pixel collects the given "
        f"fraction of the full well; {', '.join(f'{n} at {f:g}' for f, n in draws.items())} noise draws. "
        "Centroids against the exact marker images.",
    )
    bias_table, stats, se = _bias_table(groups)
    return StudyResult(
        "Study: error against exposure",
        "How photon and read noise at a given exposure limit the "
        "centroids and the one-shot calibration (thesis §2.8.2 / §2.9.1).",
        [t, bias_table],
        _noise_plots(ctx.out, groups, stats, se, draws),
        {
            "rows": jsonable(good),
            "bias_scatter_um": {str(f): stats[f][1] for f in x},
            "bias_standard_error_um": {str(f): se[f] for f in x},
        },
        notes,
    )
