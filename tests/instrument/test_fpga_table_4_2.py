"""Thesis Table 4.2 ('Machine instruction for the configuration of a light source'), checked against bytes
worked out by hand from the table, not by any encoder of the project.

The table: byte 0 = 0x01 (write), 1 = address of the light source, 2 = 12 (number of following bytes),
3-4 = current index MSB..LSB, 5 = use duration, 6-9 = duration MSB..LSB, 10 = listen to global trigger,
11-14 = global trigger delay MSB..LSB. Durations and delays count microseconds, the current index
steps of 0.1 mA (the driver's default ``current_step_ma``); light i sits at address 0x10 + i.

Worked examples (hex by hand):

- light 1, 123.4 mA, duration 0.25 s, use it, listen, delay 1.5 ms:
  index 1234 = 0x04D2; 250000 us = 0x0003D090; 1500 us = 0x000005DC.
- light 3, 6000.0 mA, duration 16.909060 s, do not use it, do not listen, delay 0.197121 s:
  index 60000 = 0xEA60; 16909060 us = 0x01020304; 197121 us = 0x00030201.
"""

from __future__ import annotations

import time

import pytest

from scopetwin.instrument.devices import LightConfig
from scopetwin.instrument.drivers.fpga_board import (
    WRITE,
    Packet,
    decode_light_config,
    decode_packet,
    encode_light_config,
)
from scopetwin.instrument.emulators.fpga_board import FpgaBoardEmulator, read_light_config

CASES = [
    (
        1,
        LightConfig(
            current_ma=123.4,
            duration_s=0.25,
            use_duration=True,
            listen_global_trigger=True,
            global_trigger_delay_s=0.0015,
        ),
        b"\x01\x11\x0c\x04\xd2\x01\x00\x03\xd0\x90\x01\x00\x00\x05\xdc",
        (1234, 1, 250000, 1, 1500),
    ),
    (
        3,
        LightConfig(
            current_ma=6000.0,
            duration_s=16.909060,
            use_duration=False,
            listen_global_trigger=False,
            global_trigger_delay_s=0.197121,
        ),
        b"\x01\x13\x0c\xea\x60\x00\x01\x02\x03\x04\x00\x00\x03\x02\x01",
        (60000, 0, 16909060, 0, 197121),
    ),
]


@pytest.mark.parametrize(("channel", "config", "wire", "fields"), CASES)
def test_driver_encodes_table_4_2_bytes(channel, config, wire, fields):
    assert len(wire) == 15  # bytes 0..14 of Table 4.2
    packet = Packet(WRITE, 0x10 + channel, encode_light_config(config, 0.1))
    assert packet.encode() == wire


@pytest.mark.parametrize(("channel", "config", "wire", "fields"), CASES)
def test_driver_decodes_table_4_2_bytes(channel, config, wire, fields):
    packet = decode_packet(wire)
    assert (packet.opcode, packet.address) == (0x01, 0x10 + channel)
    back = decode_light_config(packet.payload, 0.1)
    assert back.current_ma == pytest.approx(config.current_ma)
    assert back.duration_s == pytest.approx(config.duration_s, abs=1e-9)
    assert back.global_trigger_delay_s == pytest.approx(config.global_trigger_delay_s, abs=1e-9)
    assert (back.use_duration, back.listen_global_trigger) == (config.use_duration, config.listen_global_trigger)


@pytest.mark.parametrize(("channel", "config", "wire", "fields"), CASES)
def test_emulator_reads_table_4_2_bytes(channel, config, wire, fields):
    assert read_light_config(wire[3:]) == fields
    board = FpgaBoardEmulator()
    assert board.handle(wire) == bytes([0x81, 0x10 + channel, 0])  # acknowledged write
    assert board.light_config[channel] == wire[3:]


def test_emulator_acts_on_the_hand_made_fields():
    """The emulator's behaviour follows the fields at the table's byte positions: the delay (bytes 11-14)
    switches the light on after the global trigger, the duration (bytes 6-9) switches it off again."""
    board = FpgaBoardEmulator()
    assert board.handle(CASES[0][2]) == b"\x81\x11\x00"
    t0 = time.monotonic()
    assert board.handle(b"\x01\x40\x01\x01") == b"\x81\x40\x00"  # global trigger
    on = [t for t, kind, ch in board.events if kind == "light-on" and ch == 1]
    assert len(on) == 1 and on[0] - t0 == pytest.approx(0.0015, abs=0.05)
    assert board.light_on(1, on[0] + 0.2499) and not board.light_on(1, on[0] + 0.2501)
    assert not board.light_on(3, on[0] + 0.1)  # light 3 does not listen


def test_emulator_checks_the_current_index_in_bytes_3_and_4():
    board = FpgaBoardEmulator(max_current_index=1233)
    assert board.handle(CASES[0][2]) == b"\xff\x11\x01\x04"  # error 4: value out of range
    board = FpgaBoardEmulator(max_current_index=1234)
    assert board.handle(CASES[0][2]) == b"\x81\x11\x00"
