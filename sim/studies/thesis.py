"""The ``thesis`` study: every table of Part I of the thesis side by side (§1.10, Tables 2.2-2.8) and Part III's
§8.3 figures of the GRIN objectives.

The tasks (``*_task``, :func:`oneshot_exact`) compute our figures; the thesis's figures and each table's title, note and
rows are module-level data (``SEED_*``, :data:`TABLES`, ``ROWS_*``); one builder per table (:data:`BUILDERS`) turns
the task results into the table, and :func:`thesis` runs the tasks and the builders.
"""

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
    """RMS and peak-to-valley of |model - measured| marker images, mm (thesis Tables 2.2, 2.3)."""
    res = camera.project(np.column_stack([xy, np.zeros(len(xy))])) - px
    r = np.linalg.norm(res, axis=1) * pitch
    return float(np.sqrt(np.mean(r**2))), float(np.ptp(r))


def oneshot_exact() -> dict[str, Any]:
    """Tables 2.2, 2.3, 2.4, 2.8: one-shot calibration on exact marker images (thesis §2.8.1, §2.8.2, §2.8.5)."""
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
    """Tables 2.5, 2.6 (thesis §2.8.3): calibrate camera and pattern from rendered target and mirror images."""
    from scopetwin.calib.setup_calibration import calibrate_setup_from_images
    from scopetwin.scenes.mitsuba.render import render_setup
    from scopetwin.scenes.setup import load_setup

    quiet()
    ss, sm = load_setup("thesis-2.8.3-substrate"), load_setup("thesis-2.8.3-mirror")
    img_s = render_setup(ss, None, spp=spp, seed=1)
    img_m = render_setup(sm, None, spp=spp, seed=2)
    cal = calibrate_setup_from_images(img_s, img_m, ss, sm, nominal=load_setup(THESIS_DEFLECTOMETRY))
    r = cal.calibration
    cam_t, pat_t = ss.camera_model, sm.marker_pattern.frame
    pitch_um = ss.camera.pixel_pitch * 1e3
    return {
        "camera": {**frame_deviation(r.camera.frame, cam_t.frame), "b": r.camera.b - cam_t.b},
        "pattern": frame_deviation(r.pattern, pat_t),
        "substrate_rms_um": r.substrate.residual_rms_px * pitch_um,
        "substrate_pv_um": r.substrate.residual_pv_px * pitch_um,
        "mirror_rms_um": r.mirror.residual_rms_px * pitch_um,
        "mirror_pv_um": r.mirror.residual_pv_px * pitch_um,
        "markers": [int(len(cal.target.markers.ij)), int(len(cal.mirror.markers.ij))],
        "calibrated_setup": cal.setup.to_json(),
    }


def grin_task(preset: str) -> dict[str, Any]:
    """§8.3: the GRIN objective's paraxial and traced figures beside the thesis's Zemax numbers."""
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


#: The thesis's numbers (Part I), transcribed from the tables; vectors are (x, y, z).
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

# -- the tables, as data: title, note (a str.format template over the builder's values) and rows ------------------

EXACT_NOTE = (
    "Exact marker images ({markers} markers); image distance: {lens}. Values near 1e-13 and below are round-off "
    "on both sides: their ratio means nothing."
)

#: Title and note of each table, in the report's order.
TABLES: dict[str, tuple[str, str]] = {
    "1.10": (
        "§1.10 Simulations: reconstruction with the ideal setup",
        "Height distributions 1 and 2 of the thesis (Fig. 1.10) are not published as data; ours are §1.9 "
        "random surfaces with the same 40 µm range (surface seeds 1 and 2). Mitsuba renders at "
        "{spp} spp, no sensor noise, markers found and indexed in the image (recon.markers).",
    ),
    "2.2": (
        "Table 2.2: one-shot calibration, perpendicular view (§2.8.1)",
        EXACT_NOTE,
    ),
    "2.3": (
        "Table 2.3: one-shot calibration, angular view (§2.8.1)",
        EXACT_NOTE,
    ),
    "2.4": (
        "Table 2.4: calibration with marker images disturbed by σ = 0.233 µm (§2.8.2)",
        "One seeded draw of the disturbance (as the thesis's single draw) and, for a fair comparison, the RMS over "
        "200 draws.",
    ),
    "2.8": (
        "Table 2.8: distortion and optical axis (§2.8.5)",
        "r_cs = (46.5, 46.5) µm, c_2 = 0.00123 /mm refined together with the pose; exact images.",
    ),
    "2.5": (
        "Table 2.5: setup calibration, camera (§2.8.3)",
        "From Mitsuba renders ({spp} spp) of the target on the frame and of the pattern in a flat mirror; "
        "{substrate_markers} and {mirror_markers} markers; bias-corrected centroids.",
    ),
    "2.6": ("Table 2.6: setup calibration, pattern (§2.8.3)", ""),
    "2.7": (
        "Table 2.7: reconstruction with ideal and with calibrated setup (§2.8.4)",
        "Height distribution 2 (ours: surface seed 2); the calibrated setup is the one of Tables 2.5/2.6.",
    ),
    "8.3": (
        "Part III §8.3: GRIN objectives (the thesis's Zemax figures)",
        "Our figures: real rays traced through the radial index profiles (scenes.grin), image plane at best focus.",
    ),
}

