"""What a dataset's files must be: the JSON Schemas shipped with scopetwin, and the checks of their values.

The schemas (``scopetwin/sim/datasets/schemas/*.schema.json``, package data; docs/contract.md "Datasets") describe
``dataset.json``, ``sample.json``, ``truth.json`` and the channel set of every EXR of a sample, each for one format
version (their ``$id`` ends in it). :func:`check_sample` validates one finished sample against them and checks its
values — every number finite and in range, every image finite and carrying signal, the maps consistent — which is
what ``scopetwin dataset verify`` runs on every sample. :func:`check_image` is the check every sample writer runs on
a render before it is written (a black or non-finite render is refused, never listed).

The files are read through :mod:`scopetwin.scenes.safe_read`: names kept inside the sample folder, regular files
only, JSON of bounded depth, ``sample.json`` and ``truth.json`` of a format this scopetwin reads, and every image's
and map's size checked from its EXR header against the sample's camera before it is decoded. A file that fails one
of these checks makes the sample invalid, with the reason.
"""

from __future__ import annotations

import json
from collections.abc import Collection
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.inputs import parse_json
from scopetwin.scenes.safe_read import check_format, read_json_inside, resolve_inside

#: The schema files and the format version each validates.
SCHEMAS = {"dataset": 2, "sample": 2, "truth": 2, "exr": 1}
#: The format of an EXR without a ``scopetwin_format`` header attribute, by its file name.
LEGACY_EXR_FORMAT = {"image": "image/1", "fringe_": "image/1", "surface": "heightmap/1", "height_": "heightmap/1"}


class InvalidImage(ScopetwinError):
    """A render or image whose values cannot be true: non-finite, or carrying no signal (constant, all black)."""


def check_image(image: NDArray[Any], what: str) -> None:
    """Refuse an image that has non-finite values or carries no signal (all pixels equal, or none above zero).

    Raises
    ------
    InvalidImage
        The message says which and names ``what``.
    """
    reason = image_problem(image)
    if reason is not None:
        raise InvalidImage(f"{what} {reason}; nothing is written for it")


def image_problem(image: NDArray[Any]) -> str | None:
    """Why an image cannot be a true image (non-finite values, no signal), or None."""
    a = np.asarray(image)
    if a.size == 0:
        return "is empty"
    finite = np.isfinite(a)
    if not finite.all():
        return f"has {int(a.size - finite.sum())} non-finite pixel(s)"
    hi, lo = float(a.max()), float(a.min())
    if not hi > 0:
        return "is black (no pixel above 0)"
    if hi == lo:
        return f"carries no signal (every pixel is {hi:g})"
    return None


@cache
def schema(name: str) -> dict[str, Any]:
    """The shipped JSON Schema ``name`` (``dataset``, ``sample``, ``truth``, ``exr``)."""
    from importlib.resources import files

    text = (files("scopetwin.sim.datasets") / "schemas" / f"{name}.schema.json").read_text()
    return dict(json.loads(text))


def schema_errors(data: Any, name: str) -> list[str]:
    """The ways ``data`` breaks schema ``name`` (JSON paths and messages; empty when it is valid)."""
    from jsonschema import Draft202012Validator

    validator = Draft202012Validator(schema(name))
    out = []
    for err in sorted(validator.iter_errors(data), key=lambda e: list(map(str, e.absolute_path))):
        where = "/".join(str(p) for p in err.absolute_path) or "(top level)"
        out.append(f"{where}: {err.message}")
    return out


def sample_image_shape(truth: dict[str, Any], kind: str) -> tuple[int, int] | None:
    """(rows, cols) of a sample's images and maps as its truth gives them: the camera's pixels of a Part I sample
    (``setup_json`` ``camera.pixels``), the window of a ``cmu`` sample; None where the truth does not say.

    Raises
    ------
    ScopetwinError
        The truth gives a size that is not two positive integers.
    """
    try:
        if kind in ("deflectometry", "calibration") and truth.get("setup_json") is not None:
            setup = truth["setup_json"]
            if isinstance(setup, str):
                setup = parse_json(setup, "truth.json", "setup_json")
            nx, ny = setup["camera"]["pixels"]
            rows, cols = ny, nx
        elif kind == "cmu" and "window" in truth:
            _, _, rows, cols = truth["window"]
        else:
            return None
        if isinstance(rows, bool) or isinstance(cols, bool) or not (isinstance(rows, int) and isinstance(cols, int)):
            raise TypeError("not integers")
        if min(rows, cols) < 1:
            raise ValueError("not positive")
    except (KeyError, TypeError, ValueError) as exc:
        raise ScopetwinError(f"truth.json does not give the image size as two positive integers ({exc})") from None
    return rows, cols


