"""``scopetwin calibrate`` and ``scopetwin calibrate-setup`` (docs/contract.md, "Command line"; thesis ch. 2).

:func:`register` adds both sub-commands to the ``scopetwin`` parser; each sets ``func`` to a
function that takes the parsed arguments and returns the JSON-ready result (the caller writes
``--json``). Bad input raises :class:`~scopetwin.scenes.errors.ScopetwinError` before anything is written.

Markers are found and indexed with :func:`scopetwin.recon.markers.find_markers_for` (thesis §1.5, §2.6;
whole-spot first-moment centroids). Their centroid bias (perspective makes a round marker's
image asymmetric) is corrected by alternating calibration and the spot model
:func:`scopetwin.recon.bias.spot_bias_model` until the parameters settle (``--no-bias-correction``
switches it off).
"""

from __future__ import annotations

import argparse
import time
from typing import TYPE_CHECKING, Any

import numpy as np

from scopetwin.cli.options import conventions, finite_float, finite_vector, positive_float
from scopetwin.scenes.errors import ScopetwinError

if TYPE_CHECKING:
    from numpy.typing import NDArray

    from scopetwin.calib.oneshot import Calibration, Prior
    from scopetwin.scenes.geometry import Frame
    from scopetwin.scenes.setup import Setup

#: ``--lens``'s choices: :data:`scopetwin.calib.oneshot.LENS_MODES`, spelt out so that the parser (``--help``) does
#: not import the calibration.
LENS_MODES: tuple[str, ...] = ("auto", "thin-lens", "free", "fixed")

#: How the calibration's note about the mirror-ambiguous pose (calib.oneshot.calibration) starts.
_AMBIGUOUS = "does not tell the two mirror-ambiguous poses"


def _warnings(cal: Calibration, view: str, nz_estimate: Any, what_to_do: str) -> list[str]:
    """The calibration's notes as the lines to print, the mirror-ambiguity note said in plain words.

    A planar target seen in perspective fits two camera poses nearly equally well (thesis §2.4.2: the sign s of the
    linear approximation); the a-priori sensor normal N_z picks one. When it lies midway, the calibration keeps
    the pose with the smaller residual, which is right whenever that residual is small.
    """
    lines = []
    for note in cal.warnings:
        if _AMBIGUOUS in note:
            est = ", ".join(f"{v:.3g}" for v in np.round(np.asarray(nz_estimate, dtype=np.float64), 6) + 0.0)
            note = (
                f"{view}: the a-priori sensor normal ({est}) lies midway between the two camera poses that fit a "
                "flat target about equally well (thesis §2.4.2), so the pose with the smaller residual "
                f"({cal.residual_rms_px:.3g} px rms) was kept. No action is needed when that residual is small "
                f"(well below 1 px); otherwise {what_to_do}"
            )
        else:
            note = f"{view}: {note}"
        lines.append(f"warning: {note}")
    return lines


def _load_image(path: str) -> tuple[NDArray, Setup | None]:
    from scopetwin.scenes.io import read_image
    from scopetwin.scenes.setup import setup_from_json

    image, attrs = read_image(path)
    header = attrs.get("scopetwin_setup")
    setup = None
    if isinstance(header, bytes):
        header = header.decode()
    if isinstance(header, str) and header:
        setup = setup_from_json(header)
    return image, setup


def _setup(arg: str | None, header: Setup | None, image: str, what: str) -> Setup:
    from scopetwin.scenes.setup import load_setup

    if arg is not None:
        return load_setup(arg)
    if header is None:
        raise ScopetwinError(f"{image} carries no setup in its header: give {what}")
    return header


def _own_camera(setup: Setup, header: Setup | None) -> bool:
    """Whether the image's header carries the camera of ``setup`` (the image was rendered with it)."""
    if header is None:
        return False
    a, b = setup.camera_model, header.camera_model
    same_pose = np.allclose(a.frame.origin, b.frame.origin, atol=1e-9) and np.allclose(
        a.frame.rotation, b.frame.rotation, atol=1e-12
    )
    return bool(same_pose and abs(a.b - b.b) <= 1e-9 * a.b)