#: §1.10, per height distribution and reconstruction: (quantity, thesis key, our key, unit).
ROWS_110 = (
    ("outer iterations", "outer", "outer_iterations", ""),
    ("Δh of the frame maxima", "delta_h_um", "delta_h_max_um", "µm"),
    ("max deviation, whole substrate", "all_max_um", "all_max_um", "µm"),
    ("RMS deviation, whole substrate", "all_rms_um", "all_rms_um", "µm"),
    ("max deviation, ROI", "roi_max_um", "roi_max_um", "µm"),
    ("RMS deviation, ROI", "roi_rms_um", "roi_rms_um", "µm"),
)
#: §1.10: the reconstructions compared (result key with ``{hd}``, label).
RECONSTRUCTIONS_110 = (
    ("hd{hd}", "ours (Gaussian SBF, bias-corrected)"),
    ("hd{hd}_thesis", "the thesis's 9x5 IMQ (9 along y), Δh_max = 0 by a secant"),
)
#: Tables 2.2, 2.3, after the frame rows of each step: (quantity, key, unit).
ROWS_22 = (("Δb", "b", "mm"), ("RMS of the marker-centre comparison", "rms", "mm"), ("peak-to-valley", "pv", "mm"))
#: Table 2.8, after the frame rows: (quantity, thesis key, our key, unit, scale of ours or None).
ROWS_28 = (
    ("Δr_cs", "r_cs_um", "r_cs", "µm", 1e3),
    ("Δc_0", "c0", "c0", "", None),
    ("Δc_2", "c2", "c2", "1/mm", None),
    ("RMS of the marker-centre comparison", "rms", "rms", "mm", None),
    ("peak-to-valley", "pv", "pv", "mm", None),
    ("RMS without offset and distortion", "rms_without", "rms_without", "mm", None),
    ("peak-to-valley without offset and distortion", "pv_without", "pv_without", "mm", None),
)
#: Table 2.5, after the camera's frame rows: (quantity, thesis key, our key, unit); Δb is the camera's.
ROWS_25 = (
    ("substrate-plane residual RMS", "substrate_rms_um", "substrate_rms_um", "µm"),
    ("substrate-plane residual peak-to-valley", "substrate_pv_um", "substrate_pv_um", "µm"),
)
#: Table 2.6, after the pattern's frame rows.
ROWS_26 = (
    ("mirror residual RMS", "mirror_rms_um", "mirror_rms_um", "µm"),
    ("mirror residual peak-to-valley", "mirror_pv_um", "mirror_pv_um", "µm"),
)
#: Table 2.7: (label, result key, thesis key), each with the ROI maximum and RMS.
ROWS_27 = (("with ideal data", "hd2", "ideal"), ("with calibration data", "hd2_calibrated", "calibrated"))
#: §8.3: the GRIN objectives (result keys) and their quantities (key, unit).
GRIN_RESULTS = ("grin_831", "grin_832")
GRIN_QUANTITIES = (
    ("magnification", ""),
    ("na_object", ""),
    ("rms_axis_um", "µm"),
    ("rms_edge_um", "µm"),
    ("airy_um", "µm"),
    ("image_distance", "mm"),
    ("object_distance", "mm"),
)

