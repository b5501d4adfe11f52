"""Accuracy studies against rendered truth, run on Dask like the datasets (issue 9, DESIGN.md "Scale").

A study is a function of a :class:`StudyContext` that fans its work out as independent tasks (on the
same Dask client the datasets use, or in this process), tabulates the errors against the truth, and
returns :class:`Table` objects, plots and a JSON summary; :func:`run_study` writes ``report.md``,
``results.json`` and the PNG plots into the output folder (staged, moved into place on success).

* ``thesis`` — every table of Part I of the seed side by side: §1.10 (both height distributions),
  Tables 2.2-2.4 and 2.8 (one-shot calibration on exact marker images), Tables 2.5-2.7 (setup
  calibration from renders, and the reconstruction with calibrated data), plus Part III's §8.3
  figures of the GRIN objectives.
* ``noise`` — centroid and calibration error against the exposure (EMVA sensor model), on a
  generated dataset of calibration views.
* ``angle`` — centroid and calibration error against the viewing angle (seed §2.8.2), on a
  generated dataset of calibration views.
* ``surface`` — reconstruction error against the surface's correlation length and range, and
  against the density of the shifted basis (seed §1.8), on a generated deflectometry dataset.

Each study names the modules it needs; when one is not in this installation the study stops with a
:class:`StudyError` naming the missing capability, before any work.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import math
import shutil
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from scenes.errors import ScopetwinError

THESIS_DEFLECTOMETRY = "thesis-1.10-deflectometry"
PITCH_UM = 4.65


class StudyError(ScopetwinError, ValueError):
    """A study that cannot run (unknown name, missing capability); the message names it."""


# -- tables and report --------------------------------------------------------------------------------
@dataclass
class Row:
    """One quantity: the seed's value, ours (scalars or vectors), and the unit they are printed in."""

    label: str
    seed: Any
    ours: Any
    unit: str = ""


@dataclass
class Table:
    """A titled table of :class:`Row` (seed | ours | ratio) or of free columns (``columns`` + ``cells``)."""

    title: str
    rows: list[Row] = field(default_factory=list)
    note: str = ""
    columns: list[str] | None = None
    cells: list[list[Any]] | None = None


def _norm(v: Any) -> float | None:
    if v is None:
        return None
    a = np.atleast_1d(np.asarray(v, dtype=np.float64))
    if not np.all(np.isfinite(a)):
        return None
    return float(np.linalg.norm(a))


def ratio(seed: Any, ours: Any) -> float | None:
    """|ours| / |seed| (Euclidean norms for vectors); None when the seed is 0, missing or not finite."""
    s, o = _norm(seed), _norm(ours)
    if s is None or o is None or s == 0:
        return None
    return o / s


def fmt(v: Any, digits: int = 3) -> str:
    """Scalars and vectors in compact scientific notation ('—' for missing values)."""
    if v is None:
        return "—"
    if isinstance(v, str):
        return v
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, int | np.integer):
        return str(int(v))
    a = np.atleast_1d(np.asarray(v, dtype=np.float64))
    if a.size == 1:
        x = float(a[0])
        if not math.isfinite(x):
            return "—"
        return f"{x:.{digits}g}" if 1e-3 <= abs(x) < 1e4 or x == 0 else f"{x:.{digits}e}"
    return "(" + ", ".join(fmt(float(x), digits) for x in a) + ")"


def table_markdown(t: Table) -> str:
    """A table as GitHub markdown."""
    lines = [f"### {t.title}", ""]
    if t.columns is not None:
        lines += ["| " + " | ".join(t.columns) + " |", "|" + "---|" * len(t.columns)]
        lines += ["| " + " | ".join(fmt(c) for c in row) + " |" for row in t.cells or []]
    else:
        lines += ["| quantity | seed | ours | ratio ours/seed |", "|---|---|---|---|"]
        for r in t.rows:
            q = ratio(r.seed, r.ours)
            unit = f" {r.unit}" if r.unit else ""
            lines.append(
                f"| {r.label}{(' [' + r.unit + ']') if r.unit else ''} | {fmt(r.seed)} | {fmt(r.ours)} | "
                f"{'—' if q is None else f'{q:.3g}'} |".replace(unit + " |", " |")
            )
    if t.note:
        lines += ["", t.note]
    return "\n".join(lines) + "\n"


