"""CMU samples (kind ``cmu``, thesis Part II §5.1-§5.2): the four-channel unit of each sample and its writer.

A sample is one image per channel of the compact microscope unit (:mod:`scopetwin.scenes.mitsuba.cmu`), each camera at
its
own refocused image distance (plus ``channel_defocus``), offset and tilt; the splitters' modelled bows and residual
seeds vary per sample. The truth of each channel is the numpy tracer's object -> pixel map of its camera.
"""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from scopetwin.scenes.errors import ScopetwinError, SetupError
from scopetwin.sim.datasets.config import SAMPLE_PACKAGES, DatasetConfig, DatasetError
from scopetwin.sim.datasets.seeding import sample_seed
from scopetwin.sim.datasets.validate import check_image
from scopetwin.sim.measurement import StagedOutput, versions, write_preview


def cmu_channels(cfg: DatasetConfig, base: dict[str, Any]) -> list[str]:
    """The channels a cmu sample renders, in the setup's order."""
    wanted = cfg.cmu.channels
    return [c for c in base["channels"] if wanted is None or c in wanted]


def cmu_base(cfg: DatasetConfig) -> dict[str, Any]:
    """The unit every cmu sample starts from (preset/TOML plus ``[setup]``), with ``[cmu]`` checked against it."""
    from scopetwin.scenes.cmu.layout import load_cmu_setup

    try:
        setup = load_cmu_setup(cfg.dataset.setup, cfg.setup or None)
    except ScopetwinError as exc:
        raise DatasetError(f"dataset config: key dataset.setup / [setup]: {exc}") from None
    c = cfg.cmu
    if c.channels is not None:
        bad = [ch for ch in c.channels if ch not in setup.channels]
        if bad or len(set(c.channels)) != len(c.channels):
            what = f"unknown channel {bad[0]!r}" if bad else "a channel is named twice"
            raise DatasetError(f"dataset config: key cmu.channels: {what} (the setup has {', '.join(setup.channels)})")
    if c.window is not None:
        r0, c0, h, w = c.window
        cam = setup.camera
        if min(r0, c0) < 0 or min(h, w) < 1 or r0 + h > cam.height_px or c0 + w > cam.width_px:
            raise DatasetError(
                f"dataset config: key cmu.window: {list(c.window)} (row0, col0, height, width) must lie "
                f"inside the {cam.width_px} x {cam.height_px} px sensor"
            )
    return json.loads(setup.to_json())


@dataclass(frozen=True)
class CmuSample:
    """One cmu sample's unit and cameras: per channel the defocus (mm), tilt (deg) and offset (px, (col, row))."""

    setup: Any
    target: Literal["star", "cells"]
    channels: tuple[str, ...]
    defocus: dict[str, float]
    tilt_deg: dict[str, float]
    offset_px: dict[str, tuple[float, float]]
    exposure_fill: float | None


def cmu_sample(cfg: DatasetConfig, base: dict[str, Any], index: int, params: dict[str, Any]) -> CmuSample:
    """The unit of sample ``index``: the splitters' bows and residual seeds, the cells' seed, the camera poses.

    With the Siemens star, every channel's frame must lie inside the image at the nominal magnification
    f_tube / f_objective (the bows change it by < 2 %): checked here, before any work.
    """
    from scopetwin.scenes.cmu.layout import cmu_setup_from_dict

    master = cfg.dataset.master_seed
    d = json.loads(json.dumps(base))
    for name, el in d["splitters"].items():
        if "bow_range_um" in params:
            el["bow_range_um"] = params["bow_range_um"][name]
        if "bow_scale" in params:
            el["bow_range_um"] = float(el.get("bow_range_um", 0.0)) * params["bow_scale"][name]
        if "residual_rms_um" in params:
            el["residual_rms_um"] = params["residual_rms_um"][name]
        el["residual_seed"] = sample_seed(master, index, f"residual:{name}")
    d.setdefault("cells", {})["seed"] = sample_seed(master, index, "cells")
    d["name"] = f"{d.get('name') or 'cmu'}-sample-{index:06d}"
    try:
        setup = cmu_setup_from_dict(d, f"sample {index}")
    except SetupError as exc:
        raise DatasetError(f"sample {index} (parameters {params}): {exc}") from None
    channels = tuple(cmu_channels(cfg, base))
    per = {k: params.get(k, {}) for k in ("channel_defocus", "channel_tilt_deg", "channel_offset_px")}
    sample = CmuSample(
        setup,
        "cells" if params.get("target", "star") == "cells" else "star",
        channels,
        {c: float(per["channel_defocus"].get(c, 0.0)) for c in channels},
        {c: float(per["channel_tilt_deg"].get(c, 0.0)) for c in channels},
        {c: _pair(per["channel_offset_px"].get(c, (0.0, 0.0))) for c in channels},
        params.get("exposure_fill"),
    )
    if sample.target == "star":
        check_star_in_image(cfg, sample, index, params)
    return sample


