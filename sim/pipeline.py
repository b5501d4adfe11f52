"""The end-to-end job of ``scopetwin run``: simulate, render, calibrate, reconstruct, compare, report.

1. a §1.9 random surface on the §1.10 substrate (40 µm range);
2. Mitsuba renders, sensor noise on: the target on the holding frame and the pattern in a flat mirror
   (the two calibration images of §2.7) and the measurement image of the bent substrate (§1.10);
3. calibration of the setup from the two calibration images (``calib``, §2.7);
4. marker detection (``recon.markers``) and reconstruction (``recon.reconstruct``, §1.4) with the
   calibrated and with the ideal setup, centroid-bias correction on;
5. comparison with the truth over the region of interest — absolute height (ROI mean error), shape
   (RMS after removing the ROI mean), RMS and maximum — beside the seed's §1.10 / Table 2.7 figures;
6. a report folder: ``report.md``, EXR height and error maps, PNG plots, the focus map, ``summary.json``.

The caller stages ``out_dir`` atomically; this module only writes into it.
"""

from __future__ import annotations

import json
import time
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap

MEASUREMENT = "thesis-1.10-deflectometry"
TARGET = "thesis-2.8.3-substrate"
MIRROR = "thesis-2.8.3-mirror"

#: The seed's figures (§1.10 height distribution 2, §2.8.4 Table 2.7), µm.
SEED = {"ideal": {"roi_rms_um": 0.091, "roi_max_um": 0.357}, "calibrated": {"roi_rms_um": 0.414, "roi_max_um": 1.162}}


def render_with_noise(setup: Setup, heights: HeightMap | None, spp: int, seed: int) -> NDArray[np.float32]:
    """Mitsuba render plus the EMVA sensor model (:func:`scopetwin.sim.measurement.apply_sensor`), as float32."""
    from scopetwin.scenes.mitsuba.render import render_setup
    from scopetwin.sim.measurement import apply_sensor

    image = render_setup(setup, heights, spp=spp, seed=seed)
    return np.asarray(apply_sensor(setup, image, seed), dtype=np.float32)