def _jsonable(v: Any) -> Any:
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return _jsonable(v.tolist())
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def table_json(t: Table) -> dict[str, Any]:
    if t.columns is not None:
        return {"title": t.title, "columns": t.columns, "cells": _jsonable(t.cells), "note": t.note}
    return {
        "title": t.title,
        "note": t.note,
        "rows": [
            {
                "label": r.label,
                "unit": r.unit,
                "seed": _jsonable(r.seed),
                "ours": _jsonable(r.ours),
                "ratio": ratio(r.seed, r.ours),
            }
            for r in t.rows
        ],
    }


# -- context: where tasks run ------------------------------------------------------------------------
@dataclass
class StudyContext:
    """What a study function gets: the staging folder, the Dask client (or None), progress flag."""

    out: Path
    client: Any | None
    progress: bool = True
    threads: int | None = None

    def map(self, func: Callable[..., Any], args: Sequence[tuple], desc: str) -> list[Any]:
        """Run ``func(*a)`` for each ``a`` (on the cluster); results in order, exceptions in their place."""
        from tqdm import tqdm

        from sim.dataset import run_tasks

        results: list[Any] = [None] * len(args)
        with tqdm(total=len(args), desc=desc, unit="task", disable=not self.progress) as bar:
            for k, res, err in run_tasks(func, args, self.client):
                results[k] = err if err is not None else res
                bar.update(1)
        return results

    def dataset(self, config: dict[str, Any], name: str) -> Path:
        """Generate a dataset (a config dict as in ``examples/datasets``) under ``out/name`` on the same client."""
        from sim.dataset import Plan, config_from_dict, generate

        plan = Plan.build(config_from_dict(config, f"study dataset {name}"))
        root = self.out / name
        generate(
            plan,
            root,
            threads=self.threads,
            progress=self.progress,
            client=self.client,
            workers=None if self.client is not None else 0,
        )
        return root


@dataclass
class StudyResult:
    """Tables, plots (file names in the output folder), free text and a JSON summary."""

    title: str
    intro: str
    tables: list[Table]
    plots: list[str] = field(default_factory=list)
    summary: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)


def require(study: str, modules: dict[str, str]) -> None:
    """Raise :class:`StudyError` naming the first missing capability (module -> what it provides)."""
    for module, what in modules.items():
        try:
            found = importlib.util.find_spec(module) is not None
        except ModuleNotFoundError:
            found = False
        if not found:
            raise StudyError(f"study {study!r} needs {what} ({module}), which is not in this installation yet")


def _failed(v: Any) -> bool:
    return isinstance(v, BaseException)


def _error_text(v: BaseException) -> str:
    from sim.dataset import failure_text

    return failure_text(v)


# -- shared measurement helpers (run on workers) ---------------------------------------------------------
def _quiet() -> None:
    warnings.simplefilter("ignore")


def frame_deviation(frame, truth) -> dict[str, list[float]]:
    """Differences of origin and axes (ours - truth)."""
    return {
        "r": (frame.origin - truth.origin).tolist(),
        "t_x": (frame.tx - truth.tx).tolist(),
        "t_y": (frame.ty - truth.ty).tolist(),
        "n_z": (frame.nz - truth.nz).tolist(),
    }


def axis_angle(frame, truth) -> float:
    """Rotation angle between two frames, rad."""
    r = np.stack([frame.tx, frame.ty, frame.nz]) @ np.stack([truth.tx, truth.ty, truth.nz]).T
    return float(np.arccos(np.clip((np.trace(r) - 1.0) / 2.0, -1.0, 1.0)))


def _exact_case(name: str, camera: dict[str, Any] | None = None):
    from calib.oneshot import Prior
    from scenes.setup import load_setup

    s = load_setup(name, {"camera": camera} if camera else None)
    pat = s.marker_pattern
    prior = Prior.from_camera(s.camera_model, s.camera.focal_length, r_cs=(0.0, 0.0), c0=1.0, c2=0.0)
    xy = pat.centers_local()
    return s, xy, s.camera_model.project(pat.centers()), prior