def _pair(values: Any) -> tuple[float, float]:
    """Two numbers as a (float, float) pair."""
    a, b = values
    return float(a), float(b)


def image_box(cfg: DatasetConfig, setup: Any) -> tuple[int, int, int, int]:
    """(row0, col0, height, width) of the rendered part of the sensor."""
    return cfg.cmu.window or (0, 0, setup.camera.height_px, setup.camera.width_px)


def check_star_in_image(cfg: DatasetConfig, sample: CmuSample, index: int, params: dict[str, Any]) -> None:
    """Raise when the Siemens-star frame of a channel leaves the written image (offset, tilt, window)."""
    setup = sample.setup
    r0, c0, h, w = image_box(cfg, setup)
    m0 = setup.tube.focal_length / setup.objective.focal_length
    half = 1.02 * m0 * (0.5 * setup.target.frame_side + setup.target.frame_line) / (setup.camera.pixel_um * 1e-3)
    for ch in sample.channels:
        t = math.radians(sample.tilt_deg[ch])
        rot = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
        corners = (rot @ (half * np.array([[-1, -1, 1, 1], [-1, 1, -1, 1]]))).T
        centre = np.array(
            [
                0.5 * setup.camera.width_px + sample.offset_px[ch][0] - c0,
                0.5 * setup.camera.height_px + sample.offset_px[ch][1] - r0,
            ]
        )
        pts = corners + centre
        if pts.min() < 0 or pts[:, 0].max() > w or pts[:, 1].max() > h:
            key = next((k for k in ("channel_offset_px", "channel_tilt_deg") if k in params), "cmu.window")
            key = key if key == "cmu.window" else f"vary.{key}"
            raise DatasetError(
                f"sample {index}: key {key}: the Siemens-star frame ({2 * half:.0f} px wide) of channel "
                f"{ch} leaves the {w} x {h} px image (offset {list(sample.offset_px[ch])} px, tilt "
                f"{sample.tilt_deg[ch]:g} deg); use smaller offsets or a larger window"
            )


#: 18 ke-, 10 e- dark noise); the quantum efficiency is 1 because the rendered image already counts electrons
#: (the detection response includes the camera's QE), and the gain fills the ADC as the Part I default does.
CMU_FILL_DEFAULT = 0.7


def cmu_sensor(bit_depth: int) -> Any:
    """The EMVA 1288 model of the CMU cameras (see :data:`CMU_FILL_DEFAULT`) at ``bit_depth``."""
    from scopetwin.scenes.emva1288 import EmvaSensor

    full_well = 18000.0
    return EmvaSensor(
        quantum_efficiency=1.0,
        full_well_e=full_well,
        gain_dn_per_e=(2**bit_depth - 96) / full_well,
        bit_depth=bit_depth,
    )