def calibrate_from_images(
    target_setup: Setup, mirror_setup: Setup, img_target: NDArray[Any], img_mirror: NDArray[Any]
) -> tuple[Setup, str]:
    """Setup calibration of §2.7 with calib/ (bias-corrected): the calibrated deflectometry setup and its TOML."""
    from scopetwin.calib.oneshot import Prior
    from scopetwin.calib.setup_calibration import (
        calibrate_setup,
        calibrated_setup_dict,
        mirror_prior,
        toml_dumps,
        virtual_coordinates,
    )
    from scopetwin.recon.bias import spot_bias_model
    from scopetwin.recon.markers import find_markers_for
    from scopetwin.scenes.setup import setup_from_dict

    tframe = target_setup.marker_pattern.frame
    prior_s = Prior.from_camera(target_setup.camera_model, target_setup.camera.focal_length, plane=tframe)
    prior_m = mirror_prior(mirror_setup)
    tp, pp = target_setup.marker_pattern, mirror_setup.marker_pattern
    found_s = find_markers_for(img_target, target_setup)
    found_m = find_markers_for(img_mirror, mirror_setup)
    xs = tp.centers_local(found_s.ij)
    xm = virtual_coordinates(pp, found_m.ij)
    result = calibrate_setup(
        xs,
        found_s.centroids,
        prior_s,
        xm,
        found_m.centroids,
        prior_m,
        target_frame=tframe,
        substrate_bias=spot_bias_model(xs, tp.radii(found_s.ij)),
        mirror_bias=spot_bias_model(xm, pp.radii(found_m.ij)),
    )
    data = calibrated_setup_dict(mirror_setup, result)
    text = toml_dumps(data, "scopetwin run: setup calibrated as in seed §2.7")
    return setup_from_dict(data, "calibrated setup"), text


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
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = []
    ext = [-0.5 * sub.size_x, 0.5 * sub.size_x, -0.5 * sub.size_y, 0.5 * sub.size_y]
    xx, yy = np.meshgrid(np.linspace(ext[0], ext[1], 126), np.linspace(ext[2], ext[3], 286))
    fig, axes = plt.subplots(1, 1 + len(results), figsize=(4 + 4 * len(results), 6), constrained_layout=True)
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
    fig.savefig(out / "height.png", dpi=90)
    plt.close(fig)
    names.append("height.png")

    fig, axes = plt.subplots(1, len(results), figsize=(4.5 * len(results), 6), constrained_layout=True, squeeze=False)
    roi = np.abs(yy) < 0.5 * sub.roi_length
    for ax, (name, r) in zip(axes[0], results.items(), strict=True):
        err = np.where(roi, (r["result"].surface.height(xx, yy) - truth.height(xx, yy)) * 1e3, np.nan)
        im = ax.imshow(err, origin="lower", extent=ext, cmap="RdBu_r")
        ax.set_title(f"error in the ROI ({name}), µm")
        fig.colorbar(im, ax=ax)
    fig.savefig(out / "error.png", dpi=90)
    plt.close(fig)
    names.append("error.png")

    fig, ax = plt.subplots(figsize=(10, 7.5), constrained_layout=True)
    ax.imshow(image, cmap="gray", vmax=float(np.percentile(image, 99.9)))
    ax.plot(found.centroids[:, 0] - 0.5, found.centroids[:, 1] - 0.5, "r+", ms=4, mew=0.6)
    ref = np.flatnonzero((found.ij[:, 0] == 0) & (found.ij[:, 1] == 0))
    if len(ref):
        ax.plot(*(found.centroids[ref[0]] - 0.5), "co", mfc="none", ms=12)
    ax.set_title(f"measurement image with {len(found.ij)} indexed markers (cyan: reference)")
    fig.savefig(out / "markers.png", dpi=80)
    plt.close(fig)
    names.append("markers.png")

    fig, axes = plt.subplots(1, 2, figsize=(11, 4), constrained_layout=True)
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
    fig.savefig(out / "convergence.png", dpi=90)
    plt.close(fig)
    names.append("convergence.png")
    return names


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
    camera = setup.camera.model_dump(exclude_none=True)
    target = load_setup(TARGET, {**render_over, "camera": camera})
    mirror = load_setup(
        MIRROR,
        {
            **render_over,
            "camera": camera,
            "pattern": setup.pattern.model_dump(exclude_none=True) if setup.pattern is not None else {},
            "substrate": setup.substrate.model_dump(exclude_none=True),
        },
    )
    return setup, target, mirror


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
        Folder to write into (created; the caller stages it atomically).
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


