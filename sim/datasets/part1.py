"""Part I samples (kinds ``deflectometry`` and ``calibration``): each sample's setup and its writer.

A sample is one measurement (:mod:`scopetwin.sim.measurement`): image, truth (marker images, camera, seeds), the
surface's
height map and normals (deflectometry), preview.
"""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap
from scopetwin.sim.datasets.config import DatasetConfig, DatasetError, merge
from scopetwin.sim.datasets.seeding import sample_seed
from scopetwin.sim.measurement import StagedOutput, apply_sensor, render_measurement, write_measurement


def base_setup_dict(cfg: DatasetConfig) -> dict[str, Any]:
    """The setup (Part I) dictionary every sample starts from: the preset/TOML chain plus ``[setup]``."""
    from scopetwin.scenes.setup import resolve_toml

    try:
        data, _ = resolve_toml(cfg.dataset.setup)
    except SetupError as exc:
        raise DatasetError(f"dataset config: key dataset.setup: {exc}") from None
    kind = data.pop("kind", None)
    if kind not in (None, "setup"):
        raise DatasetError(
            f"dataset config: key dataset.setup: {cfg.dataset.setup!r} is a {kind!r} preset, not a "
            f"Part I setup (kind {cfg.dataset.kind!r})"
        )
    return merge(data, cfg.setup)


def _rotation(rotvec: Sequence[float]) -> np.ndarray:
    """Rotation matrix of a rotation vector (axis * angle, rad)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(rotvec, dtype=np.float64)).as_matrix()


def _vary_surface(d: dict[str, Any], params: dict[str, Any], master: int, index: int) -> None:
    """Give the deflectometry substrate's surface its sample seed and its drawn range, length, kind and roughness."""
    surf = d.setdefault("substrate", {}).setdefault("surface", {})
    surf["seed"] = sample_seed(master, index, "surface")
    for key, field in (
        ("surface_range_um", "range_um"),
        ("surface_correlation_length", "correlation_length"),
        ("surface_kind", "kind"),
        ("surface_broadband_rms_nm", "broadband_rms_nm"),
    ):
        if key in params:
            surf[field] = params[key]


def _view_from_angle(d: dict[str, Any], cam: dict[str, Any], params: dict[str, Any]) -> None:
    """Place the camera on the target's y-z circle at the drawn viewing angle and distance (camera given by axes)."""
    if d.get("scene") != "target":
        raise DatasetError("dataset config: key vary.view_angle_deg: the viewing-angle scan needs a target scene")
    a = math.radians(float(params.get("view_angle_deg", 90.0)))
    dist = float(params.get("view_distance", math.dist(cam.get("origin", (0, 0, 0)), (0, 0, 0))))
    s, c = math.sin(a), math.cos(a)
    centre = np.asarray(d.get("pattern", {}).get("origin", (0.0, 0.0, 0.0)), dtype=np.float64)
    for k in ("r_0", "phi"):
        cam.pop(k, None)
    cam.update(
        origin=(centre + [0.0, -dist * c, dist * s]).tolist(),
        t_x=[1.0, 0.0, 0.0],
        t_y=[0.0, s, c],
        n_z=[0.0, -c, s],
    )
    cam.setdefault("image_distance", 28.0)


def _vary_camera(cam: dict[str, Any], params: dict[str, Any]) -> None:
    """Apply the drawn camera shift and rotation, f-number, distortion and principal-point offset."""
    if "camera_shift" in params:
        cam["origin"] = (np.asarray(cam["origin"], dtype=np.float64) + params["camera_shift"]).tolist()
    if "camera_rotation" in params:
        if cam.get("t_x") is None:
            raise DatasetError(
                "dataset config: key vary.camera_rotation: needs a camera given by its axes "
                "(t_x, t_y, n_z), not by r_0/phi"
            )
        rot = _rotation(params["camera_rotation"])
        for k in ("t_x", "t_y", "n_z"):
            cam[k] = (rot @ np.asarray(cam[k], dtype=np.float64)).tolist()
    if "f_number" in params:
        cam["f_number"] = params["f_number"]
    if "distortion_c2" in params:
        cam["c2"] = params["distortion_c2"]
    if "principal_offset" in params:
        cam["r_cs"] = list(params["principal_offset"])


