"""Wire-protocol emulators (PI GCS, jena piezo, FPGA board) on pseudo-terminals.

:data:`EMULATORS` maps a protocol name to its emulator class; the pyserial URL
``emu://NAME?key=value&...`` (see :mod:`scopetwin.instrument.emulators.protocol_emu`)
starts one in-process and opens its pseudo-terminal.
"""

from __future__ import annotations

from scopetwin.instrument.emulators.base import Fault, PtyEmulator
from scopetwin.instrument.emulators.fpga_board import FpgaBoardEmulator
from scopetwin.instrument.emulators.jena_piezo import JenaPiezoEmulator
from scopetwin.instrument.emulators.pi_gcs import PiGcsEmulator

EMULATORS: dict[str, type[PtyEmulator]] = {
    "pi-gcs": PiGcsEmulator,
    "jena-piezo": JenaPiezoEmulator,
    "fpga-board": FpgaBoardEmulator,
}

__all__ = ["EMULATORS", "Fault", "FpgaBoardEmulator", "JenaPiezoEmulator", "PiGcsEmulator", "PtyEmulator"]
