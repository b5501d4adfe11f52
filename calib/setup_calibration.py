"""Calibration of the whole deflectometry setup (seed §2.7).

Three steps, as in the seed:

1. §2.7.1 — the camera against a calibration target lying on the holding frame: the
   target defines the global frame, so this gives the global camera.
2. §2.7.2 — the camera against the deflectometry pattern seen in a flat mirror on the
   holding frame: a calibration against the *virtual* (mirrored) pattern. The mirror z = 0
   maps the pattern point of local coordinates (x, y) to the virtual point (x, -y) of the
   mirrored frame (:meth:`scopetwin.scenes.geometry.Frame.mirrored_z`), which is right-handed.
3. The virtual pattern is transferred from the camera's frame into the global frame with the
   global camera of step 1, then mirrored into the real pattern (negate the z components,
   then T_y as a whole, Fig. 2.8).

Better than the seed: the camera is the same in both images, so by default the second
calibration keeps the first one's image distance b (and distortion, if refined) instead of
deriving b anew from the thin-lens equation. This matters because the pattern is seen
nearly face-on in the mirror, where b cannot be told from the distance.

The result is written as a setup TOML (:func:`write_setup_toml`) that
:func:`scopetwin.scenes.setup.load_setup` reads back.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from scopetwin.calib.oneshot import Calibration, CalibrationError, LensMode, Prior, calibrate, calibrate_bias_corrected
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array, Frame
from scopetwin.scenes.pattern import MarkerPattern
from scopetwin.scenes.setup import Setup

BiasModel = Callable[[Camera], Array]

# -- geometry of §2.7.2 --------------------------------------------------------------------------


def virtual_coordinates(pattern: MarkerPattern, ij: ArrayLike) -> Array:
    """Local coordinates (x, -y) of markers ``ij`` on the virtual (mirrored) pattern, mm (seed §2.7.2)."""
    xy = pattern.centers_local(np.asarray(ij))
    return xy * np.array([1.0, -1.0])


def pattern_in_camera(camera_in_pattern: Frame) -> Frame:
    """The pattern's frame expressed in the camera's frame (seed §2.7.2, first transformation).

    ``camera_in_pattern`` is the camera frame (r_c, T_x, T_y, N_z) in pattern coordinates;
    the pattern origin in camera coordinates is (-r.T_x, -r.T_y, -r.N_z) and its axes are the
    rows e_x, e_y, e_z seen in the camera's axes.
    """
    c = camera_in_pattern
    origin = c.to_local(np.zeros(3))
    return Frame(
        origin,
        c.vectors_to_local([1.0, 0.0, 0.0]),
        c.vectors_to_local([0.0, 1.0, 0.0]),
        c.vectors_to_local([0.0, 0.0, 1.0]),
    )


def compose(outer: Frame, inner: Frame) -> Frame:
    """A frame given in ``outer``'s coordinates, expressed in the coordinates ``outer`` is given in."""
    return Frame(
        outer.to_global(inner.origin),
        outer.vectors_to_global(inner.tx),
        outer.vectors_to_global(inner.ty),
        outer.vectors_to_global(inner.nz),
    )


def real_pattern(camera_global: Frame, camera_in_virtual: Frame) -> tuple[Frame, Frame]:
    """Virtual and real pattern in the global frame (seed §2.7.2, transfer and mirror).

    Parameters
    ----------
    camera_global : Frame
        The camera in the global frame (substrate calibration, §2.7.1).
    camera_in_virtual : Frame
        The camera in the virtual pattern's coordinates (mirror calibration).
    """
    virtual = compose(camera_global, pattern_in_camera(camera_in_virtual))
    return virtual, virtual.mirrored_z()