def _validated_setup(d: dict[str, Any], cam: dict[str, Any], index: int, params: dict[str, Any]) -> Setup:
    """Validate ``d`` as sample ``index``'s setup; a drawn defocus moves the thin lens's focus and validates again."""
    from scopetwin.scenes.setup import setup_from_dict

    try:
        setup = setup_from_dict(d, f"sample {index}")
        if "defocus" in params:
            g0 = setup.camera_model.focus_distance()
            if g0 is None:
                raise DatasetError(
                    "dataset config: key vary.defocus: needs a thin lens: set camera.f_number in "
                    "[setup] or vary f_number"
                )
            cam["focus_distance"] = g0 + float(params["defocus"])
            setup = setup_from_dict(d, f"sample {index}")
    except SetupError as exc:
        raise DatasetError(f"sample {index} (parameters {params}): {exc}") from None
    return setup


def part1_setup(cfg: DatasetConfig, base: dict[str, Any], index: int, params: dict[str, Any]) -> Setup:
    """The validated :class:`scopetwin.scenes.setup.Setup` of sample ``index`` (varied quantities applied).

    Parameters
    ----------
    cfg : DatasetConfig
        The dataset config.
    base : dict
        The setup dictionary every sample starts from (:func:`base_setup_dict`).
    index : int
        The sample.
    params : dict
        Its varied quantities (:func:`scopetwin.sim.datasets.seeding.draw_parameters`).
    """
    d = json.loads(json.dumps(base))
    cam = d.setdefault("camera", {})
    master = cfg.dataset.master_seed
    if cfg.dataset.kind == "deflectometry":
        _vary_surface(d, params, master, index)
    if "view_angle_deg" in params or "view_distance" in params:
        _view_from_angle(d, cam, params)
    _vary_camera(cam, params)
    if "exposure_fill" in params:
        d.setdefault("sensor", {})["fill_fraction"] = params["exposure_fill"]
    if "exposure_s" in params:
        d.setdefault("sensor", {})["exposure_s"] = params["exposure_s"]
    d.setdefault("render", {}).update(
        spp=cfg.dataset.spp,
        seed=sample_seed(master, index, "render"),
        noise=bool(cfg.dataset.noise or "exposure_fill" in params or "exposure_s" in params),
    )
    d["name"] = f"{d.get('name', 'setup')}-sample-{index:06d}"
    return _validated_setup(d, cam, index, params)


def write_normals(path: Path, heights: HeightMap) -> None:
    """Unit surface normals at the height-map nodes: channels NX, NY, NZ (plus Z), extents as in the contract."""
    import OpenEXR

    from scopetwin.scenes.io import EXTENT_KEYS, atomic_path, exr_write_error

    xx, yy = np.meshgrid(heights.x_nodes, heights.y_nodes)
    n = heights.normals(xx, yy)
    chans = {"NX": n[..., 0], "NY": n[..., 1], "NZ": n[..., 2], "Z": heights.z}
    chans = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in chans.items()}
    header: dict[str, Any] = {
        "compression": OpenEXR.ZIP_COMPRESSION,
        "type": OpenEXR.scanlineimage,
        "scopetwin_format": "normals/1",
    }
    header.update(zip(EXTENT_KEYS, (heights.x_min, heights.x_max, heights.y_min, heights.y_max), strict=True))
    with atomic_path(path) as tmp:
        try:
            OpenEXR.File(header, chans).write(str(tmp))
        except RuntimeError as exc:
            raise exr_write_error(path, exc) from None


def write_part1(cfg: DatasetConfig, index: int, setup: Setup, stage: StagedOutput) -> dict[str, Any]:
    """Render and write Part I sample ``index`` (its ``setup``) into ``stage``; returns its files and truth.

    A setup with a ``[fringes]`` table (phase-measuring deflectometry) writes its K frames instead of one image
    (:func:`write_fringe_frames`); the truth, normals and per-pixel maps are the same for both.
    """
    from scopetwin.sim.datasets.validate import check_image
    from scopetwin.sim.surfaces import surface_for

    heights = surface_for(setup)
    spp, seed = setup.render.spp, setup.render.seed
    if setup.fringe_display is not None:
        names, truth = write_fringe_frames(index, setup, heights, stage)
    else:
        # the render is checked before the sensor model (whose dark noise would hide a black render), then after it
        image, _ = render_measurement(setup, heights, spp, seed, False)
        check_image(image, f"sample {index}: the render")
        if setup.render.noise:
            image = apply_sensor(setup, image, seed)
            check_image(image, f"sample {index}: the image after the sensor model")
        names = write_measurement(stage, "", setup, heights, image, spp, seed, "mitsuba")
        if not cfg.dataset.preview:
            stage.path(names.pop("preview")).unlink()
        truth = json.loads(stage.path(names["truth"]).read_text())
    return {"files": names, "truth": _part1_truth(cfg, setup, heights, stage, names, truth)}


