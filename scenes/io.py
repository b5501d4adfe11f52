"""OpenEXR files of the contract (docs/contract.md, "Files"): images (channel ``Y``) and height maps (channel ``Z``).

Writes are atomic: the file is written next to its destination under a
temporary name and moved into place with :func:`os.replace`, so a reader never
sees a half-written file and a failure leaves nothing behind. The temporary
file is made by :func:`tempfile.mkstemp` (``O_EXCL``: never a file or link that
was there), and :func:`os.replace` replaces a symbolic link at the destination
rather than following it. :func:`open_append` opens a log for appending without
following a link. Nothing here writes through a link scopetwin did not make.

:func:`check_surface` refuses a height map that cannot be a substrate's surface
(heights beyond ±:data:`MAX_HEIGHT_MM`, an extent short of the substrate).
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import stat
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np
import OpenEXR
from numpy.typing import NDArray

from scopetwin.scenes.errors import FileFormatError, ScopetwinError
from scopetwin.scenes.inputs import check_input_file, native_output_captured
from scopetwin.scenes.limits import FLOATS_PER_PIXEL
from scopetwin.scenes.safe_read import check_exr_header

if TYPE_CHECKING:
    from scopetwin.scenes.surface import HeightMap

EXTENT_KEYS = ("x_min_mm", "x_max_mm", "y_min_mm", "y_max_mm")
#: The largest absolute height a substrate's surface may have, mm (bows are µm to a few mm; thesis §1.9).
MAX_HEIGHT_MM = 10.0
#: How far (relative to the substrate's size) a height map's extent may fall short of the substrate's edge.
COVER_TOLERANCE = 1e-6
#: 4-byte numbers per node of a height map read from a file: as for a setup's generated surface grid
#: (``scopetwin.scenes.setup.SURFACE_FLOATS_PER_NODE``), so a file holds no grid a setup could not have.
HEIGHTMAP_FLOATS_PER_NODE = 24
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


def open_append(path: str | Path) -> IO[str]:
    """Open the regular file ``path`` for appending text (created with the usual permissions when missing).

    A symbolic link at ``path`` is refused, not followed (``O_NOFOLLOW``; where the platform has none, checked
    with :func:`os.lstat` first), and so is anything but a regular file (a FIFO, a device).

    Raises
    ------
    OSError
        ``path`` is a link or not a regular file, or cannot be opened (the error names the path).
    """
    text = os.fspath(path)
    link = OSError(errno.ELOOP, "is a symbolic link; scopetwin writes through no link it did not make", text)
    if not hasattr(os, "O_NOFOLLOW") and os.path.islink(text):  # pragma: no cover - Windows
        raise link
    flags = os.O_WRONLY | os.O_APPEND | os.O_CREAT | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
    try:
        fd = os.open(text, flags, 0o666)
    except OSError as exc:
        if exc.errno == errno.ELOOP or os.path.islink(text):
            raise link from None
        raise
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise OSError(errno.EINVAL, "is not a regular file", text)
    return os.fdopen(fd, "a", encoding="utf-8")


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


def _read_exr(
    path: str | Path,
    channel: str,
    shape: tuple[int, int] | None = None,
    floats_per_pixel: int = FLOATS_PER_PIXEL,
) -> tuple[NDArray[np.float32], dict[str, Any]]:
    p = Path(path)
    check_input_file(p, "EXR")  # a regular file under the size limit: a FIFO or /dev/zero is one line
    # the declared size checked from the header (against ``shape`` and this machine's memory) before any decoding
    check_exr_header(p, "EXR file", shape, floats_per_pixel)
    failed: Exception | None = None
    with native_output_captured() as said:  # OpenEXR prints its own "Warning: ..." lines on a truncated file
        try:
            f = OpenEXR.File(str(p), separate_channels=True)
            channels = f.channels()
            header = dict(f.header())
        except Exception as exc:  # OpenEXR raises bare RuntimeError/ValueError on corrupt files
            failed = exc
    if failed is not None or said:
        why = next((line for line in said if "EXR_ERR" in line), said[0] if said else str(failed))
        why = why.removeprefix(f"{p}: ")
        raise FileFormatError(f"{p} is not a readable OpenEXR file (truncated or corrupt: {why})")
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


def read_image(path: str | Path, shape: tuple[int, int] | None = None) -> tuple[NDArray[np.float32], dict[str, Any]]:
    """Read a camera image (channel ``Y``) and its header attributes.

    The size the header declares is checked before any pixel is decoded: it must be ``shape`` (rows, cols) when
    given (the camera the image is for) and fit in this machine's memory as a camera image
    (:func:`scopetwin.scenes.safe_read.check_exr_header`).

    Raises
    ------
    FileFormatError
        Missing or unreadable file, a declared size other than ``shape`` or too large, no ``Y`` channel, or
        non-finite pixels.
    """
    data, attrs = _read_exr(path, "Y", shape)
    if not np.all(np.isfinite(data)):
        raise FileFormatError(f"{path}: image channel Y contains NaN or infinite values")
    return data, attrs


def write_heightmap(
    path: str | Path,
    heights: HeightMap,
    std: HeightMap | None = None,
    measured: NDArray[np.bool_] | None = None,
    **attrs: Any,
) -> None:
    """Write a height map in the contract's format (channel ``Z`` in mm, extents as header attributes).

    ``std``: the per-node standard uncertainty of a reconstruction on the same nodes, written as channel ``Z_std``
    (mm; docs/contract.md, "Height maps"). ``measured``: which nodes the reconstruction's markers measure
    (:meth:`scopetwin.recon.reconstruct.ReconstructionResult.measured_mask`); the others are written NaN in ``Z``
    and the mask as channel ``Z_measured`` (1 measured, 0 not).
    """
    extents = dict(zip(EXTENT_KEYS, (heights.x_min, heights.x_max, heights.y_min, heights.y_max), strict=True))
    extra: dict[str, NDArray] = {}
    z = heights.z
    if std is not None:
        if std.z.shape != heights.z.shape:
            raise FileFormatError(f"Z_std has {std.z.shape} nodes but Z has {heights.z.shape}")
        extra["Z_std"] = std.z
    if measured is not None:
        if measured.shape != heights.z.shape:
            raise FileFormatError(f"Z_measured has {measured.shape} nodes but Z has {heights.z.shape}")
        z = np.where(measured, z, np.nan)
        extra["Z_measured"] = measured.astype(np.float32)
    _write_exr(path, "Z", z, {**extents, **attrs}, extra or None)


def read_heightmap_std(path: str | Path) -> HeightMap | None:
    """The ``Z_std`` channel of a height-map EXR (per-node standard uncertainty, mm), or None when it has none."""
    from scopetwin.scenes.surface import HeightMap  # scipy's splines, loaded where a height map is made

    hm = read_heightmap(path)
    try:
        data, _ = _read_exr(path, "Z_std", hm.z.shape, HEIGHTMAP_FLOATS_PER_NODE)
    except FileFormatError:
        return None
    return HeightMap(data.astype(np.float64), hm.x_min, hm.x_max, hm.y_min, hm.y_max)


def read_heightmap(path: str | Path) -> HeightMap:
    """Read a height-map EXR (channel ``Z``, extents ``x_min_mm`` ... ``y_max_mm``).

    The grid the header declares must fit in this machine's memory as a setup's surface grid would
    (:data:`HEIGHTMAP_FLOATS_PER_NODE`), checked before any node is decoded.

    Raises
    ------
    FileFormatError
        Missing/unreadable file, a declared grid too large, missing channel or extent attribute, or invalid heights.
    """
    data, attrs = _read_exr(path, "Z", floats_per_pixel=HEIGHTMAP_FLOATS_PER_NODE)
    missing = [k for k in EXTENT_KEYS if k not in attrs]
    if missing:
        raise FileFormatError(f"{path}: height map lacks the header attribute(s) {', '.join(missing)}")
    try:
        ext = [float(attrs[k]) for k in EXTENT_KEYS]
    except (TypeError, ValueError):
        raise FileFormatError(f"{path}: height-map extents must be numbers") from None
    if not all(np.isfinite(ext)):
        raise FileFormatError(f"{path}: height-map extents must be finite, got {', '.join(f'{e:g}' for e in ext)}")
    from scopetwin.scenes.errors import GeometryError
    from scopetwin.scenes.surface import HeightMap  # scipy's splines, loaded where a height map is made

    unmeasured = int(np.count_nonzero(np.isnan(data)))
    if unmeasured:
        raise FileFormatError(
            f"{path}: {unmeasured} node(s) of Z are NaN (a reconstruction leaves the nodes no marker measured NaN, "
            "see its Z_measured channel); a height map read as a surface must be finite everywhere"
        )
    try:
        return HeightMap(data.astype(np.float64), *ext)
    except GeometryError as exc:
        raise FileFormatError(f"{path}: {exc}") from None


def check_surface(
    heights: HeightMap, substrate_size: Sequence[float] | None, where: str, extrapolate: bool = False
) -> HeightMap:
    """Refuse a height map that cannot be the substrate's surface; returns it.

    Its heights must lie within ±:data:`MAX_HEIGHT_MM` and its extent cover the substrate (``substrate_size``, x and
    y in mm, centred on the origin; None: no substrate to cover): beyond its extent a height map continues with its
    edge values, which only ``extrapolate`` accepts.

    Raises
    ------
    ScopetwinError
        One line naming ``where``: heights out of range, or the extent short of the substrate.
    """
    top = float(np.max(np.abs(heights.z)))
    if top > MAX_HEIGHT_MM:
        raise ScopetwinError(
            f"{where}: heights reach {top:.4g} mm; a substrate's surface lies within ±{MAX_HEIGHT_MM:g} mm"
        )
    if substrate_size is None or extrapolate:
        return heights
    sx, sy = (float(v) for v in substrate_size)
    tol = COVER_TOLERANCE * max(sx, sy)
    covers = (
        heights.x_min <= -0.5 * sx + tol
        and heights.x_max >= 0.5 * sx - tol
        and heights.y_min <= -0.5 * sy + tol
        and heights.y_max >= 0.5 * sy - tol
    )
    if not covers:
        raise ScopetwinError(
            f"{where} spans x {heights.x_min:g}..{heights.x_max:g}, y {heights.y_min:g}..{heights.y_max:g} mm but "
            f"the substrate spans x {-0.5 * sx:g}..{0.5 * sx:g}, y {-0.5 * sy:g}..{0.5 * sy:g} mm; give a map that "
            "covers it (or --extrapolate to continue its edge values)"
        )
    return heights
