"""Study tables (the thesis's value | ours | their ratio), their markdown and JSON forms, and the study plots."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np


@dataclass
class Row:
    """One quantity: the thesis's value, ours (scalars or vectors), and the unit they are printed in."""

    label: str
    seed: Any
    ours: Any
    unit: str = ""


@dataclass
class Table:
    """A titled table of :class:`Row` (thesis | ours | ratio) or of free columns (``columns`` + ``cells``)."""

    title: str
    rows: list[Row] = field(default_factory=list)
    note: str = ""
    columns: list[str] | None = None
    cells: list[list[Any]] | None = None


def norm(v: Any) -> float | None:
    """Euclidean norm of a scalar or vector; None when missing or not finite."""
    if v is None:
        return None
    a = np.atleast_1d(np.asarray(v, dtype=np.float64))
    if not np.all(np.isfinite(a)):
        return None
    return float(np.linalg.norm(a))


def ratio(seed: Any, ours: Any) -> float | None:
    """|ours| / |thesis| (Euclidean norms for vectors); None when the thesis's value is 0, missing or not finite."""
    s, o = norm(seed), norm(ours)
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
        lines += ["| quantity | thesis | ours | ratio ours/thesis |", "|---|---|---|---|"]
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


def jsonable(v: Any) -> Any:
    """Numpy values as Python ones, tuples as lists, non-finite floats as None (results.json)."""
    if isinstance(v, dict):
        return {str(k): jsonable(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [jsonable(x) for x in v]
    if isinstance(v, np.ndarray):
        return jsonable(v.tolist())
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def table_json(t: Table) -> dict[str, Any]:
    """A table for results.json (rows with their ratio, or columns and cells)."""
    if t.columns is not None:
        return {"title": t.title, "columns": t.columns, "cells": jsonable(t.cells), "note": t.note}
    return {
        "title": t.title,
        "note": t.note,
        "rows": [
            {
                "label": r.label,
                "unit": r.unit,
                "seed": jsonable(r.seed),
                "ours": jsonable(r.ours),
                "ratio": ratio(r.seed, r.ours),
            }
            for r in t.rows
        ],
    }


def group(rows: list[dict[str, Any]], key: str) -> dict[Any, list[dict[str, Any]]]:
    """Rows grouped by the value of the varied parameter ``key``."""
    out: dict[Any, list[dict[str, Any]]] = {}
    for r in rows:
        out.setdefault(r["parameters"][key], []).append(r)
    return out


def mean(rows: list[dict[str, Any]], key: str) -> float | None:
    """Mean of ``key`` over the rows that have it (None if none has)."""
    v = [r[key] for r in rows if r.get(key) is not None]
    return float(np.mean(v)) if v else None


def line_plot(
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
    """A log-y line plot of ``series`` against ``x`` (optional horizontal reference lines) as ``out/name``."""
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


def view_table(title: str, groups: dict[Any, list[dict[str, Any]]], xname: str, note: str) -> Table:
    """Centroid and calibration errors of calibration views, one row per value of the varied parameter."""
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
                mean(rows, "markers"),
                mean(rows, "raw_rms_px"),
                mean(rows, "corrected_rms_px"),
                max((r["corrected_max_px"] for r in rows), default=None),
                mean(rows, "raw_r_c_um"),
                mean(rows, "corrected_r_c_um"),
                mean(rows, "corrected_angle_urad"),
                mean(rows, "corrected_b_um"),
                fails,
            ]
        )
    return Table(title, columns=cols, cells=cells, note=note)
