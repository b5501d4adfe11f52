"""instrument: device interfaces, simulated devices, hardware drivers, wire-protocol emulators and rigs.

``open_rig(path)`` opens a rig TOML (simulated devices, hardware drivers, or drivers
on emulators) as a context manager; acquisition routines live in
:mod:`instrument.acquisition`, Micro-Manager interop (pymmcore-plus, MDA) in
:mod:`instrument.micromanager`, python-microscope adapters in
:mod:`instrument.pymicroscope`, the emulator server behind ``scopetwin emulate`` in
:mod:`instrument.emulators.serve`; the ``rig`` command in :mod:`sim.cli.rig`.
"""

from instrument.errors import (
    DisconnectedError,
    InstrumentError,
    InstrumentTimeout,
    OutOfRangeError,
    ProtocolError,
    RigError,
)
from instrument.rig import Rig, load_rig, open_rig

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