def _residual_mm(camera, xy, px, pitch: float) -> tuple[float, float]:
    """RMS and peak-to-valley of |model - measured| marker images, mm (seed Tables 2.2, 2.3)."""
    res = camera.project(np.column_stack([xy, np.zeros(len(xy))])) - px
    r = np.linalg.norm(res, axis=1) * pitch
    return float(np.sqrt(np.mean(r**2))), float(np.ptp(r))


def oneshot_exact() -> dict[str, Any]:
    """Tables 2.2, 2.3, 2.4, 2.8: one-shot calibration on exact marker images (seed §2.8.1, §2.8.2, §2.8.5)."""
    from calib.oneshot import calibrate

    _quiet()
    out: dict[str, Any] = {}
    for key, name, lens in (("t22", "thesis-2.8.1-perpendicular", "fixed"), ("t23", "thesis-2.8.1-angular", "auto")):
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


def _measurement_setup(surface_seed: int, spp: int, overrides: dict[str, Any] | None = None):
    from scenes.setup import load_setup

    over = {"substrate": {"surface": {"seed": int(surface_seed)}}, "render": {"spp": spp, "seed": 0}}
    if overrides:
        from sim.dataset import _merge

        over = _merge(over, overrides)
    return load_setup(THESIS_DEFLECTOMETRY, over)


def _reconstruct(setup, heights, image, recon_setup=None, config: str = "default") -> dict[str, Any]:
    """Find markers with the nominal setup, reconstruct with ``recon_setup`` (default: the same), compare."""
    from recon.markers import find_markers_for
    from recon.reconstruct import (
        MarkerObservations,
        ReconstructionConfig,
        Reconstructor,
        Substrate2D,
        centroid_bias_step,
    )
    from sim.pipeline import roi_errors

    rs = recon_setup or setup
    found = find_markers_for(image, setup)
    cfg = None
    if config == "thesis":
        cfg = ReconstructionConfig.thesis(literal_axes=False)
    elif config.startswith("spacing="):
        cfg = ReconstructionConfig(spacing=float(config.split("=")[1]))
    t0 = time.perf_counter()
    res = Reconstructor.from_setup(rs, cfg, bias=centroid_bias_step(rs)).run(
        MarkerObservations(found.ij, found.centroids)
    )
    errs = roi_errors(res.surface.height, heights, Substrate2D.from_setup(setup))
    return {
        **errs,
        "outer_iterations": res.outer_iterations,
        "inner_iterations": res.inner_iterations,
        "delta_h_max_um": res.delta_h_max_um,
        "markers": int(len(found.ij)),
        "seconds": time.perf_counter() - t0,
    }


def measurement_task(
    surface_seed: int, spp: int, config: str = "default", calibrated_json: str | None = None
) -> dict[str, Any]:
    """§1.10 / §2.8.4: render the measurement of a random surface, reconstruct (ideal or calibrated setup)."""
    from scenes.mitsuba.render import render_setup
    from scenes.setup import setup_from_json
    from sim.surfaces import surface_for

    _quiet()
    setup = _measurement_setup(surface_seed, spp)
    heights = surface_for(setup)
    image = render_setup(setup, heights, spp=spp, seed=0)
    recon_setup = setup_from_json(calibrated_json) if calibrated_json else None
    return _reconstruct(setup, heights, image, recon_setup, config)


def setup_calibration_task(spp: int) -> dict[str, Any]:
    """Tables 2.5, 2.6 (seed §2.8.3): calibrate camera and pattern from rendered target and mirror images."""
    from calib.oneshot import Prior, spot_bias_model
    from calib.setup_calibration import calibrate_setup, calibrated_setup_dict, mirror_prior, virtual_coordinates
    from recon.markers import find_markers_for
    from scenes.mitsuba.render import render_setup
    from scenes.setup import load_setup, setup_from_dict

    _quiet()
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
    from scenes.grin.analysis import analyse
    from scenes.grin.setup import load_grin_setup

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