def write_fringe_frames(
    index: int, setup: Setup, heights: HeightMap | None, stage: StagedOutput
) -> tuple[dict[str, Any], dict[str, Any]]:
    """Render a fringe setup's sequence (:func:`scopetwin.sim.fringes.render_fringes`, the sample's spp, seed and
    noise) and write it as :func:`scopetwin.sim.fringes.write_fringes` does: ``fringe_0000.exr`` ... (one per frame,
    the frame in its header), ``fringes.json`` (the frames, sequence, display, exposure, noise seeds) and
    ``surface.exr``. Returns the file names and the truth's first keys (no marker is shown: ``markers`` is empty;
    ``fringes`` names the JSON, ``frames`` the images in order, ``exposure_s`` the one exposure of all frames).

    Raises
    ------
    InvalidImage
        A frame is non-finite or carries no signal (after the sensor model): nothing is written for the sample.
    """
    from scopetwin.sim.datasets.validate import check_image
    from scopetwin.sim.fringes import render_fringes, write_fringes

    m = render_fringes(setup, heights, setup.render.spp, setup.render.seed, setup.render.noise)
    for k in range(len(m.frames)):
        check_image(m.images[k], f"sample {index}: fringe frame {k}")
    written = write_fringes(stage, m)
    names: dict[str, Any] = {f"frame_{k:04d}": name for k, name in enumerate(written["images"])}
    names["fringes"] = written["fringes"]
    names["truth"] = "truth.json"
    if written["surface"] is not None:
        names["surface"] = written["surface"]
    truth = {
        "setup": setup.name,
        "scene": setup.scene,
        "surface": written["surface"],
        "markers": [],
        "fringes": written["fringes"],
        "frames": list(written["images"]),
        "exposure_s": m.exposure_s,
    }
    return names, truth


def _part1_truth(
    cfg: DatasetConfig,
    setup: Setup,
    heights: HeightMap | None,
    stage: StagedOutput,
    names: dict[str, Any],
    truth: dict[str, Any],
) -> dict[str, Any]:
    """Write the normals and (``[dataset] maps``) the per-pixel maps of a Part I sample; the truth completed with the
    camera (thesis's and OpenCV's), the maps' description, the setup and the seeds."""
    from scopetwin.scenes.opencv_camera import opencv_camera
    from scopetwin.sim.datasets.maps import MAPS_FILE, MAPS_FORMAT, MAPS_VERSION, part1_maps, write_maps

    seed = setup.render.seed
    if heights is not None:
        write_normals(stage.path("normals.exr"), heights)
        names["normals"] = "normals.exr"
    maps_entry = None
    if cfg.dataset.maps:
        maps = part1_maps(setup, heights)
        write_maps(stage.path(MAPS_FILE), maps, cfg.dataset.maps_compression)
        names["maps"] = MAPS_FILE
        maps_entry = {"file": MAPS_FILE, "format": f"{MAPS_FORMAT}/{MAPS_VERSION}", "layers": list(maps)}
    cam = setup.camera_model
    truth.update(
        camera={
            "r_c": cam.frame.origin.tolist(),
            "t_x": cam.frame.tx.tolist(),
            "t_y": cam.frame.ty.tolist(),
            "n_z": cam.frame.nz.tolist(),
            "b": cam.b,
            "r_cs": list(cam.r_cs),
            "c0": cam.c0,
            "c2": cam.c2,
            "focus_distance": cam.focus_distance(),
            "nx": cam.nx,
            "ny": cam.ny,
            "pitch": cam.pitch,
        },
        camera_opencv=opencv_camera(cam).as_dict(),
        **({"maps": maps_entry} if maps_entry else {}),
        setup_json=json.loads(setup.to_json()),
        seeds={
            "surface": setup.substrate.surface.seed if setup.substrate else None,
            "render": seed,
            "noise": seed if setup.render.noise else None,
        },
    )
    return truth
