"""Pictures the commands write beside their numbers: the indexed-marker overlay (thesis §1.5, §2.6) and the GRIN spot
diagrams (thesis §8.3). Each is written atomically; a path that cannot be written is a user error."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.recon.markers import MarkerError, Markers
from scopetwin.scenes.io import atomic_path


def label_step(centroids: NDArray[Any], label_width_px: float) -> int:
    """Every how many-th marker (along i and j) gets a label, so that labels of width ``label_width_px`` do not
    run together: the smallest k with k x (median marker spacing) >= 1.3 x the label width."""
    pts = np.asarray(centroids, dtype=np.float64).reshape(-1, 2)
    if len(pts) < 2:
        return 1
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(pts).query(pts, k=2)
    spacing = float(np.median(dist[:, 1]))
    if not spacing > 0:
        return 1
    return max(1, int(np.ceil(1.3 * label_width_px / spacing)))


def _text(out: NDArray[Any], text: str, org: tuple[int, int], scale: float, colour: tuple[int, int, int]) -> None:
    """Text with a dark halo, legible on bright and dark ground."""
    import cv2

    font = cv2.FONT_HERSHEY_SIMPLEX
    cv2.putText(out, text, org, font, scale, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(out, text, org, font, scale, colour, 1, cv2.LINE_AA)


def overlay_image(image: NDArray[Any], markers: Markers) -> NDArray[np.uint8]:
    """8-bit BGR picture of the image with the indexed markers (green crosses), the reference (yellow) and the
    rejected candidates (red circles).

    Every marker gets a cross; the index "i,j" is written (with a dark halo) beside every k-th marker along i and
    j, k chosen from the marker spacing so that the labels do not run together (:func:`label_step`), and beside
    the reference marker (0, 0).
    """
    import cv2

    img = np.asarray(image, dtype=np.float64)
    lo = markers.spots.background
    hi = float(np.percentile(markers.peak, 90)) if len(markers) else float(img.max())
    grey = np.clip((img - lo) / max(hi - lo, 1e-300), 0.0, 1.0) ** 0.5 * 255.0
    out = cv2.cvtColor(grey.astype(np.uint8), cv2.COLOR_GRAY2BGR)
    kept = {tuple(np.round(c, 6)) for c in markers.centroids}
    for c in markers.spots.centroids:
        if tuple(np.round(c, 6)) not in kept:
            cv2.circle(out, (int(c[0]), int(c[1])), 6, (0, 0, 255), 1, cv2.LINE_AA)
    scale = 0.4
    if len(markers):
        widest = max((f"{i},{j}" for i, j in markers.ij), key=len)
        (tw, _), _ = cv2.getTextSize(widest, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
        step = label_step(markers.centroids, tw)
    for (i, j), (col, row) in zip(markers.ij, markers.centroids, strict=True):
        ref = i == 0 and j == 0
        colour = (0, 255, 255) if ref else (0, 255, 0)
        p = (int(round(col - 0.5)), int(round(row - 0.5)))
        cv2.drawMarker(out, p, colour, cv2.MARKER_CROSS, 6, 1)
        if ref or (i % step == 0 and j % step == 0):
            _text(out, f"{i},{j}", (p[0] + 4, p[1] - 4), scale, colour)
    return np.asarray(out, dtype=np.uint8)


def write_overlay(path: str | Path, image: NDArray[Any], markers: Markers) -> None:
    """Write the overlay PNG atomically; a path that cannot be written is a :class:`MarkerError`."""
    import cv2

    dest = Path(path)
    if dest.suffix.lower() != ".png":
        raise MarkerError(f"overlay must be a .png file, got {dest}")
    ok, data = cv2.imencode(".png", overlay_image(image, markers))
    if not ok:  # pragma: no cover - OpenCV cannot fail on a valid 8-bit image
        raise MarkerError("could not encode the overlay PNG")
    try:
        with atomic_path(dest) as tmp:
            tmp.write_bytes(data.tobytes())
    except OSError as exc:
        raise MarkerError(f"cannot write overlay {dest}: {exc.strerror or exc}") from None


def write_spots(path: Path, setup: Any, stack: Any, image_distance: float, na: float) -> None:
    """Spot diagrams of a GRIN objective (thesis §8.3) at field 0, 0.7, 1 on the best-focus plane (PNG, atomic)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from scopetwin.scenes.grin.analysis import FIELDS, bundle
    from scopetwin.scenes.spots import rms_radius

    fig, axes = plt.subplots(1, len(FIELDS), figsize=(4 * len(FIELDS), 4))
    for ax, f in zip(axes, FIELDS, strict=True):
        b = bundle(stack, f * setup.object.field_radius, na)
        x, y = b.spot(image_distance)
        cx, cy = x.mean(), y.mean()
        ax.plot((x - cx) * 1e3, (y - cy) * 1e3, ".", ms=1.5)
        ax.set_aspect("equal")
        ax.set_title(
            f"field {f:.1f} ({f * setup.object.field_radius * 1e3:.0f} µm): RMS {rms_radius(x, y) * 1e3:.2f} µm"
        )
        ax.set_xlabel("x (µm)")
        ax.set_ylabel("y (µm)")
    fig.suptitle(f"{setup.section} spot diagrams, image plane {image_distance:.3f} mm")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)