# -- the thesis study --------------------------------------------------------------------------------------
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
    "calib.oneshot": "one-shot camera calibration",
    "calib.setup_calibration": "setup calibration",
    "recon.markers": "marker detection and indexing",
    "recon.reconstruct": "height reconstruction",
    "recon.bias": "centroid-bias prediction",
    "scenes.grin.analysis": "GRIN objective analysis",
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
    res = dict(zip([t[0] for t in tasks], ctx.map(_call, [(f, a) for _, f, a in tasks], "thesis tasks"), strict=True))
    cal = res["setup_cal"]
    if not _failed(cal):
        res["hd2_calibrated"] = ctx.map(
            _call,
            [(measurement_task, (2, spp, "default", cal["calibrated_setup"]))],
            "reconstruction with calibration data",
        )[0]
    else:
        res["hd2_calibrated"] = cal
    tables: list[Table] = []
    notes: list[str] = []
    for name, r in res.items():
        if _failed(r):
            notes.append(f"**{name} failed**: {_error_text(r)}")

    def ok(name: str) -> dict[str, Any] | None:
        r = res.get(name)
        return None if _failed(r) else r

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
        _jsonable(
            {
                k: (_error_text(v) if _failed(v) else {kk: vv for kk, vv in v.items() if kk != "calibrated_setup"})
                for k, v in res.items()
            }
        ),
        notes,
    )


def _call(func: Callable[..., Any], args: tuple) -> Any:
    return func(*args)


def _thesis_plot(out: Path, tables: list[Table]) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    pts = []
    for t in tables:
        for r in t.rows:
            q, s = ratio(r.seed, r.ours), _norm(r.seed)
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


# -- dataset-based studies ---------------------------------------------------------------------------------
CALIB_MODULES = {
    "recon.markers": "marker detection and indexing",
    "recon.bias": "centroid-bias prediction",
    "calib.oneshot": "one-shot camera calibration",
}


def _read_sample(folder: str) -> tuple[Any, np.ndarray, dict[str, Any]]:
    from scenes.io import read_image
    from scenes.setup import setup_from_dict

    p = Path(folder)
    truth = json.loads((p / "truth.json").read_text())
    image, _ = read_image(p / "image.exr")
    return setup_from_dict(truth["setup_json"], str(p)), image, truth


def calibration_view_task(folder: str) -> dict[str, Any]:
    """Centroid and one-shot calibration errors of one calibration-view sample against its truth."""
    from calib.oneshot import Prior, calibrate, calibrate_bias_corrected, spot_bias_model
    from recon.bias import correct_centroids, model_for_setup
    from recon.markers import find_markers_for

    _quiet()
    setup, image, truth = _read_sample(folder)
    try:
        found = find_markers_for(image, setup)
    except ScopetwinError as exc:  # e.g. too little light to find the markers: a result, not a crash
        return {"folder": folder, "parameters": truth["parameters"], "error": f"{type(exc).__name__}: {exc}"}
    key = {(m["i"], m["j"]): (m["center_col"], m["center_row"]) for m in truth["markers"]}
    true_px = np.array([key[(int(i), int(j))] for i, j in found.ij], dtype=np.float64)
    corrected, _ = correct_centroids(found.centroids, found.ij, model_for_setup(setup))
    raw_err = np.linalg.norm(found.centroids - true_px, axis=1)
    cor_err = np.linalg.norm(corrected - true_px, axis=1)
    pat = setup.marker_pattern
    xy = pat.centers_local(found.ij)
    prior = Prior.from_camera(setup.camera_model, setup.camera.focal_length, plane=pat.frame)
    cam_t = setup.camera_model
    out = {
        "folder": folder,
        "parameters": truth["parameters"],
        "markers": int(len(found.ij)),
        "raw_rms_px": float(np.sqrt(np.mean(raw_err**2))),
        "raw_max_px": float(raw_err.max()),
        "corrected_rms_px": float(np.sqrt(np.mean(cor_err**2))),
        "corrected_max_px": float(cor_err.max()),
    }
    for label, fn in (
        ("raw", lambda: calibrate(xy, found.centroids, prior)),
        (
            "corrected",
            lambda: calibrate_bias_corrected(xy, found.centroids, prior, spot_bias_model(xy, pat.radii(found.ij)))[0],
        ),
    ):
        try:
            cal = fn()
            cam = cal.to_global(pat.frame)
            out[f"{label}_r_c_um"] = float(np.linalg.norm(cam.center - cam_t.center) * 1e3)
            out[f"{label}_angle_urad"] = axis_angle(cam.frame, cam_t.frame) * 1e6
            out[f"{label}_b_um"] = float((cam.b - cam_t.b) * 1e3)
            out[f"{label}_residual_rms_px"] = cal.residual_rms_px
        except ScopetwinError as exc:
            out[f"{label}_error"] = str(exc)
    return out