def _prior(setup: Setup, plane: Frame, args: argparse.Namespace, header: Setup | None = None) -> Prior:
    """The a-priori values of ``setup``'s camera with the command line's changes.

    Its image distance is an a-priori b only for the image's own camera (the header's) or given by
    ``--image-distance``: for another image (``--target`` naming a setup the image was not rendered with) a setup's
    b belongs to its own distance, and ``--lens auto`` takes the thin-lens b of the measured magnification
    instead (thesis §2.4.2); ``--lens fixed`` still holds the setup's b.
    """
    from scopetwin.calib.oneshot import Prior

    cam = setup.camera_model
    f = args.focal_length if args.focal_length is not None else setup.camera.focal_length
    changes: dict[str, Any] = {}
    if args.pixel_pitch is not None:
        changes["pitch"] = args.pixel_pitch
    if getattr(args, "nz_estimate", None) is not None:
        changes["nz_estimate"] = tuple(args.nz_estimate)
    if getattr(args, "image_distance", None) is not None:
        changes["image_distance"] = args.image_distance
    elif args.lens == "auto" and not _own_camera(setup, header):
        changes["image_distance"] = None
    if getattr(args, "focal_length_tolerance", None) is not None:
        changes["focal_length_tolerance"] = args.focal_length_tolerance
    return Prior.from_camera(cam, f, plane=plane, **changes)


def cmd_calibrate(args: argparse.Namespace) -> dict[str, Any]:
    """One-shot calibration from one image of the target of ``--target`` (thesis §2.4-2.5)."""
    from scopetwin.calib.oneshot import CalibrationError
    from scopetwin.calib.oneshot.from_image import calibrate_image

    t0 = time.perf_counter()
    image, header = _load_image(args.image)
    setup = _setup(args.target, header, args.image, "--target SETUP")
    if setup.scene != "target":
        raise CalibrationError(f"setup {setup.name} is a {setup.scene} scene, not a calibration target")
    plane = setup.marker_pattern.frame
    prior = _prior(setup, plane, args, header)
    cal, found = calibrate_image(  # the one path from an image to a calibration (also scopetwin.calibrate)
        image,
        setup,
        prior=prior,
        lens=args.lens,
        distortion=args.distortion,
        image_distance=args.image_distance,
        bias_correction=not args.no_bias_correction,
        name=args.image,
    )
    bias = not args.no_bias_correction
    out = cal.as_dict(plane=plane)
    out.update(
        {
            "image": str(args.image),
            "target": setup.name,
            "markers_used": int(len(found.ij)),
            "markers_rejected": int(found.rejected),
            "bias_corrected": bias,
            "seconds": time.perf_counter() - t0,
        }
    )
    c = out["camera"]
    print(
        f"calibrated {args.image}: r_c = ({c['r_c'][0]:.4f}, {c['r_c'][1]:.4f}, {c['r_c'][2]:.4f}) mm, "
        f"b = {c['b']:.4f} mm ({cal.lens}), residual {cal.residual_rms_px:.4f} px rms, {len(found.ij)} markers"
    )
    hint = "give --nz-estimate X,Y,Z close to the true sensor normal (target coordinates) to choose the pose."
    for line in _warnings(cal, args.image, prior.nz_estimate, hint):
        print(line)
    return out


def cmd_calibrate_setup(args: argparse.Namespace) -> dict[str, Any]:
    """Calibration of the deflectometry setup from the substrate and mirror images (thesis §2.7)."""
    from scopetwin.calib.setup_calibration import CALIBRATE_SETUP_COMMENT, calibrate_setup_from_images
    from scopetwin.scenes.io import write_text_atomic

    t0 = time.perf_counter()
    img_s, head_s = _load_image(args.substrate_image)
    img_m, head_m = _load_image(args.mirror_image)
    target = _setup(args.target, head_s, args.substrate_image, "--target SETUP")
    nominal = _setup(args.pattern_setup, head_m, args.mirror_image, "--pattern-setup SETUP")
    cal = calibrate_setup_from_images(
        img_s,
        img_m,
        target,
        nominal,
        focal_length=args.focal_length,
        pixel_pitch=args.pixel_pitch,
        lens=args.lens,
        distortion=args.distortion,
        share_intrinsics=not args.per_view_lens,
        bias_correction=not args.no_bias_correction,
        comment=CALIBRATE_SETUP_COMMENT,
        image_names=(args.substrate_image, args.mirror_image),
    )
    write_text_atomic(args.out, cal.toml)
    result = cal.calibration
    out = result.as_dict()
    out.update(
        {
            "setup_toml": str(args.out),
            "toml": cal.toml,
            "markers_used": {"substrate": int(len(cal.target.markers.ij)), "mirror": int(len(cal.mirror.markers.ij))},
            "seconds": time.perf_counter() - t0,
        }
    )
    o = result.pattern.origin
    print(
        f"calibrated setup -> {args.out}: camera r_c = {np.round(result.camera.center, 4).tolist()} mm, "
        f"pattern centre = ({o[0]:.4f}, {o[1]:.4f}, {o[2]:.4f}) mm"
    )
    hint = "give the setup's camera (in --target / --pattern-setup) a pose closer to the real one."
    for line in _warnings(result.substrate, "substrate view", cal.target.prior.nz_estimate, hint) + _warnings(
        result.mirror, "mirror view", cal.mirror.prior.nz_estimate, hint
    ):
        print(line)
    return out


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", metavar="PATH", help="write machine-readable results here")
    p.add_argument(
        "--focal-length", type=positive_float(), metavar="F", help="a-priori focal length, mm (default: the setup's)"
    )
    p.add_argument("--pixel-pitch", type=positive_float(), metavar="P", help="pixel size, mm (default: the setup's)")
    p.add_argument(
        "--lens",
        choices=LENS_MODES,
        default="auto",
        help="image distance b: thin-lens from f (seed), free parameter, fixed, or auto (default)",
    )
    p.add_argument("--distortion", action="store_true", help="also refine r_cs, c0, c2 (thesis §2.5.1)")
    p.add_argument(
        "--no-bias-correction",
        action="store_true",
        help="use the raw centroids (default: alternate calibration and centroid-bias correction)",
    )


