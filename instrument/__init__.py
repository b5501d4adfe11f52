"""instrument: device interfaces, simulated devices, hardware drivers, wire-protocol emulators and rigs.

``open_rig(path)`` opens a rig TOML (simulated devices, hardware drivers, or drivers
on emulators) as a context manager; acquisition routines live in
:mod:`scopetwin.instrument.acquisition`, Micro-Manager interop (pymmcore-plus, MDA) in
:mod:`scopetwin.instrument.micromanager`, python-microscope adapters in
:mod:`scopetwin.instrument.pymicroscope`, the emulator server behind ``scopetwin emulate`` in
:mod:`scopetwin.instrument.emulators.serve`; the ``rig`` command in :mod:`scopetwin.cli.rig`.
"""

from __future__ import annotations

if __name__ == "instrument":  # the bare folder, from the checkout's root: a second copy of scopetwin.instrument
    raise ImportError(
        "instrument is part of scopetwin: import scopetwin.instrument (install with `make setup` or `pip install -e .`)"
    )

from typing import TYPE_CHECKING, Any

from scopetwin.instrument.errors import (
    DisconnectedError,
    InstrumentError,
    InstrumentTimeout,
    OutOfRangeError,
    ProtocolError,
    RigError,
)

if TYPE_CHECKING:
    from scopetwin.instrument.rig import Rig, load_rig, open_rig

__all__ = [
    "DisconnectedError",
    "InstrumentError",
    "InstrumentTimeout",
    "OutOfRangeError",
    "ProtocolError",
    "Rig",
    "RigError",
    "load_rig",
    "open_rig",
]


def __getattr__(name: str) -> Any:
    """``Rig``, ``load_rig``, ``open_rig`` from :mod:`scopetwin.instrument.rig`, imported on first use: a module of
    the package (:mod:`scopetwin.instrument.interrupts`, which every command of the command line uses) loads without
    the rig and its devices."""
    if name in ("Rig", "load_rig", "open_rig"):
        from scopetwin.instrument import rig

        return getattr(rig, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