def _exr_header(path: Path) -> dict[str, Any]:
    import OpenEXR

    try:
        return dict(OpenEXR.File(str(path), header_only=True).header())
    except Exception as exc:  # OpenEXR raises bare RuntimeError/ValueError on corrupt files
        raise ScopetwinError(f"{path.name} is not a readable OpenEXR file ({exc})") from None


def exr_format(path: Path, header: dict[str, Any] | None = None) -> str:
    """The format of an EXR's channel set (``image/1``, ``heightmap/1``, ``normals/1``, ``maps/1``): its header's
    ``scopetwin_format``, else format 1 of its file's role (``image*``, ``surface*``, ``height_*``)."""
    fmt = (header if header is not None else _exr_header(path)).get("scopetwin_format")
    if fmt is None:
        fmt = next((v for k, v in LEGACY_EXR_FORMAT.items() if path.name.startswith(k)), "unknown")
    return str(fmt)


def exr_description(path: Path, kind: str) -> dict[str, Any]:
    """What the ``exr`` schema validates of an EXR file: its format, channels and header attribute names."""
    header = _exr_header(path)
    channels = sorted(c.name for c in header.get("channels", []))
    fmt = exr_format(path, header)
    return {"file": path.name, "kind": kind, "format": fmt, "channels": channels, "attributes": sorted(header)}


def _finite(value: Any) -> bool:
    """Whether every number in a JSON value is finite (None counts as no number)."""
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
    if isinstance(value, list):
        return all(_finite(v) for v in value)
    if isinstance(value, float):
        return bool(np.isfinite(value))
    return True


def _truth_problems(truth: dict[str, Any], index: int) -> list[str]:
    from scopetwin.sim.datasets.config import DatasetError, check_parameters

    out = []
    try:
        check_parameters(truth.get("parameters", {}), index)
    except DatasetError as exc:
        out.append(f"truth.json: {exc}")
    for key in ("parameters", "camera", "camera_opencv", "markers", "channels", "magnification", "image_distance_mm"):
        if key in truth and not _finite(truth[key]):
            out.append(f"truth.json: {key} holds a non-finite number")
    if truth.get("sample", index) != index:
        out.append(f"truth.json: sample {truth.get('sample')} in the folder of sample {index}")
    return out


def _maps_problems(maps: dict[str, NDArray[Any]], shape: tuple[int, ...]) -> list[str]:
    """Consistency of the per-pixel maps (module :mod:`~scopetwin.sim.datasets.maps`)."""
    out = []
    for name, arr in maps.items():
        if arr.shape[:2] != shape:
            out.append(f"maps.exr: {name} is {arr.shape[:2]}, the image {shape}")
    if out or "mask" not in maps:
        return out
    mask = maps["mask"]
    if not mask.any():
        out.append("maps.exr: no pixel sees the reflecting element or the target (mask is empty)")
    for name in ("point", "surface_xy", "height", "normal"):
        if name in maps:
            a = maps[name].reshape(*shape, -1)
            if not np.isfinite(a[mask]).all() or np.isfinite(a[~mask]).any():
                out.append(f"maps.exr: {name} is not finite exactly where mask is 1")
    if "normal" in maps:
        n = maps["normal"][mask]
        if n.size and not np.allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5):
            out.append("maps.exr: normal is not of unit length")
    if "marker_id" in maps and "marker" in maps:
        ids, ij = maps["marker_id"], maps["marker"]
        if (ids < -1).any() or not np.array_equal(ids >= 0, np.isfinite(ij).all(axis=-1)):
            out.append("maps.exr: marker and marker_id disagree (marker_id -1 exactly where marker is NaN)")
        if "pattern_xy" in maps and not np.isfinite(maps["pattern_xy"][ids >= 0]).all():
            out.append("maps.exr: a pixel with a marker has no pattern_xy")
    return out


