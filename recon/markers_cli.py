"""``scopetwin markers IMAGE.exr --pattern SETUP [--json PATH] [--overlay PNG]`` (issue 3, DESIGN.md contract).

Finds, filters and indexes the markers of a camera image (:func:`recon.markers.find_markers_for`) with
the pattern, camera and reflecting region of a setup (preset name or TOML path). The result is the
``markers`` JSON of DESIGN.md, ``{"markers": [{i, j, col, row, area}], "rejected": n}`` (continuous
pixel coordinates; (i, j) are positions on the pattern), with a ``saturated`` flag per marker and the
rejection reasons added. ``--overlay`` writes a PNG of the image with every marker's index drawn.

Bad input (missing or unreadable image, NaNs, unknown setup, an image whose size is not the
setup's camera, no reference marker, ...) raises a :class:`~scenes.errors.ScopetwinError`; the
command line turns it into exit code 2 and writes nothing.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from recon.markers import MarkerError, Markers, find_markers_for
from scenes.io import atomic_path, read_image
from scenes.setup import load_setup


def overlay_image(image: NDArray, markers: Markers) -> NDArray[np.uint8]:
    """8-bit BGR picture of the image with the indexed markers (green, index "i,j"), the reference (yellow)
    and the rejected candidates (red circles)."""
    img = np.asarray(image, dtype=np.float64)
    lo = markers.spots.background
    hi = float(np.percentile(markers.peak, 90)) if len(markers) else float(img.max())
    grey = np.clip((img - lo) / max(hi - lo, 1e-300), 0.0, 1.0) ** 0.5 * 255.0
    out = cv2.cvtColor(grey.astype(np.uint8), cv2.COLOR_GRAY2BGR)
    kept = {tuple(np.round(c, 6)) for c in markers.centroids}
    for c in markers.spots.centroids:
        if tuple(np.round(c, 6)) not in kept:
            cv2.circle(out, (int(c[0]), int(c[1])), 6, (0, 0, 255), 1, cv2.LINE_AA)
    scale = 0.3 if len(markers) > 200 else 0.45
    for (i, j), (col, row) in zip(markers.ij, markers.centroids, strict=True):
        ref = i == 0 and j == 0
        colour = (0, 255, 255) if ref else (0, 255, 0)
        p = (int(round(col - 0.5)), int(round(row - 0.5)))
        cv2.drawMarker(out, p, colour, cv2.MARKER_CROSS, 6, 1)
        cv2.putText(out, f"{i},{j}", (p[0] + 3, p[1] - 3), cv2.FONT_HERSHEY_SIMPLEX, scale, colour, 1, cv2.LINE_AA)
    return out


def write_overlay(path: str | Path, image: NDArray, markers: Markers) -> None:
    """Write the overlay PNG atomically; a path that cannot be written is a :class:`MarkerError`."""
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


def cmd_markers(args: argparse.Namespace) -> dict[str, Any]:
    """Handler of ``scopetwin markers``: returns the JSON-ready result (the caller writes ``--json``)."""
    setup = load_setup(args.pattern)
    image, _ = read_image(args.image)
    cam = setup.camera_model
    if image.shape != (cam.ny, cam.nx):
        raise MarkerError(
            f"image {args.image} is {image.shape[1]}x{image.shape[0]} px but setup {args.pattern} "
            f"has a {cam.nx}x{cam.ny} px camera"
        )
    markers = find_markers_for(image, setup)
    result = markers.as_json()
    if args.overlay:
        write_overlay(args.overlay, image, markers)
    print(
        f"{len(markers)} markers indexed, {markers.rejected} candidates rejected, "
        f"{int(markers.saturated.sum())} saturated ({args.image})"
    )
    return result


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``markers`` to a ``scopetwin`` subparsers object (sets ``func`` = :func:`cmd_markers`)."""
    help_ = "find and index the markers of a camera image (seed §1.5, §2.6)"
    p = subparsers.add_parser("markers", help=help_, description=help_)
    p.add_argument("image", help="camera image (OpenEXR, channel Y)")
    p.add_argument(
        "--pattern",
        required=True,
        metavar="SETUP",
        help="setup (preset name or TOML path) giving the pattern, camera and reflecting region",
    )
    p.add_argument("--json", metavar="PATH", help="write the indexed markers here (DESIGN.md `markers`)")
    p.add_argument("--overlay", metavar="PNG", help="write a picture of the image with the indices drawn")
    p.set_defaults(func=cmd_markers)
    return p
