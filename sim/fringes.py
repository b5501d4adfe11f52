"""A rendered fringe measurement (phase-measuring deflectometry in the thesis §1.10 setup): render, sensor noise,
write and read back.

:func:`render_fringes` renders every frame of a ``[fringes]`` setup's sequence with Mitsuba
(:func:`scopetwin.scenes.mitsuba.fringes.render_fringe_frames`) and, with noise, applies the EMVA 1288 sensor model
(:func:`scopetwin.sim.measurement.apply_sensor`) to each frame with its own seed. The exposure is one for the whole
sequence — a phase-shifting decoder assumes the same offset A and modulation B in every step — : the setup's
``sensor.exposure_s`` or, without one, the exposure at which the brightest pixel of all frames fills the setup's
``fill_fraction`` of the full well.

A measurement folder (:func:`write_fringes`, :func:`read_fringes`) holds

* ``fringe_0000.exr`` ... one camera image per frame, in the sequence's order (docs/contract.md "Images": channel
  ``Y`` float32, the setup and the provenance in the header, plus ``scopetwin_fringe``: the frame as JSON);
* ``surface.exr``: the true height map (deflectometry);
* ``fringes.json``: ``format`` (:data:`FRINGES_VERSION`), ``kind`` = ``"fringes"``, ``shape`` [rows, cols],
  ``frames`` (``file``, ``direction``, ``period_mm``, ``shift_rad``), ``sequence`` (``periods_mm``, ``steps``),
  ``display`` (:meth:`scopetwin.scenes.fringes.FringeDisplay.to_dict`), ``setup`` (the setup's JSON),
  ``surface`` (file name or null), ``spp``, ``seed``, ``noise``, ``exposure_s`` (null without noise),
  ``noise_seeds`` (one per frame), ``seconds_per_frame`` and ``provenance`` (seed, spp, renderer, versions).

The folder is written through :class:`scopetwin.sim.measurement.StagedOutput` (every file staged, moved into place
when all succeeded) and read with :mod:`scopetwin.scenes.safe_read`'s checks: file names stay inside the folder, each
file is a regular file under its size limit, the format version is known, and every image's size is read from its
header and checked against the setup's camera (and all K images against this machine's memory) before decoding.

A second display position (the display moved along its normal by a stage, thesis §1.3: :attr:`FringeMeasurement.
second`) is written into the same folder with the prefix ``shifted_`` on every file (``shifted_fringe_0000.exr`` ...,
``shifted_surface.exr``, ``shifted_fringes.json``, its ``setup`` the moved one), as the marker render writes
``shifted_image.exr``; :func:`read_fringes` reads either JSON by its path.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.errors import FileFormatError, ScopetwinError, SetupError
from scopetwin.scenes.fringes import MAX_FRAMES, FringeDisplay, FringeFrame, FringeSequence
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap
from scopetwin.sim.measurement import StagedOutput, apply_sensor, check_rendered, provenance

FRINGES_FILE = "fringes.json"
FRINGES_KIND = "fringes"
FRINGES_VERSION = 1
#: The format versions :func:`read_fringes` reads.
READABLE_VERSIONS = frozenset({1})
SURFACE_FILE = "surface.exr"
RENDERER = "mitsuba-fringes"


def frame_file(index: int) -> str:
    """The image file name of frame ``index`` (``fringe_0000.exr``)."""
    return f"fringe_{index:04d}.exr"


@dataclass(frozen=True)
class FringeMeasurement:
    """The camera images of a fringe sequence and what they show.

    Attributes
    ----------
    images : ndarray
        (K, rows, cols) float32: linear irradiance, or digital numbers with ``noise``.
    frames : tuple of FringeFrame
        The frame of each image, in order (:meth:`scopetwin.scenes.fringes.FringeSequence.frames`).
    display : FringeDisplay
        The display that showed them.
    sequence : FringeSequence
        The sequence the frames come from.
    setup : Setup
        The setup (its ``[fringes]`` table holds the display and the sequence).
    heights : HeightMap or None
        The true surface (deflectometry).
    spp, seed : int
        Samples per pixel and the render seed.
    noise : bool
        Whether the EMVA 1288 sensor model was applied.
    exposure_s : float or None
        The one exposure of every frame (None without noise).
    noise_seeds : tuple of int
        The sensor-noise seed of each frame (derived from ``seed``).
    seconds_per_frame : tuple of float
        Wall time of each frame's render.
    provenance : dict
        Seed, spp, renderer and package versions (docs/contract.md, "Images").
    second : FringeMeasurement or None
        The same sequence with the display moved along its normal by a stage (its own setup; thesis §1.3).
    """

    images: NDArray[np.float32]
    frames: tuple[FringeFrame, ...]
    display: FringeDisplay
    sequence: FringeSequence
    setup: Setup
    heights: HeightMap | None
    spp: int
    seed: int
    noise: bool
    exposure_s: float | None = None
    noise_seeds: tuple[int, ...] = ()
    seconds_per_frame: tuple[float, ...] = ()
    provenance: dict[str, Any] = field(default_factory=dict)
    second: FringeMeasurement | None = None

    def frame_index(self, direction: str, period: int, step: int) -> int:
        """Position of a frame in :attr:`images` (:meth:`scopetwin.scenes.fringes.FringeSequence.index`)."""
        return self.sequence.index(direction, period, step)  # type: ignore[arg-type]


def noise_seeds(seed: int, count: int) -> tuple[int, ...]:
    """One 31-bit sensor-noise seed per frame, derived from ``seed`` (``SeedSequence([seed, k, crc32(name)])``)."""
    from scopetwin.sim.datasets.seeding import sample_seed

    return tuple(sample_seed(seed, k, "fringe sensor noise") for k in range(count))


def _fringe_parts(setup: Setup) -> tuple[FringeDisplay, FringeSequence]:
    display, sequence = setup.fringe_display, setup.fringe_sequence
    if display is None or sequence is None:
        raise SetupError(f"setup {setup.name} has no [fringes] table: it is a marker setup (render it with render)")
    return display, sequence


def render_fringes(
    setup: Setup,
    heights: HeightMap | None,
    spp: int | None = None,
    seed: int | None = None,
    noise: bool | None = None,
    variant: str | None = None,
) -> FringeMeasurement:
    """Render every frame of a ``[fringes]`` setup with Mitsuba; with ``noise``, the EMVA 1288 sensor model per frame.

    Parameters
    ----------
    setup : Setup
        A deflectometry or mirror setup with a ``[fringes]`` table.
    heights : HeightMap, optional
        The substrate's height map (deflectometry).
    spp, seed : int, optional
        Samples per pixel and the seed (default ``setup.render``); the render seed of every frame, and the root of
        the per-frame noise seeds (:func:`noise_seeds`).
    noise : bool, optional
        Apply the sensor model (default ``setup.render.noise``) with one exposure for all frames (module docstring).
    variant : str, optional
        Mitsuba variant (default ``choose("mono")``).

    Raises
    ------
    SetupError
        A setup without ``[fringes]``, or a deflectometry setup without ``heights``.
    ScopetwinError
        A frame renders non-finite or all black.
    LimitError
        The images or the render time exceed this machine's limits (before anything is rendered).
    """
    from scopetwin.scenes.mitsuba.fringes import render_fringe_frames

    display, sequence = _fringe_parts(setup)
    spp = int(spp or setup.render.spp)
    seed = int(setup.render.seed if seed is None else seed)
    noise = bool(setup.render.noise if noise is None else noise)
    frames = sequence.frames()
    images, seconds = render_fringe_frames(setup, heights, frames, display, spp, seed, variant)
    for k in range(len(frames)):
        check_rendered(images[k], f"the render of {setup.name}, fringe frame {k}")
    exposure: float | None = None
    seeds: tuple[int, ...] = ()
    if noise:
        t0 = time.perf_counter()
        exposure = setup.sensor.exposure_s
        if exposure is None:
            sensor = setup.sensor.sensor()
            exposure = sensor.exposure_for(
                float(images.max()), setup.sensor.photons_per_unit_s, setup.sensor.fill_fraction
            )
        fixed = setup.model_copy(update={"sensor": setup.sensor.model_copy(update={"exposure_s": exposure})})
        seeds = noise_seeds(seed, len(frames))
        for k in range(len(frames)):
            images[k] = apply_sensor(fixed, images[k], seeds[k])
        share = (time.perf_counter() - t0) / len(frames)
        seconds = [s + share for s in seconds]
    return FringeMeasurement(
        images,
        frames,
        display,
        sequence,
        setup,
        heights,
        spp,
        seed,
        noise,
        exposure,
        seeds,
        tuple(seconds),
        provenance(seed, spp, RENDERER),
    )


def render_second_fringes(
    setup: Setup,
    heights: HeightMap | None,
    spp: int | None = None,
    seed: int | None = None,
    noise: bool | None = None,
    shift_mm: float | None = None,
    variant: str | None = None,
) -> FringeMeasurement:
    """The sequence at the second display position of a stage (thesis §1.3): the same scene with the display moved
    ``shift_mm`` along its normal N_z (default: the setup's ``[pattern_stage]``), rendered as :func:`render_fringes`
    renders the first, with seed ``seed + 1`` (its own samplers and sensor noise); its ``setup`` is the moved one.

    Raises
    ------
    SetupError
        No shift given and no ``[pattern_stage]`` table, a shift of 0, or as :func:`render_fringes`.
    """
    from scopetwin.scenes.pattern_stage import shift_pattern, stage_shift

    moved = shift_pattern(setup, stage_shift(setup, shift_mm))
    first_seed = int(setup.render.seed if seed is None else seed)
    return render_fringes(moved, heights, spp, (first_seed + 1) % 2**32, noise, variant)


def write_fringes(stage: StagedOutput, measurement: FringeMeasurement, prefix: str = "") -> dict[str, Any]:
    """Write a measurement's images, surface and ``fringes.json`` into a staging folder (module docstring), every
    file name with ``prefix`` (``"shifted_"`` for a second display position). :attr:`FringeMeasurement.second` is
    not written here (the caller writes it with its prefix).

    Returns
    -------
    dict
        ``{"images": [file names], "fringes": "fringes.json", "surface": name or None}``.
    """
    from scopetwin.scenes.io import write_heightmap, write_image, write_json_atomic

    m = measurement
    setup_json = m.setup.to_json()
    files = [prefix + frame_file(k) for k in range(len(m.frames))]
    for k, (name, frame) in enumerate(zip(files, m.frames, strict=True)):
        write_image(
            stage.path(name), m.images[k], setup_json, m.provenance, scopetwin_fringe=json.dumps(frame.to_dict())
        )
    surface = None
    if m.heights is not None:
        surface = prefix + SURFACE_FILE
        write_heightmap(stage.path(surface), m.heights)
    rows, cols = m.images.shape[1:]
    data = {
        "format": FRINGES_VERSION,
        "kind": FRINGES_KIND,
        "shape": [int(rows), int(cols)],
        "frames": [{"file": name, **frame.to_dict()} for name, frame in zip(files, m.frames, strict=True)],
        "sequence": m.sequence.to_dict(),
        "display": m.display.to_dict(),
        "setup": json.loads(setup_json),
        "surface": surface,
        "spp": m.spp,
        "seed": m.seed,
        "noise": m.noise,
        "exposure_s": m.exposure_s,
        "noise_seeds": list(m.noise_seeds),
        "seconds_per_frame": list(m.seconds_per_frame),
        "provenance": m.provenance,
    }
    write_json_atomic(stage.path(prefix + FRINGES_FILE), data)
    return {"images": files, "fringes": prefix + FRINGES_FILE, "surface": surface}


def save_fringes(measurement: FringeMeasurement, out: str | Path) -> dict[str, Any]:
    """Write a measurement to the folder ``out`` atomically (staged beside it, moved into place when complete).

    Returns
    -------
    dict
        ``{"images": [paths], "fringes": path, "surface": path or None}``.
    """
    stage = StagedOutput(Path(out))
    try:
        names = write_fringes(stage, measurement)
        moved = stage.commit()
    except BaseException:
        stage.discard()
        raise
    return {
        "images": [str(moved[n]) for n in names["images"]],
        "fringes": str(moved[names["fringes"]]),
        "surface": None if names["surface"] is None else str(moved[names["surface"]]),
    }


def _number(data: dict[str, Any], key: str, kind: type, what: str) -> Any:
    value = data.get(key)
    if isinstance(value, bool) != (kind is bool) or not isinstance(value, kind):
        raise FileFormatError(f"{what}: {key!r} must be {kind.__name__}, got {value!r:.80}")
    return value


def _numbers(data: dict[str, Any], key: str, kind: Any, what: str) -> list[Any]:
    value = data.get(key, [])
    if not isinstance(value, list) or len(value) > MAX_FRAMES:
        raise FileFormatError(f"{what}: {key!r} must be a list of at most {MAX_FRAMES} numbers")
    if any(isinstance(v, bool) or not isinstance(v, kind) for v in value):
        raise FileFormatError(f"{what}: {key!r} must hold numbers only")
    return value


def _description(
    data: dict[str, Any], what: str
) -> tuple[Setup, FringeDisplay, FringeSequence, list[object], list[FringeFrame]]:
    """The setup, display, sequence, frame file names and frames of a ``fringes.json`` (names not yet checked).

    Raises
    ------
    FileFormatError
        A part missing, of the wrong type or out of range (the message names it).
    """
    from scopetwin.scenes.setup import setup_from_dict

    try:
        setup_data = data.get("setup")
        if not isinstance(setup_data, dict):
            raise SetupError("setup must be an object")
        setup = setup_from_dict(setup_data, what)
        display = FringeDisplay.from_dict(data.get("display"))
        seq = data.get("sequence")
        if not isinstance(seq, dict) or set(seq) != {"periods_mm", "steps"} or not isinstance(seq["periods_mm"], list):
            raise SetupError(f"sequence must be an object {{periods_mm: [...], steps: N}}, got {seq!r:.120}")
        sequence = FringeSequence(tuple(seq["periods_mm"]), seq["steps"])
        listed = data.get("frames")
        if not isinstance(listed, list) or not 1 <= len(listed) <= MAX_FRAMES:
            raise SetupError(f"frames must be a list of 1 to {MAX_FRAMES} frames")
        files: list[object] = []
        frames = []
        for entry in listed:
            if not isinstance(entry, dict):
                raise SetupError(f"a frame must be an object, got {entry!r:.80}")
            entry = dict(entry)
            files.append(entry.pop("file", None))
            frames.append(FringeFrame.from_dict(entry))
    except (ScopetwinError, TypeError, ValueError) as exc:
        raise FileFormatError(f"{what}: {exc}") from None
    return setup, display, sequence, files, frames


def read_fringes(folder: str | Path) -> FringeMeasurement:
    """Read a measurement folder written by :func:`write_fringes`, every name and size checked before decoding.

    ``folder`` is the folder (its ``fringes.json`` is read) or the path of a JSON file in it (``fringes.json``,
    ``shifted_fringes.json``); the files it names are read from its folder.

    Raises
    ------
    scopetwin.scenes.safe_read.UnsafeInput
        ``fringes.json`` or a file it names is missing, leaves the folder, is not a regular file or is too large;
        a format newer than this scopetwin reads; an image whose header declares another size than the setup's
        camera.
    FileFormatError
        A field missing or of the wrong type, a frame list that is empty, too long, names a file twice or is not the
        sequence's frames in order, an invalid setup or display, or an unreadable image.
    LimitError
        The K images do not fit in this machine's memory.
    """
    from scopetwin.scenes.io import read_heightmap, read_image
    from scopetwin.scenes.limits import FLOATS_PER_PIXEL, check_image_size
    from scopetwin.scenes.safe_read import check_format, read_json_inside, resolve_inside

    root, name = Path(folder), FRINGES_FILE
    if root.suffix.lower() == ".json" and not root.is_dir():
        root, name = root.parent, root.name
    if not root.is_dir():
        raise FileFormatError(f"fringe measurement {root}: not a folder")
    what = f"{root / name}"
    data = read_json_inside(root, name, f"fringe measurement's {name}")
    check_format(data.get("format"), READABLE_VERSIONS, what)
    if data.get("kind") != FRINGES_KIND:
        raise FileFormatError(f"{what}: kind must be {FRINGES_KIND!r}, got {data.get('kind')!r:.80}")
    setup, display, sequence, files, frames = _description(data, what)
    spp = _number(data, "spp", int, what)
    seed = _number(data, "seed", int, what)
    noise = _number(data, "noise", bool, what)
    cam = setup.camera_model
    shape = (cam.ny, cam.nx)
    if data.get("shape") != list(shape):
        raise FileFormatError(f"{what}: shape {data.get('shape')!r:.40} is not the setup camera's {list(shape)}")
    if len(set(map(str, files))) != len(files):
        raise FileFormatError(f"{what}: two frames name the same file")
    if tuple(frames) != sequence.frames():
        raise FileFormatError(
            f"{what}: its {len(frames)} frames are not the {len(sequence)} frames of its sequence, in order"
        )
    # all K images at once, checked before the first is decoded
    check_image_size(cam.nx, cam.ny, f"{what}: {len(files)} images", FLOATS_PER_PIXEL + len(files))
    paths = [resolve_inside(root, name, f"{what} frame {k}") for k, name in enumerate(files)]
    images = np.empty((len(paths), *shape), dtype=np.float32)
    for k, path in enumerate(paths):
        images[k], _ = read_image(path, shape)
    heights = None
    if data.get("surface") is not None:
        heights = read_heightmap(resolve_inside(root, data["surface"], f"{what} surface"))
    exposure = data.get("exposure_s")
    if exposure is not None and (isinstance(exposure, bool) or not isinstance(exposure, int | float)):
        raise FileFormatError(f"{what}: exposure_s must be a number or null, got {exposure!r:.80}")
    prov = data.get("provenance")
    return FringeMeasurement(
        images,
        tuple(frames),
        display,
        sequence,
        setup,
        heights,
        spp,
        seed,
        noise,
        None if exposure is None else float(exposure),
        tuple(int(s) for s in _numbers(data, "noise_seeds", int, what)),
        tuple(float(s) for s in _numbers(data, "seconds_per_frame", int | float, what)),
        prov if isinstance(prov, dict) else {},
    )


@dataclass(frozen=True)
class DisplayCalibrationImages:
    """The two calibration images of a fringe setup (thesis §2.7) with the display showing the marker pattern.

    Attributes
    ----------
    target_setup, mirror_setup : Setup
        The §2.8.3 target on the holding frame and the display seen in a flat mirror on it, both by the fringe
        setup's camera (:func:`scopetwin.sim.pipeline.calibration_setups`).
    target_image, mirror_image : ndarray
        float32 (rows, cols): the target's render and the display's (showing the marker pattern of the setup's
        ``[pattern]`` through its pixels, look-up table, bit depth and blur), with the sensor model where asked.
    """

    target_setup: Setup
    mirror_setup: Setup
    target_image: NDArray[np.float32]
    mirror_image: NDArray[np.float32]


def render_display_calibration(
    setup: Setup, spp: int, seed: int, noise: bool = False, variant: str | None = None
) -> DisplayCalibrationImages:
    """Render the setup calibration's two images of a fringe setup, the display showing the marker pattern.

    A display can show the marker pattern itself (thesis §1.6.3: each display pixel the pattern's grey value at its
    centre, :meth:`scopetwin.scenes.fringes.FringeDisplay.marker_values`), so the calibration of thesis §2.7 finds
    the display's pose as it finds a printed pattern's: the mirror image is rendered with the display's emitter
    (:func:`scopetwin.scenes.mitsuba.fringes.render_display_image`), the target image as any (seed + 1). With
    ``noise`` each gets the EMVA 1288 sensor model (:func:`scopetwin.sim.measurement.apply_sensor`).

    Raises
    ------
    SetupError
        A setup without ``[fringes]`` or without a substrate.
    """
    from scopetwin.scenes.mitsuba.fringes import render_display_image
    from scopetwin.scenes.mitsuba.render import render_setup
    from scopetwin.sim.pipeline import calibration_setups

    display, _ = _fringe_parts(setup)
    if setup.substrate is None:
        raise SetupError(f"setup {setup.name} has no substrate: its calibration needs the holding frame")
    target_setup, mirror_setup = calibration_setups(setup)
    values = display.marker_values(mirror_setup.marker_pattern)
    mirror = check_rendered(
        render_display_image(mirror_setup, None, display, values, spp, seed, variant), "the display in the mirror"
    )
    target = check_rendered(render_setup(target_setup, None, spp=spp, seed=seed + 1), "the calibration target")
    if noise:
        mirror = apply_sensor(mirror_setup, mirror, seed)
        target = apply_sensor(target_setup, target, seed + 1)
    return DisplayCalibrationImages(target_setup, mirror_setup, target, mirror)


def calibrate_display(setup: Setup, images: DisplayCalibrationImages) -> Any:
    """The fringe setup calibrated from its two calibration images (thesis §2.7,
    :func:`scopetwin.calib.setup_calibration.calibrate_setup_from_images` with the fringe setup as the nominal one):
    the calibrated setup keeps its ``[fringes]`` table, its pattern pose is the display's.

    Returns
    -------
    scopetwin.calib.setup_calibration.CalibratedSetup
    """
    from scopetwin.calib.setup_calibration import calibrate_setup_from_images

    _fringe_parts(setup)
    return calibrate_setup_from_images(
        images.target_image,
        images.mirror_image,
        images.target_setup,
        images.mirror_setup,
        nominal=setup,
        comment="fringe setup calibrated as in thesis §2.7, the display showing the marker pattern",
        image_names=("target image", "display in the mirror"),
    )


__all__ = [
    "DisplayCalibrationImages",
    "calibrate_display",
    "render_display_calibration",
    "FRINGES_FILE",
    "FRINGES_VERSION",
    "FringeMeasurement",
    "frame_file",
    "noise_seeds",
    "read_fringes",
    "render_fringes",
    "render_second_fringes",
    "save_fringes",
    "write_fringes",
]
