"""python-microscope's own device test mixins against the rig's devices (simulated, and drivers on emulators)."""

from __future__ import annotations

import threading
import unittest
from pathlib import Path

import pytest

pytest.importorskip("microscope", reason="python-microscope is not installed")

from microscope.testsuite.test_devices import CameraTests, DeviceTests, LightSourceTests  # noqa: E402

from scopetwin.instrument.devices import CameraLimits  # noqa: E402
from scopetwin.instrument.drivers.fpga_board import FpgaBoard, FpgaLight  # noqa: E402
from scopetwin.instrument.emulators import FpgaBoardEmulator  # noqa: E402
from scopetwin.instrument.pymicroscope import make_device_classes, microscope_devices, serve_devices  # noqa: E402
from scopetwin.instrument.rig import open_rig  # noqa: E402
from scopetwin.instrument.simulated.devices import SimCamera, SimFocus, SimLight, SimStage  # noqa: E402
from scopetwin.instrument.simulated.renderers import FlatTextureRenderer  # noqa: E402
from scopetwin.instrument.simulated.world import VirtualWorld  # noqa: E402

CLASSES = make_device_classes()
RIGS = Path(__file__).resolve().parents[2] / "rigs"


class _LightFake:
    """What LightSourceTests reads from its ``fake``: power range in mW-like units and the default."""

    min_power = 0.0
    max_power = 100.0
    default_power = 0.0


class _LightTests(LightSourceTests):
    def test_get_is_on(self):
        # the mixin reads a serial fake's ``connection.light``; ours has no serial fake: check the light itself
        self.device.enable()
        self.assertTrue(self.device.get_is_on() and self.rig_light.is_on)
        self.device.disable()
        self.assertFalse(self.device.get_is_on() or self.rig_light.is_on)


class TestSimLightAsMicroscopeLight(unittest.TestCase, _LightTests):
    def setUp(self):
        self.rig_light = SimLight("uv", VirtualWorld(), max_current_ma=500.0)
        self.rig_light.initialize()
        self.device = CLASSES["light"](self.rig_light)
        self.fake = _LightFake()


class TestFpgaLightOnEmulatorAsMicroscopeLight(unittest.TestCase, _LightTests):
    def setUp(self):
        import serial

        self.emulator = FpgaBoardEmulator()
        self.emulator.start()
        self.port = serial.Serial(self.emulator.port, 115200, timeout=0.02)
        self.rig_light = FpgaLight("uv", FpgaBoard(self.port), channel=1, max_current_ma=500.0)
        self.rig_light.initialize()
        self.device = CLASSES["light"](self.rig_light)
        self.fake = _LightFake()

    def tearDown(self):
        self.device.shutdown()
        self.port.close()
        self.emulator.stop()

    def test_board_light_follows_power(self):
        self.device.power = 0.5
        self.device.enable()
        self.assertEqual(self.emulator.lights_on(), [1])
        self.assertAlmostEqual(self.rig_light.current_ma, 250.0)
        self.device.disable()
        self.assertEqual(self.emulator.lights_on(), [])


class TestSimCameraAsMicroscopeCamera(unittest.TestCase, CameraTests):
    def setUp(self):
        world = VirtualWorld()
        light = SimLight("led", world, max_current_ma=100.0)
        light.initialize()
        light.switch_on(50.0)
        self.rig_camera = SimCamera(
            "cam", world, renderer=FlatTextureRenderer(), limits=CameraLimits(sensor_shape=(48, 64)), timeout_s=0.05
        )
        self.rig_camera.initialize()
        self.device = CLASSES["camera"](self.rig_camera)

    def tearDown(self):
        self.device.shutdown()

    def test_software_trigger_delivers_a_frame(self):
        frames = []
        self.device.enable()
        self.device._fetch_data()  # nothing triggered yet: nothing
        self.device.trigger()
        frames.append(self.device._fetch_data())
        self.assertEqual(frames[0].shape, (48, 64))
        self.assertGreater(frames[0].mean(), 100)
        self.assertEqual(self.device.get_sensor_shape(), (64, 48))

    def test_exposure_roi_binning_map_to_the_rig_camera(self):
        import microscope

        self.device.set_exposure_time(0.02)
        self.assertAlmostEqual(self.rig_camera.exposure_s, 0.02)
        self.device.set_roi(microscope.ROI(8, 4, 32, 16))  # left, top, width, height
        self.assertEqual((self.rig_camera.roi.row, self.rig_camera.roi.col), (4, 8))
        self.assertEqual(self.rig_camera.frame_shape, (16, 32))
        self.assertEqual(self.device.get_setting("bit depth"), 12)


