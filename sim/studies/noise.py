"""The ``noise`` study: centroid and calibration error against the exposure (EMVA 1288 sensor model).

Eight noise draws per exposure separate the calibration's bias (the length of the mean error vector of the camera
centre) from its scatter (the RMS of the error vectors about their mean), issue 14 item 4.
"""

from __future__ import annotations

from collections import Counter
from typing import Any

import numpy as np

from sim.studies.context import StudyContext, StudyResult, error_text, failed, require
from sim.studies.tables import Table, group, jsonable, line_plot, mean, view_table
from sim.studies.tasks import CALIB_MODULES, calibration_dataset, calibration_view_task, sample_folders

FILLS = [0.02, 0.05, 0.1, 0.2, 0.4, 0.7, 0.95]


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


def failure_notes(rows: list[Any], good: list[dict[str, Any]]) -> list[str]:
    """One line per distinct failure: 'fill F: message (k of n draws)' (issue 14 item 5: each listed once)."""
    notes = [f"sample failed: {m} ({k}x)" for m, k in Counter(error_text(r) for r in rows if failed(r)).items()]
    per_fill: dict[float, list[dict[str, Any]]] = {}
    for r in good:
        per_fill.setdefault(r["parameters"]["exposure_fill"], []).append(r)
    for fill, rs in sorted(per_fill.items()):
        counts = Counter(r[k] for r in rs for k in ("error", "raw_error", "corrected_error") if k in r)
        notes += [f"fill {fill:g}: {msg} ({k} of {len(rs)} draws)" for msg, k in counts.items()]
    return notes


def noise(ctx: StudyContext, spp: int = 16, replicates: int = 8) -> StudyResult:
    """Centroid and calibration error against the exposure (EMVA sensor model), angular calibration view."""
    require("noise", CALIB_MODULES)
    cfg = calibration_dataset(
        {"exposure_fill": {"sweep": FILLS}}, "thesis-2.8.1-angular", len(FILLS) * replicates, 2013, True, spp
    )
    root = ctx.dataset(cfg, "samples-noise")
    rows = ctx.map(calibration_view_task, [(f,) for f in sample_folders(root)], "noise: calibrate")
    good = [r for r in rows if not failed(r)]
    notes = failure_notes(rows, good)
    groups = dict(sorted(group(good, "exposure_fill").items()))
    x = list(groups)
    t = view_table(
        "Centroid and calibration error against the exposure",
        groups,
        "full-well fill at the peak",
        f"Angular view of §2.8.1 (11x9 target), Mitsuba {spp} spp, EMVA 1288 sensor (12 bit, 18 ke- full "
        f"well, 10 e- dark noise); exposure set so the brightest pixel collects the given fraction of the "
        f"full well; {replicates} noise draws per exposure. Centroids against the exact marker images.",
    )
    stats = {fill: (bias_and_scatter(g, "raw_r_c_vec_um"), bias_and_scatter(g)) for fill, g in groups.items()}
    cells = []
    for fill, g in groups.items():
        (raw_b, raw_s), (cor_b, cor_s) = stats[fill]
        n = sum(1 for r in g if r.get("corrected_r_c_vec_um") is not None)
        cells.append([fill, n, raw_b, raw_s, cor_b, cor_s, None if cor_s is None else cor_s / np.sqrt(max(n, 1))])
    bias_table = Table(
        "Camera-centre bias and scatter against the exposure",
        columns=[
            "full-well fill at the peak",
            "draws",
            "bias raw (µm)",
            "scatter raw (µm)",
            "bias corrected (µm)",
            "scatter corrected (µm)",
            "standard error of the bias (µm)",
        ],
        cells=cells,
        note="bias = |mean of the camera-centre error vectors| over the draws; scatter = RMS of the vectors about "
        "their mean (3-D); the bias is known to about scatter / sqrt(draws). Target (issue 14): bias <= 2 µm.",
    )
    plots = [
        line_plot(
            ctx.out,
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
            ctx.out,
            "noise-calibration.png",
            x,
            {
                "bias (µm)": [stats[f][1][0] for f in x],
                "scatter (µm)": [stats[f][1][1] for f in x],
                "bias raw centroids (µm)": [stats[f][0][0] for f in x],
            },
            "fill of the full well at the peak",
            "camera-centre error (µm)",
            f"Calibration bias and scatter vs exposure ({replicates} draws each)",
            logx=True,
            refs={"2 µm target": 2.0},
        ),
    ]
    return StudyResult(
        "Study: error against exposure",
        "How photon and read noise at a given exposure limit the "
        "centroids and the one-shot calibration (seed §2.8.2 / §2.9.1).",
        [t, bias_table],
        plots,
        {"rows": jsonable(good), "bias_scatter_um": {str(f): stats[f][1] for f in x}},
        notes,
    )
