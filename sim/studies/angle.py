"""The ``angle`` study: centroid and calibration error against the viewing angle (thesis §2.8.2 angle scan)."""

from __future__ import annotations

from scopetwin.sim.studies.context import StudyContext, StudyResult, error_text, failed, require
from scopetwin.sim.studies.tables import group, jsonable, line_plot, mean, view_table
from scopetwin.sim.studies.tasks import CALIB_MODULES, calibration_dataset, calibration_view_task, sample_folders


def angle(ctx: StudyContext, spp: int = 16) -> StudyResult:
    """Centroid and calibration error against the viewing angle (thesis §2.8.2 angle scan), noise-free."""
    require("angle", CALIB_MODULES)
    angles = [90.0, 80.0, 70.0, 60.0, 50.0, 40.0, 30.0, 20.0, 10.0]
    cfg = calibration_dataset(
        {"view_angle_deg": {"sweep": angles}, "view_distance": {"fixed": 233.24}},
        "thesis-2.8.1-perpendicular",
        len(angles),
        282,
        False,
        spp,
    )
    root = ctx.dataset(cfg, "samples-angle")
    rows = ctx.map(calibration_view_task, [(f,) for f in sample_folders(root)], "angle: calibrate")
    good = [r for r in rows if not failed(r)]
    notes = [f"sample failed: {error_text(r)}" for r in rows if failed(r)]
    notes += [f"angle {r['parameters']['view_angle_deg']:g}°: {r['error']}" for r in good if "error" in r]
    groups = dict(sorted(group(good, "view_angle_deg").items(), reverse=True))
    x = list(groups)
    t = view_table(
        "Centroid and calibration error against the viewing angle (§2.8.2)",
        groups,
        "angle (deg)",
        f"Camera 233.24 mm from the 11x9 target centre, elevation from 90° down; Mitsuba {spp} spp, no "
        "noise. Thesis: centroid accuracy between 1/40 and 1/20 px over the scan (Fig. 2.11).",
    )
    plots = [
        line_plot(
            ctx.out,
            "angle-centroids.png",
            x,
            {
                "raw": [mean(g, "raw_rms_px") for g in groups.values()],
                "bias-corrected": [mean(g, "corrected_rms_px") for g in groups.values()],
            },
            "viewing angle (deg)",
            "centroid RMS error (px)",
            "Centroid error vs viewing angle",
            refs={"1/20 px (thesis worst)": 0.05, "1/40 px (thesis best)": 0.025},
        ),
        line_plot(
            ctx.out,
            "angle-calibration.png",
            x,
            {
                "|Δr_c| raw (µm)": [mean(g, "raw_r_c_um") for g in groups.values()],
                "|Δr_c| corrected (µm)": [mean(g, "corrected_r_c_um") for g in groups.values()],
            },
            "viewing angle (deg)",
            "camera-centre error (µm)",
            "Calibration error vs viewing angle",
        ),
    ]
    return StudyResult(
        "Study: error against viewing angle",
        "The thesis's §2.8.2 angle scan, with the one-shot calibration of each view added.",
        [t],
        plots,
        {"rows": jsonable(good)},
        notes,
    )