class TestSimStagesAsMicroscopeStage(unittest.TestCase, DeviceTests):
    def setUp(self):
        world = VirtualWorld()
        self.x = SimStage("x", world, travel_mm=(0.0, 150.0), max_velocity_mm_s=50.0)
        self.y = SimStage("y", world, travel_mm=(0.0, 300.0), max_velocity_mm_s=100.0)
        for d in (self.x, self.y):
            d.initialize()
        self.device = CLASSES["stage"]({"x": self.x, "y": self.y})

    def test_moves_in_micrometres_and_clips_to_limits(self):
        self.device.enable()
        self.device.move_to({"x": 1500.0, "y": 2500.0})
        self.assertAlmostEqual(self.x.position_mm, 1.5)
        self.assertEqual(self.device.position, {"x": 1500.0, "y": 2500.0})
        self.device.move_by({"x": -1e9})  # clipped to the lower limit, no exception
        self.assertAlmostEqual(self.x.position_mm, 0.0)
        self.assertEqual(self.device.axes["y"].limits.upper, 300000.0)
        self.assertFalse(self.device.may_move_on_enable())


class TestFocusAsMicroscopeStage(unittest.TestCase, DeviceTests):
    def setUp(self):
        self.focus = SimFocus("focus", VirtualWorld())
        self.focus.initialize()
        self.device = CLASSES["stage"]({"z": self.focus})

    def test_z_axis_in_micrometres(self):
        self.device.axes["z"].move_to(123.5)
        self.assertAlmostEqual(self.focus.position_um, 123.5)
        self.assertEqual(self.device.axes["z"].limits.upper, 400.0)


def test_microscope_devices_of_emulated_hardware_rig():
    import microscope.abc

    with open_rig(RIGS / "emulated-hardware.toml") as rig:
        devices = microscope_devices(rig)
        assert set(devices) == {"camera", "uv", "blue_led", "halogen", "deep_red", "xy", "focus"}
        assert all(isinstance(d, microscope.abc.Device) for d in devices.values())
        assert isinstance(devices["xy"], microscope.abc.Stage) and isinstance(devices["uv"], microscope.abc.LightSource)
        devices["uv"].power = 0.4
        devices["uv"].enable()
        board = rig.light("uv").board.link.transport.emulator
        assert board.lights_on() == [0]
        devices["xy"].move_to({"x": 2000.0})
        assert rig.stage("x").position_mm == pytest.approx(2.0)
        devices["uv"].disable()
        assert board.lights_on() == []


def test_served_devices_answer_a_python_microscope_client():
    from scopetwin.instrument.pymicroscope import connect

    key = b"k" * 32
    world = VirtualWorld()
    light = SimLight("uv", world, max_current_ma=500.0)
    light.initialize()
    stop = threading.Event()
    uris: dict = {}
    got = threading.Event()
    thread = threading.Thread(
        target=serve_devices,
        args=({"uv": CLASSES["light"](light)},),
        kwargs={"key": key, "port": 0, "stop": stop, "ready": lambda u: (uris.update(u), got.set())},
        daemon=True,
    )
    thread.start()
    assert got.wait(10)
    assert "127.0.0.1" in uris["uv"]
    client = connect(uris["uv"], key)  # python-microscope's Client, signing with the server's key
    client.enable()
    assert light.is_on
    client.disable()
    assert not light.is_on
    stop.set()
    thread.join(5)