def _calibration_dataset(
    kind_vary: dict[str, Any], setup: str, count: int, seed: int, noise: bool, spp: int
) -> dict[str, Any]:
    return {
        "dataset": {
            "kind": "calibration",
            "setup": setup,
            "count": count,
            "master_seed": seed,
            "spp": spp,
            "noise": noise,
            "preview": False,
        },
        "vary": kind_vary,
    }


def _group(rows: list[dict[str, Any]], key: str) -> dict[Any, list[dict[str, Any]]]:
    out: dict[Any, list[dict[str, Any]]] = {}
    for r in rows:
        out.setdefault(r["parameters"][key], []).append(r)
    return out


def _mean(rows: list[dict[str, Any]], key: str) -> float | None:
    v = [r[key] for r in rows if r.get(key) is not None]
    return float(np.mean(v)) if v else None


def _line_plot(
    out: Path,
    name: str,
    x: list[float],
    series: dict[str, list[float | None]],
    xlabel: str,
    ylabel: str,
    title: str,
    logx: bool = False,
    refs: dict[str, float] | None = None,
) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4), constrained_layout=True)
    for label, ys in series.items():
        ax.plot(x, [np.nan if y is None else y for y in ys], "o-", label=label)
    for label, y in (refs or {}).items():
        ax.axhline(y, ls="--", lw=0.8, color="gray")
        ax.text(x[0], y, label, fontsize=7, va="bottom")
    if logx:
        ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(out / name, dpi=100)
    plt.close(fig)
    return name


def _view_table(title: str, groups: dict[Any, list[dict[str, Any]]], xname: str, note: str) -> Table:
    cols = [
        xname,
        "samples",
        "markers",
        "centroid RMS raw (px)",
        "centroid RMS corrected (px)",
        "max corrected (px)",
        "‖Δr_c‖ raw (µm)",
        "‖Δr_c‖ corrected (µm)",
        "axis angle corrected (µrad)",
        "Δb corrected (µm)",
        "failures",
    ]
    cells = []
    for x, all_rows in groups.items():
        rows = [r for r in all_rows if "error" not in r]
        fails = len(all_rows) - len(rows) + sum(1 for r in rows if "corrected_error" in r or "raw_error" in r)
        cells.append(
            [
                x,
                len(all_rows),
                _mean(rows, "markers"),
                _mean(rows, "raw_rms_px"),
                _mean(rows, "corrected_rms_px"),
                max((r["corrected_max_px"] for r in rows), default=None),
                _mean(rows, "raw_r_c_um"),
                _mean(rows, "corrected_r_c_um"),
                _mean(rows, "corrected_angle_urad"),
                _mean(rows, "corrected_b_um"),
                fails,
            ]
        )
    return Table(title, columns=cols, cells=cells, note=note)


def _sample_folders(root: Path) -> list[str]:
    return [str(p) for p in sorted((root / "samples").iterdir()) if p.is_dir() and p.name.isdigit()]


