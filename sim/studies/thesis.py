"""The ``thesis`` study: every table of Part I of the seed side by side (§1.10, Tables 2.2-2.8) and Part III's
§8.3 figures of the GRIN objectives."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.camera import Camera
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.setup import Setup
from scopetwin.sim.studies.context import StudyContext, StudyResult, error_text, failed, require
from scopetwin.sim.studies.tables import Row, Table, jsonable, norm, ratio
from scopetwin.sim.studies.tasks import (
    THESIS_DEFLECTOMETRY,
    frame_deviation,
    measurement_setup,
    quiet,
    reconstruct,
)


def _exact_case(name: str, camera: dict[str, Any] | None = None) -> tuple[Setup, NDArray[Any], NDArray[Any], Any]:
    from scopetwin.calib.oneshot import Prior
    from scopetwin.scenes.setup import load_setup

    s = load_setup(name, {"camera": camera} if camera else None)
    pat = s.marker_pattern
    prior = Prior.from_camera(s.camera_model, s.camera.focal_length, r_cs=(0.0, 0.0), c0=1.0, c2=0.0)
    xy = pat.centers_local()
    return s, xy, s.camera_model.project(pat.centers()), prior


def _residual_mm(camera: Camera, xy: NDArray[Any], px: NDArray[Any], pitch: float) -> tuple[float, float]:
    """RMS and peak-to-valley of |model - measured| marker images, mm (seed Tables 2.2, 2.3)."""
    res = camera.project(np.column_stack([xy, np.zeros(len(xy))])) - px
    r = np.linalg.norm(res, axis=1) * pitch
    return float(np.sqrt(np.mean(r**2))), float(np.ptp(r))


def oneshot_exact() -> dict[str, Any]:
    """Tables 2.2, 2.3, 2.4, 2.8: one-shot calibration on exact marker images (seed §2.8.1, §2.8.2, §2.8.5)."""
    from scopetwin.calib.oneshot import calibrate

    quiet()
    out: dict[str, Any] = {}
    cases: tuple[tuple[str, str, Literal["fixed", "auto"]], ...] = (
        ("t22", "thesis-2.8.1-perpendicular", "fixed"),
        ("t23", "thesis-2.8.1-angular", "auto"),
    )
    for key, name, lens in cases:
        s, xy, px, prior = _exact_case(name)
        cal = calibrate(xy, px, prior, lens=lens)
        truth = s.camera_model
        rows = {}
        for label, cam in (("linear", cal.linear.camera), ("nonlinear", cal.camera)):
            rms, pv = _residual_mm(cam, xy, px, prior.pitch)
            rows[label] = {**frame_deviation(cam.frame, truth.frame), "b": cam.b - truth.b, "rms": rms, "pv": pv}
        out[key] = {**rows, "lens": cal.lens, "markers": len(xy)}
    # Table 2.4: a ~30 degree view, marker images disturbed by sigma = 0.233 µm (1/20 px), one seeded draw
    a = math.radians(30.0)
    cam30 = {
        "origin": [0.0, -233.24 * math.cos(a), 233.24 * math.sin(a)],
        "t_x": [1.0, 0.0, 0.0],
        "t_y": [0.0, math.sin(a), math.cos(a)],
        "n_z": [0.0, -math.cos(a), math.sin(a)],
    }
    s, xy, px, prior = _exact_case("thesis-2.8.1-perpendicular", cam30)
    truth = s.camera_model
    rng = np.random.default_rng(24)
    noisy = px + rng.normal(0.0, 0.233e-3 / prior.pitch, px.shape)
    t24 = {}
    for label, p in (("with", noisy), ("without", px)):
        cal = calibrate(xy, p, prior, lens="auto")
        t24[label] = {**frame_deviation(cal.camera.frame, truth.frame), "b": cal.camera.b - truth.b}
    draws = []
    for _ in range(200):
        cal = calibrate(xy, px + rng.normal(0.0, 0.233e-3 / prior.pitch, px.shape), prior, lens="auto")
        draws.append(cal.camera.center - truth.center)
    t24["rms_r_200"] = np.sqrt(np.mean(np.square(draws), axis=0)).tolist()
    out["t24"] = t24
    # Table 2.8: principal-point offset and distortion refined
    s, xy, px, prior = _exact_case("thesis-2.8.5-distortion")
    truth = s.camera_model
    cal = calibrate(xy, px, prior, lens="thin-lens", distortion=True)
    c = cal.camera
    rms, pv = _residual_mm(c, xy, px, prior.pitch)
    without = calibrate(xy, px, prior, lens="thin-lens", distortion=False)
    rms0, pv0 = _residual_mm(without.camera, xy, px, prior.pitch)
    out["t28"] = {
        **frame_deviation(c.frame, truth.frame),
        "r_cs": np.subtract(c.r_cs, truth.r_cs).tolist(),
        "c0": c.c0 - truth.c0,
        "c2": c.c2 - truth.c2,
        "rms": rms,
        "pv": pv,
        "rms_without": rms0,
        "pv_without": pv0,
        "b": c.b - truth.b,
    }
    return out


def measurement_task(
    surface_seed: int, spp: int, config: str = "default", calibrated_json: str | None = None
) -> dict[str, Any]:
    """§1.10 / §2.8.4: render the measurement of a random surface, reconstruct (ideal or calibrated setup)."""
    from scopetwin.scenes.mitsuba.render import render_setup
    from scopetwin.scenes.setup import setup_from_json
    from scopetwin.sim.surfaces import surface_for

    quiet()
    setup = measurement_setup(surface_seed, spp)
    heights = surface_for(setup)
    if heights is None:
        raise ScopetwinError(f"{setup.name} has no substrate surface to reconstruct")
    image = render_setup(setup, heights, spp=spp, seed=0)
    recon_setup = setup_from_json(calibrated_json) if calibrated_json else None
    return reconstruct(setup, heights, image, recon_setup, config)


def setup_calibration_task(spp: int) -> dict[str, Any]:
    """Tables 2.5, 2.6 (seed §2.8.3): calibrate camera and pattern from rendered target and mirror images."""
    from scopetwin.calib.oneshot import Prior
    from scopetwin.calib.setup_calibration import (
        calibrate_setup,
        calibrated_setup_dict,
        mirror_prior,
        virtual_coordinates,
    )
    from scopetwin.recon.bias import spot_bias_model
    from scopetwin.recon.markers import find_markers_for
    from scopetwin.scenes.mitsuba.render import render_setup
    from scopetwin.scenes.setup import load_setup, setup_from_dict

    quiet()
    ss, sm = load_setup("thesis-2.8.3-substrate"), load_setup("thesis-2.8.3-mirror")
    img_s = render_setup(ss, None, spp=spp, seed=1)
    img_m = render_setup(sm, None, spp=spp, seed=2)
    fs, fm = find_markers_for(img_s, ss), find_markers_for(img_m, sm)
    xs = ss.marker_pattern.centers_local(fs.ij)
    xm = virtual_coordinates(sm.marker_pattern, fm.ij)
    tframe = ss.marker_pattern.frame
    ps = Prior.from_camera(ss.camera_model, ss.camera.focal_length, plane=tframe)
    r = calibrate_setup(
        xs,
        fs.centroids,
        ps,
        xm,
        fm.centroids,
        mirror_prior(sm),
        target_frame=tframe,
        substrate_bias=spot_bias_model(xs, ss.marker_pattern.radii(fs.ij)),
        mirror_bias=spot_bias_model(xm, sm.marker_pattern.radii(fm.ij)),
    )
    cam_t, pat_t = ss.camera_model, sm.marker_pattern.frame
    calibrated = setup_from_dict(calibrated_setup_dict(load_setup(THESIS_DEFLECTOMETRY), r), "calibrated setup")
    pitch_um = ss.camera.pixel_pitch * 1e3
    return {
        "camera": {**frame_deviation(r.camera.frame, cam_t.frame), "b": r.camera.b - cam_t.b},
        "pattern": frame_deviation(r.pattern, pat_t),
        "substrate_rms_um": r.substrate.residual_rms_px * pitch_um,
        "substrate_pv_um": r.substrate.residual_pv_px * pitch_um,
        "mirror_rms_um": r.mirror.residual_rms_px * pitch_um,
        "mirror_pv_um": r.mirror.residual_pv_px * pitch_um,
        "markers": [int(len(fs.ij)), int(len(fm.ij))],
        "calibrated_setup": calibrated.to_json(),
    }


def grin_task(preset: str) -> dict[str, Any]:
    """§8.3: the GRIN objective's paraxial and traced figures beside the seed's Zemax numbers."""
    from scopetwin.scenes.grin.analysis import analyse
    from scopetwin.scenes.grin.setup import load_grin_setup

    setup = load_grin_setup(preset)
    rep = analyse(setup)
    return {
        "section": setup.section,
        "seed": setup.seed.model_dump(),
        "ours": {
            "magnification": rep.magnification,
            "na_object": rep.na_object,
            "rms_axis_um": rep.rms_spot_um["axis"],
            "rms_edge_um": rep.rms_spot_um["edge"],
            "airy_um": rep.airy_um,
            "image_distance": rep.image_distance_mm,
            "object_distance": rep.object_distance_mm,
        },
    }


#: The seed's numbers (Part I), transcribed from the tables; vectors are (x, y, z).
SEED_110 = {
    1: {
        "outer": 14,
        "delta_h_um": -0.15,
        "all_max_um": 7.577,
        "all_rms_um": 4.578,
        "roi_max_um": 0.697,
        "roi_rms_um": 0.097,
    },
    2: {
        "outer": 9,
        "delta_h_um": -0.009,
        "all_max_um": 1.943,
        "all_rms_um": 0.213,
        "roi_max_um": 0.359,
        "roi_rms_um": 0.092,
    },
}
SEED_22 = {
    "linear": {
        "r": (1.432e-7, 5.017e-6, -2.842e-14),
        "t_x": (-1.11e-16, 0, -6.141e-10),
        "t_y": (-1.321e-17, -2.22e-16, -2.151e-8),
        "n_z": (6.141e-10, 2.151e-8, -1.11e-16),
        "b": 0.0,
        "rms": 1.063e-9,
        "pv": 1.953e-9,
    },
    "nonlinear": {
        "r": (1.79e-13, -6.787e-14, 0),
        "t_x": (-1.11e-16, -2.009e-18, -7.673e-16),
        "t_y": (2.009e-18, 1.11e-16, 2.912e-16),
        "n_z": (7.673e-16, -2.912e-16, 0),
        "b": 0.0,
        "rms": 4.722e-16,
        "pv": 1.110e-15,
    },
}
SEED_23 = {
    "linear": {
        "r": (-1.557e-15, 4.366e-1, -1.485e-2),
        "t_x": (0, 0, 7.698e-18),
        "t_y": (-6.6e-18, 3.342e-4, -2.006e-4),
        "n_z": (-3.963e-18, 2.006e-4, 3.342e-4),
        "b": 2.6e-3,
        "rms": 1.477e-2,
        "pv": 4.934e-3,
    },
    "nonlinear": {
        "r": (6.071e-15, 3.126e-13, 3.979e-13),
        "t_x": (0, 1.289e-17, -3.053e-17),
        "t_y": (1.955e-17, 1.665e-15, -1.221e-15),
        "n_z": (2.676e-17, 1.221e-15, 1.665e-15),
        "b": 0.0,
        "rms": 9.076e-15,
        "pv": 1.719e-14,
    },
}
SEED_24 = {
    "with": {
        "r": (1.09e-3, 5.72e-3, 6.91e-3),
        "t_x": (4.32e-11, 1.17e-6, 9.22e-6),
        "t_y": (7.31e-6, 1.03e-5, 6.21e-6),
        "n_z": (5.74e-6, 6.21e-6, 1.03e-5),
    },
    "without": {
        "r": (1.59e-16, 0, 1.42e-14),
        "t_x": (0, 5.42e-18, 1.00e-17),
        "t_y": (1.14e-17, 0, 1.11e-16),
        "n_z": (5.25e-19, 1.11e-16, 0),
    },
}
SEED_25 = {
    "r": (4.383e-3, 3.979e-3, -1.598e-2),
    "t_x": (-1.704e-10, 1.536e-5, -1.024e-5),
    "t_y": (8.765e-7, -4.664e-5, 2.799e-5),
    "n_z": (1.844e-5, -2.799e-5, -4.665e-5),
    "b": -9.653e-5,
    "substrate_rms_um": 0.153,
    "substrate_pv_um": 0.260,
}
SEED_26 = {
    "r": (-1.639e-3, 2.520e-2, 7.904e-3),
    "t_x": (-1.704e-10, 1.536e-5, 1.024e-5),
    "t_y": (-8.688e-7, -3.123e-4, 1.875e-4),
    "n_z": (1.844e-5, 1.875e-4, -3.123e-4),
    "mirror_rms_um": 0.364,
    "mirror_pv_um": 3.307,
}
SEED_27 = {
    "ideal": {"roi_max_um": 0.357, "roi_rms_um": 0.091},
    "calibrated": {"roi_max_um": 1.162, "roi_rms_um": 0.414},
}
SEED_28 = {
    "r_um": (2.62e-6, 34.0, 20.4),
    "t_x": (0, 4.37e-10, 2.53e-10),
    "t_y": (7.83e-12, 2.43e-4, 1.46e-4),
    "n_z": (5.05e-10, 1.46e-4, 2.43e-4),
    "r_cs_um": (0.02, 7.94),
    "c0": 2.47e-4,
    "c2": 9.11e-7,
    "rms": 3.844e-10,
    "pv": 4.136e-10,
    "rms_without": 8.553e-4,
    "pv_without": 1.542e-3,
}
AXES = (("r", "Δr_c", "mm"), ("t_x", "ΔT_x", ""), ("t_y", "ΔT_y", ""), ("n_z", "ΔN_z", ""))

THESIS_MODULES = {
    "scopetwin.calib.oneshot": "one-shot camera calibration",
    "scopetwin.calib.setup_calibration": "setup calibration",
    "scopetwin.recon.markers": "marker detection and indexing",
    "scopetwin.recon.reconstruct": "height reconstruction",
    "scopetwin.recon.bias": "centroid-bias prediction",
    "scopetwin.scenes.grin.analysis": "GRIN objective analysis",
}


def _frame_rows(seed: dict[str, Any], ours: dict[str, Any], suffix: str = "") -> list[Row]:
    return [Row(f"{lab}{suffix}", seed.get(k), ours.get(k), unit) for k, lab, unit in AXES]


def thesis(ctx: StudyContext, spp: int = 16) -> StudyResult:
    """Every Part I table of the seed side by side (module docstring)."""
    require("thesis", THESIS_MODULES)
    tasks: list[tuple[str, Callable[..., Any], tuple]] = [
        ("oneshot", oneshot_exact, ()),
        ("hd1", measurement_task, (1, spp, "default")),
        ("hd2", measurement_task, (2, spp, "default")),
        ("hd1_thesis", measurement_task, (1, spp, "thesis")),
        ("hd2_thesis", measurement_task, (2, spp, "thesis")),
        ("setup_cal", setup_calibration_task, (spp,)),
        ("grin_831", grin_task, ("thesis-8.3.1-grin-optimized",)),
        ("grin_832", grin_task, ("thesis-8.3.2-grin-realized",)),
    ]
    res = dict(zip([t[0] for t in tasks], ctx.map(call, [(f, a) for _, f, a in tasks], "thesis tasks"), strict=True))
    cal = res["setup_cal"]
    if not failed(cal):
        res["hd2_calibrated"] = ctx.map(
            call,
            [(measurement_task, (2, spp, "default", cal["calibrated_setup"]))],
            "reconstruction with calibration data",
        )[0]
    else:
        res["hd2_calibrated"] = cal
    tables: list[Table] = []
    notes: list[str] = []
    for name, r in res.items():
        if failed(r):
            notes.append(f"**{name} failed**: {error_text(r)}")

    def ok(name: str) -> dict[str, Any] | None:
        r = res.get(name)
        return None if failed(r) else r

    # §1.10
    rows = []
    for hd in (1, 2):
        s = SEED_110[hd]
        for key, label in (
            (f"hd{hd}", "ours (Gaussian SBF, bias-corrected)"),
            (f"hd{hd}_thesis", "seed's 9x5 IMQ (9 along y)"),
        ):
            o = ok(key)
            if o is None:
                continue
            rows += [
                Row(f"HD{hd} {label}: outer iterations", s["outer"], o["outer_iterations"]),
                Row(f"HD{hd} {label}: Δh of the frame maxima", s["delta_h_um"], o["delta_h_max_um"], "µm"),
                Row(f"HD{hd} {label}: max deviation, whole substrate", s["all_max_um"], o["all_max_um"], "µm"),
                Row(f"HD{hd} {label}: RMS deviation, whole substrate", s["all_rms_um"], o["all_rms_um"], "µm"),
                Row(f"HD{hd} {label}: max deviation, ROI", s["roi_max_um"], o["roi_max_um"], "µm"),
                Row(f"HD{hd} {label}: RMS deviation, ROI", s["roi_rms_um"], o["roi_rms_um"], "µm"),
            ]
    tables.append(
        Table(
            "§1.10 Simulations: reconstruction with the ideal setup",
            rows,
            "Height distributions 1 and 2 of the seed (Fig. 1.10) are not published as data; ours are §1.9 "
            "random surfaces with the same 40 µm range (surface seeds 1 and 2). Mitsuba renders at "
            f"{spp} spp, no sensor noise, markers found and indexed in the image (recon.markers).",
        )
    )
    o = ok("oneshot")
    if o is not None:
        for key, seed, title in (
            ("t22", SEED_22, "Table 2.2: one-shot calibration, perpendicular view (§2.8.1)"),
            ("t23", SEED_23, "Table 2.3: one-shot calibration, angular view (§2.8.1)"),
        ):
            rows = []
            for kind in ("linear", "nonlinear"):
                sfx = f" ({'non-linear' if kind == 'nonlinear' else 'linear'})"
                rows += _frame_rows(seed[kind], o[key][kind], sfx)
                rows += [
                    Row(f"Δb{sfx}", seed[kind]["b"], o[key][kind]["b"], "mm"),
                    Row(f"RMS of the marker-centre comparison{sfx}", seed[kind]["rms"], o[key][kind]["rms"], "mm"),
                    Row(f"peak-to-valley{sfx}", seed[kind]["pv"], o[key][kind]["pv"], "mm"),
                ]
            tables.append(
                Table(
                    title,
                    rows,
                    f"Exact marker images ({o[key]['markers']} markers); image distance: "
                    f"{o[key]['lens']}. Values near 1e-13 and below are round-off on both "
                    "sides: their ratio means nothing.",
                )
            )
        t24 = o["t24"]
        rows = _frame_rows(SEED_24["with"], t24["with"], " (with distortion)")
        rows += _frame_rows(SEED_24["without"], t24["without"], " (without)")
        rows.append(Row("RMS Δr_c over 200 draws (with distortion)", None, t24["rms_r_200"], "mm"))
        tables.append(
            Table(
                "Table 2.4: calibration with marker images disturbed by σ = 0.233 µm (§2.8.2)",
                rows,
                "One seeded draw of the disturbance (as the seed's single draw) and, for a fair "
                "comparison, the RMS over 200 draws.",
            )
        )
        t28 = o["t28"]
        rows = [Row("Δr_c", SEED_28["r_um"], np.asarray(t28["r"]) * 1e3, "µm")] + _frame_rows(SEED_28, t28)[1:]
        rows += [
            Row("Δr_cs", SEED_28["r_cs_um"], np.asarray(t28["r_cs"]) * 1e3, "µm"),
            Row("Δc_0", SEED_28["c0"], t28["c0"]),
            Row("Δc_2", SEED_28["c2"], t28["c2"], "1/mm"),
            Row("RMS of the marker-centre comparison", SEED_28["rms"], t28["rms"], "mm"),
            Row("peak-to-valley", SEED_28["pv"], t28["pv"], "mm"),
            Row("RMS without offset and distortion", SEED_28["rms_without"], t28["rms_without"], "mm"),
            Row("peak-to-valley without offset and distortion", SEED_28["pv_without"], t28["pv_without"], "mm"),
        ]
        tables.append(
            Table(
                "Table 2.8: distortion and optical axis (§2.8.5)",
                rows,
                "r_cs = (46.5, 46.5) µm, c_2 = 0.00123 /mm refined together with the pose; exact images.",
            )
        )
    c = ok("setup_cal")
    if c is not None:
        rows = _frame_rows(SEED_25, c["camera"]) + [
            Row("Δb", SEED_25["b"], c["camera"]["b"], "mm"),
            Row("substrate-plane residual RMS", SEED_25["substrate_rms_um"], c["substrate_rms_um"], "µm"),
            Row("substrate-plane residual peak-to-valley", SEED_25["substrate_pv_um"], c["substrate_pv_um"], "µm"),
        ]
        tables.append(
            Table(
                "Table 2.5: setup calibration, camera (§2.8.3)",
                rows,
                f"From Mitsuba renders ({spp} spp) of the target on the frame and of the pattern in a flat "
                f"mirror; {c['markers'][0]} and {c['markers'][1]} markers; bias-corrected centroids.",
            )
        )
        rows = _frame_rows(SEED_26, c["pattern"]) + [
            Row("mirror residual RMS", SEED_26["mirror_rms_um"], c["mirror_rms_um"], "µm"),
            Row("mirror residual peak-to-valley", SEED_26["mirror_pv_um"], c["mirror_pv_um"], "µm"),
        ]
        tables.append(Table("Table 2.6: setup calibration, pattern (§2.8.3)", rows))
    ideal, calibrated = ok("hd2"), ok("hd2_calibrated")
    rows = []
    for label, r, s in (
        ("with ideal data", ideal, SEED_27["ideal"]),
        ("with calibration data", calibrated, SEED_27["calibrated"]),
    ):
        if r is not None:
            rows += [
                Row(f"max deviation (ROI), {label}", s["roi_max_um"], r["roi_max_um"], "µm"),
                Row(f"RMS (ROI), {label}", s["roi_rms_um"], r["roi_rms_um"], "µm"),
            ]
    tables.append(
        Table(
            "Table 2.7: reconstruction with ideal and with calibrated setup (§2.8.4)",
            rows,
            "Height distribution 2 (ours: surface seed 2); the calibrated setup is the one of Tables 2.5/2.6.",
        )
    )
    rows = []
    for key in ("grin_831", "grin_832"):
        g = ok(key)
        if g is None:
            continue
        for q, unit in (
            ("magnification", ""),
            ("na_object", ""),
            ("rms_axis_um", "µm"),
            ("rms_edge_um", "µm"),
            ("airy_um", "µm"),
            ("image_distance", "mm"),
            ("object_distance", "mm"),
        ):
            rows.append(Row(f"{g['section']} {q}", g["seed"].get(q), g["ours"].get(q), unit))
    tables.append(
        Table(
            "Part III §8.3: GRIN objectives (seed's Zemax figures)",
            rows,
            "Our figures: real rays traced through the radial index profiles (scenes.grin), image plane at best focus.",
        )
    )
    plots = _thesis_plot(ctx.out, tables)
    intro = (
        "Every table of Part I of the seed (§1.10, Tables 2.2-2.8) and the §8.3 GRIN figures, reproduced with "
        "scopetwin: the seed's number, ours, and their ratio (|ours|/|seed|; vector rows compare Euclidean "
        "norms). Deviations are ours minus truth."
    )
    return StudyResult(
        "Study: the seed's tables side by side",
        intro,
        tables,
        plots,
        jsonable(
            {
                k: (error_text(v) if failed(v) else {kk: vv for kk, vv in v.items() if kk != "calibrated_setup"})
                for k, v in res.items()
            }
        ),
        notes,
    )


def call(func: Callable[..., Any], args: tuple) -> Any:
    """Run ``func(*args)`` (the thesis tasks have different signatures; this is what is mapped)."""
    return func(*args)


def _thesis_plot(out: Path, tables: list[Table]) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = []
    for t in tables:
        for r in t.rows:
            q, s = ratio(r.seed, r.ours), norm(r.seed)
            if q is not None and s is not None and s > 1e-12:
                pts.append((t.title.split(":")[0], r.label, q))
    if not pts:
        return []
    fig, ax = plt.subplots(figsize=(9, max(3.0, 0.22 * len(pts))), constrained_layout=True)
    y = np.arange(len(pts))
    ax.barh(y, [p[2] for p in pts], color="tab:blue")
    ax.set_xscale("log")
    ax.axvline(1.0, color="k", lw=0.8)
    ax.set_yticks(y, [f"{p[0]} — {p[1]}" for p in pts], fontsize=6)
    ax.invert_yaxis()
    ax.set_xlabel("ours / seed (log)")
    ax.set_title("Ratio of our figures to the seed's (seed values above round-off only)")
    fig.savefig(out / "ratios.png", dpi=100)
    plt.close(fig)
    return ["ratios.png"]