def _run(
    out_dir: Path,
    spp: int | None,
    seed: int | None,
    progress: bool,
    setup_name: str | None,
    surface_file: str | Path | None,
) -> dict[str, Any]:
    from tqdm import tqdm

    from scopetwin.recon.focusmap import focus_map
    from scopetwin.recon.markers import find_markers_for
    from scopetwin.recon.reconstruct import MarkerObservations, Reconstructor, Substrate2D, centroid_bias_step
    from scopetwin.scenes.io import write_heightmap, write_image
    from scopetwin.sim.surfaces import surface_for
    from scopetwin.sim.truth import marker_truth

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    timings: dict[str, float] = {}
    bar = tqdm(total=7, desc="scopetwin run", unit="step", disable=not progress)

    def tick(name: str, t0: float) -> float:
        timings[name] = time.perf_counter() - t0
        bar.update(1)
        bar.set_postfix_str(name)
        return time.perf_counter()

    t = time.perf_counter()
    over: dict[str, Any] = {"render": {"noise": True}}
    if spp is not None:
        over["render"]["spp"] = spp
    if seed is not None:
        over["render"]["seed"] = seed
        over["substrate"] = {"surface": {"seed": seed}}
    setup, target_setup, mirror_setup = run_setups(setup_name, surface_file, over)
    heights = surface_for(setup)
    assert heights is not None
    sub = Substrate2D.from_setup(setup)
    r_spp, r_seed = setup.render.spp, setup.render.seed
    t = tick("surface", t)

    img_target = render_with_noise(target_setup, None, r_spp, r_seed + 1)
    img_mirror = render_with_noise(mirror_setup, None, r_spp, r_seed + 2)
    t = tick("render calibration images", t)
    image = render_with_noise(setup, heights, r_spp, r_seed)
    t = tick("render measurement", t)

    calibration_note = "calib/ (§2.7: target on the frame + pattern in a flat mirror, bias-corrected)"
    try:
        calibrated, toml_text = calibrate_from_images(target_setup, mirror_setup, img_target, img_mirror)
        (out / "calibrated-setup.toml").write_text(toml_text)
    except (ImportError, ScopetwinError) as exc:
        calibrated = None
        calibration_note = f"UNAVAILABLE ({type(exc).__name__}: {exc}); the 'calibrated' row uses the ideal setup"
        traceback.print_exc()
    t = tick("calibrate", t)

    found = find_markers_for(image, setup)
    obs = MarkerObservations(found.ij, found.centroids)
    setups = {"ideal": setup, "calibrated": calibrated if calibrated is not None else setup}
    results: dict[str, Any] = {}
    for name, s in setups.items():
        t0 = time.perf_counter()
        rec = Reconstructor.from_setup(s, bias=centroid_bias_step(s))
        res = rec.run(obs, history_path=out / f"{name}-history.json")
        results[name] = {
            "result": res,
            "seconds": time.perf_counter() - t0,
            "errors": roi_errors(res.surface.height, heights, sub),
        }
    t = tick("detect + reconstruct", t)

    truth = marker_truth(setup, heights)
    exact = MarkerObservations(truth.ij[truth.visible], truth.center_px[truth.visible])
    res_exact = Reconstructor.from_setup(setup).run(exact)
    exact_err = roi_errors(res_exact.surface.height, heights, sub)
    t = tick("truth reference", t)

    write_heightmap(out / "truth-heights.exr", heights)
    write_image(out / "measurement.exr", image, setup.to_json())
    write_image(out / "calib-target.exr", img_target, target_setup.to_json())
    write_image(out / "calib-mirror.exr", img_mirror, mirror_setup.to_json())
    files = ["truth-heights.exr", "measurement.exr", "calib-target.exr", "calib-mirror.exr"]
    if calibrated is not None:
        files.append("calibrated-setup.toml")
    for name, r in results.items():
        hm = r["result"].heightmap(heights.z.shape[1] // 2, heights.z.shape[0] // 2)
        write_heightmap(
            out / f"heights-{name}.exr", hm, r["result"].std_heightmap(heights.z.shape[1] // 2, heights.z.shape[0] // 2)
        )
        err = HeightMap(
            hm.z - heights.height(*np.meshgrid(hm.x_nodes, hm.y_nodes)), hm.x_min, hm.x_max, hm.y_min, hm.y_max
        )
        write_heightmap(out / f"error-{name}.exr", err)
        files += [f"heights-{name}.exr", f"error-{name}.exr"]
    cal_res = results["calibrated"]["result"]
    cal_std = cal_res.std_heightmap()
    fm = focus_map(
        cal_res.surface.height,
        sub.x_range,
        (-0.5 * sub.roi_length, 0.5 * sub.roi_length),
        height_std=cal_std.height if cal_std is not None else None,
    )
    (out / "focusmap.csv").write_text(fm.to_csv())
    files += ["focusmap.csv"] + _plots(out, image, found, heights, results, sub)

    surface = setup.substrate.surface if setup.substrate is not None else None
    if surface is None:
        raise ScopetwinError(f"setup {setup.name} has no substrate surface to compare with")
    summary: dict[str, Any] = {
        "setup": setup.name,
        "surface": {
            "kind": surface.kind,
            "description": surface_description(setup),
            "range_um": surface.range_um,
            "correlation_length_mm": surface.correlation_length,
            "seed": surface.seed,
            "broadband_rms_nm": surface.broadband_rms_nm,
        },
        "spp": r_spp,
        "render_seed": r_seed,
        "markers": int(len(obs.ij)),
        "calibration": calibration_note,
        "reconstructions": {
            name: {
                **r["errors"],
                "outer_iterations": r["result"].outer_iterations,
                "inner_iterations": r["result"].inner_iterations,
                "delta_h_max_um": r["result"].delta_h_max_um,
                "seconds": r["seconds"],
                "sigma_mm": r["result"].surface.basis.sigma[0],
                **({"uncertainty": r["result"].uncertainty.summary()} if r["result"].uncertainty is not None else {}),
                "history": r["result"].history_dicts(),
            }
            for name, r in results.items()
        },
        "exact_markers": {
            **exact_err,
            "outer_iterations": res_exact.outer_iterations,
            **({"uncertainty": res_exact.uncertainty.summary()} if res_exact.uncertainty is not None else {}),
        },
        "focus_map": fm.summary(),
        "timings_s": timings,
        "files": files,
    }
    if calibrated is not None:
        cam_i, cam_c = setup.camera_model, calibrated.camera_model
        pat_i, pat_c = setup.marker_pattern.frame, calibrated.marker_pattern.frame
        summary["calibration_deviation"] = {
            "camera_r_c_mm": (cam_c.center - cam_i.center).tolist(),
            "camera_b_mm": cam_c.b - cam_i.b,
            "camera_n_z": (cam_c.frame.nz - cam_i.frame.nz).tolist(),
            "pattern_r_c_mm": (pat_c.origin - pat_i.origin).tolist(),
            "pattern_n_z": (pat_c.nz - pat_i.nz).tolist(),
        }
    summary["seconds"] = time.perf_counter() - t_start
    (out / "report.md").write_text(_report(summary))
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    bar.update(1)
    bar.close()
    return summary


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
        "## ROI errors beside the seed (µm)",
        "",
        "u: one standard uncertainty as reported by the reconstruction (no truth used).",
        "",
        "| reconstruction | ROI RMS | ROI max | absolute (ROI mean) | u(absolute) | shape (RMS - mean) | u(shape) "
        "| whole RMS | outer | inner | seed ROI RMS | seed ROI max |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]

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
            f"{r['inner_iterations']} | {sd['roi_rms_um']} | {sd['roi_max_um']} |"
        )
    ua, us = u_cells(ex)
    lines.append(
        f"| exact marker images, ideal setup | {ex['roi_rms_um']:.4f} | {ex['roi_max_um']:.4f} | "
        f"{ex['roi_absolute_um']:+.4f} | {ua} | {ex['roi_shape_um']:.4f} | {us} | {ex['all_rms_um']:.3f} | "
        f"{ex['outer_iterations']} | | | |"
    )
    lines += ["", "Seed figures: §1.10 height distribution 2 (ideal) and §2.8.4 Table 2.7 (calibrated).", ""]
    if "calibration_deviation" in s:
        d = s["calibration_deviation"]
        lines += [
            "## Calibration deviation from the ideal setup",
            "",
            f"- camera r_c: {np.round(d['camera_r_c_mm'], 5).tolist()} mm, b: {d['camera_b_mm']:+.2e} mm, "
            f"N_z: {np.round(d['camera_n_z'], 7).tolist()}",
            f"- pattern r_c: {np.round(d['pattern_r_c_mm'], 5).tolist()} mm, "
            f"N_z: {np.round(d['pattern_n_z'], 7).tolist()}",
            "",
        ]
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
    lines += [f"- {k}: {v:.2f}" for k, v in s["timings_s"].items()]
    lines += ["", f"Total {s['seconds']:.1f} s.", "", "Files: " + ", ".join(s["files"]), ""]
    return "\n".join(lines)
