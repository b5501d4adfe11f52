"""Faults on the line give the right InstrumentError within the timeout; decoders survive random bytes."""

from __future__ import annotations

import time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from scopetwin.instrument.devices import LightConfig
from scopetwin.instrument.drivers import fpga_board as fpga
from scopetwin.instrument.drivers import jena_piezo, pi_gcs
from scopetwin.instrument.drivers.fpga_board import FpgaBoard, FpgaLight
from scopetwin.instrument.drivers.jena_piezo import JenaPiezoFocus
from scopetwin.instrument.drivers.pi_gcs import PiGcsStage
from scopetwin.instrument.emulators import Fault
from scopetwin.instrument.errors import (
    ControllerError,
    DisconnectedError,
    InstrumentError,
    InstrumentTimeout,
    OutOfRangeError,
    ProtocolError,
)

TIMEOUT_S = 0.3
EXPECTED = {
    Fault.SILENT: (InstrumentTimeout,),
    Fault.GARBAGE: (ProtocolError,),
    Fault.DROP: (DisconnectedError, InstrumentTimeout),
}


def _check_fault(emulator, fault, operation):
    emulator.fault = fault
    t0 = time.monotonic()
    with pytest.raises(EXPECTED[fault]):
        operation()
    # the error comes within the configured timeout (plus scheduling slack), never hangs
    assert time.monotonic() - t0 < TIMEOUT_S + 1.0


@pytest.mark.parametrize("fault", list(EXPECTED))
def test_pi_stage_faults(pi_line, fault):
    emulator, port = pi_line
    stage = PiGcsStage("x", port, travel_mm=(0.0, 150.0), max_velocity_mm_s=50.0, timeout_s=TIMEOUT_S)
    stage.initialize()
    _check_fault(emulator, fault, lambda: stage.position_mm)


@pytest.mark.parametrize("fault", list(EXPECTED))
def test_jena_focus_faults(jena_line, fault):
    emulator, port = jena_line
    focus = JenaPiezoFocus("focus", port, timeout_s=TIMEOUT_S)
    focus.initialize()
    _check_fault(emulator, fault, lambda: focus.move_absolute_um(10.0))


@pytest.mark.parametrize("fault", list(EXPECTED))
def test_fpga_light_faults(fpga_line, fault):
    emulator, port = fpga_line
    light = FpgaLight("uv", FpgaBoard(port, timeout_s=TIMEOUT_S), channel=0, max_current_ma=500.0)
    light.initialize()
    _check_fault(emulator, fault, lambda: light.switch_on(100.0))


def test_controller_errors_are_decoded(pi_line, jena_line):
    _, pi_port = pi_line
    stage = PiGcsStage("x", pi_port, travel_mm=(0.0, 150.0), max_velocity_mm_s=50.0)
    stage.initialize()
    with pytest.raises(ControllerError) as info:
        stage.controller.command("XYZ 1")
    assert info.value.code == 2
    with pytest.raises(OutOfRangeError):  # the controller's own limit (GCS error 7) if ours were wider
        stage.controller.command("MOV 1 151")
    emulator, jena_port = jena_line
    focus = JenaPiezoFocus("focus", jena_port)
    focus.initialize()
    with pytest.raises(ControllerError) as info:
        focus.set_command("zz")
    assert info.value.code == 1
    focus.move_absolute_um(50.0)  # the line is clean after an error
    assert focus.position_um == pytest.approx(50.0)


def test_configured_travel_beyond_controller_is_refused(pi_line):
    _, port = pi_line
    stage = PiGcsStage("x", port, travel_mm=(0.0, 200.0), max_velocity_mm_s=50.0)
    with pytest.raises(OutOfRangeError, match="exceeds"):
        stage.initialize()


# fuzzing -------------------------------------------------------------------------------------------------
DOCUMENTED = (ProtocolError,)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.binary(max_size=40), min_size=1, max_size=4))
def test_fuzz_pi_decoders(raw_lines):
    try:
        lines = pi_gcs.decode_lines(raw_lines)
    except DOCUMENTED:
        return
    for parse in (
        pi_gcs.parse_axis_values,
        lambda ls: pi_gcs.parse_error_code(ls[0]),
        lambda ls: pi_gcs.parse_motion_status(ls[0]),
    ):
        try:
            parse(lines)
        except DOCUMENTED:
            pass


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=40), st.sampled_from(sorted(jena_piezo.DIALECTS)))
def test_fuzz_jena_decoder(raw, model):
    try:
        value = jena_piezo.decode_reply(raw, jena_piezo.DIALECTS[model])
    except DOCUMENTED:
        return
    assert isinstance(value, float)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=64))
def test_fuzz_fpga_decoders(raw):
    for decode in (fpga.decode_packet, fpga.split_packets, lambda b: fpga.decode_light_config(b, 0.1)):
        try:
            decode(raw)
        except DOCUMENTED:
            pass


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 0xFFFF), st.booleans(), st.integers(0, 2**32 - 1), st.booleans(), st.integers(0, 2**32 - 1))
def test_light_config_roundtrip(index, use, duration_us, listen, delay_us):
    cfg = LightConfig(index * 0.1, duration_us * 1e-6, use, listen, delay_us * 1e-6)
    payload = fpga.encode_light_config(cfg, 0.1)
    assert len(payload) == 12  # Table 4.2: 12 bytes follow the length byte
    frame = fpga.Packet(fpga.WRITE, fpga.LIGHT_CONFIG, payload).encode()
    assert frame[:3] == bytes([0x01, 0x10, 12])
    back = fpga.decode_light_config(fpga.decode_packet(frame).payload, 0.1)
    assert back.use_duration == use and back.listen_global_trigger == listen
    assert round(back.current_ma / 0.1) == index
    assert round(back.duration_s * 1e6) == duration_us and round(back.global_trigger_delay_s * 1e6) == delay_us


class _RandomReplies:
    """A transport that answers anything with the given bytes."""

    def __init__(self, data: bytes) -> None:
        self.data = bytearray(data)
        self.timeout = 0.0
        self.is_open = True

    @property
    def in_waiting(self) -> int:
        return len(self.data)

    def read(self, n: int) -> bytes:
        out, self.data[:n] = bytes(self.data[:n]), b""
        return out

    def write(self, data: bytes) -> int:
        return len(data)

    def reset_input_buffer(self) -> None:
        pass

    def flush(self) -> None:
        pass


@settings(max_examples=60, deadline=None)
@given(st.binary(max_size=48))
def test_fuzz_drivers_on_random_replies(raw):
    board = FpgaBoard(_RandomReplies(raw), timeout_s=0.005)
    controller = pi_gcs.PiGcsController(_RandomReplies(raw), timeout_s=0.005)
    focus = JenaPiezoFocus("focus", _RandomReplies(raw), timeout_s=0.005)
    for call in (
        lambda: board.read(fpga.LIGHT_ACTION),
        lambda: board.write(fpga.GLOBAL_TRIGGER, b"\x01"),
        lambda: controller.axis_values("POS?", "1"),
        controller.motion_mask,
        controller.error_code,
        focus._read_raw,
    ):
        try:
            call()
        except InstrumentError:
            pass
