"""``scopetwin reconstruct IMAGE.exr --setup SETUP --out heights.exr [--json PATH]`` (docs/contract.md, thesis §1.4);
``scopetwin reconstruct fringes.json --out heights.exr`` for a fringe measurement.

Detects and indexes the markers of a deflectometry image (:mod:`scopetwin.recon.markers`), runs the
nested start-height iteration (:mod:`scopetwin.recon.reconstruct`) and writes the substrate's height map
in the contract's format (channel ``Z`` in mm over the whole substrate, channel ``Z_std``: its per-node standard
uncertainty), and reports the standard uncertainties of the absolute height and of the shape. Bad input raises a
:class:`~scopetwin.scenes.errors.ScopetwinError` (exit code 2) and writes no height map; when the outer loop
does not converge, its partial history is written to ``OUT.history.json`` for diagnosis.

A fringe measurement (the ``fringes.json`` that ``scopetwin render`` writes for a ``[fringes]`` setup, read with every
check of :func:`scopetwin.sim.fringes.read_fringes`) is reconstructed by the fringe method
(:func:`scopetwin.recon.strategy.reconstruct_fringe_images`): the setup is the JSON's own unless ``--setup`` names a
(calibrated) one, whose ``[fringes]`` sequence must list the same frames; ``--second shifted_fringes.json`` is the
sequence at the second display position (the shift: ``--pattern-shift``, else the setup's ``[pattern_stage]``, else
the move along the display's normal between the two JSONs' setups).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from scopetwin.cli.options import conventions, finite_float
from scopetwin.scenes.errors import ScopetwinError

if TYPE_CHECKING:  # loaded when a reconstruction runs, not when the parser is built
    from scopetwin.recon.config import ReconstructionConfig
    from scopetwin.recon.policy import ReconstructionPolicy


def _config(args: argparse.Namespace) -> ReconstructionConfig:
    from scopetwin.recon.config import ReconstructionConfig

    if args.thesis:
        return ReconstructionConfig.thesis(search="secant")
    changes: dict[str, Any] = {}
    if args.sigma is not None:
        changes["sigma"] = (args.sigma, args.sigma)
        changes["sigma_candidates"] = None
    if args.criterion is not None:
        changes["criterion"] = args.criterion
    if args.posterior is not None:
        changes["posterior"] = args.posterior
    if args.local_features:
        changes["local_features"] = True
    if args.prior is not None:
        changes["prior"] = args.prior
    return ReconstructionConfig(**changes)


def _policy(args: argparse.Namespace) -> ReconstructionPolicy:
    """The strategy's policy: the default, without the bias step under ``--no-bias-correction``, without the scale
    choice on the data under ``--hold``."""
    from scopetwin.recon.policy import DEFAULT_POLICY

    policy = DEFAULT_POLICY.with_changes(bias_step=not args.no_bias_correction)
    return policy.with_changes(rechoose_scale=False) if args.hold else policy


def cmd_reconstruct(args: argparse.Namespace) -> dict[str, Any]:
    """Handler of ``scopetwin reconstruct``."""
    from scopetwin.recon.strategy import reconstruct
    from scopetwin.scenes.io import read_image, write_heightmap
    from scopetwin.scenes.setup import load_setup

    t0 = time.perf_counter()
    out = Path(args.out)
    if out.suffix.lower() != ".exr":
        raise ScopetwinError(f"--out must name an .exr height-map file, got {out}")
    if _is_fringe_input(args.image):
        return _cmd_fringes(args, out, t0)
    if args.setup is None:
        raise ScopetwinError("--setup is required with a camera image (a fringes.json carries its own setup)")
    if args.method == "fringes":
        raise ScopetwinError(f"--method fringes takes a fringe measurement's fringes.json, not the image {args.image}")
    start, scale, held = _previous(args)
    setup = load_setup(args.setup)
    if setup.scene != "deflectometry":
        raise ScopetwinError(f"setup {args.setup} is a {setup.scene!r} scene; reconstruct needs a deflectometry setup")
    cam = setup.camera_model
    image, _ = read_image(args.image, (cam.ny, cam.nx))  # the header's size checked before decoding
    if image.shape != (cam.ny, cam.nx):
        raise ScopetwinError(
            f"{args.image} is {image.shape[1]} x {image.shape[0]} px but the setup's camera has {cam.nx} x {cam.ny}"
        )
    if args.second is not None:
        return _cmd_two_positions(args, setup, image, out, t0)
    if args.method == "inverse":
        return _cmd_inverse(args, setup, image, out, t0)
    history_path = out.with_name(out.name + ".history.json")
    # every fallback is the strategy's (recon.strategy); NotConvergedError: history saved, no map written
    done = reconstruct(
        image,
        setup,
        "centroid",
        config=_config(args).starting_at(scale),
        policy=_policy(args),
        history_path=history_path,
        evidence_start=start,
        held_prior=held,
    )
    found, result = done.markers, done.result
    heights = result.heightmap()
    write_heightmap(
        out,
        heights,
        result.std_heightmap(),
        result.measured_mask(),  # ROI nodes beyond two marker spacings of every marker: NaN, Z_measured 0
        scopetwin_reconstruction=f"outer={result.outer_iterations} "
        f"inner={result.inner_iterations} delta_h_max_um={result.delta_h_max_um:.4g}",
    )
    seconds = time.perf_counter() - t0
    u = result.uncertainty
    u_text = f", u(absolute) = {u.absolute_um:.3f} µm, u(shape) = {u.shape_um:.3f} µm" if u is not None else ""
    coverage = result.roi_coverage()
    cover_text = f", ROI measured {100.0 * coverage:.0f} %" if coverage is not None and coverage < 1.0 else ""
    print(
        f"reconstructed {len(found.ij)} markers: {result.outer_iterations} start heights, "
        f"{result.inner_iterations} inner iterations, Delta h_max = {result.delta_h_max_um:+.4f} µm{u_text}"
        f"{cover_text}, {seconds:.2f} s -> {out}"
    )
    extra: dict[str, Any] = {"uncertainty": u.summary()} if u is not None else {}
    return {
        "heights": str(out),
        "outer_iterations": result.outer_iterations,
        "inner_iterations": result.inner_iterations,
        "delta_h_max_um": result.delta_h_max_um,
        "seconds": seconds,
        "markers": len(found.ij),
        "roi_coverage": coverage,
        "strategy": list(result.strategy),
        "start_height_um": result.history[-1].start_height_um,
        **extra,
        "history": result.history_dicts(),
    }


def _previous(args: argparse.Namespace) -> tuple[Any, float | None, Any]:
    """``--previous``: the prior and the final basis scale (mm; None where the JSON has no history) an earlier
    reconstruction's JSON recorded, and under ``--hold`` the prior to hold (with its ``prior_z``), checked before any
    work; (None, None, None) without the option (the command line's ``scopetwin.reconstruct(previous=, hold=)``)."""
    if args.previous is None:
        if args.hold:
            raise ScopetwinError("--hold holds the scale and prior of --previous's frame; give --previous JSON")
        return None, None, None
    if args.second is not None or args.method == "inverse":
        raise ScopetwinError("--previous takes one image and the centroid method (no --second, no --method inverse)")
    if args.posterior == "off":
        raise ScopetwinError("--previous starts the posterior's evidence search, which --posterior off skips")
    from scopetwin.recon.posterior import recorded_prior
    from scopetwin.recon.uncertainty import HeldPrior
    from scopetwin.scenes.inputs import load_json_input

    record = load_json_input(args.previous, "reconstruction JSON", PRIOR_JSON_LIMIT)
    prior = recorded_prior(record, args.previous)
    held = HeldPrior(prior, _recorded_z(record, args.previous)) if args.hold else None
    history = record.get("history")
    last = history[-1] if isinstance(history, list) and history and isinstance(history[-1], dict) else {}
    scale = last.get("sigma_mm")
    if scale is None:
        return prior, None, held
    if isinstance(scale, bool) or not isinstance(scale, int | float) or not 0.0 < scale <= MAX_SCALE_MM:
        raise ScopetwinError(f"{args.previous}: history[-1].sigma_mm must be a basis scale in (0, {MAX_SCALE_MM}] mm")
    return prior, float(scale), held


def _recorded_z(record: dict[str, Any], where: str) -> float:
    """``uncertainty.prior_z`` of a reconstruction's JSON: the prior's plausibility on that frame, which ``--hold``
    compares the next frame's with."""
    z = (record.get("uncertainty") or {}).get("prior_z")
    if isinstance(z, bool) or not isinstance(z, int | float) or not abs(z) < 1e12:
        raise ScopetwinError(f"{where}: --hold needs uncertainty.prior_z, a finite number (got {z!r})")
    return float(z)


#: Largest basis scale ``--previous`` takes from a JSON, mm (the scale choice's candidates reach 24 mm).
MAX_SCALE_MM = 1000.0
#: Largest ``--previous`` file read, bytes: a reconstruction's JSON with its history is ~10-50 kB.
PRIOR_JSON_LIMIT = 4 << 20


def _is_fringe_input(path: str) -> bool:
    """A fringe measurement: a JSON file (``fringes.json``, ``shifted_fringes.json``) or a folder holding one."""
    p = Path(path)
    return p.suffix.lower() == ".json" or p.is_dir()


#: Options of the marker methods that a fringe measurement does not take (argparse dest -> option).
_MARKER_ONLY = {
    "sigma": "--sigma",
    "thesis": "--thesis",
    "no_bias_correction": "--no-bias-correction",
    "refine_setup": "--refine-setup",
    "posterior": "--posterior",
    "local_features": "--local-features",
    "prior": "--prior",
    "previous": "--previous",
    "hold": "--hold",
}


def _cmd_fringes(args: argparse.Namespace, out: Path, t0: float) -> dict[str, Any]:
    """A fringe measurement (module docstring): the checks before any work, the strategy's fringe method, the height
    map (+ ``Z_std``, + measured mask) and the contract's keys where they apply."""
    from scopetwin.recon.fringes.reconstruct import FringeConfig
    from scopetwin.recon.strategy import reconstruct
    from scopetwin.scenes.io import write_heightmap
    from scopetwin.scenes.setup import load_setup
    from scopetwin.sim.fringes import read_fringes

    if args.method not in (None, "fringes"):
        raise ScopetwinError(
            f"{args.image} is a fringe measurement: it takes the fringe method, not --method {args.method}"
        )
    given = [opt for dest, opt in _MARKER_ONLY.items() if getattr(args, dest, None) not in (None, False)]
    if given:
        raise ScopetwinError(f"{', '.join(given)}: marker-method options; {args.image} is a fringe measurement")
    measurement = read_fringes(args.image)  # names, sizes and memory checked before any image is decoded
    setup = measurement.setup if args.setup is None else load_setup(args.setup)
    _check_frames(setup, measurement.frames, args.image)
    second, shift = None, None
    if args.second is not None:
        if not _is_fringe_input(args.second):
            raise ScopetwinError(f"--second {args.second}: a fringe measurement's second position is its JSON")
        other = read_fringes(args.second)
        _check_frames(setup, other.frames, args.second)
        shift = _fringe_shift(setup, measurement.setup, other.setup, args)
        second = (other.images, shift)
    elif args.pattern_shift is not None:
        raise ScopetwinError("--pattern-shift applies with --second")
    config = FringeConfig(criterion=args.criterion or "level")
    done = reconstruct(measurement.images, setup, "fringes", second=second, fringe_config=config)
    result = done.result
    write_heightmap(
        out,
        result.heightmap(),
        result.std_heightmap(),
        result.measured_mask(),  # ROI nodes farther than 0.5 mm from every decoded pixel's point: NaN, Z_measured 0
        scopetwin_reconstruction=f"method=fringes absolute={result.method} outer={len(result.history)} "
        f"start_height_um={result.start_height_mm * 1e3:.4g}",
    )
    seconds = time.perf_counter() - t0
    u = done.uncertainty
    coverage = result.roi_coverage()
    summary = done.summary()
    where = "frame criterion" if result.method == "frame-criterion" else f"two display positions ({shift:+g} mm)"
    print(
        f"reconstructed {summary['observations']} pixel slopes of {len(measurement.frames)} fringe frames ({where}): "
        f"{summary['outer_iterations']} start heights, {summary['inner_iterations']} inner iterations, "
        f"u(absolute) = {u.absolute_um:.3f} µm, u(shape) = {u.shape_um:.3f} µm, ROI measured {100.0 * coverage:.0f} %, "
        f"{seconds:.2f} s -> {out}"
    )
    best = min(result.history, key=lambda s: abs(s.criterion_um)) if result.history else None
    delta = None if best is None or result.method != "frame-criterion" else best.max_1_um - best.max_2_um
    return {
        "heights": str(out),
        "method": "fringes",
        "absolute_from": result.method,
        "outer_iterations": summary["outer_iterations"],
        "inner_iterations": summary["inner_iterations"],
        "delta_h_max_um": delta,
        "seconds": seconds,
        "observations": summary["observations"],
        "roi_coverage": coverage,
        "strategy": list(done.strategy),
        "start_height_um": summary["start_height_um"],
        "converged": summary["converged"],
        "uncertainty": {"absolute_um": u.absolute_um, "shape_um": u.shape_um},
        **({} if shift is None else {"pattern_shift_mm": shift}),
        "history": summary["history"],
    }


def _check_frames(setup: Any, frames: Any, name: str) -> None:
    """The measurement's frames are the setup's sequence (the frames' meaning comes from the setup)."""
    from scopetwin.recon.fringes.frames import fringe_parts

    _, sequence = fringe_parts(setup)  # a marker setup: one clear error
    if tuple(frames) != sequence.frames():
        raise ScopetwinError(
            f"{name}: its {len(frames)} frames are not the {len(sequence)} frames of setup {setup.name}'s sequence "
            f"(periods {list(sequence.periods_mm)} mm, {sequence.steps} steps)"
        )


def _fringe_shift(setup: Any, first: Any, second: Any, args: argparse.Namespace) -> float:
    """The second display position's shift along the display's normal, mm: ``--pattern-shift``, else the setup's
    ``[pattern_stage]``, else the move between the two measurements' own setups (which must be along N_z only)."""
    import numpy as np

    from scopetwin.scenes.pattern_stage import stage_shift

    if args.pattern_shift is not None or setup.pattern_stage is not None:
        return stage_shift(setup, args.pattern_shift)
    a, b = first.pattern, second.pattern
    move = np.asarray(b.origin, dtype=float) - np.asarray(a.origin, dtype=float)
    shift = float(move @ np.asarray(a.n_z, dtype=float))
    same_axes = all(np.allclose(getattr(a, k), getattr(b, k), atol=1e-9) for k in ("t_x", "t_y", "n_z"))
    if not same_axes or not np.allclose(move, shift * np.asarray(a.n_z, dtype=float), atol=1e-6):
        raise ScopetwinError(
            f"--second {args.second}: its display is not the first's moved along the display's normal; give "
            "--pattern-shift"
        )
    return stage_shift(setup, shift)


def _cmd_two_positions(args: argparse.Namespace, setup: Any, image: Any, out: Path, t0: float) -> dict[str, Any]:
    """``--second IMAGE2 [--pattern-shift MM]`` (:mod:`scopetwin.recon.two_positions`): the absolute height from a
    second image with the pattern moved along its normal, combined with the frame criterion's. A second image that
    does not belong to the first is a :class:`~scopetwin.recon.errors.MismatchedPairError` (one line, exit 2, no
    height map)."""
    from scopetwin.recon.strategy import reconstruct
    from scopetwin.scenes.io import read_image, write_heightmap
    from scopetwin.scenes.pattern_stage import stage_shift

    if args.method not in (None, "centroid"):
        raise ScopetwinError("--second takes the centroid method (the inverse fit uses one image)")
    shift = stage_shift(setup, args.pattern_shift)
    second, _ = read_image(args.second, image.shape)  # the header's size checked before decoding
    if second.shape != image.shape:
        raise ScopetwinError(
            f"{args.second} is {second.shape[1]} x {second.shape[0]} px but {args.image} is "
            f"{image.shape[1]} x {image.shape[0]}"
        )
    done = reconstruct(image, setup, "centroid", config=_config(args), policy=_policy(args), second=(second, shift))
    result, est = done.result, done.result.estimate
    write_heightmap(
        out,
        result.heightmap(),
        result.std_heightmap(),
        result.measured_mask(),
        scopetwin_reconstruction=f"two pattern positions shift_mm={shift:g} height_um={est.height_um:.4g}",
    )
    seconds = time.perf_counter() - t0
    print(
        f"reconstructed from two pattern positions ({shift:+g} mm): {est.markers[0]} + {est.markers[1]} markers, "
        f"absolute height {est.height_um:+.3f} µm, u(absolute) = {est.std_um:.3f} µm (frame criterion "
        f"{'failed' if est.frame_um is None else f'{est.frame_um:+.3f} µm'}, two positions {est.pair_um:+.3f} ± "
        f"{est.pair_std_um:.3f} µm), {seconds:.2f} s -> {out}"
    )
    summary = result.summary()
    return {
        "heights": str(out),
        "outer_iterations": summary.pop("outer_iterations"),
        "inner_iterations": summary.pop("inner_iterations"),
        "delta_h_max_um": summary.pop("delta_h_max_um"),
        "seconds": seconds,
        "markers": len(done.markers.ij),
        "uncertainty": {"absolute_um": done.uncertainty.absolute_um, "shape_um": done.uncertainty.shape_um},
        **{k: v for k, v in summary.items() if k not in ("seconds", "uncertainty")},
    }


def _cmd_inverse(args: argparse.Namespace, setup: Any, image: Any, out: Path, t0: float) -> dict[str, Any]:
    """``--method inverse`` (:mod:`scopetwin.recon.inverse`): start from the centroid method's surface where it
    succeeds."""
    from scopetwin.recon.inverse import InverseConfig, pose_sigma_for
    from scopetwin.recon.strategy import reconstruct
    from scopetwin.scenes.io import write_heightmap

    # the inverse fit from the best start the strategy can give (recon.strategy.inverse_start): the centroid
    # method's surface where it reconstructs, else without its bias step, an unconverged start-height loop's last
    # surface, a coarse fit of the markers, a plane — holding the start's height unless it is a plane
    cfg = InverseConfig(
        refine_setup=bool(args.refine_setup),
        pose_sigma=pose_sigma_for(setup),  # the calibration's uncertainties where the setup carries them
        criterion=args.criterion or "level",
    )
    done = reconstruct(image, setup, "inverse", config=_config(args), inverse_config=cfg, policy=_policy(args))
    result, start_note = done.result, done.start or ""
    u_abs = done.uncertainty.absolute_um
    write_heightmap(
        out,
        result.heightmap(),
        scopetwin_reconstruction=f"method=inverse outer={result.outer_iterations} steps={len(result.history)} "
        f"delta_h_max_um={result.delta_h_max_um:.4g}",
    )
    seconds = time.perf_counter() - t0
    print(
        f"inverse rendering from the {start_note.split(' ')[0]} start: {result.outer_iterations} start heights, "
        f"{len(result.history)} Gauss-Newton steps, Delta h_max = {result.delta_h_max_um:+.4f} µm, "
        f"{seconds:.1f} s -> {out}"
    )
    summary = result.summary()
    return {
        "heights": str(out),
        "outer_iterations": summary.pop("outer_iterations"),
        "inner_iterations": summary.pop("inner_iterations"),
        "delta_h_max_um": summary.pop("delta_h_max_um"),
        "seconds": seconds,
        "start": start_note,
        "uncertainty": {"absolute_um": u_abs, "shape_um": result.shape_std_um},
        "strategy": list(done.strategy),
        **(
            {
                "camera": result.camera.as_dict(),
                "pattern": result.pattern.frame.as_dict(),
                "pose_prior_std": dict(zip(_POSE_PRIOR_KEYS, cfg.pose_sigma, strict=True)),
            }
            if args.refine_setup
            else {}
        ),
        **summary,
    }


#: Names of InverseConfig.pose_sigma's entries in the JSON of ``--refine-setup``.
_POSE_PRIOR_KEYS = ("camera_shift_mm", "camera_rotation_rad", "pattern_shift_mm", "pattern_rotation_rad")


def register(subparsers: Any) -> None:
    """Add ``reconstruct`` to the ``scopetwin`` sub-command parsers."""
    h = "deflectometric height reconstruction from one image and a (calibrated) setup (thesis §1.4)"
    p = subparsers.add_parser(
        "reconstruct",
        help=h,
        description=h,
        **conventions(
            "scopetwin reconstruct r1/image.exr --setup thesis-1.10-deflectometry --out r1/heights.exr --json r1.json",
            "scopetwin reconstruct f1/fringes.json --out f1/heights.exr --json f1.json",
            note="The images first: 'scopetwin render thesis-1.10-deflectometry --out r1 --spp 16' (markers), "
            "'scopetwin render thesis-1.10-fringes --out f1 --spp 16 --noise' (a fringe sequence, fringes.json).",
        ),
    )
    p.set_defaults(func=cmd_reconstruct, outputs=[("out", "file"), ("json", "file")])
    p.add_argument(
        "image",
        help="camera image of the reflected pattern (OpenEXR, channel Y), or a fringe measurement's fringes.json "
        "(scopetwin render of a [fringes] setup writes it)",
    )
    p.add_argument(
        "--setup",
        help="preset name or TOML (e.g. the one calibrate-setup wrote); required with an image, for a fringes.json "
        "its own setup by default",
    )
    p.add_argument("--out", required=True, help="height-map EXR to write (channel Z, mm)")
    p.add_argument("--json", metavar="PATH", help="write machine-readable results here")
    p.add_argument("--sigma", type=float, help="fixed basis scale, mm (default: chosen from the data)")
    p.add_argument("--criterion", choices=("level", "delta"), help="frame-region criterion (default level)")
    p.add_argument("--thesis", action="store_true", help="the thesis's 9x5 inverse-multiquadric basis and Delta h_max")
    p.add_argument("--no-bias-correction", action="store_true", help="use the raw centroids")
    p.add_argument(
        "--method",
        choices=("centroid", "inverse", "fringes"),
        help="marker centroids (thesis §1.4-1.8, the default for an image) or inverse rendering: the surface fitted to "
        "the whole image through a differentiable render, started from the centroid result; fringes (the default "
        "and only method for a fringes.json)",
    )
    p.add_argument(
        "--refine-setup",
        action="store_true",
        help="inverse: also fit camera and pattern pose, within 3 sigma of the setup's calibration (one image of an "
        "unknown surface hardly determines them: measured, the poses run to those bounds; benchmarks/refine_setup.py)",
    )
    p.add_argument(
        "--second",
        metavar="IMAGE2",
        help="a second image with the pattern moved along its normal by a stage (render --pattern-shift writes it as "
        "shifted_image.exr): the absolute height from both images, combined with the frame criterion's (thesis "
        "§1.3); a second image that does not belong to the first (another substrate, another shift) is refused. "
        "For a fringes.json: the second display position's JSON (shifted_fringes.json)",
    )
    p.add_argument(
        "--pattern-shift",
        type=finite_float(-500.0, 500.0),
        metavar="MM",
        help="with --second: the pattern's shift along its normal between the images, mm (default: the setup's "
        "[pattern_stage] shift_mm)",
    )
    p.add_argument(
        "--posterior",
        choices=("correct", "report", "off"),
        help="uncertainty from the Bayesian reading of the fit; 'correct' (default) also takes the start "
        "height from the posterior frame maxima, 'report' only reports, 'off' skips both",
    )
    p.add_argument(
        "--prior",
        choices=("auto", "process"),
        help="the posterior's prior: 'auto' (default) the basis fit itself as a Bayesian linear model where the "
        "evidence peaks at one of its scales (smooth surfaces), else the Gaussian process; 'process' always the latter",
    )
    _add_rig_options(p)
    p.add_argument(
        "--local-features",
        action="store_true",
        help="let the posterior follow local dimples and bumps of micrometres over 2.5-14 mm (full width) that the "
        "basis fit smooths away, where the evidence asks for them (one more evidence maximisation: ~0.3-0.6 s)",
    )


def _add_rig_options(p: argparse.ArgumentParser) -> None:
    """``--previous`` and ``--hold``: a rig's next frame, started from (or holding) an earlier frame's scale and
    prior."""
    p.add_argument(
        "--previous",
        metavar="JSON",
        help="the --json output of an earlier frame of the same setup (a rig's frames one after another): the search "
        "starts on the basis scale that frame ended on and the posterior's prior is searched by evidence from that "
        "frame's (uncertainty.prior); the result then depends on that frame within the evidence's flatness, so leave "
        "it out where each frame must stand alone",
    )
    p.add_argument(
        "--hold",
        action="store_true",
        help="with --previous: hold that frame's basis scale and prior (no scale choice on the data; the posterior "
        "read with the prior as it is where this frame's gradients are a plausible draw of it, else searched again "
        "from it): a rig's frames of one surface, about half the time of --previous alone",
    )
