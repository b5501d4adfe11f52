"""OpenEXR files of the contract (docs/contract.md, "Files"): images (channel ``Y``) and height maps (channel ``Z``).

Writes are atomic: the file is written next to its destination under a
temporary name and moved into place with :func:`os.replace`, so a reader never
sees a half-written file and a failure leaves nothing behind.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import OpenEXR
from numpy.typing import NDArray

from scopetwin.scenes.errors import FileFormatError
from scopetwin.scenes.surface import HeightMap

EXTENT_KEYS = ("x_min_mm", "x_max_mm", "y_min_mm", "y_max_mm")
_UMASK = os.umask(0o022)
os.umask(_UMASK)
_RESERVED = {
    "channels",
    "compression",
    "dataWindow",
    "displayWindow",
    "lineOrder",
    "pixelAspectRatio",
    "screenWindowCenter",
    "screenWindowWidth",
    "type",
}


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; move it onto ``path`` only if the block succeeds."""
    dest = Path(path)
    dest.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{dest.name}.", suffix=".part" + dest.suffix, dir=dest.parent)
    os.close(fd)
    os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; a finished file gets the usual permissions
    try:
        yield Path(tmp)
        os.replace(tmp, dest)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)


def exr_write_error(path: str | Path, exc: RuntimeError) -> OSError:
    """The OSError for OpenEXR's RuntimeError on a failed write (ENOSPC when the disk is full), naming ``path``."""
    text = str(exc)
    if "No space left on device" in text:
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
    return OSError(errno.EIO, f"could not write the EXR file ({text})", str(path))


def write_text_atomic(path: str | Path, text: str) -> None:
    """Write a text file atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json_atomic(path: str | Path, data: Any) -> None:
    """Write JSON atomically (indented, keys in the given order)."""
    write_text_atomic(path, json.dumps(data, indent=2) + "\n")


def _write_exr(
    path: str | Path, channel: str, data: NDArray, attrs: dict[str, Any], extra: dict[str, NDArray] | None = None
) -> None:
    arr = np.ascontiguousarray(np.asarray(data, dtype=np.float32))
    if arr.ndim != 2:
        raise FileFormatError(f"an EXR channel must be a 2-D array, got shape {arr.shape}")
    channels = {channel: arr}
    for name, values in (extra or {}).items():
        more = np.ascontiguousarray(np.asarray(values, dtype=np.float32))
        if more.shape != arr.shape:
            raise FileFormatError(f"EXR channel {name!r} is {more.shape}, channel {channel!r} is {arr.shape}")
        channels[name] = more
    header: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    for key, value in attrs.items():
        if key in _RESERVED:
            raise FileFormatError(f"EXR attribute name {key!r} is reserved")
        header[key] = value if isinstance(value, str | float | int) else json.dumps(value)
    with atomic_path(path) as tmp:
        try:
            OpenEXR.File(header, channels).write(str(tmp))
        except RuntimeError as exc:
            raise exr_write_error(path, exc) from None


def _read_exr(path: str | Path, channel: str) -> tuple[NDArray[np.float32], dict[str, Any]]:
    p = Path(path)
    if not p.is_file():
        raise FileFormatError(f"EXR file {p} does not exist")
    try:
        f = OpenEXR.File(str(p), separate_channels=True)
        channels = f.channels()
        header = dict(f.header())
    except Exception as exc:  # OpenEXR raises bare RuntimeError/ValueError on corrupt files
        raise FileFormatError(f"{p} is not a readable OpenEXR file ({exc})") from None
    if channel not in channels:
        raise FileFormatError(f"{p} has no channel {channel!r} (channels: {', '.join(sorted(channels)) or 'none'})")
    data = np.asarray(channels[channel].pixels, dtype=np.float32)
    attrs = {k: v for k, v in header.items() if k not in _RESERVED}
    return data, attrs


def write_image(
    path: str | Path,
    image: NDArray,
    setup_json: str | None = None,
    provenance: dict[str, Any] | None = None,
    **attrs: Any,
) -> None:
    """Write a camera image: channel ``Y`` float32, setup and provenance as header attributes."""
    extra: dict[str, Any] = dict(attrs)
    if setup_json is not None:
        extra["scopetwin_setup"] = setup_json
    if provenance is not None:
        extra["scopetwin_provenance"] = json.dumps(provenance)
    _write_exr(path, "Y", image, extra)


def read_image(path: str | Path) -> tuple[NDArray[np.float32], dict[str, Any]]:
    """Read a camera image (channel ``Y``) and its header attributes.

    Raises
    ------
    FileFormatError
        Missing or unreadable file, no ``Y`` channel, or non-finite pixels.
    """
    data, attrs = _read_exr(path, "Y")
    if not np.all(np.isfinite(data)):
        raise FileFormatError(f"{path}: image channel Y contains NaN or infinite values")
    return data, attrs


def write_heightmap(path: str | Path, heights: HeightMap, std: HeightMap | None = None, **attrs: Any) -> None:
    """Write a height map in the contract's format (channel ``Z`` in mm, extents as header attributes).

    ``std``: the per-node standard uncertainty of a reconstruction on the same nodes, written as channel ``Z_std``
    (mm; docs/contract.md, "Height maps").
    """
    extents = dict(zip(EXTENT_KEYS, (heights.x_min, heights.x_max, heights.y_min, heights.y_max), strict=True))
    extra = None
    if std is not None:
        if std.z.shape != heights.z.shape:
            raise FileFormatError(f"Z_std has {std.z.shape} nodes but Z has {heights.z.shape}")
        extra = {"Z_std": std.z}
    _write_exr(path, "Z", heights.z, {**extents, **attrs}, extra)


def read_heightmap_std(path: str | Path) -> HeightMap | None:
    """The ``Z_std`` channel of a height-map EXR (per-node standard uncertainty, mm), or None when it has none."""
    hm = read_heightmap(path)
    try:
        data, _ = _read_exr(path, "Z_std")
    except FileFormatError:
        return None
    return HeightMap(data.astype(np.float64), hm.x_min, hm.x_max, hm.y_min, hm.y_max)


def read_heightmap(path: str | Path) -> HeightMap:
    """Read a height-map EXR (channel ``Z``, extents ``x_min_mm`` ... ``y_max_mm``).

    Raises
    ------
    FileFormatError
        Missing/unreadable file, missing channel or extent attribute, or invalid heights.
    """
    data, attrs = _read_exr(path, "Z")
    missing = [k for k in EXTENT_KEYS if k not in attrs]
    if missing:
        raise FileFormatError(f"{path}: height map lacks the header attribute(s) {', '.join(missing)}")
    try:
        ext = [float(attrs[k]) for k in EXTENT_KEYS]
    except (TypeError, ValueError):
        raise FileFormatError(f"{path}: height-map extents must be numbers") from None
    from scopetwin.scenes.errors import GeometryError

    try:
        return HeightMap(data.astype(np.float64), *ext)
    except GeometryError as exc:
        raise FileFormatError(f"{path}: {exc}") from None
