"""A contact sheet of a dataset (``scopetwin dataset show DIR --out sheet.png``): look before training.

One tile per sample: the camera image (grey, scaled to its 99.9th percentile, gamma 1/2.2 as the previews) with its
truth drawn over it — for Part I samples the outline of the substrate (or mirror, or target plate) and of the region
of interest from the per-pixel maps, the true height as a colour map over the substrate, and the (i, j) of every
visible marker at its exact image; four-channel samples show their channels side by side, GRIN samples their
target's name. The title of a tile names the sample and its varied quantities. Drawn with matplotlib's Agg canvas
(no pyplot, no display).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.sim.datasets.config import DatasetError

#: Most tiles one sheet shows (a larger selection is refused: split it with --indices).
MAX_TILES = 64
#: Most marker labels drawn per tile (every k-th visible marker beyond it).
MAX_LABELS = 40


def _grey(image: NDArray[Any]) -> NDArray[np.float64]:
    top = float(np.percentile(image, 99.9)) or 1.0
    low = float(np.percentile(image, 0.1))
    span = top - low if top > low else 1.0
    return np.asarray(np.clip((image - low) / span, 0, 1) ** (1 / 2.2), dtype=np.float64)


def _title(sample: Any) -> str:
    parts = []
    for name, value in sample.truth.get("parameters", {}).items():
        if isinstance(value, int | float) and not isinstance(value, bool):
            parts.append(f"{name}={value:.3g}")
        elif isinstance(value, str):
            parts.append(f"{name}={value}")
    return "\n".join([f"#{sample.index} {sample.kind}", *parts[:3]])


def _draw_part1(ax: Any, sample: Any) -> None:
    maps = sample.maps
    ax.imshow(_grey(sample.image), cmap="gray", interpolation="nearest")
    if "height" in maps:
        h = np.where(maps["mask"], maps["height"] * 1e3, np.nan)  # µm
        im = ax.imshow(h, cmap="viridis", alpha=0.45, interpolation="nearest")
        bar = ax.figure.colorbar(im, ax=ax, fraction=0.035, pad=0.01)
        bar.set_label("height, µm", fontsize=6)
        bar.ax.tick_params(labelsize=5)
    ax.contour(maps["mask"].astype(float), levels=[0.5], colors="red", linewidths=0.8)
    if "roi" in maps and maps["roi"].any():
        ax.contour(maps["roi"].astype(float), levels=[0.5], colors="orange", linewidths=0.6, linestyles="dashed")
    table = sample.truth.markers
    vis = np.flatnonzero(table.visible & np.isfinite(table.center_px).all(axis=1))
    step = max(1, math.ceil(len(vis) / MAX_LABELS))
    for k in vis[::step]:
        col, row = table.center_px[k] - 0.5  # array coordinates: pixel centres at integers
        i, j = table.ij[k]
        ax.text(col, row, f"{i},{j}", color="yellow", fontsize=4, ha="center", va="center")


def _draw_cmu(ax: Any, sample: Any) -> None:
    images = sample.images
    tiles = [_grey(images[k]) for k in sorted(images)]
    ax.imshow(np.hstack(tiles), cmap="gray", interpolation="nearest")
    w = tiles[0].shape[1]
    for n, key in enumerate(sorted(images)):
        ax.text(n * w + 4, 12, key.removeprefix("image_"), color="yellow", fontsize=6, va="top")
        entry = sample.truth.get("channels", {}).get(key.removeprefix("image_"), {})
        if "frame_center_px" in entry:
            c, r = entry["frame_center_px"]
            ax.plot([n * w + c - 0.5], [r - 0.5], "+", color="red", markersize=6)


def _draw_grin(ax: Any, sample: Any) -> None:
    ax.imshow(_grey(sample.image), cmap="gray", interpolation="nearest")
    target = sample.truth.get("target", {})
    ax.text(4, 12, str(target.get("name", "")), color="yellow", fontsize=6, va="top")


def contact_sheet(dataset: Any, indices: Sequence[int], out: str | Path, columns: int | None = None) -> dict[str, Any]:
    """Draw the samples at positions ``indices`` of ``dataset`` into one PNG (module docstring).

    Returns
    -------
    dict
        ``out``, ``samples`` (their indices), ``columns``, ``rows``.

    Raises
    ------
    DatasetError
        No samples, or more than :data:`MAX_TILES`.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from scopetwin.scenes.io import atomic_path

    picked = [dataset[k] for k in indices]
    if not picked:
        raise DatasetError(f"{dataset.root}: no finished samples to show")
    if len(picked) > MAX_TILES:
        raise DatasetError(f"{len(picked)} samples make too large a sheet (at most {MAX_TILES}): use --indices A:B")
    cols = columns or min(4, len(picked))
    rows = math.ceil(len(picked) / cols)
    shape = picked[0].image.shape
    wide = 4 if picked[0].kind == "cmu" else 1
    aspect = shape[0] / (shape[1] * wide)
    fig = Figure(figsize=(3.2 * cols, 3.2 * rows * aspect + 0.5 * rows), dpi=150)
    FigureCanvasAgg(fig)
    draw = {"cmu": _draw_cmu, "grin": _draw_grin}
    for n, sample in enumerate(picked):
        ax = fig.add_subplot(rows, cols, n + 1)
        draw.get(sample.kind, _draw_part1)(ax, sample)
        ax.set_title(_title(sample), fontsize=6)
        ax.set_axis_off()
    fig.tight_layout()
    path = Path(out)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return {"out": str(path), "samples": [s.index for s in picked], "columns": cols, "rows": rows}
