"""instrument: device interfaces, simulated devices, hardware drivers, wire-protocol emulators and rigs.

``open_rig(path)`` opens a rig TOML (simulated devices, hardware drivers, or drivers
on emulators) as a context manager; acquisition routines live in
:mod:`instrument.acquisition`, the ``rig`` command in :mod:`instrument.cli`.
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
