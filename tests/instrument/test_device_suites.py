"""The device suites run against the simulated devices AND the drivers on their emulators."""

from __future__ import annotations

import pytest
from instrument_suites import CameraSuite, FocusSuite, LightSuite, ShutterSuite, StageSuite, TriggerSuite

from scopetwin.instrument.devices import CameraLimits
from scopetwin.instrument.drivers.fpga_board import FpgaBoard, FpgaLight, FpgaShutter, FpgaTrigger
from scopetwin.instrument.drivers.jena_piezo import JenaPiezoFocus
from scopetwin.instrument.drivers.pi_gcs import PiGcsStage
from scopetwin.instrument.simulated.devices import SimCamera, SimFocus, SimLight, SimShutter, SimStage, SimTrigger
from scopetwin.instrument.simulated.renderers import FlatTextureRenderer


def _initialized(device):
    device.initialize()
    yield device
    device.shutdown()


class SimIo:
    """``io_count`` for simulated devices: operations logged by the world."""

    @pytest.fixture
    def io_count(self, world):
        return lambda: len(world.io_log)


class EmulatorIo:
    """``io_count`` for drivers: bytes the emulator received."""

    @pytest.fixture
    def io_count(self, wire):
        emulator, _ = wire
        return lambda: len(emulator.received)


# stages --------------------------------------------------------------------------------------------
class TestSimStage(SimIo, StageSuite):
    @pytest.fixture
    def device(self, world):
        yield from _initialized(SimStage("x", world, travel_mm=(0.0, 150.0), max_velocity_mm_s=50.0))


class TestPiStageOnEmulator(EmulatorIo, StageSuite):
    @pytest.fixture
    def wire(self, pi_line):
        return pi_line

    @pytest.fixture
    def device(self, wire):
        yield from _initialized(PiGcsStage("x", wire[1], travel_mm=(0.0, 150.0), max_velocity_mm_s=50.0))


# focus ----------------------------------------------------------------------------------------------
class TestSimFocus(SimIo, FocusSuite):
    @pytest.fixture
    def device(self, world):
        yield from _initialized(SimFocus("focus", world))


class TestJenaFocusOnEmulator(EmulatorIo, FocusSuite):
    @pytest.fixture
    def wire(self, jena_line):
        return jena_line

    @pytest.fixture
    def device(self, wire):
        yield from _initialized(JenaPiezoFocus("focus", wire[1]))


# lights, shutter, trigger ---------------------------------------------------------------------------------
class TestSimLight(SimIo, LightSuite):
    @pytest.fixture
    def device(self, world):
        yield from _initialized(SimLight("uv", world, max_current_ma=500.0))


class TestFpgaLightOnEmulator(EmulatorIo, LightSuite):
    @pytest.fixture
    def wire(self, fpga_line):
        return fpga_line

    @pytest.fixture
    def device(self, wire):
        yield from _initialized(FpgaLight("uv", FpgaBoard(wire[1]), channel=2, max_current_ma=500.0))

    def test_board_holds_table_4_2_config(self, device, wire):
        cfg = device.configure(
            current_ma=123.4,
            duration_s=0.25,
            use_duration=True,
            listen_global_trigger=True,
            global_trigger_delay_s=0.0015,
        )
        assert device.read_config() == cfg
        assert wire[0].light_config[2] == bytes([0x04, 0xD2, 1, 0x00, 0x03, 0xD0, 0x90, 1, 0, 0, 0x05, 0xDC])


class TestSimShutter(SimIo, ShutterSuite):
    @pytest.fixture
    def device(self, world):
        yield from _initialized(SimShutter("shutter", world))


class TestFpgaShutterOnEmulator(EmulatorIo, ShutterSuite):
    @pytest.fixture
    def wire(self, fpga_line):
        return fpga_line

    @pytest.fixture
    def device(self, wire):
        yield from _initialized(FpgaShutter("shutter", FpgaBoard(wire[1])))


class TestSimTrigger(SimIo, TriggerSuite):
    @pytest.fixture
    def device(self, world):
        yield from _initialized(SimTrigger("trigger", world))

    @pytest.fixture
    def trigger_events(self, world):
        def events():
            return [(k, int(n) if n else -1) for k, n in world.events if k in ("global-trigger", "camera-pulse")]

        return events


class TestFpgaTriggerOnEmulator(EmulatorIo, TriggerSuite):
    @pytest.fixture
    def wire(self, fpga_line):
        return fpga_line

    @pytest.fixture
    def device(self, wire):
        yield from _initialized(FpgaTrigger("trigger", FpgaBoard(wire[1])))

    @pytest.fixture
    def trigger_events(self, wire):
        def events():
            out = []
            for _, kind, line in wire[0].events:
                if kind == "global-trigger":
                    out.append((kind, -1))
                elif kind == "camera-pulse":
                    out.append((kind, line))
            return out

        return events

    def test_global_trigger_pulses_listening_lines(self, device, wire):
        device.configure_camera_line(1, True, 0.002)
        device.configure_camera_line(2, False, 0.0)
        device.fire()
        pulses = [e for e in wire[0].events if e[1] == "camera-pulse"]
        assert [p[2] for p in pulses] == [1]


# camera -----------------------------------------------------------------------------------------------------
class TestSimCamera(SimIo, CameraSuite):
    @pytest.fixture
    def device(self, world):
        light = SimLight("led", world, max_current_ma=100.0)
        light.initialize()
        light.switch_on(50.0)
        cam = SimCamera(
            "cam",
            world,
            renderer=FlatTextureRenderer(peak=0.5),
            limits=CameraLimits(sensor_shape=(64, 80)),
            timeout_s=0.05,
        )
        yield from _initialized(cam)
