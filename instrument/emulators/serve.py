"""Serve one wire-protocol emulator on a pseudo-terminal until told to stop (``scopetwin emulate``).

:func:`serve` starts the emulator named ``kind`` (``pi-gcs``, ``jena-piezo``,
``fpga-board``), announces the slave tty's path (the first line a caller prints),
optionally appends one JSON object per request to a log file —
``{"request": ..., "reply": ..., "state": {...}}`` with the emulator's state after
the request (:meth:`~scopetwin.instrument.emulators.base.PtyEmulator.state`; the board's
has ``"lights_on"``, the channels that are on) — and returns when ``stop`` is
set or, in the main thread, on SIGINT/SIGTERM. Text protocols log requests and
replies as text; the FPGA board's binary packets as hex bytes (``"01 11 0c ..."``).
"""

from __future__ import annotations

import json
import signal
import threading
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import IO, Any

from scopetwin.instrument.emulators import EMULATORS
from scopetwin.instrument.emulators.base import PtyEmulator, require_pty
from scopetwin.instrument.emulators.protocol_emu import option_value
from scopetwin.instrument.errors import RigError
from scopetwin.scenes.io import open_append

BINARY_PROTOCOLS = {"fpga-board"}


def parse_options(pairs: Iterable[str]) -> dict[str, Any]:
    """``["travel_mm=0,150", "model=nv40-3"]`` -> emulator keyword arguments (as ``emu://`` queries).

    Raises
    ------
    RigError
        For an item without ``=`` or a value that is not a number (list) where one is needed.
    """
    options: dict[str, Any] = {}
    for pair in pairs:
        key, sep, text = pair.partition("=")
        if not sep or not key:
            raise RigError(f"emulator option {pair!r} is not KEY=VALUE")
        options[key.strip().replace("-", "_")] = option_value(key.strip().replace("-", "_"), text.strip())
    return options


def make_emulator(kind: str, options: dict[str, Any] | None = None) -> PtyEmulator:
    """The emulator ``kind`` built with ``options`` (not started).

    Raises
    ------
    RigError
        Unknown kind or option.
    """
    if kind not in EMULATORS:
        raise RigError(f"unknown emulator {kind!r}; choose from {sorted(EMULATORS)}")
    try:
        return EMULATORS[kind](**(options or {}))
    except (TypeError, ValueError) as exc:
        raise RigError(f"emulator {kind}: bad option ({exc})") from exc


def _text(data: bytes, binary: bool) -> str:
    if binary:
        return " ".join(f"{b:02x}" for b in data)
    return data.decode("ascii", errors="backslashreplace")


def request_logger(stream: IO[str], binary: bool) -> Callable[[bytes, bytes, dict[str, Any]], None]:
    """A :attr:`PtyEmulator.on_request` hook that writes one JSON line per request to ``stream``."""

    def log(request: bytes, reply: bytes, state: dict[str, Any]) -> None:
        record = {"request": _text(request, binary), "reply": _text(reply, binary), "state": state}
        stream.write(json.dumps(record) + "\n")
        stream.flush()

    return log


def serve(
    kind: str,
    options: dict[str, Any] | None = None,
    *,
    log_path: str | Path | None = None,
    announce: Callable[[str], None] = print,
    stop: threading.Event | None = None,
) -> dict[str, Any]:
    """Run emulator ``kind`` on a pseudo-terminal until ``stop`` is set (or SIGINT/SIGTERM).

    Parameters
    ----------
    kind : str
        ``"pi-gcs"``, ``"jena-piezo"`` or ``"fpga-board"``.
    options : dict, optional
        Emulator keyword arguments (``model``, ``travel_mm``, ...), e.g. from :func:`parse_options`.
    log_path : str or Path, optional
        File to append one JSON object per request to.
    announce : callable
        Receives the port path once the emulator listens (default: print it, the first stdout line).
    stop : threading.Event, optional
        Set it to stop; without one, SIGINT and SIGTERM stop (signal handlers need the main thread).

    Returns
    -------
    dict
        ``{"emulator": kind, "port": path, "requests": n, "state": {...}}`` after stopping.

    Raises
    ------
    EmulatorUnavailable
        The platform has no POSIX pseudo-terminal (Windows).
    RigError
        Unknown kind or option.
    """
    require_pty()  # before the log file is opened: nothing is left behind where emulators cannot run
    emulator = make_emulator(kind, options)
    stop = stop or threading.Event()
    counter = {"n": 0}
    log_file: IO[str] | None = open_append(log_path) if log_path else None  # never through a link
    logger = request_logger(log_file, kind in BINARY_PROTOCOLS) if log_file is not None else None

    def on_request(request: bytes, reply: bytes, state: dict[str, Any]) -> None:
        counter["n"] += 1
        if logger is not None:
            logger(request, reply, state)

    emulator.on_request = on_request
    previous: dict[signal.Signals, Any] = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: stop.set())
    try:
        port = emulator.start()
        announce(port)
        while not stop.wait(0.1):
            pass
        return {"emulator": kind, "port": port, "requests": counter["n"], "state": emulator.state()}
    finally:
        emulator.stop()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        if log_file is not None:
            log_file.close()
