"""Input files read safely: regular files under a size limit, parsed with a bounded nesting depth.

Every file scopetwin reads as input — a setup or rig TOML, a dataset configuration, an MDA sequence, an EXR image or
height map — goes through here first, so that none can hang, recurse or exhaust the machine:

* **a regular file**: opened with ``O_NONBLOCK`` (a FIFO does not block the open) and checked with :func:`os.fstat`
  on the open descriptor; a FIFO, a device (``/dev/zero``), a socket or a folder is refused with one line;
* **under a size limit** per kind (:data:`LIMITS`: 16 MiB for the text formats, 4 GiB for EXR files), checked
  before reading and again while reading (a file that grows meanwhile reads no further than the limit);
* **bounded nesting** (:data:`MAX_DEPTH` levels of arrays and tables): a bracket scan of the text before the parser
  runs (TOML and JSON parsers recurse once a level, so a 3000-deep array would end in a ``RecursionError``), the
  parser's own ``RecursionError`` caught, and an iterative walk of the parsed data.

Each failure is one :class:`InputError` (a :class:`~scopetwin.scenes.errors.FileFormatError`, so exit code 2) naming
the kind, the path and the limit. :func:`native_output_captured` keeps what a C library prints on the process's own
stdout and stderr (OpenEXR's ``Warning:`` on a truncated file) off the terminal, so the caller can turn it into its
one line.
"""

from __future__ import annotations

import contextlib
import importlib
import io
import json
import math
import os
import stat
import sys
import tempfile
import tomllib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from scopetwin.scenes.errors import FileFormatError

MiB = 2**20
#: Largest file of each kind, bytes (docs/contract.md, "Files").
LIMITS = {
    "setup": 16 * MiB,
    "rig": 16 * MiB,
    "dataset configuration": 16 * MiB,
    "MDA sequence": 16 * MiB,
    "JSON": 16 * MiB,
    "EXR": 4 * 1024 * MiB,
}
#: Largest text file when the kind has no entry in :data:`LIMITS`.
TEXT_LIMIT = 16 * MiB
#: Deepest nesting of arrays and tables an input may have (the deepest shipped file has 4).
MAX_DEPTH = 64


class InputError(FileFormatError):
    """An input that is not a regular file, is too large, nests too deep, or is not text of its format."""


def _limit(kind: str, limit: int | None) -> int:
    return int(limit if limit is not None else LIMITS.get(kind, TEXT_LIMIT))


def file_kind(st_mode: int) -> str:
    """What a file that is not a regular file is, from its ``st_mode``, in words ("a FIFO (named pipe)", ...)."""
    if stat.S_ISDIR(st_mode):
        return "a folder"
    if stat.S_ISFIFO(st_mode):
        return "a FIFO (named pipe)"
    if stat.S_ISCHR(st_mode) or stat.S_ISBLK(st_mode):
        return "a device"
    if stat.S_ISSOCK(st_mode):
        return "a socket"
    return "not a regular file"


def _size(n: int) -> str:
    return f"{n / MiB:.0f} MiB" if n >= MiB else f"{n} bytes"


def _open_regular(path: str | Path, kind: str, limit: int) -> tuple[int, os.stat_result]:
    """An open descriptor of the regular file ``path`` no larger than ``limit`` bytes, and its status."""
    text = os.fspath(path)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0) | getattr(os, "O_BINARY", 0)
    try:
        fd = os.open(text, flags)
    except FileNotFoundError:
        raise InputError(f"{kind} file {text} does not exist") from None
    except OSError as exc:
        raise InputError(f"cannot read {kind} file {text}: {exc.strerror or exc}") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise InputError(f"{kind} file {text} is {file_kind(st.st_mode)}, not a regular file")
        if st.st_size > limit:
            raise InputError(f"{kind} file {text} is {_size(st.st_size)}, over the limit of {_size(limit)}")
    except BaseException:
        os.close(fd)
        raise
    return fd, st


def check_input_file(path: str | Path, kind: str, limit: int | None = None) -> int:
    """Check that ``path`` is a regular file of at most ``limit`` bytes (default: :data:`LIMITS` of ``kind``);
    return its size.

    Raises
    ------
    InputError
        Missing, unreadable, not a regular file (a FIFO, a device, a folder), or over the limit.
    """
    fd, st = _open_regular(path, kind, _limit(kind, limit))
    os.close(fd)
    return int(st.st_size)