TITLE = "Study: the thesis's tables side by side"
INTRO = (
    "Every table of Part I of the thesis (§1.10, Tables 2.2-2.8) and the §8.3 GRIN figures, reproduced with "
    "scopetwin: the thesis's number, ours, and their ratio (|ours|/|thesis|; vector rows compare Euclidean "
    "norms). Deviations are ours minus truth."
)

THESIS_MODULES = {
    "scopetwin.calib.oneshot": "one-shot camera calibration",
    "scopetwin.calib.setup_calibration": "setup calibration",
    "scopetwin.recon.markers": "marker detection and indexing",
    "scopetwin.recon.reconstruct": "height reconstruction",
    "scopetwin.recon.bias": "centroid-bias prediction",
    "scopetwin.scenes.grin.analysis": "GRIN objective analysis",
}

#: Task results by key, failed tasks left out (a builder's table needs only its own tasks).
Results = dict[str, Any]


def _frame_rows(seed: dict[str, Any], ours: dict[str, Any], suffix: str = "") -> list[Row]:
    return [Row(f"{lab}{suffix}", seed.get(k), ours.get(k), unit) for k, lab, unit in AXES]


def _table(key: str, rows: list[Row], **values: Any) -> Table:
    """Table ``key`` of :data:`TABLES` with ``rows``, its note filled in with ``values``."""
    title, note = TABLES[key]
    return Table(title, rows, note.format(**values))


# -- one builder per table: the task results -> the table (None where its task failed) -------------------------
def _table_110(ok: Results, spp: int) -> Table | None:
    """§1.10: reconstruction of height distributions 1 and 2 with the ideal setup."""
    rows = []
    for hd in (1, 2):
        s = SEED_110[hd]
        for key, label in RECONSTRUCTIONS_110:
            o = ok.get(key.format(hd=hd))
            if o is not None:
                rows += [Row(f"HD{hd} {label}: {q}", s[sk], o[ok_], u) for q, sk, ok_, u in ROWS_110]
    return _table("1.10", rows, spp=spp)


def _table_exact_oneshot(table: str, key: str, seed: dict[str, Any], o: dict[str, Any] | None) -> Table | None:
    """Tables 2.2 and 2.3: linear and non-linear one-shot calibration on exact marker images."""
    if o is None:
        return None
    t = o[key]
    rows = []
    for kind in ("linear", "nonlinear"):
        sfx = f" ({'non-linear' if kind == 'nonlinear' else 'linear'})"
        rows += _frame_rows(seed[kind], t[kind], sfx)
        rows += [Row(f"{q}{sfx}", seed[kind][k], t[kind][k], u) for q, k, u in ROWS_22]
    return _table(table, rows, markers=t["markers"], lens=t["lens"])


def _table_22(ok: Results, spp: int) -> Table | None:
    """Table 2.2: one-shot calibration, perpendicular view."""
    return _table_exact_oneshot("2.2", "t22", SEED_22, ok.get("oneshot"))


def _table_23(ok: Results, spp: int) -> Table | None:
    """Table 2.3: one-shot calibration, angular view."""
    return _table_exact_oneshot("2.3", "t23", SEED_23, ok.get("oneshot"))


def _table_24(ok: Results, spp: int) -> Table | None:
    """Table 2.4: calibration with disturbed marker images (one draw and the RMS over 200)."""
    o = ok.get("oneshot")
    if o is None:
        return None
    t24 = o["t24"]
    rows = _frame_rows(SEED_24["with"], t24["with"], " (with distortion)")
    rows += _frame_rows(SEED_24["without"], t24["without"], " (without)")
    rows.append(Row("RMS Δr_c over 200 draws (with distortion)", None, t24["rms_r_200"], "mm"))
    return _table("2.4", rows)


def _table_28(ok: Results, spp: int) -> Table | None:
    """Table 2.8: principal-point offset and distortion refined with the pose."""
    o = ok.get("oneshot")
    if o is None:
        return None
    t28 = o["t28"]
    rows = [Row("Δr_c", SEED_28["r_um"], np.asarray(t28["r"]) * 1e3, "µm")] + _frame_rows(SEED_28, t28)[1:]
    for q, sk, k, u, scale in ROWS_28:
        rows.append(Row(q, SEED_28[sk], t28[k] if scale is None else np.asarray(t28[k]) * scale, u))
    return _table("2.8", rows)


