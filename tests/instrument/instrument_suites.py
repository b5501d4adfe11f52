"""Device test suites, one per device protocol (python-microscope style mixins).

Each suite is mixed into a concrete test class that provides two fixtures:
``device`` (an initialised device) and ``io_count`` (a callable returning how
much I/O has happened so far: bytes an emulator received, or operations a
simulated world logged). The trigger suite also needs ``trigger_events``: a
callable returning the trigger events the world or the emulator recorded so far,
as ``(kind, line)`` pairs (``("global-trigger", -1)``, ``("camera-pulse", 3)``).
The same tests run against the simulated device and the driver talking to its
emulator through a pseudo-terminal. Every test asserts something that fails when
the device does nothing.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from scopetwin.instrument.devices import TriggerMode, TriggerType
from scopetwin.instrument.errors import InstrumentTimeout, OutOfRangeError


class StageSuite:
    """A stage axis: moves, velocity, and limits checked before any I/O."""

    def test_move_absolute_reaches_target(self, device):
        target = device.travel.low + 1.25
        device.move_absolute(target)
        assert device.position_mm == pytest.approx(target, abs=1e-5)
        assert not device.is_moving()

    def test_move_relative_adds_step(self, device):
        device.move_absolute(device.travel.low + 1.0)
        device.move_relative(0.5)
        device.move_relative(-0.25)
        assert device.position_mm == pytest.approx(device.travel.low + 1.25, abs=1e-5)

    def test_velocity_roundtrip(self, device):
        device.set_velocity(device.velocity_range.high / 2)
        assert device.velocity_mm_s == pytest.approx(device.velocity_range.high / 2, rel=1e-6)

    @pytest.mark.parametrize("offset", [1e-3, 10.0, math.inf, math.nan])
    def test_target_beyond_travel_sends_nothing(self, device, io_count, offset):
        before = io_count()
        with pytest.raises(OutOfRangeError):
            device.move_absolute(device.travel.high + offset)
        assert io_count() == before

    def test_velocity_above_maximum_sends_nothing(self, device, io_count):
        before = io_count()
        with pytest.raises(OutOfRangeError):
            device.set_velocity(device.velocity_range.high * 1.01)
        with pytest.raises(OutOfRangeError):
            device.set_velocity(0.0)
        assert io_count() == before

    def test_relative_step_beyond_travel_does_not_move(self, device):
        device.move_absolute(device.travel.low + 1.0)
        with pytest.raises(OutOfRangeError):
            device.move_relative(-2.0)
        assert device.position_mm == pytest.approx(device.travel.low + 1.0, abs=1e-5)

    def test_describe_has_limits(self, device):
        info = device.describe()
        assert info["kind"] == "stage" and info["travel_mm"] == device.travel.as_list()


class FocusSuite:
    """A focus drive in µm: moves and its 0-400 µm range checked before any I/O."""

    @pytest.mark.parametrize("target", [0.0, 123.456, 400.0])
    def test_move_absolute_reaches_target(self, device, target):
        device.move_absolute_um(target)
        assert device.position_um == pytest.approx(target, abs=device.tolerance_um)

    def test_move_relative(self, device):
        device.move_absolute_um(100.0)
        device.move_relative_um(-12.5)
        assert device.position_um == pytest.approx(87.5, abs=device.tolerance_um)

    @pytest.mark.parametrize("target", [-0.001, 400.001, 1e6, math.nan])
    def test_outside_range_sends_nothing(self, device, io_count, target):
        before = io_count()
        with pytest.raises(OutOfRangeError):
            device.move_absolute_um(target)
        assert io_count() == before


class LightSuite:
    """A light source: configuration, on/off, and the current limit checked before any I/O."""

    def test_switch_on_and_off(self, device):
        device.switch_on(device.current_range.high / 2)
        assert device.is_on
        device.switch_off()
        assert not device.is_on

    def test_configure_keeps_all_fields(self, device):
        cfg = device.configure(
            current_ma=device.current_range.high * 0.25,
            duration_s=0.0125,
            use_duration=True,
            listen_global_trigger=True,
            global_trigger_delay_s=0.002,
        )
        assert device.config == cfg
        assert cfg.current_ma == pytest.approx(device.current_range.high * 0.25)

    @pytest.mark.parametrize(
        "changes",
        [
            {"current_ma": 1e9},
            {"current_ma": -1.0},
            {"duration_s": 1e4},
            {"global_trigger_delay_s": -1e-3},
            {"colour": 3},
        ],
    )
    def test_bad_settings_send_nothing(self, device, io_count, changes):
        before = io_count()
        with pytest.raises(OutOfRangeError):
            device.configure(**changes)
        assert io_count() == before

    def test_current_just_above_maximum_sends_nothing(self, device, io_count):
        before = io_count()
        with pytest.raises(OutOfRangeError):
            device.switch_on(device.current_range.high + 0.5)
        assert io_count() == before
        assert not device.is_on


class ShutterSuite:
    """A shutter: open, close, state."""

    def test_open_close(self, device):
        device.open()
        assert device.is_open
        device.close()
        assert not device.is_open

    def test_shutdown_closes(self, device):
        device.open()
        device.shutdown()
        device.initialize()
        assert not device.is_open


class TriggerSuite:
    """The trigger controller: camera lines and the global trigger."""

    def test_fire_and_pulse(self, device, trigger_events):
        before = len(trigger_events())
        device.configure_camera_line(0, True, 0.001)
        device.fire()
        device.trigger_camera(3)
        new = trigger_events()[before:]
        assert ("global-trigger", -1) in new and ("camera-pulse", 3) in new
        assert new.index(("global-trigger", -1)) < new.index(("camera-pulse", 3))  # in the order sent
        assert ("camera-pulse", 2) not in new  # only the line asked for

    @pytest.mark.parametrize("line", [-1, 4, 1.5])
    def test_bad_line_sends_nothing(self, device, io_count, line):
        before = io_count()
        with pytest.raises(OutOfRangeError):
            device.configure_camera_line(line, True)
        with pytest.raises(OutOfRangeError):
            device.trigger_camera(line)
        assert io_count() == before

    def test_negative_delay_sends_nothing(self, device, io_count):
        before = io_count()
        with pytest.raises(OutOfRangeError):
            device.configure_camera_line(0, True, -1e-6)
        assert io_count() == before


class CameraSuite:
    """A camera: frames, settings, trigger model, limits checked before any I/O."""

    def test_grab_returns_float_frame_of_roi(self, device):
        device.set_roi(8, 16, 32, 48)
        frame = device.grab()
        assert frame.dtype == np.float32 and frame.shape == (32, 48) == device.frame_shape
        assert 0 <= frame.min() and frame.max() <= device.saturation_dn

    def test_binning_halves_frame(self, device):
        device.set_roi(0, 0, 32, 48)
        device.set_binning(2)
        assert device.grab().shape == (16, 24)

    def test_settings_roundtrip(self, device):
        device.set_exposure_s(0.005)
        device.set_gain_db(device.limits.gain_db.low)
        device.set_black_level_dn(device.limits.black_level_dn.low)
        device.set_bit_depth(max(device.limits.bit_depths))
        device.set_fps(min(10.0, device.limits.fps.high))
        assert device.exposure_s == pytest.approx(0.005, rel=1e-3)
        assert device.saturation_dn == 2 ** max(device.limits.bit_depths) - 1
        assert device.serial_number

    @pytest.mark.parametrize(
        "call",
        [
            lambda c: c.set_exposure_s(c.limits.exposure_s.high * 2),
            lambda c: c.set_exposure_s(-1.0),
            lambda c: c.set_roi(0, 0, c.sensor_shape[0] + 1, 8),
            lambda c: c.set_roi(c.sensor_shape[0] - 4, 0, 8, 8),
            lambda c: c.set_binning(3),
            lambda c: c.set_bit_depth(7),
            lambda c: c.set_gain_db(c.limits.gain_db.high + 1),
            lambda c: c.set_trigger(TriggerType.SOFTWARE, TriggerMode.BULB),
        ],
    )
    def test_bad_settings_send_nothing(self, device, io_count, call):
        before = io_count()
        with pytest.raises(OutOfRangeError):
            call(device)
        assert io_count() == before

    def test_stream_yields_frames(self, device):
        device.set_roi(0, 0, 16, 16)
        frames = list(device.stream(3))
        assert len(frames) == 3 and all(f.shape == (16, 16) for f in frames)

    def test_hardware_trigger_without_arm_times_out(self, device):
        device.set_trigger(TriggerType.RISING_EDGE)
        with pytest.raises(InstrumentTimeout):
            device.grab(timeout_s=0.05)
        device.set_trigger(TriggerType.SOFTWARE)
        assert device.grab().ndim == 2