def object_to_pixel(
    setup: Any,
    opt: Any,
    channel: str,
    pose: Any,
    box: tuple[int, int, int, int],
    half: float,
    n_pupil: int = 15,
    return_residual: bool = False,
) -> Any:
    """Affine map (2 x 3) from object (x, y, 1) in mm to (col, row) in the written image's pixel coordinates.

    Fitted to the traced spot centroids (numpy tracer, the channel's real plates) of a 3 x 3 object grid of
    +-``half`` mm on the camera plane at ``pose.image_distance``, expressed in the camera's axes and tilt as
    :func:`scopetwin.scenes.mitsuba.cmu.render_channel` does, and mapped to pixels by the sensor's
    :class:`scopetwin.scenes.camera.PixelGrid`; the camera offset (col, row) shifts the grid centre. Pixel (r, c) covers
    [c, c+1) x [r, r+1) (docs/contract.md, "Camera"), so the star's centre is at ``A[:, 2]``; ``box`` = (row0, col0,
    height, width) is the written part of the sensor. With ``return_residual``: (map, the largest distance in px
    between a traced centroid and the affine map's pixel of its object point).
    """
    from scopetwin.scenes.camera import PixelGrid
    from scopetwin.scenes.cmu.analysis import image_rays
    from scopetwin.scenes.mitsuba.cmu import sensor_axes
    from scopetwin.scenes.spots import pupil_disk

    ex, ey = sensor_axes(setup, channel)
    to_ab = np.linalg.inv(np.column_stack([ex, ey]))
    t = math.radians(pose.tilt_deg)
    rot = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    p_mm = setup.camera.pixel_um * 1e-3
    grid = PixelGrid(
        setup.camera.width_px,
        setup.camera.height_px,
        p_mm,
        r_cs=(-pose.offset_px[0] * p_mm, pose.offset_px[1] * p_mm),
    )
    r0, c0, _, _ = box
    px, py = pupil_disk(n_pupil)
    obj, img = [], []
    for x0 in (-half, 0.0, half):
        for y0 in (-half, 0.0, half):
            u, v = image_rays(opt, x0, y0, px, py).at(pose.image_distance)
            a, b = rot @ (to_ab @ np.array([u.mean(), v.mean()]))
            col, row = grid.xy(a, b)
            img.append((col - c0, row - r0))
            obj.append((x0, y0, 1.0))
    coef, *_ = np.linalg.lstsq(np.asarray(obj), np.asarray(img), rcond=None)
    residual = float(np.abs(np.asarray(obj) @ coef - np.asarray(img)).max())
    if return_residual:
        return coef.T, residual
    return coef.T


def affine_truth(a: np.ndarray, pixel_um: float) -> dict[str, Any]:
    """Magnification (sqrt |det|, and the singular values), centre and displayed tilt of an object->pixel map.

    The tilt is the rotation of the displayed image (rows up), counter-clockwise positive, as
    :mod:`scopetwin.calib.channels` measures it.
    """
    lin = a[:, :2]
    p_mm = pixel_um * 1e-3
    sv = np.linalg.svd(lin, compute_uv=False) * p_mm
    return {
        "magnification": float(math.sqrt(abs(np.linalg.det(lin))) * p_mm),
        "magnification_xy": [float(sv[0]), float(sv[1])],
        "frame_center_px": [float(a[0, 2]), float(a[1, 2])],
        "image_tilt_deg": float(math.degrees(math.atan2(-lin[1, 0] - lin[0, 1], lin[0, 0] - lin[1, 1]))),
        "object_to_pixel": a.tolist(),
    }


@dataclass(frozen=True)
class _UnitRender:
    """What every channel of one cmu sample shares: plate maps, scene, window, sensor, fill and truth-grid half size."""

    maps: dict[str, Any]
    scene: Any
    box: tuple[int, int, int, int]
    sensor: Any
    fill: float
    half: float


def _write_plates(setup: Any, maps: dict[str, Any], stage: StagedOutput, files: dict[str, str]) -> dict[str, Any]:
    """Write the height map of every splitter and every bent mirror (adding them to ``files``); their truth entries."""
    from scopetwin.scenes.io import write_heightmap

    plates = {}
    for name, spec in {**setup.splitters, **setup.mirrors}.items():
        role = "splitter" if name in setup.splitters else "mirror"
        if role == "mirror" and not np.any(maps[name].z):
            continue
        fname = f"height_{name}.exr"
        write_heightmap(stage.path(fname), maps[name], scopetwin_element=name, scopetwin_format="heightmap/1")
        files[f"height_{name}"] = fname
        plates[name] = {
            "file": fname,
            "role": role,
            "bow_range_um": spec.bow_range_um,
            "residual_rms_um": spec.residual_rms_um,
            "residual_seed": spec.residual_seed,
            "concave": spec.concave,
            "height_map": spec.height_map,
            "range_um": float(np.ptp(maps[name].z) * 1e3),
        }
    return plates


