"""The ``noise`` study: centroid and calibration error against the exposure (EMVA 1288 sensor model)."""

from __future__ import annotations

from sim.studies.context import StudyContext, StudyResult, error_text, failed, require
from sim.studies.tables import group, jsonable, line_plot, mean, view_table
from sim.studies.tasks import CALIB_MODULES, calibration_dataset, calibration_view_task, sample_folders


def noise(ctx: StudyContext, spp: int = 16, replicates: int = 2) -> StudyResult:
    """Centroid and calibration error against the exposure (EMVA sensor model), angular calibration view."""
    require("noise", CALIB_MODULES)
    fills = [0.02, 0.05, 0.1, 0.2, 0.4, 0.7, 0.95]
    cfg = calibration_dataset(
        {"exposure_fill": {"sweep": fills}}, "thesis-2.8.1-angular", len(fills) * replicates, 2013, True, spp
    )
    root = ctx.dataset(cfg, "samples-noise")
    rows = ctx.map(calibration_view_task, [(f,) for f in sample_folders(root)], "noise: calibrate")
    good = [r for r in rows if not failed(r)]
    notes = [f"sample failed: {error_text(r)}" for r in rows if failed(r)]
    notes += [f"fill {r['parameters']['exposure_fill']:g}: {r['error']}" for r in good if "error" in r]
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
                "|Δr_c| raw (µm)": [mean(g, "raw_r_c_um") for g in groups.values()],
                "|Δr_c| corrected (µm)": [mean(g, "corrected_r_c_um") for g in groups.values()],
            },
            "fill of the full well at the peak",
            "camera-centre error (µm)",
            "Calibration error vs exposure",
            logx=True,
        ),
    ]
    return StudyResult(
        "Study: error against exposure",
        "How photon and read noise at a given exposure limit the "
        "centroids and the one-shot calibration (seed §2.8.2 / §2.9.1).",
        [t],
        plots,
        {"rows": jsonable(good)},
        notes,
    )
