"""``scopetwin markers IMAGE.exr --pattern SETUP [--json PATH] [--overlay PNG]`` (docs/contract.md).

Finds, filters and indexes the markers of a camera image (:func:`scopetwin.recon.markers.find_markers_for`) with
the pattern, camera and reflecting region of a setup (preset name or TOML path). The result is the
``markers`` JSON of docs/contract.md, ``{"markers": [{i, j, col, row, area}], "rejected": n}`` (continuous
pixel coordinates; (i, j) are positions on the pattern), with a ``saturated`` flag per marker and the
rejection reasons added. ``--overlay`` writes a PNG of the image with every marker's index drawn
(:func:`scopetwin.sim.figures.write_overlay`).

Bad input (missing or unreadable image, NaNs, unknown setup, an image whose size is not the
setup's camera, no reference marker, ...) raises a :class:`~scopetwin.scenes.errors.ScopetwinError`; the
command line turns it into exit code 2 and writes nothing.
"""

from __future__ import annotations

import argparse
from typing import Any

from scopetwin.cli.options import conventions


def cmd_markers(args: argparse.Namespace) -> dict[str, Any]:
    """Handler of ``scopetwin markers``: returns the JSON-ready result (the caller writes ``--json``)."""
    from scopetwin.recon.markers import MarkerError, find_markers_for
    from scopetwin.scenes.io import read_image
    from scopetwin.scenes.setup import load_setup
    from scopetwin.sim.figures import write_overlay

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
        f"{int(markers.saturated.sum())} saturated"
        + (" — numbered by the grid's topology (the flood stopped early)" if markers.indexing == "lattice" else "")
        + f" ({args.image})"
    )
    return result


def register(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Add ``markers`` to a ``scopetwin`` subparsers object (sets ``func`` = :func:`cmd_markers`)."""
    help_ = "find and index the markers of a camera image (thesis §1.5, §2.6)"
    p = subparsers.add_parser(
        "markers",
        help=help_,
        description=help_,
        **conventions(
            "scopetwin render thesis-1.10-deflectometry --out r1 --spp 16",
            "scopetwin markers r1/image.exr --pattern thesis-1.10-deflectometry --overlay r1/markers.png",
        ),
    )
    p.add_argument("image", help="camera image (OpenEXR, channel Y)")
    p.add_argument(
        "--pattern",
        required=True,
        metavar="SETUP",
        help="setup (preset name or TOML path) giving the pattern, camera and reflecting region",
    )
    p.add_argument(
        "--json", metavar="PATH", help="write the indexed markers here (the markers JSON of docs/contract.md)"
    )
    p.add_argument("--overlay", metavar="PNG", help="write a picture of the image with the indices drawn")
    p.set_defaults(func=cmd_markers, outputs=[("json", "file"), ("overlay", "file")])
    return p