def _expose(
    sensor: Any, img: np.ndarray, fill: float, master: int, index: int, ch: str
) -> tuple[np.ndarray, float, int]:
    """Capture ``img`` through the noise model at the exposure that fills its 99.9th percentile to ``fill``."""
    peak = float(np.percentile(img, 99.9))  # Monte-Carlo outliers above it saturate, as hot spots would
    if not peak > 0:
        raise ScopetwinError(
            f"sample {index}, channel {ch}: the rendered image is black: cannot choose an exposure for the noise model"
        )
    exposure = sensor.exposure_for(peak, 1.0, fill)
    nseed = sample_seed(master, index, f"noise:{ch}")
    return sensor.capture(img, 1.0, exposure, rng=nseed), exposure, nseed


def _write_channel(
    cfg: DatasetConfig, index: int, sample: CmuSample, ch: str, unit: _UnitRender, stage: StagedOutput
) -> tuple[str, np.ndarray, dict[str, Any]]:
    """Render, expose and write channel ``ch`` at its refocused distance plus defocus; file name, image and truth."""
    from scopetwin.scenes.cmu.analysis import analyse, channel_optics
    from scopetwin.scenes.io import write_image
    from scopetwin.scenes.mitsuba.cmu import CameraPose, render_channel

    setup = sample.setup
    master, spp = cfg.dataset.master_seed, cfg.dataset.spp
    opt = channel_optics(setup, ch, unit.maps, stop=cfg.cmu.stop)
    focus = analyse(setup, opt, n_pupil=cfg.cmu.n_pupil)
    b = focus.image_distance_mm + sample.defocus[ch]
    res = focus if sample.defocus[ch] == 0 else analyse(setup, opt, n_pupil=cfg.cmu.n_pupil, image_distance=b)
    pose = CameraPose(b, sample.tilt_deg[ch], sample.offset_px[ch])
    rseed = sample_seed(master, index, f"render:{ch}")
    img = render_channel(
        setup, ch, pose, sample.target, spp=spp, window=unit.box, stop=cfg.cmu.stop, seed=rseed, scene=unit.scene
    )
    check_image(img, f"sample {index}, channel {ch}: the render")
    exposure, nseed = None, None
    if unit.sensor is not None:
        img, exposure, nseed = _expose(unit.sensor, img, unit.fill, master, index, ch)
        check_image(img, f"sample {index}, channel {ch}: the image after the sensor model")
    fname = f"image_{ch}.exr"
    prov = {
        "seed": rseed,
        "spp": spp,
        "renderer": "mitsuba-cmu",
        "channel": ch,
        "target": sample.target,
        "noise_seed": nseed,
        "versions": versions(SAMPLE_PACKAGES),
    }
    write_image(
        stage.path(fname),
        img,
        setup.to_json(),
        prov,
        image_distance_mm=float(b),
        scopetwin_channel=ch,
        scopetwin_format="image/1",
    )
    spec = setup.channels[ch]
    affine, residual = object_to_pixel(setup, opt, ch, pose, unit.box, unit.half, return_residual=True)
    entry = {
        "image": fname,
        "path": list(spec.path),
        "filter": spec.filter,
        "image_distance_mm": float(b),
        "refocused_image_distance_mm": focus.image_distance_mm,
        "defocus_mm": sample.defocus[ch],
        "camera": {"tilt_deg": pose.tilt_deg, "offset_px": list(pose.offset_px)},
        **affine_truth(affine, setup.camera.pixel_um),
        "object_to_pixel_residual_px": residual,
        "rms_spot_um": res.rms_spot_um,
        "astigmatism_mm": res.astigmatism_mm,
        "transmitted_fraction": res.transmitted_fraction,
        "exposure_e_per_unit": exposure,
        "seeds": {"render": rseed, "noise": nseed},
    }
    return fname, img, entry