def noise(ctx: StudyContext, spp: int = 16, replicates: int = 2) -> StudyResult:
    """Centroid and calibration error against the exposure (EMVA sensor model), angular calibration view."""
    require("noise", CALIB_MODULES)
    fills = [0.02, 0.05, 0.1, 0.2, 0.4, 0.7, 0.95]
    cfg = _calibration_dataset(
        {"exposure_fill": {"sweep": fills}}, "thesis-2.8.1-angular", len(fills) * replicates, 2013, True, spp
    )
    root = ctx.dataset(cfg, "samples-noise")
    rows = ctx.map(calibration_view_task, [(f,) for f in _sample_folders(root)], "noise: calibrate")
    good = [r for r in rows if not _failed(r)]
    notes = [f"sample failed: {_error_text(r)}" for r in rows if _failed(r)]
    notes += [f"fill {r['parameters']['exposure_fill']:g}: {r['error']}" for r in good if "error" in r]
    groups = dict(sorted(_group(good, "exposure_fill").items()))
    x = list(groups)
    t = _view_table(
        "Centroid and calibration error against the exposure",
        groups,
        "full-well fill at the peak",
        f"Angular view of §2.8.1 (11x9 target), Mitsuba {spp} spp, EMVA 1288 sensor (12 bit, 18 ke- full "
        f"well, 10 e- dark noise); exposure set so the brightest pixel collects the given fraction of the "
        f"full well; {replicates} noise draws per exposure. Centroids against the exact marker images.",
    )
    plots = [
        _line_plot(
            ctx.out,
            "noise-centroids.png",
            x,
            {
                "raw": [_mean(g, "raw_rms_px") for g in groups.values()],
                "bias-corrected": [_mean(g, "corrected_rms_px") for g in groups.values()],
            },
            "fill of the full well at the peak (∝ exposure time)",
            "centroid RMS error (px)",
            "Centroid error vs exposure",
            logx=True,
            refs={"1/20 px": 0.05, "1/40 px": 0.025},
        ),
        _line_plot(
            ctx.out,
            "noise-calibration.png",
            x,
            {
                "|Δr_c| raw (µm)": [_mean(g, "raw_r_c_um") for g in groups.values()],
                "|Δr_c| corrected (µm)": [_mean(g, "corrected_r_c_um") for g in groups.values()],
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
        {"rows": _jsonable(good)},
        notes,
    )


def angle(ctx: StudyContext, spp: int = 16) -> StudyResult:
    """Centroid and calibration error against the viewing angle (seed §2.8.2 angle scan), noise-free."""
    require("angle", CALIB_MODULES)
    angles = [90.0, 80.0, 70.0, 60.0, 50.0, 40.0, 30.0, 20.0, 10.0]
    cfg = _calibration_dataset(
        {"view_angle_deg": {"sweep": angles}, "view_distance": {"fixed": 233.24}},
        "thesis-2.8.1-perpendicular",
        len(angles),
        282,
        False,
        spp,
    )
    root = ctx.dataset(cfg, "samples-angle")
    rows = ctx.map(calibration_view_task, [(f,) for f in _sample_folders(root)], "angle: calibrate")
    good = [r for r in rows if not _failed(r)]
    notes = [f"sample failed: {_error_text(r)}" for r in rows if _failed(r)]
    notes += [f"angle {r['parameters']['view_angle_deg']:g}°: {r['error']}" for r in good if "error" in r]
    groups = dict(sorted(_group(good, "view_angle_deg").items(), reverse=True))
    x = list(groups)
    t = _view_table(
        "Centroid and calibration error against the viewing angle (§2.8.2)",
        groups,
        "angle (deg)",
        f"Camera 233.24 mm from the 11x9 target centre, elevation from 90° down; Mitsuba {spp} spp, no "
        "noise. Seed: centroid accuracy between 1/40 and 1/20 px over the scan (Fig. 2.11).",
    )
    plots = [
        _line_plot(
            ctx.out,
            "angle-centroids.png",
            x,
            {
                "raw": [_mean(g, "raw_rms_px") for g in groups.values()],
                "bias-corrected": [_mean(g, "corrected_rms_px") for g in groups.values()],
            },
            "viewing angle (deg)",
            "centroid RMS error (px)",
            "Centroid error vs viewing angle",
            refs={"1/20 px (seed worst)": 0.05, "1/40 px (seed best)": 0.025},
        ),
        _line_plot(
            ctx.out,
            "angle-calibration.png",
            x,
            {
                "|Δr_c| raw (µm)": [_mean(g, "raw_r_c_um") for g in groups.values()],
                "|Δr_c| corrected (µm)": [_mean(g, "corrected_r_c_um") for g in groups.values()],
            },
            "viewing angle (deg)",
            "camera-centre error (µm)",
            "Calibration error vs viewing angle",
        ),
    ]
    return StudyResult(
        "Study: error against viewing angle",
        "The seed's §2.8.2 angle scan, with the one-shot calibration of each view added.",
        [t],
        plots,
        {"rows": _jsonable(good)},
        notes,
    )


SURFACE_MODULES = {
    "recon.markers": "marker detection and indexing",
    "recon.reconstruct": "height reconstruction",
    "recon.bias": "centroid-bias prediction",
}


def surface_task(folder: str, config: str = "default") -> dict[str, Any]:
    """Reconstruction error of one deflectometry sample (ideal setup) against its true surface."""
    from scenes.io import read_heightmap

    _quiet()
    setup, image, truth = _read_sample(folder)
    heights = read_heightmap(Path(folder) / "surface.exr")
    return {
        "folder": folder,
        "parameters": truth["parameters"],
        "config": config,
        **_reconstruct(setup, heights, image, None, config),
    }


def surface(ctx: StudyContext, spp: int = 16) -> StudyResult:
    """Reconstruction error against correlation length and range, and against the basis density."""
    require("surface", SURFACE_MODULES)
    lengths, ranges = [6.0, 12.0, 24.0], [20.0, 40.0, 80.0]
    cfg = {
        "dataset": {
            "kind": "deflectometry",
            "setup": THESIS_DEFLECTOMETRY,
            "count": len(lengths) * len(ranges),
            "master_seed": 19,
            "spp": spp,
            "noise": False,
            "preview": False,
        },
        "vary": {"surface_correlation_length": {"sweep": lengths}, "surface_range_um": {"sweep": ranges}},
    }
    root = ctx.dataset(cfg, "samples-surface")
    folders = _sample_folders(root)
    nominal = next(
        f
        for f in folders
        if json.loads((Path(f) / "truth.json").read_text())["parameters"]
        == {"surface_correlation_length": 12.0, "surface_range_um": 40.0}
    )
    densities = ["spacing=0.5", "spacing=0.7", "spacing=1.0", "spacing=1.5", "thesis"]
    args = [(f, "default") for f in folders] + [(nominal, d) for d in densities if d != "spacing=0.7"]
    rows = ctx.map(surface_task, args, "surface: reconstruct")
    notes = [f"sample failed: {_error_text(r)}" for r in rows if _failed(r)]
    good = [r for r in rows if not _failed(r)]
    grid = {
        (r["parameters"]["surface_correlation_length"], r["parameters"]["surface_range_um"]): r
        for r in good
        if r["config"] == "default"
    }
    cells = []
    for L in lengths:
        for R in ranges:
            r = grid.get((L, R))
            cells.append(
                [L, R]
                + (
                    [r["roi_rms_um"], r["roi_max_um"], r["all_rms_um"], r["outer_iterations"], r["markers"]]
                    if r
                    else [None] * 5
                )
            )
    t1 = Table(
        "Reconstruction error against the surface (ideal setup)",
        columns=[
            "correlation length (mm)",
            "range (µm)",
            "ROI RMS (µm)",
            "ROI max (µm)",
            "whole RMS (µm)",
            "outer iterations",
            "markers",
        ],
        cells=cells,
        note=f"§1.10 setup, §1.9 random surfaces, Mitsuba {spp} spp, no noise; default "
        "reconstruction (Gaussian shifted basis, scale chosen from the data, centroid-"
        "bias correction). Seed: ROI RMS 0.092-0.097 µm at 40 µm range.",
    )
    dens = {"spacing=0.7": grid.get((12.0, 40.0))}
    dens.update({r["config"]: r for r in good if r["config"] != "default"})
    cells = []
    for d in densities:
        r = dens.get(d)
        label = (
            "seed's 9x5 IMQ (9 along y), σ = (3, 4) mm"
            if d == "thesis"
            else f"Gaussian grid, spacing {d.split('=')[1]} σ"
        )
        cells.append(
            [label]
            + (
                [r["roi_rms_um"], r["roi_max_um"], r["all_rms_um"], r["outer_iterations"], r["seconds"]]
                if r
                else [None] * 5
            )
        )
    t2 = Table(
        "Reconstruction error against the basis density (12 mm, 40 µm surface)",
        columns=["basis", "ROI RMS (µm)", "ROI max (µm)", "whole RMS (µm)", "outer iterations", "seconds"],
        cells=cells,
    )
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4), constrained_layout=True)
    for R in ranges:
        ys = [grid[(L, R)]["roi_rms_um"] if (L, R) in grid else np.nan for L in lengths]
        ax.plot(lengths, ys, "o-", label=f"range {R:g} µm")
    ax.axhline(0.092, ls="--", color="gray", lw=0.8)
    ax.set_xlabel("correlation length (mm)")
    ax.set_ylabel("ROI RMS error (µm)")
    ax.set_yscale("log")
    ax.legend(fontsize=8)
    ax.grid(True, which="both", alpha=0.3)
    ax.set_title("Reconstruction error vs surface")
    fig.savefig(ctx.out / "surface-errors.png", dpi=100)
    plt.close(fig)
    return StudyResult(
        "Study: reconstruction error against the surface",
        "How the shape of the substrate and the "
        "density of the shifted basis functions (seed §1.8) limit the reconstruction.",
        [t1, t2],
        ["surface-errors.png"],
        {"rows": _jsonable(good)},
        notes,
    )


