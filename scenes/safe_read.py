"""Files someone else wrote, opened safely: names kept inside their folder, plain files only, sizes, nesting depth,
format versions and image dimensions checked before anything is read or decoded.

A dataset folder, a sample's ``truth.json`` or an EXR handed over by another lab names further files and declares
what it holds. Every reader of such files goes through these functions first:

* :func:`resolve_inside` — a file name taken from a file (``truth.json``'s ``"surface"``, the ``files`` of a
  ``sample.json``) must stay inside the folder it belongs to: no absolute path, no ``..``, no symbolic link that
  ends outside the folder (``/dev/zero``, another user's file);
* :func:`check_regular` — the file is a regular file (``os.stat`` before it is opened: a FIFO would block the open,
  a device never ends) no larger than a limit;
* :func:`read_json_inside` — both of the above, then the JSON parsed with a bounded nesting depth (a 100000-deep
  array is one error, never a ``RecursionError``; :func:`scopetwin.scenes.inputs.parse_json`);
* :func:`check_format` — a format version newer than this scopetwin reads is one error that says so;
* :func:`check_exr_header` — an EXR's dimensions read from its header (no pixel decoded) and checked against the
  size the caller expects and against this machine's memory (:func:`scopetwin.scenes.limits.check_image_size`).

Every refusal is an :class:`UnsafeInput` (an :class:`~scopetwin.scenes.inputs.InputError`, so the command line
prints one line and exits with status 2) whose message names the file and the reason.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Collection
from pathlib import Path, PurePosixPath, PureWindowsPath
from typing import Any

from scopetwin.scenes.inputs import (
    LIMITS,
    TEXT_LIMIT,
    InputError,
    file_kind,
    native_output_captured,
    parse_json,
    read_text_input,
)
from scopetwin.scenes.limits import FLOATS_PER_PIXEL, check_image_size

#: Most pixels an image or height map read without an expected size may declare: 2^28 (268 Mpx), well above the
#: largest scientific camera sensors (about 150 Mpx) and below what a forged header would make this machine decode
#: (20000 x 20000 px = 400 Mpx; the memory check alone passes it on a machine with 24 GiB).
MAX_IMAGE_PIXELS = 1 << 28


class UnsafeInput(InputError):
    """A file name that leaves its folder, a file that is not a regular file or is too large, a format newer than
    this scopetwin reads, or an image whose header declares a size that cannot be read here."""


def _inside(path: str, folder: str) -> bool:
    return path == folder or path.startswith(folder.rstrip(os.sep) + os.sep)


def resolve_inside(root: str | Path, name: object, what: str) -> Path:
    """The real path of the relative file name ``name`` inside the folder ``root``.

    Parameters
    ----------
    root : str or path
        The folder the name must stay in (a dataset folder, a sample folder).
    name : object
        The name as it was read from a file: it must be a non-empty string.
    what : str
        Names the reference in the message (``"truth.json surface"``).

    Returns
    -------
    Path
        ``root / name`` with every symbolic link resolved; it lies inside the resolved ``root``.

    Raises
    ------
    UnsafeInput
        ``name`` is not a string, is empty or holds a NUL, is absolute (POSIX or Windows form), has a ``..``
        component, or resolves (through a symbolic link) to a place outside ``root``.
    """
    if not isinstance(name, str) or not name:
        raise UnsafeInput(f"{what}: {name!r} is not a file name")
    if "\0" in name:
        raise UnsafeInput(f"{what}: {name!r} holds a NUL character")
    if PurePosixPath(name).is_absolute() or PureWindowsPath(name).anchor:
        raise UnsafeInput(f"{what}: {name!r} is an absolute path; only names inside {root} are read")
    if ".." in PureWindowsPath(name).parts or ".." in PurePosixPath(name).parts:
        raise UnsafeInput(f"{what}: {name!r} leaves {root} ('..'); only names inside it are read")
    folder = os.path.realpath(root)
    real = os.path.realpath(os.path.join(folder, name))
    if not _inside(real, folder):
        raise UnsafeInput(f"{what}: {name!r} is a link to {real}, outside {root}; only files inside it are read")
    return Path(real)


def check_regular(path: str | Path, what: str, limit: int = TEXT_LIMIT) -> int:
    """Check, before opening it, that ``path`` is a regular file of at most ``limit`` bytes; return its size.

    ``os.stat`` follows a link, so a link to ``/dev/zero`` is seen as the device it names.

    Raises
    ------
    UnsafeInput
        Missing, unreadable, a FIFO, a device, a socket or a folder, or larger than ``limit``.
    """
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise UnsafeInput(f"{what}: {path} does not exist") from None
    except OSError as exc:
        raise UnsafeInput(f"{what}: cannot read {path}: {exc.strerror or exc}") from None
    if not stat.S_ISREG(st.st_mode):
        raise UnsafeInput(f"{what}: {path} is {file_kind(st.st_mode)}, not a regular file")
    if st.st_size > limit:
        raise UnsafeInput(f"{what}: {path} is {st.st_size} bytes, over the limit of {limit} bytes")
    return int(st.st_size)


def read_json_inside(root: str | Path, name: object, what: str, limit: int | None = None) -> dict[str, Any]:
    """The JSON object in file ``name`` of folder ``root``, read with every check of this module.

    Parameters
    ----------
    root : str or path
        The folder the file must lie in.
    name : object
        Its name relative to ``root`` (as read from another file, or a fixed name such as ``"truth.json"``).
    what : str
        Names the file in messages.
    limit : int, optional
        Largest size in bytes (default: the ``JSON`` entry of :data:`scopetwin.scenes.inputs.LIMITS`).

    Raises
    ------
    UnsafeInput
        As :func:`resolve_inside` and :func:`check_regular`.
    InputError
        Not UTF-8, not valid JSON, nested deeper than :data:`scopetwin.scenes.inputs.MAX_DEPTH`, or not an object.
    """
    most = LIMITS["JSON"] if limit is None else int(limit)
    path = resolve_inside(root, name, what)
    check_regular(path, what, most)
    data = parse_json(read_text_input(path, what, most), what, f"file {path}")
    if not isinstance(data, dict):
        raise InputError(f"{what} file {path} does not hold a JSON object")
    return data


def check_format(value: object, readable: Collection[int], what: str) -> int:
    """The format version ``value`` if this scopetwin reads it.

    Parameters
    ----------
    value : object
        The ``"format"`` entry as read (``None`` where the file has none: the caller passes its default).
    readable : collection of int
        The versions this scopetwin reads.
    what : str
        Names the file in the message.

    Raises
    ------
    UnsafeInput
        A version newer than the newest readable one (the message says a newer scopetwin is needed), or anything
        that is not one of ``readable``.
    """
    known = ", ".join(map(str, sorted(readable)))
    if isinstance(value, bool) or not isinstance(value, int):
        raise UnsafeInput(f"{what}: format {value!r} is not a format version (this scopetwin reads {known})")
    if value > max(readable):
        raise UnsafeInput(
            f"{what} is of format {value}, newer than this scopetwin reads ({known}); install a newer scopetwin"
        )
    if value not in readable:
        raise UnsafeInput(f"{what}: format {value} is not one this scopetwin reads ({known})")
    return value


def exr_header(path: str | Path, what: str) -> dict[str, Any]:
    """The header of the EXR file ``path`` (a regular file under the EXR size limit), read without any pixel.

    Raises
    ------
    UnsafeInput
        As :func:`check_regular`.
    InputError
        Not a readable OpenEXR header.
    """
    import OpenEXR

    check_regular(path, what, LIMITS["EXR"])
    failed: Exception | None = None
    header: dict[str, Any] = {}
    with native_output_captured() as said:  # OpenEXR prints its own lines on a damaged file
        try:
            header = dict(OpenEXR.File(str(path), header_only=True).header())
        except Exception as exc:  # OpenEXR raises bare RuntimeError/ValueError on corrupt files
            failed = exc
    if failed is not None or "dataWindow" not in header:
        told = next((line for line in said if "EXR_ERR" in line), said[0] if said else None)
        why = (told or (str(failed) if failed is not None else "no data window")).removeprefix(f"{path}: ")
        raise InputError(f"{path} is not a readable OpenEXR file (truncated or corrupt: {why})")
    return header


def exr_shape(header: dict[str, Any]) -> tuple[int, int]:
    """(rows, cols) of an EXR header's data window."""
    lo, hi = header["dataWindow"]
    return int(hi[1]) - int(lo[1]) + 1, int(hi[0]) - int(lo[0]) + 1