def _cmu_truth(
    cfg: DatasetConfig, sample: CmuSample, unit: _UnitRender, channels: dict[str, Any], plates: dict[str, Any]
) -> dict[str, Any]:
    """The sample's truth: target, window, sensor, per-channel truth, plates and every seed."""
    setup = sample.setup
    target = setup.target if sample.target == "star" else setup.cells
    sensor = unit.sensor
    return {
        "setup": setup.name,
        "scene": "cmu",
        "target": {"name": sample.target, **target.model_dump()},
        "window": list(unit.box),
        "stop": cfg.cmu.stop,
        "spp": cfg.dataset.spp,
        "sensor": None if sensor is None else {**dataclasses.asdict(sensor), "fill_fraction": unit.fill},
        "channels": channels,
        "plates": plates,
        "seeds": {
            "residual": {n: s.residual_seed for n, s in setup.splitters.items()},
            "cells": setup.cells.seed,
            "render": {c: v["seeds"]["render"] for c, v in channels.items()},
            "noise": {c: v["seeds"]["noise"] for c, v in channels.items()},
        },
        "setup_json": json.loads(setup.to_json()),
    }


def write_cmu(cfg: DatasetConfig, index: int, sample: CmuSample, stage: StagedOutput) -> dict[str, Any]:
    """One channel set of the four-channel unit (thesis §5.1.2, §5.2.2): an image per channel, the plates' maps, truth.

    Each camera sits at its channel's refocused image distance (the numpy tracer's RMS-spot focus, §5.1.2) plus
    the drawn defocus, with the drawn tilt and offset; the truth is the tracer's object->pixel map of that camera.

    Parameters
    ----------
    cfg : DatasetConfig
        The dataset's configuration (seeds, spp, noise, preview, the ``cmu`` table).
    index : int
        Sample index (seeds the render and noise of each channel).
    sample : CmuSample
        The sample's unit and camera poses (:func:`cmu_sample`).
    stage : StagedOutput
        Where the sample's files are written.

    Returns
    -------
    dict
        ``files`` (role -> file name) and ``truth``.
    """
    from scopetwin.scenes.cmu.plates import plate_heightmap
    from scopetwin.scenes.mitsuba.cmu import unit_scene

    setup = sample.setup
    files: dict[str, str] = {}
    elements = {**setup.splitters, **setup.mirrors}
    maps = {name: plate_heightmap(spec, setup.plate) for name, spec in elements.items()}
    plates = _write_plates(setup, maps, stage, files)
    noise = bool(cfg.dataset.noise or sample.exposure_fill is not None)
    unit = _UnitRender(
        maps=maps,
        scene=unit_scene(setup, maps),
        box=image_box(cfg, setup),
        sensor=cmu_sensor(setup.camera.bit_depth) if noise else None,
        fill=CMU_FILL_DEFAULT if sample.exposure_fill is None else float(sample.exposure_fill),
        half=0.5 * setup.target.frame_side if sample.target == "star" else 0.25 * min(setup.field_mm),
    )
    channels, images = {}, []
    for ch in sample.channels:
        fname, img, channels[ch] = _write_channel(cfg, index, sample, ch, unit, stage)
        files[f"image_{ch}"] = fname
        images.append(img)
    if cfg.dataset.preview:
        tiles = [im / (float(np.percentile(im, 99.9)) or 1.0) for im in images]
        write_preview(stage.path("preview.png"), np.hstack(tiles))
        files["preview"] = "preview.png"
    truth = _cmu_truth(cfg, sample, unit, channels, plates)
    if cfg.dataset.maps:
        from scopetwin.sim.datasets.maps import MAPS_FILE, MAPS_FORMAT, MAPS_VERSION, cmu_object_maps, write_maps

        _, _, h, w = unit.box
        object_maps = cmu_object_maps(channels, h, w)
        write_maps(stage.path(MAPS_FILE), object_maps, cfg.dataset.maps_compression)
        files["maps"] = MAPS_FILE
        truth["maps"] = {"file": MAPS_FILE, "format": f"{MAPS_FORMAT}/{MAPS_VERSION}", "layers": list(object_maps)}
    return {"files": files, "truth": truth}