def _fringe_problems(folder: Path, files: dict[str, Any]) -> tuple[list[str], tuple[int, ...] | None]:
    """A fringe sample's frames checked with their ``fringes.json`` (:func:`scopetwin.sim.fringes.read_fringes`:
    names inside the folder, format, sizes from the headers against the setup's camera): the frames it lists are the
    sample's ``fringe_*.exr`` files, and each frame is finite and carries signal. Returns the problems and the
    frames' (rows, cols) (None where they could not be read)."""
    from scopetwin.sim.fringes import FRINGES_FILE, read_fringes

    listed_frames = sorted(n for n in files if n.startswith("fringe_") and n.endswith(".exr"))
    try:
        data = read_json_inside(folder, FRINGES_FILE, FRINGES_FILE)
        frames = data.get("frames")
        if not isinstance(frames, list) or not all(isinstance(f, dict) for f in frames):
            return [f"{FRINGES_FILE}: frames must be a list of objects"], None
        named = sorted(str(f.get("file")) for f in frames)
        if named != listed_frames:
            return [f"{FRINGES_FILE}: lists frames {named[:4]}... but the sample holds {listed_frames[:4]}..."], None
        m = read_fringes(folder)
    except ScopetwinError as exc:
        return [f"{FRINGES_FILE}: {exc}"], None
    problems = []
    for k in range(len(m.images)):
        reason = image_problem(m.images[k])
        if reason is not None:
            problems.append(f"fringe frame {k} {reason}")
    return problems, tuple(m.images.shape[1:])


def check_sample(folder: Path, fmt: int, readable: Collection[int]) -> list[str]:
    """Every way a finished sample (its hashes already checked) breaks its format's schemas or holds values that
    cannot be true; empty when it is valid.

    Format 2 samples are validated against the schemas (``sample``, ``truth``, ``exr``) and their values checked;
    format 1 samples (written before the schemas) have their values checked only. ``sample.json`` and
    ``truth.json`` must be of a format in ``readable`` (the formats this scopetwin reads).
    """
    from scopetwin.scenes.io import read_heightmap, read_image
    from scopetwin.sim.datasets.maps import MAPS_FILE, read_maps
    from scopetwin.sim.fringes import FRINGES_FILE

    problems: list[str] = []
    try:
        body = read_json_inside(folder, "sample.json", "sample.json")
        check_format(body.get("format", 1), readable, "sample.json")
        index = int(body.get("index", -1))
    except (ScopetwinError, TypeError, ValueError) as exc:
        return [f"sample.json: {exc}"]
    kind = str(body.get("kind", ""))
    try:
        truth = read_json_inside(folder, "truth.json", "truth.json")
        check_format(truth.get("format", 1), readable, "truth.json")
        image_shape = sample_image_shape(truth, kind)
    except ScopetwinError as exc:
        return [f"truth.json: {exc}"]
    if fmt >= 2:
        problems += [f"sample.json: {e}" for e in schema_errors(body, "sample")]
        problems += [f"truth.json: {e}" for e in schema_errors(truth, "truth")]
    problems += _truth_problems(truth, index)
    surface = truth.get("surface")
    if surface is not None:
        try:
            resolve_inside(folder, surface, "truth.json surface")
            if surface not in body.get("files", {}):
                problems.append(f"truth.json: surface {surface!r} is not a file of the sample")
        except ScopetwinError as exc:
            problems.append(str(exc))
    shape: tuple[int, ...] | None = None
    if FRINGES_FILE in body.get("files", {}):
        fringe_problems, shape = _fringe_problems(folder, body["files"])
        problems += fringe_problems
    for name in sorted(body.get("files", {})):
        if not name.endswith(".exr"):
            continue
        try:
            path = resolve_inside(folder, name, name)
            if fmt >= 2:
                desc = exr_description(path, kind)
                problems += [f"{name}: {e}" for e in schema_errors(desc, "exr")]
                listed = body["files"][name].get("format")
                if listed is not None and listed != desc["format"]:
                    problems.append(f"{name}: sample.json lists format {listed}, the file is {desc['format']}")
            if name.startswith("image"):
                img, _ = read_image(path, image_shape)
                reason = image_problem(img)
                if reason is not None:
                    problems.append(f"{name} {reason}")
                shape = img.shape
            elif name.startswith("fringe_"):
                pass  # the frames: read and checked with their fringes.json (_fringe_problems)
            elif name.startswith(("surface", "height_")):
                read_heightmap(path)  # refuses non-finite heights, bad extents
            elif name == MAPS_FILE:
                maps = read_maps(path, image_shape)
                if kind in ("deflectometry", "calibration") and shape is not None:
                    problems += _maps_problems(maps, shape)
                else:  # object coordinates: NaN beyond the objective's field is legitimate, infinities are not
                    bad = [k for k, v in maps.items() if np.isinf(v).any() or not np.isfinite(v).any()]
                    problems += [f"maps.exr: {k} holds infinite values or no finite one" for k in bad]
        except ScopetwinError as exc:
            problems.append(f"{name}: {exc}")
    return problems