def read_bytes_input(path: str | Path, kind: str, limit: int | None = None) -> bytes:
    """The bytes of the regular file ``path``, at most ``limit`` bytes (default: :data:`LIMITS` of ``kind``).

    Raises
    ------
    InputError
        As :func:`check_input_file`, or the file grew past the limit while it was read.
    """
    most = _limit(kind, limit)
    fd, _ = _open_regular(path, kind, most)
    try:
        os.set_blocking(fd, True)
        chunks, total = [], 0
        while total <= most:
            chunk = os.read(fd, min(MiB, most + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
    except OSError as exc:
        raise InputError(f"cannot read {kind} file {os.fspath(path)}: {exc.strerror or exc}") from None
    finally:
        os.close(fd)
    if total > most:
        raise InputError(f"{kind} file {os.fspath(path)} grew past the limit of {_size(most)} while it was read")
    return b"".join(chunks)


def read_text_input(path: str | Path, kind: str, limit: int | None = None) -> str:
    """The UTF-8 text of the regular file ``path`` (see :func:`read_bytes_input`).

    Raises
    ------
    InputError
        As :func:`read_bytes_input`, or the bytes are not UTF-8 text.
    """
    data = read_bytes_input(path, kind, limit)
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InputError(f"{kind} file {os.fspath(path)} is not UTF-8 text (byte {exc.start})") from None


def bracket_depth(text: str, comments: str = "#", quotes: str = "\"'") -> int:
    """The deepest nesting of ``[``/``{`` in ``text`` outside strings and comments (a scan, no recursion).

    ``quotes`` are the string delimiters (TOML: ``"`` and ``'``, tripled for multi-line strings; JSON: ``"``);
    ``comments`` the comment character (none for JSON). Backslash escapes count inside ``"`` strings only.
    """
    depth = deepest = 0
    i, n = 0, len(text)
    while i < n:
        c = text[i]
        if c in quotes:
            triple = text.startswith(c * 3, i)
            end = c * 3 if triple else c
            i += len(end)
            while i < n and not text.startswith(end, i):
                if c == '"' and text[i] == "\\":
                    i += 1
                elif not triple and text[i] == "\n":
                    break
                i += 1
            i += len(end)
            continue
        if comments and c in comments:
            newline = text.find("\n", i)
            i = n if newline < 0 else newline + 1
            continue
        if c in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif c in "]}":
            depth = max(0, depth - 1)
        i += 1
    return deepest


def data_depth(data: Any) -> int:
    """The nesting depth of parsed data (dicts and lists; a scalar is 0), by an iterative walk."""
    deepest = 0
    stack: list[tuple[Any, int]] = [(data, 0)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, dict):
            children: Any = item.values()
        elif isinstance(item, list | tuple):
            children = item
        else:
            continue
        deepest = max(deepest, depth + 1)
        if deepest > MAX_DEPTH:
            return deepest
        stack.extend((child, depth + 1) for child in children)
    return deepest


def check_depth(data: Any, kind: str, where: str, max_depth: int = MAX_DEPTH) -> None:
    """Refuse parsed data nested deeper than ``max_depth`` (one :class:`InputError` naming ``where``)."""
    if data_depth(data) > max_depth:
        raise InputError(f"{kind} {where} nests arrays or tables more than {max_depth} levels deep")


def _too_deep(kind: str, where: str) -> InputError:
    return InputError(f"{kind} {where} nests arrays or tables more than {MAX_DEPTH} levels deep")


def parse_toml(text: str, kind: str, where: str) -> dict[str, Any]:
    """Parse TOML text with bounded nesting.

    Raises
    ------
    InputError
        Nested deeper than :data:`MAX_DEPTH`.
    tomllib.TOMLDecodeError
        Not valid TOML (the caller words the message for its kind).
    """
    if bracket_depth(text) > MAX_DEPTH:
        raise _too_deep(kind, where)
    try:
        data = tomllib.loads(text)
    except RecursionError:
        raise _too_deep(kind, where) from None
    check_depth(data, kind, where)
    return data


def load_toml_input(path: str | Path, kind: str, limit: int | None = None) -> dict[str, Any]:
    """Read and parse the TOML file ``path`` of ``kind`` with every check of this module.

    Raises
    ------
    InputError
        Not a regular file, over the size limit, not UTF-8, nested too deep, or not valid TOML.
    """
    text = read_text_input(path, kind, limit)
    try:
        return parse_toml(text, f"{kind} file", os.fspath(path))
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{kind} file {os.fspath(path)} is not valid TOML: {exc}") from None


def non_finite(data: Any) -> str | None:
    """The path (``a.b[2]``) of the first number in parsed ``data`` that is not finite (``NaN``, ``Infinity``, or a
    literal too large for a float), or ``None``; an iterative walk."""
    stack: list[tuple[Any, str]] = [(data, "")]
    while stack:
        item, path = stack.pop()
        if isinstance(item, dict):
            stack.extend((v, f"{path}.{k}" if path else str(k)) for k, v in item.items())
        elif isinstance(item, list | tuple):
            stack.extend((v, f"{path}[{i}]") for i, v in enumerate(item))
        elif isinstance(item, float) and not math.isfinite(item):
            return path or "(top level)"
    return None


def _check_finite(data: Any, kind: str, where: str) -> None:
    path = non_finite(data)
    if path is not None:
        raise InputError(f"{kind} {where}: {path} is not a finite number")


def parse_json(text: str, kind: str, where: str, finite: bool = False) -> Any:
    """Parse JSON text with bounded nesting; with ``finite``, every number must be finite.

    Raises
    ------
    InputError
        Nested deeper than :data:`MAX_DEPTH`, not valid JSON, or (``finite``) a ``NaN``/``Infinity``.
    """
    brackets = text.count("[") + text.count("{")  # fewer brackets than the limit cannot nest deeper: no scan
    if brackets > MAX_DEPTH and bracket_depth(text, comments="", quotes='"') > MAX_DEPTH:
        raise _too_deep(kind, where)
    try:
        data = json.loads(text)
    except RecursionError:
        raise _too_deep(kind, where) from None
    except ValueError as exc:
        raise InputError(f"{kind} {where} is not valid JSON: {exc}") from None
    check_depth(data, kind, where)
    if finite:
        _check_finite(data, kind, where)
    return data


def load_json_input(path: str | Path, kind: str, limit: int | None = None) -> Any:
    """Read and parse the JSON file ``path`` of ``kind`` with every check of this module."""
    return parse_json(read_text_input(path, kind, limit), f"{kind} file", os.fspath(path))


def parse_yaml(text: str, kind: str, where: str, finite: bool = False) -> Any:
    """Parse YAML text (safe loader) with bounded nesting; with ``finite``, every number must be finite.

    Raises
    ------
    InputError
        Nested deeper than :data:`MAX_DEPTH`, not valid YAML, or (``finite``) a ``.nan``/``.inf``.
    """
    try:
        yaml: Any = importlib.import_module("yaml")  # PyYAML (comes with useq-schema); untyped
    except ImportError:
        raise InputError(f"{kind} {where}: reading YAML needs PyYAML (pip install pyyaml)") from None
    if bracket_depth(text, quotes='"') > MAX_DEPTH:
        raise _too_deep(kind, where)
    try:
        data = yaml.safe_load(text)
    except RecursionError:
        raise _too_deep(kind, where) from None
    except yaml.YAMLError as exc:
        first = " ".join(str(exc).split())
        raise InputError(f"{kind} {where} is not valid YAML: {first}") from None
    check_depth(data, kind, where)
    if finite:
        _check_finite(data, kind, where)
    return data


def _flush_c_stdio() -> None:
    """``fflush(NULL)``: what native code left in the C library's stdio buffers goes to its descriptors now."""
    with contextlib.suppress(Exception):
        import ctypes

        ctypes.CDLL(None).fflush(None)


@contextlib.contextmanager
def native_output_captured() -> Iterator[list[str]]:
    """Hold what native code writes on file descriptors 1 and 2 (and through Python's ``sys.stdout`` and
    ``sys.stderr``) inside the block; yield a list that receives its non-empty lines when the block ends.

    Where the descriptors cannot be redirected (no real stdout, e.g. under some test runners) nothing is held.
    """
    lines: list[str] = []
    saved: list[tuple[int, int]] = []
    with tempfile.TemporaryFile() as sink:
        for stream in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        _flush_c_stdio()
        for fd in (1, 2):
            try:
                saved.append((fd, os.dup(fd)))
                os.dup2(sink.fileno(), fd)
            except OSError:
                pass
        python = io.StringIO()  # a binding may print through Python's sys.stdout (pybind11's py::print)
        try:
            with contextlib.redirect_stdout(python), contextlib.redirect_stderr(python):
                yield lines
        finally:
            _flush_c_stdio()  # C++ iostreams write through C stdio, which holds a piped stdout in its buffer
            for fd, copy in saved:
                os.dup2(copy, fd)
                os.close(copy)
            sink.seek(0)
            text = python.getvalue() + sink.read().decode("utf-8", errors="replace")
            lines.extend(line.strip() for line in text.splitlines() if line.strip())


def load_structured_input(path: str | Path, kind: str, limit: int | None = None, finite: bool = True) -> Any:
    """Read and parse a JSON (``.json``) or YAML (``.yaml``, ``.yml``) file with every check of this module; every
    number must be finite unless ``finite`` is false.

    Raises
    ------
    InputError
        Another suffix, or any failure of :func:`read_text_input`, :func:`parse_json`, :func:`parse_yaml`.
    """
    suffix = Path(path).suffix.lower()
    if suffix not in (".json", ".yaml", ".yml"):
        raise InputError(f"{kind} file {os.fspath(path)} must end in .json, .yaml or .yml")
    text = read_text_input(path, kind, limit)
    where = f"file {os.fspath(path)}"
    if suffix == ".json":
        return parse_json(text, kind, where, finite)
    return parse_yaml(text, kind, where, finite)


def validation_line(exc: Exception) -> str:
    """One line for a pydantic ``ValidationError`` (or any error): the most telling problem, its field, and how many
    more there are — never pydantic's multi-line text with its URLs.

    Of a union's alternatives the first problem that is not a missing field is shown (it says what was wrong with
    the value given).
    """
    errors = getattr(exc, "errors", None)
    try:
        found = list(errors()) if callable(errors) else []
    except Exception:  # noqa: BLE001 - not a pydantic error after all
        found = []
    if not found:
        return " ".join(str(exc).split()) or type(exc).__name__
    best = next((e for e in found if e.get("type") != "missing"), found[0])
    loc = ".".join(str(p) for p in best.get("loc", ())) or "(top level)"
    msg = str(best.get("msg", "invalid")).removeprefix("Value error, ")
    more = f" (and {len(found) - 1} more problem(s))" if len(found) > 1 else ""
    return f"field {loc}: {' '.join(msg.split())}{more}"
