"""instrument: device interfaces, simulated devices, hardware drivers, wire-protocol emulators and rigs.

``open_rig(path)`` opens a rig TOML (simulated devices, hardware drivers, or drivers
on emulators) as a context manager; acquisition routines live in
:mod:`scopetwin.instrument.acquisition`, Micro-Manager interop (pymmcore-plus, MDA) in
:mod:`scopetwin.instrument.micromanager`, python-microscope adapters in
:mod:`scopetwin.instrument.pymicroscope`, the emulator server behind ``scopetwin emulate`` in
:mod:`scopetwin.instrument.emulators.serve`; the ``rig`` command in :mod:`scopetwin.sim.cli.rig`.
"""

from scopetwin.instrument.errors import (
    DisconnectedError,
    InstrumentError,
    InstrumentTimeout,
    OutOfRangeError,
    ProtocolError,
    RigError,
)
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