def check_exr_header(
    path: str | Path,
    what: str,
    shape: tuple[int, int] | None = None,
    floats_per_pixel: int = FLOATS_PER_PIXEL,
    memory: int | None = None,
) -> dict[str, Any]:
    """The header of the EXR file ``path`` once its dimensions are known to be readable; no pixel is decoded.

    Parameters
    ----------
    path : str or path
        The EXR file.
    what : str
        Names the file in messages.
    shape : (int, int), optional
        The (rows, cols) the caller expects (a setup's camera, the image a map belongs to).
    floats_per_pixel : int
        4-byte numbers a pixel costs while it is read and used (for
        :func:`scopetwin.scenes.limits.check_image_size`).
    memory : int, optional
        Bytes the image may claim (default: this machine's physical memory).

    Raises
    ------
    UnsafeInput
        The header declares an empty data window, a size other than ``shape``, or (without ``shape``) more than
        :data:`MAX_IMAGE_PIXELS`.
    scopetwin.scenes.limits.LimitError
        The declared size does not fit in ``memory``.
    InputError
        As :func:`exr_header`.
    """
    header = exr_header(path, what)
    rows, cols = exr_shape(header)
    if rows < 1 or cols < 1:
        raise UnsafeInput(f"{what}: {path} declares an empty image ({cols} x {rows} px)")
    if shape is not None and (rows, cols) != tuple(shape):
        raise UnsafeInput(
            f"{what}: {path} declares {cols} x {rows} px, but {shape[1]} x {shape[0]} px are expected; "
            "nothing was decoded"
        )
    if shape is None and rows * cols > MAX_IMAGE_PIXELS:
        raise UnsafeInput(
            f"{what}: {path} declares {cols} x {rows} px ({rows * cols / 1e6:.0f} Mpx), more than the "
            f"{MAX_IMAGE_PIXELS / 1e6:.0f} Mpx an image read here may have; nothing was decoded"
        )
    check_image_size(cols, rows, f"{what} {path}", floats_per_pixel, memory)
    return header
