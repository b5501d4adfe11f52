"""Calibration of the whole deflectometry setup (thesis §2.7).

Three steps, as in the thesis:

1. §2.7.1 — the camera against a calibration target lying on the holding frame: the
   target defines the global frame, so this gives the global camera.
2. §2.7.2 — the camera against the deflectometry pattern seen in a flat mirror on the
   holding frame: a calibration against the *virtual* (mirrored) pattern. The mirror z = 0
   maps the pattern point of local coordinates (x, y) to the virtual point (x, -y) of the
   mirrored frame (:meth:`scopetwin.scenes.geometry.Frame.mirrored_z`), which is right-handed.
3. The virtual pattern is transferred from the camera's frame into the global frame with the
   global camera of step 1, then mirrored into the real pattern (negate the z components,
   then T_y as a whole, Fig. 2.8).

Better than the thesis: the camera is the same in both images, so by default the second
calibration keeps the first one's image distance b (and distortion, if refined) instead of
deriving b anew from the thin-lens equation. This matters because the pattern is seen
nearly face-on in the mirror, where b cannot be told from the distance.

The result is written as a setup TOML (:func:`write_setup_toml`) that
:func:`scopetwin.scenes.setup.load_setup` reads back.

:func:`calibrate_setup_from_images` is the whole job from the two calibration images to the calibrated setup and
its TOML text (markers found and indexed with :mod:`scopetwin.recon.markers`, centroid bias corrected with
:func:`scopetwin.recon.bias.spot_bias_model`); ``scopetwin run``, ``scopetwin calibrate-setup``, the ``thesis``
study and ``benchmarks/calibration_setup.py`` all call it.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from scopetwin.calib.oneshot import (
    MIN_MARKERS,
    Calibration,
    CalibrationError,
    LensMode,
    Prior,
    calibrate,
    calibrate_bias_corrected,
)
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array, Frame
from scopetwin.scenes.pattern import MarkerPattern
from scopetwin.scenes.setup import Setup

if TYPE_CHECKING:
    from scopetwin.recon.markers import Markers

BiasModel = Callable[[Camera], Array]

# -- geometry of §2.7.2 --------------------------------------------------------------------------


def virtual_coordinates(pattern: MarkerPattern, ij: ArrayLike) -> Array:
    """Local coordinates (x, -y) of markers ``ij`` on the virtual (mirrored) pattern, mm (thesis §2.7.2)."""
    xy = pattern.centers_local(np.asarray(ij))
    return xy * np.array([1.0, -1.0])


def pattern_in_camera(camera_in_pattern: Frame) -> Frame:
    """The pattern's frame expressed in the camera's frame (thesis §2.7.2, first transformation).

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
    """Virtual and real pattern in the global frame (thesis §2.7.2, transfer and mirror).

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
    """Camera and pattern of the deflectometry setup in one global frame (thesis §2.7).

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
    """Calibrate camera and pattern of the deflectometry setup from the two calibration images (thesis §2.7).

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
        the thesis's way, each view with its own thin-lens b.
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

    The camera's are the substrate view's (thesis §2.7.1: camera against the target on the holding frame); the
    pattern is placed through both views (its mirror image against the camera, thesis §2.7.2), so its standard
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


#: The first line of the TOML that ``scopetwin calibrate-setup`` writes.
CALIBRATE_SETUP_COMMENT = "scopetwin calibrate-setup: deflectometry setup calibrated as in thesis §2.7"


def calibrated_setup(nominal: Setup, result: SetupCalibration, comment: str) -> tuple[Setup, str]:
    """The calibrated setup (validated) and its TOML text headed by ``comment`` (:func:`calibrated_setup_dict`)."""
    from scopetwin.scenes.setup import setup_from_dict

    data = calibrated_setup_dict(nominal, result)
    setup = setup_from_dict(data, "calibrated setup")  # validate before anything is written
    return setup, toml_dumps(data, comment)


def write_setup_toml(path: str | Path, nominal: Setup, result: SetupCalibration) -> str:
    """Write the calibrated setup as TOML (atomically) and return the text; :func:`scopetwin.scenes.setup.load_setup`
    reads it."""
    from scopetwin.scenes.io import write_text_atomic

    text = calibrated_setup(nominal, result, CALIBRATE_SETUP_COMMENT)[1]
    write_text_atomic(path, text)
    return text


# -- from the two calibration images ------------------------------------------------------------
@dataclass(frozen=True)
class CalibrationView:
    """One calibration image as it entered the calibration (thesis §2.7.1 or §2.7.2).

    Attributes
    ----------
    markers : Markers
        The markers found and indexed in the image (:func:`scopetwin.recon.markers.find_markers_for`).
    xy : ndarray, (n, 2)
        Their centres in the view's plane coordinates, mm: the target's (§2.7.1) or the virtual pattern's
        (:func:`virtual_coordinates`, §2.7.2).
    prior : Prior
        The a-priori camera values of the view (N_z estimate in the view's plane coordinates).
    bias : callable or None
        The centroid-bias model of the markers (:func:`scopetwin.recon.bias.spot_bias_model`); None with the bias
        correction off.
    """

    markers: Markers
    xy: Array
    prior: Prior
    bias: BiasModel | None


@dataclass(frozen=True)
class CalibratedSetup:
    """The deflectometry setup calibrated from the two calibration images (thesis §2.7).

    Attributes
    ----------
    calibration : SetupCalibration
        Camera and pattern in the global frame and both one-shot calibrations (:func:`calibrate_setup`).
    setup : Setup
        The calibrated deflectometry setup: the nominal setup with the calibrated camera and pattern and the
        ``[calibration]`` pose uncertainties (:func:`calibrated_setup_dict`).
    toml : str
        Its TOML text (:func:`toml_dumps`), read back by :func:`scopetwin.scenes.setup.load_setup`.
    uncertainties : dict or None
        Standard deviations of the camera and pattern poses (:func:`pose_uncertainties`; None where a calibration
        left one undetermined).
    target, mirror : CalibrationView
        The substrate-target view (§2.7.1) and the mirror view (§2.7.2) as calibrated.
    """

    calibration: SetupCalibration
    setup: Setup
    toml: str
    uncertainties: dict[str, Any] | None
    target: CalibrationView
    mirror: CalibrationView


def _check_setups(target_setup: Setup, mirror_setup: Setup) -> None:
    if mirror_setup.scene != "mirror":
        raise CalibrationError(
            f"the pattern setup {mirror_setup.name} is a {mirror_setup.scene} scene; the mirror image needs "
            "a mirror scene (thesis §2.7.2)"
        )
    if target_setup.scene != "target":
        raise CalibrationError(
            f"the target setup {target_setup.name} is a {target_setup.scene} scene, not a calibration target"
        )


def _check_image_format(image: Any, prior: Prior, name: str) -> None:
    shape = np.shape(image)
    if shape != (prior.ny, prior.nx):
        raise CalibrationError(
            f"{name} has {shape[1]} x {shape[0]} pixels but the setup's camera has {prior.nx} x {prior.ny}"
        )


def _priors(
    target_setup: Setup, mirror_setup: Setup, focal_length: float | None, pixel_pitch: float | None
) -> tuple[Prior, Prior]:
    """A-priori camera values of the target view (target coordinates) and of the mirror view (:func:`mirror_prior`)."""
    f = focal_length if focal_length is not None else target_setup.camera.focal_length
    target = Prior.from_camera(target_setup.camera_model, f, plane=target_setup.marker_pattern.frame)
    mirror = mirror_prior(mirror_setup, focal_length)
    if pixel_pitch is None:
        return target, mirror
    return replace(target, pitch=pixel_pitch), replace(mirror, pitch=pixel_pitch)


def _view(image: Any, setup: Setup, prior: Prior, bias: bool, name: str) -> CalibrationView:
    """Markers of one calibration image, their plane coordinates and bias model (recon.markers, recon.bias).

    The plane coordinates are the target's in a ``target`` scene, the virtual pattern's in a ``mirror`` scene.
    """
    from scopetwin.recon.bias import spot_bias_model
    from scopetwin.recon.markers import find_markers_for

    found = find_markers_for(image, setup)
    if len(found) < MIN_MARKERS:
        raise CalibrationError(f"{name}: only {len(found)} markers were found and indexed")
    pattern = setup.marker_pattern
    xy = virtual_coordinates(pattern, found.ij) if setup.scene == "mirror" else pattern.centers_local(found.ij)
    model = spot_bias_model(xy, pattern.radii(found.ij)) if bias else None
    return CalibrationView(found, xy, prior, model)


def calibrate_setup_from_images(
    target_image: ArrayLike,
    mirror_image: ArrayLike,
    target_setup: Setup,
    mirror_setup: Setup,
    *,
    nominal: Setup | None = None,
    focal_length: float | None = None,
    pixel_pitch: float | None = None,
    lens: LensMode = "auto",
    distortion: bool = False,
    share_intrinsics: bool = True,
    bias_correction: bool = True,
    comment: str = "deflectometry setup calibrated as in thesis §2.7",
    image_names: tuple[str, str] = ("target image", "mirror image"),
) -> CalibratedSetup:
    """Calibrate the deflectometry setup from its two calibration images, thesis §2.7 (§2.8.3 on renders).

    The target on the holding frame gives the global camera (§2.7.1; the target setup places the target in the
    global frame), the pattern seen in a flat mirror on the frame gives the pattern through its virtual image
    (§2.7.2). The markers of each image are found and indexed (:func:`scopetwin.recon.markers.find_markers_for`)
    and, with ``bias_correction``, their centroid bias corrected (:func:`scopetwin.recon.bias.spot_bias_model`);
    then :func:`calibrate_setup`, and the nominal setup with the calibrated poses, validated, and its TOML.

    Parameters
    ----------
    target_image, mirror_image : array_like, (ny, nx)
        The image of the calibration target on the holding frame and the image of the pattern in the flat mirror.
    target_setup : Setup
        A ``target`` scene: the target (its frame in the global frame) and the a-priori camera.
    mirror_setup : Setup
        A ``mirror`` scene: the nominal pattern and the a-priori camera of the mirror image.
    nominal : Setup, optional
        The setup the calibrated camera and pattern are written into (default ``mirror_setup``).
    focal_length, pixel_pitch : float, optional
        A-priori focal length and pixel size, mm (default: the setups' cameras').
    lens, distortion, share_intrinsics
        As in :func:`calibrate_setup`.
    bias_correction : bool
        Correct the markers' centroid bias (default); False: the raw centroids.
    comment : str
        The TOML's comment line.
    image_names : (str, str)
        How error messages name the two images (e.g. their paths).

    Returns
    -------
    CalibratedSetup
        The calibration, the calibrated setup and its TOML, the pose uncertainties and both views as calibrated.

    Raises
    ------
    CalibrationError
        Wrong scene kinds, an image whose format is not the camera's, fewer than :data:`MIN_MARKERS` markers in an
        image, or a calibration that fails.
    """
    _check_setups(target_setup, mirror_setup)
    prior_t, prior_m = _priors(target_setup, mirror_setup, focal_length, pixel_pitch)
    _check_image_format(target_image, prior_t, image_names[0])
    _check_image_format(mirror_image, prior_m, image_names[1])
    target = _view(target_image, target_setup, prior_t, bias_correction, image_names[0])
    mirror = _view(mirror_image, mirror_setup, prior_m, bias_correction, image_names[1])
    result = calibrate_setup(
        target.xy,
        target.markers.centroids,
        prior_t,
        mirror.xy,
        mirror.markers.centroids,
        prior_m,
        target_frame=target_setup.marker_pattern.frame,
        lens=lens,
        distortion=distortion,
        share_intrinsics=share_intrinsics,
        substrate_bias=target.bias,
        mirror_bias=mirror.bias,
    )
    setup, text = calibrated_setup(nominal if nominal is not None else mirror_setup, result, comment)
    return CalibratedSetup(result, setup, text, pose_uncertainties(result), target, mirror)
