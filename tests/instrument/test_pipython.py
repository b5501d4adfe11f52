"""PI's own Python client (pipython: GCSDevice over its serial gateway, pitools) against the PI GCS emulator.

pipython is written by PI, not by this project: what it sends on connect (``CSV?``, ``*IDN?``, ``SAI? ALL``,
``HLP?``) and in its helpers is what a real C-863 gets, so these tests show that the emulator answers where a
controller answers and stays silent (error code for ``ERR?``) where a controller does.
"""

from __future__ import annotations

import time

import pytest

pytest.importorskip("pipython", reason="pipython (dev extra) is not installed")

from pipython import GCSDevice, GCSError, pitools  # noqa: E402
from pipython.pidevice.interfaces.piserial import PISerial  # noqa: E402

from scopetwin.instrument.drivers.pi_gcs import PiGcsStage  # noqa: E402
from scopetwin.instrument.emulators import PiGcsEmulator  # noqa: E402


@pytest.fixture
def gcs():
    """An M-404.6PD on a C-863 emulator (0-150 mm, 50 mm/s) and a pipython GCSDevice connected to it."""
    emulator = PiGcsEmulator(travel_mm=(0.0, 150.0), max_velocity_mm_s=50.0)
    emulator.start()
    gateway = PISerial(emulator.port, 115200)
    gateway.settimeout(1000)  # ms: every unanswered query would cost this
    try:
        with GCSDevice(gateway=gateway) as device:  # leaving unregisters pipython's connection callback
            yield emulator, device
    finally:
        gateway.close()
        emulator.stop()


def test_connect_startup_frf_move_waitontarget(gcs):
    emulator, device = gcs
    t0 = time.monotonic()
    assert "C-863" in device.qIDN()
    assert device.axes == ["1"]
    pitools.startup(device, stages=None, refmodes="FRF")
    assert device.qFRF("1")["1"] is True and device.qSVO("1")["1"] is True
    device.MOV("1", 12.5)
    pitools.waitontarget(device, axes="1")
    assert device.qPOS("1")["1"] == pytest.approx(12.5)
    assert device.qONT("1")["1"] is True
    assert time.monotonic() - t0 < 5.0  # no timeouts on the way
    assert emulator.commands[:2] == ["CSV?", "ERR?"]  # pipython's connect asks the syntax version first
    assert emulator.errors == []


def test_helpers_answer(gcs):
    _, device = gcs
    assert device.qCSV() == pytest.approx(2.0)
    assert device.qSAI() == ["1"] and device.qSAI_ALL() == ["1"]
    assert "FW_ARM" in device.qVER()
    assert "MOV" in device.qHLP() and device.HasMOV() and device.HasqFRF() and not device.HasEAX()
    assert "0xA=" in device.qHPA()
    assert device.qCST("1")["1"] == "M-404.6PD"
    assert device.qTRS("1")["1"] is True and device.qLIM("1")["1"] is True
    assert device.qRON("1")["1"] is True
    assert device.qTMN("1")["1"] == pytest.approx(0.0) and device.qTMX("1")["1"] == pytest.approx(150.0)
    assert device.qSPA("1", 0xA)["1"][0xA] == pytest.approx(50.0)
    assert device.qVEL("1")["1"] == pytest.approx(50.0)


def test_moveandwait_and_velocity(gcs):
    _, device = gcs
    pitools.startup(device, refmodes="FRF")
    device.VEL("1", 100.0 / 4)
    assert device.qVEL("1")["1"] == pytest.approx(25.0)
    assert device.qSPA("1", 0x49)["1"][0x49] == pytest.approx(25.0)  # VEL sets parameter 0x49
    pitools.moveandwait(device, "1", 5.0)
    assert device.qPOS("1")["1"] == pytest.approx(5.0)


def test_errors_reach_pipython_with_pi_codes(gcs):
    _, device = gcs
    with pytest.raises(GCSError) as info:
        device.MOV("1", 10.0)  # servo off, not referenced
    assert info.value.val == 5
    pitools.startup(device, refmodes="FRF")
    with pytest.raises(GCSError) as info:
        device.MOV("1", 151.0)
    assert info.value.val == 7
    with pytest.raises(GCSError) as info:
        device.VEL("1", 51.0)
    assert info.value.val == 17


def test_unknown_query_is_silent_like_a_controller(gcs):
    emulator, device = gcs
    device.gcsdevice.messages.interface.settimeout(200)
    with pytest.raises(GCSError):  # no answer: pipython times out
        device.ReadGCSCommand("XYZ?")
    device.gcsdevice.messages.interface.settimeout(1000)
    assert device.qERR() == 2  # unknown command, kept for ERR?


def test_driver_reads_velocity_limit_from_controller():
    """A rig that omits max_velocity_mm_s gets the controller's parameter 0xA."""
    with PiGcsEmulator(travel_mm=(0.0, 300.0), max_velocity_mm_s=100.0) as emulator:
        import serial

        port = serial.Serial(emulator.port, 115200, timeout=0.02)
        stage = PiGcsStage("y", port, travel_mm=(0.0, 300.0), max_velocity_mm_s=None)
        stage.initialize()
        try:
            assert stage.velocity_range.high == pytest.approx(100.0)
            assert "SPA? 1 0xA" in emulator.commands
            stage.set_velocity(80.0)
            assert stage.velocity_mm_s == pytest.approx(80.0)
        finally:
            stage.shutdown()
            port.close()