# -- the whole calibration ---------------------------------------------------------------------
@dataclass(frozen=True)
class SetupCalibration:
    """Camera and pattern of the deflectometry setup in one global frame (seed §2.7).

    Attributes
    ----------
    camera : Camera
        The global camera (from the substrate calibration).
    pattern : Frame
        The real deflectometry pattern, global.
    virtual_pattern : Frame
        Its mirror image in the substrate plane, global.
    substrate : Calibration
        Camera against the target on the holding frame (target = global coordinates).
    mirror : Calibration
        Camera against the virtual pattern (virtual-pattern coordinates).
    shared_intrinsics : bool
        Whether the mirror calibration kept the substrate calibration's b and distortion.
    """

    camera: Camera
    pattern: Frame
    virtual_pattern: Frame
    substrate: Calibration
    mirror: Calibration
    shared_intrinsics: bool

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready result (docs/contract.md, ``calibrate-setup``): camera, pattern and both calibrations."""
        cal = self.substrate.as_dict()
        return {
            "camera": cal["camera"],
            "pattern": self.pattern.as_dict(),
            "virtual_pattern": self.virtual_pattern.as_dict(),
            "shared_intrinsics": self.shared_intrinsics,
            "substrate_calibration": cal,
            "mirror_calibration": self.mirror.as_dict(),
        }


def mirror_prior(nominal: Setup, focal_length: float | None = None) -> Prior:
    """Prior for the mirror view: the nominal camera's N_z in the nominal virtual pattern's coordinates."""
    virtual = nominal.marker_pattern.frame.mirrored_z()
    cam = nominal.camera_model
    f = focal_length if focal_length is not None else nominal.camera.focal_length
    return Prior.from_camera(cam, f, plane=virtual)


def calibrate_setup(
    substrate_xy: ArrayLike,
    substrate_px: ArrayLike,
    substrate_prior: Prior,
    mirror_xy: ArrayLike,
    mirror_px: ArrayLike,
    mirror_prior: Prior,
    target_frame: Frame | None = None,
    lens: LensMode = "auto",
    distortion: bool = False,
    share_intrinsics: bool = True,
    substrate_bias: BiasModel | None = None,
    mirror_bias: BiasModel | None = None,
) -> SetupCalibration:
    """Calibrate camera and pattern of the deflectometry setup from the two calibration images (seed §2.7).

    Parameters
    ----------
    substrate_xy, substrate_px : array_like (n, 2)
        Target marker coordinates (target frame) and their images (continuous px).
    substrate_prior : Prior
        A-priori values for the substrate view (N_z estimate in target coordinates).
    mirror_xy, mirror_px : array_like (k, 2)
        Virtual-pattern coordinates of the pattern markers seen in the mirror
        (:func:`virtual_coordinates`) and their images.
    mirror_prior : Prior
        A-priori values for the mirror view (:func:`mirror_prior`).
    target_frame : Frame, optional
        The target's frame in the global frame (default: it IS the global frame, §2.7.1).
    lens, distortion
        As in :func:`scopetwin.calib.oneshot.calibrate` for the substrate view.
    share_intrinsics : bool
        Keep b (and r_cs, c0, c2) of the substrate view for the mirror view (default). False:
        the seed's way, each view with its own thin-lens b.
    substrate_bias, mirror_bias : callable, optional
        Centroid-bias models (``camera -> (n, 2) px``, camera in the view's target coordinates);
        given, each view alternates calibration and bias correction
        (:func:`scopetwin.calib.oneshot.calibrate_bias_corrected`).
    """

    def one(xy: ArrayLike, px: ArrayLike, prior: Prior, bias: BiasModel | None, **kw: Any) -> Calibration:
        if bias is None:
            return calibrate(xy, px, prior, **kw)
        return calibrate_bias_corrected(xy, px, prior, bias, **kw)[0]

    sub = one(substrate_xy, substrate_px, substrate_prior, substrate_bias, lens=lens, distortion=distortion)
    camera = sub.to_global(target_frame) if target_frame is not None else sub.camera
    if share_intrinsics:
        cam = sub.camera
        prior = Prior(
            mirror_prior.focal_length,
            mirror_prior.nx,
            mirror_prior.ny,
            mirror_prior.pitch,
            mirror_prior.nz_estimate,
            cam.r_cs,
            cam.c0,
            cam.c2,
            cam.b,
        )
        mir = one(mirror_xy, mirror_px, prior, mirror_bias, lens="fixed", distortion=False, b=cam.b)
    else:
        mir = one(mirror_xy, mirror_px, mirror_prior, mirror_bias, lens="thin-lens", distortion=distortion)
    virtual, real = real_pattern(camera.frame, mir.camera.frame)
    return SetupCalibration(camera, real, virtual, sub, mir, share_intrinsics)


# -- setup TOML ------------------------------------------------------------------------------------
def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value, ensure_ascii=False)
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise CalibrationError(f"cannot write a {type(value).__name__} to TOML")


def toml_dumps(data: dict[str, Any], comment: str = "") -> str:
    """A small TOML writer for setup dictionaries: scalars and arrays, nested tables; None is left out."""
    lines = [f"# {line}" for line in comment.splitlines()]

    def table(d: dict[str, Any], prefix: str) -> None:
        scalars = {k: v for k, v in d.items() if v is not None and not isinstance(v, dict)}
        subs = {k: v for k, v in d.items() if isinstance(v, dict)}
        if prefix and (scalars or not subs):
            lines.append("")
            lines.append(f"[{prefix}]")
        for k, v in scalars.items():
            lines.append(f"{k} = {_toml_value(v)}")
        for k, v in subs.items():
            table(v, f"{prefix}.{k}" if prefix else k)

    table(data, "")
    return "\n".join(lines) + "\n"


def calibrated_setup_dict(nominal: Setup, result: SetupCalibration) -> dict[str, Any]:
    """A deflectometry setup dictionary: the nominal setup with the calibrated camera and pattern."""
    data = nominal.model_dump(exclude_none=True)
    data.pop("mirror", None)
    data["scene"] = "deflectometry"
    data["name"] = "calibrated"
    data["section"] = "§2.7"
    data["description"] = "Deflectometry setup from the calibration of §2.7 (camera, pattern; substrate plane z = 0)"
    if "substrate" not in data:
        data["substrate"] = {}
    set_poses(data, result.camera, result.pattern)
    data.pop("calibration", None)
    unc = pose_uncertainties(result)
    if unc is not None:
        data["calibration"] = unc
    return data


def set_poses(data: dict[str, Any], camera: Camera, pattern: Frame) -> None:
    """Write a camera's frame and image distance and a pattern's frame into a setup dictionary, in place."""
    cspec = data["camera"]
    for key in ("r_0", "phi"):
        cspec.pop(key, None)
    f = camera.frame
    cspec.update(
        {
            "origin": f.origin.tolist(),
            "t_x": f.tx.tolist(),
            "t_y": f.ty.tolist(),
            "n_z": f.nz.tolist(),
            "image_distance": float(camera.b),
            "r_cs": list(camera.r_cs),
            "c0": float(camera.c0),
            "c2": float(camera.c2),
        }
    )
    data["pattern"].update(
        {
            "origin": pattern.origin.tolist(),
            "t_x": pattern.tx.tolist(),
            "t_y": pattern.ty.tolist(),
            "n_z": pattern.nz.tolist(),
        }
    )


def _pose_std(sigma: dict[str, Any]) -> tuple[float, float]:
    """Largest standard deviation of a calibration's camera position (mm) and of its axes' components (rad)."""
    shift = float(np.max(np.asarray(sigma["r_c"], dtype=np.float64)))
    rot = float(max(np.max(np.asarray(sigma[k], dtype=np.float64)) for k in ("t_x", "t_y", "n_z")))
    return shift, rot


def pose_uncertainties(result: SetupCalibration) -> dict[str, Any] | None:
    """The ``[calibration]`` table of a calibrated setup: standard deviations of the camera and pattern poses.

    The camera's are the substrate view's (seed §2.7.1: camera against the target on the holding frame); the
    pattern is placed through both views (its mirror image against the camera, seed §2.7.2), so its standard
    deviations are those of the two calibrations in quadrature (first order). Components of the unit axes stand for
    the rotation angles (small angles). None where a calibration left one undetermined (infinite).
    """
    cs, cr = _pose_std(result.substrate.sigma)
    ms, mr = _pose_std(result.mirror.sigma)
    values = (cs, cr, float(np.hypot(cs, ms)), float(np.hypot(cr, mr)))
    if not all(np.isfinite(v) for v in values):
        return None
    return {
        "camera": {"shift_mm": values[0], "rotation_rad": values[1]},
        "pattern": {"shift_mm": values[2], "rotation_rad": values[3]},
    }


def write_setup_toml(path: str | Path, nominal: Setup, result: SetupCalibration) -> str:
    """Write the calibrated setup as TOML (atomically) and return the text; :func:`scopetwin.scenes.setup.load_setup`
    reads it."""
    from scopetwin.scenes.io import write_text_atomic
    from scopetwin.scenes.setup import setup_from_dict

    data = calibrated_setup_dict(nominal, result)
    setup_from_dict(data, "calibrated setup")  # validate before anything is written
    text = toml_dumps(data, "scopetwin calibrate-setup: deflectometry setup calibrated as in seed §2.7")
    write_text_atomic(path, text)
    return text
