"""Fixtures of the instrument tests: emulators on pseudo-terminals, serial ports to them, a world."""

from __future__ import annotations

import os

import pytest
import serial

os.environ.setdefault("PYLON_CAMEMU", "1")  # pylon's camera emulator, read when pypylon starts

from scopetwin.instrument.emulators import FpgaBoardEmulator, JenaPiezoEmulator, PiGcsEmulator  # noqa: E402
from scopetwin.instrument.simulated.world import VirtualWorld  # noqa: E402


def _serve(emulator, baudrate: int = 115200):
    emulator.start()
    port = serial.Serial(emulator.port, baudrate=baudrate, timeout=0.02)
    try:
        yield emulator, port
    finally:
        port.close()
        emulator.stop()


@pytest.fixture
def pi_line():
    """A PI GCS emulator (M-404.6PD: 0-150 mm, 50 mm/s) and a serial port to it."""
    yield from _serve(PiGcsEmulator(travel_mm=(0.0, 150.0), max_velocity_mm_s=50.0))


@pytest.fixture
def jena_line():
    """A jena piezo emulator (MIPOS500: 0-400 µm) and a 9600-baud serial port to it."""
    yield from _serve(JenaPiezoEmulator(), baudrate=9600)


@pytest.fixture
def fpga_line():
    """An FPGA board emulator and a serial port to it."""
    yield from _serve(FpgaBoardEmulator())


@pytest.fixture
def world():
    """An empty virtual world."""
    return VirtualWorld()