def _quiet(func: Any) -> Any:
    """Run a command with CalibrationWarnings silenced: the command prints them itself."""
    import functools
    import warnings

    @functools.wraps(func)
    def run(args: argparse.Namespace) -> dict[str, Any]:
        from scopetwin.calib.oneshot import CalibrationWarning

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", CalibrationWarning)
            return func(args)

    return run


def register(subparsers: Any) -> None:
    """Add ``calibrate`` and ``calibrate-setup`` to the ``scopetwin`` sub-command parsers."""
    h = "one-shot camera calibration from one image of a marker target (thesis ch. 2)"
    p = subparsers.add_parser(
        "calibrate",
        help=h,
        description=h,
        **conventions(
            "scopetwin render thesis-2.8.1-angular --out t1 --spp 64",
            "scopetwin calibrate t1/image.exr --target thesis-2.8.1-angular --json calibration.json",
        ),
    )
    p.set_defaults(func=_quiet(cmd_calibrate))
    p.add_argument("image", help="camera image (OpenEXR, channel Y)")
    p.add_argument(
        "--target",
        metavar="SETUP",
        help="setup (preset or TOML) with the target and the a-priori camera (default: the setup in the image header)",
    )
    p.add_argument(
        "--nz-estimate",
        type=finite_vector(3),
        metavar="X,Y,Z",
        help="coarse sensor normal in target coordinates (default: the setup camera's)",
    )
    p.add_argument(
        "--image-distance",
        type=positive_float(),
        metavar="B",
        help="a-priori b, mm: held by --lens fixed, the candidate of --lens auto (default: the image's own camera's)",
    )
    p.add_argument(
        "--focal-length-tolerance",
        type=finite_float(0.0, 0.5),
        metavar="T",
        help="relative standard uncertainty of the focal length (default 0.01): the thin-lens b's uncertainty",
    )
    _common(p)

    h = "calibrate the deflectometry setup from a substrate-target image and a mirror image (thesis §2.7)"
    p = subparsers.add_parser(
        "calibrate-setup",
        help=h,
        description=h,
        **conventions(
            "scopetwin render thesis-2.8.3-substrate --out s --spp 64; scopetwin render thesis-2.8.3-mirror --out m "
            "--spp 64",
            "scopetwin calibrate-setup --substrate-image s/image.exr --mirror-image m/image.exr --out calibrated.toml",
        ),
    )
    p.set_defaults(func=_quiet(cmd_calibrate_setup), outputs=[("out", "file"), ("json", "file")])
    p.add_argument("--substrate-image", required=True, metavar="A.exr", help="target on the holding frame")
    p.add_argument("--mirror-image", required=True, metavar="B.exr", help="pattern seen in a flat mirror on the frame")
    p.add_argument("--target", metavar="SETUP", help="setup of the substrate image (default: its header)")
    p.add_argument(
        "--pattern-setup",
        metavar="SETUP",
        help="setup with the pattern and a-priori camera of the mirror image (default: its header)",
    )
    p.add_argument(
        "--per-view-lens",
        action="store_true",
        help="the thesis's way: each view its own thin-lens b (default: the mirror view keeps the "
        "substrate view's b and distortion)",
    )
    p.add_argument("--out", required=True, metavar="setup.toml", help="calibrated setup TOML to write")
    _common(p)