def _table_25(ok: Results, spp: int) -> Table | None:
    """Table 2.5: setup calibration, the camera."""
    c = ok.get("setup_cal")
    if c is None:
        return None
    rows = _frame_rows(SEED_25, c["camera"]) + [Row("Δb", SEED_25["b"], c["camera"]["b"], "mm")]
    rows += [Row(q, SEED_25[sk], c[k], u) for q, sk, k, u in ROWS_25]
    return _table("2.5", rows, spp=spp, substrate_markers=c["markers"][0], mirror_markers=c["markers"][1])


def _table_26(ok: Results, spp: int) -> Table | None:
    """Table 2.6: setup calibration, the pattern."""
    c = ok.get("setup_cal")
    if c is None:
        return None
    rows = _frame_rows(SEED_26, c["pattern"]) + [Row(q, SEED_26[sk], c[k], u) for q, sk, k, u in ROWS_26]
    return _table("2.6", rows)


def _table_27(ok: Results, spp: int) -> Table | None:
    """Table 2.7: height distribution 2 reconstructed with the ideal and with the calibrated setup."""
    rows = []
    for label, key, seed_key in ROWS_27:
        r, s = ok.get(key), SEED_27[seed_key]
        if r is not None:
            rows += [
                Row(f"max deviation (ROI), {label}", s["roi_max_um"], r["roi_max_um"], "µm"),
                Row(f"RMS (ROI), {label}", s["roi_rms_um"], r["roi_rms_um"], "µm"),
            ]
    return _table("2.7", rows)


def _table_grin(ok: Results, spp: int) -> Table | None:
    """Part III §8.3: the GRIN objectives beside the thesis's Zemax figures."""
    rows = []
    for key in GRIN_RESULTS:
        g = ok.get(key)
        if g is not None:
            rows += [Row(f"{g['section']} {q}", g["seed"].get(q), g["ours"].get(q), u) for q, u in GRIN_QUANTITIES]
    return _table("8.3", rows)


#: The table builders in the report's order.
BUILDERS: tuple[Callable[[Results, int], Table | None], ...] = (
    _table_110,
    _table_22,
    _table_23,
    _table_24,
    _table_28,
    _table_25,
    _table_26,
    _table_27,
    _table_grin,
)


def _tasks(spp: int) -> list[tuple[str, Callable[..., Any], tuple]]:
    """The study's tasks: (result key, function, arguments)."""
    return [
        ("oneshot", oneshot_exact, ()),
        ("hd1", measurement_task, (1, spp, "default")),
        ("hd2", measurement_task, (2, spp, "default")),
        ("hd1_thesis", measurement_task, (1, spp, "thesis")),
        ("hd2_thesis", measurement_task, (2, spp, "thesis")),
        ("setup_cal", setup_calibration_task, (spp,)),
        ("grin_831", grin_task, ("thesis-8.3.1-grin-optimized",)),
        ("grin_832", grin_task, ("thesis-8.3.2-grin-realized",)),
    ]


def _run_tasks(ctx: StudyContext, spp: int) -> dict[str, Any]:
    """Every task's result (or exception) by key; then height distribution 2 with the calibrated setup."""
    tasks = _tasks(spp)
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
    return res


def thesis(ctx: StudyContext, spp: int = 16) -> StudyResult:
    """Every Part I table of the thesis side by side (module docstring)."""
    require("thesis", THESIS_MODULES)
    res = _run_tasks(ctx, spp)
    notes = [f"**{name} failed**: {error_text(r)}" for name, r in res.items() if failed(r)]
    ok = {name: r for name, r in res.items() if not failed(r)}
    tables = [t for build in BUILDERS if (t := build(ok, spp)) is not None]
    summary = {
        k: (error_text(v) if failed(v) else {kk: vv for kk, vv in v.items() if kk != "calibrated_setup"})
        for k, v in res.items()
    }
    return StudyResult(TITLE, INTRO, tables, _thesis_plot(ctx.out, tables), jsonable(summary), notes)


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
    ax.set_xlabel("ours / thesis (log)")
    ax.set_title("Ratio of our figures to the thesis's (thesis values above round-off only)")
    fig.savefig(out / "ratios.png", dpi=100)
    plt.close(fig)
    return ["ratios.png"]
