"""The ``surface`` study: reconstruction error against the surface and the density of the shifted basis (§1.8)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from scopetwin.sim.studies.context import StudyContext, StudyResult, error_text, failed, require
from scopetwin.sim.studies.tables import Table, jsonable
from scopetwin.sim.studies.tasks import THESIS_DEFLECTOMETRY, quiet, read_sample, reconstruct, sample_folders

SURFACE_MODULES = {
    "scopetwin.recon.markers": "marker detection and indexing",
    "scopetwin.recon.reconstruct": "height reconstruction",
    "scopetwin.recon.bias": "centroid-bias prediction",
}


def surface_task(folder: str, config: str = "default") -> dict[str, Any]:
    """Reconstruction error of one deflectometry sample (ideal setup) against its true surface."""
    from scopetwin.scenes.io import read_heightmap

    quiet()
    setup, image, truth = read_sample(folder)
    heights = read_heightmap(Path(folder) / "surface.exr")
    return {
        "folder": folder,
        "parameters": truth["parameters"],
        "config": config,
        **reconstruct(setup, heights, image, None, config),
    }


def broadband_task(folder: str) -> dict[str, Any]:
    """Errors and reported uncertainties of one PSD-surface sample (ideal setup, bias step on), µm."""
    from scopetwin.recon.strategy import reconstruct
    from scopetwin.recon.substrate import Substrate2D
    from scopetwin.scenes.io import read_heightmap
    from scopetwin.sim.pipeline import roi_errors

    quiet()
    setup, image, truth = read_sample(folder)
    heights = read_heightmap(Path(folder) / "surface.exr")
    res = reconstruct(image, setup).result
    u = res.uncertainty
    return {
        "folder": folder,
        "parameters": truth["parameters"],
        **roi_errors(res.surface.height, heights, Substrate2D.from_setup(setup)),
        "u_abs_um": u.absolute_um if u else None,
        "u_shape_um": u.shape_um if u else None,
        "correction_um": u.correction_um if u else None,
    }


BROADBAND_NM = [0.0, 1.0, 3.0, 10.0]


def _broadband_table(ctx: StudyContext, spp: int) -> tuple[Table, list[str]]:
    """Errors against the broadband RMS of PSD surfaces (K-correlation, B = 12 mm, C = 3, 40 µm)."""
    cfg = {
        "dataset": {
            "kind": "deflectometry",
            "setup": THESIS_DEFLECTOMETRY,
            "count": len(BROADBAND_NM),
            "master_seed": 23,
            "spp": spp,
            "noise": False,
            "preview": False,
        },
        "vary": {"surface_kind": {"choice": ["psd"]}, "surface_broadband_rms_nm": {"sweep": BROADBAND_NM}},
    }
    root = ctx.dataset(cfg, "samples-broadband")
    rows = ctx.map(broadband_task, [(f,) for f in sample_folders(root)], "surface: broadband")
    notes = [f"broadband sample failed: {error_text(r)}" for r in rows if failed(r)]
    cells = []
    for r in sorted((r for r in rows if not failed(r)), key=lambda r: r["parameters"]["surface_broadband_rms_nm"]):
        fit = r["roi_absolute_um"] - (r["correction_um"] or 0.0)
        cells.append(
            [
                r["parameters"]["surface_broadband_rms_nm"],
                fit,
                r["roi_absolute_um"],
                r["u_abs_um"],
                r["roi_shape_um"],
                r["u_shape_um"],
                r["roi_rms_um"],
            ]
        )
    return (
        Table(
            "Reconstruction error against the broadband RMS (PSD surfaces)",
            columns=[
                "broadband RMS (nm)",
                "absolute, fit (µm)",
                "absolute (µm)",
                "u(absolute) (µm)",
                "shape (µm)",
                "u(shape) (µm)",
                "ROI RMS (µm)",
            ],
            cells=cells,
            note=f"K-correlation (ABC) surfaces, B = 12 mm, C = 3, roll-off 6 mm, 40 µm, broadband part at 0.5-4 mm "
            f"wavelengths; Mitsuba {spp} spp, no noise, ideal setup, bias step on. 'fit': the shifted-basis "
            "surface's own extrapolation; 'absolute': after the posterior start height (recon.posterior).",
        ),
        notes,
    )


#: Basis densities of the second table: Gaussian grid spacings (in σ) and the thesis's own basis.
DENSITIES = ["spacing=0.5", "spacing=0.7", "spacing=1.0", "spacing=1.5", "thesis"]


def _surface_dataset(ctx: StudyContext, lengths: list[float], ranges: list[float], spp: int) -> Path:
    """Render the random surfaces of every correlation length x range (§1.9), clean, on the §1.10 setup."""
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
    return ctx.dataset(cfg, "samples-surface")


def _nominal_folder(folders: list[str]) -> str:
    """The sample with the nominal surface (12 mm correlation length, 40 µm range)."""
    return next(
        f
        for f in folders
        if json.loads((Path(f) / "truth.json").read_text())["parameters"]
        == {"surface_correlation_length": 12.0, "surface_range_um": 40.0}
    )


def _surface_table(grid: dict[tuple[float, float], Any], lengths: list[float], ranges: list[float], spp: int) -> Table:
    """Errors of the default reconstruction per correlation length and range."""
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
    return Table(
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
        "bias correction). Thesis: ROI RMS 0.092-0.097 µm at 40 µm range.",
    )


def _density_table(grid: dict[tuple[float, float], Any], good: list[dict[str, Any]]) -> Table:
    """Errors on the nominal surface per basis density (the default, spacing 0.7 σ, from the surface grid)."""
    dens = {"spacing=0.7": grid.get((12.0, 40.0))}
    dens.update({r["config"]: r for r in good if r["config"] != "default"})
    cells = []
    for d in DENSITIES:
        r = dens.get(d)
        label = (
            "the thesis's 9x5 IMQ (9 along y), σ = (3, 4) mm"
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
    return Table(
        "Reconstruction error against the basis density (12 mm, 40 µm surface)",
        columns=["basis", "ROI RMS (µm)", "ROI max (µm)", "whole RMS (µm)", "outer iterations", "seconds"],
        cells=cells,
    )


def _plot_surface_errors(
    out: Path, grid: dict[tuple[float, float], Any], lengths: list[float], ranges: list[float]
) -> None:
    """Write ``surface-errors.png``: ROI RMS error against correlation length, one line per range."""
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
    fig.savefig(out / "surface-errors.png", dpi=100)
    plt.close(fig)


def surface(ctx: StudyContext, spp: int = 16) -> StudyResult:
    """Reconstruction error against correlation length and range, and against the basis density (thesis §1.8).

    Parameters
    ----------
    ctx : StudyContext
        Where the datasets are written and the tasks run.
    spp : int
        Mitsuba samples per pixel of the renders.

    Returns
    -------
    StudyResult
        The surface, basis-density and broadband tables and the plot ``surface-errors.png``.
    """
    require("surface", SURFACE_MODULES)
    lengths, ranges = [6.0, 12.0, 24.0], [20.0, 40.0, 80.0]
    folders = sample_folders(_surface_dataset(ctx, lengths, ranges, spp))
    nominal = _nominal_folder(folders)
    args = [(f, "default") for f in folders] + [(nominal, d) for d in DENSITIES if d != "spacing=0.7"]
    rows = ctx.map(surface_task, args, "surface: reconstruct")
    notes = [f"sample failed: {error_text(r)}" for r in rows if failed(r)]
    good = [r for r in rows if not failed(r)]
    grid = {
        (r["parameters"]["surface_correlation_length"], r["parameters"]["surface_range_um"]): r
        for r in good
        if r["config"] == "default"
    }
    t1 = _surface_table(grid, lengths, ranges, spp)
    t2 = _density_table(grid, good)
    _plot_surface_errors(ctx.out, grid, lengths, ranges)
    t3, bb_notes = _broadband_table(ctx, spp)
    notes += bb_notes
    return StudyResult(
        "Study: reconstruction error against the surface",
        "How the shape of the substrate and the "
        "density of the shifted basis functions (thesis §1.8) limit the reconstruction.",
        [t1, t2, t3],
        ["surface-errors.png"],
        {"rows": jsonable(good)},
        notes,
    )