STUDIES: dict[str, Callable[[StudyContext], StudyResult]] = {
    "thesis": thesis,
    "noise": noise,
    "angle": angle,
    "surface": surface,
}


# -- running and writing -------------------------------------------------------------------------------------
def report_markdown(name: str, res: StudyResult, seconds: float, where: str) -> str:
    lines = [
        f"# {res.title}",
        "",
        res.intro,
        "",
        f"`scopetwin study {name}`: {seconds:.0f} s on {where}. Figures: {', '.join(res.plots) or 'none'}; "
        "machine-readable: results.json.",
        "",
    ]
    if res.notes:
        lines += ["## Problems", ""] + [f"- {n}" for n in res.notes] + [""]
    lines += ["## Tables", ""]
    for t in res.tables:
        lines += [table_markdown(t)]
    for p in res.plots:
        lines += [f"![{p}]({p})", ""]
    return "\n".join(lines)


def _commit(stage: Path, out: Path) -> None:
    out.mkdir(parents=True, exist_ok=True)
    for f in sorted(stage.iterdir()):
        dest = out / f.name
        if dest.is_dir():
            shutil.rmtree(dest)
        f.replace(dest)
    stage.rmdir()


def run_study(
    name: str,
    out: str | Path,
    scheduler: str | None = None,
    workers: int | None = None,
    threads: int | None = None,
    progress: bool = True,
) -> dict[str, Any]:
    """Run study ``name`` and write ``report.md``, ``results.json`` and plots into ``out`` (on success only).

    ``workers`` 0 runs every task in this process; otherwise an embedded LocalCluster (or ``scheduler``).
    """
    from sim.dataset import dask_client

    if name not in STUDIES:
        raise StudyError(f"unknown study {name!r} (known: {', '.join(STUDIES)})")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.staging-", dir=out.parent))
    t0 = time.perf_counter()
    if threads is None and scheduler is None and workers != 0:
        threads = 1
    try:
        ctx_mgr = contextlib.nullcontext(None) if (workers == 0 and not scheduler) else dask_client(scheduler, workers)
        with ctx_mgr as client:
            if client is not None and threads:
                from sim.dataset import _init_process

                client.run(_init_process, threads)
            where = (
                "this process"
                if client is None
                else (f"Dask at {client.scheduler.address} ({len(client.scheduler_info()['workers'])} workers)")
            )
            res = STUDIES[name](StudyContext(stage, client, progress, threads))
        seconds = time.perf_counter() - t0
        (stage / "report.md").write_text(report_markdown(name, res, seconds, where))
        summary = {
            "study": name,
            "seconds": seconds,
            "where": where,
            "tables": [table_json(t) for t in res.tables],
            "plots": res.plots,
            "notes": res.notes,
            "data": res.summary,
        }
        (stage / "results.json").write_text(json.dumps(_jsonable(summary), indent=2) + "\n")
        _commit(stage, out)
    except BaseException:
        shutil.rmtree(stage, ignore_errors=True)
        raise
    return {
        "study": name,
        "report": str(out / "report.md"),
        "results": str(out / "results.json"),
        "seconds": seconds,
        "plots": [str(out / p) for p in res.plots],
        "notes": res.notes,
    }
