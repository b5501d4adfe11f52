"""Driver of the FPGA light/trigger board (thesis §4.3.1) and its binary packets (Table 4.2).

Every packet is ``opcode, address, length, payload[length]`` with multi-byte
fields big-endian. The thesis documents the write of a light-source
configuration (Table 4.2): opcode 0x01, the light's address, length 12, then
current index (16 bit), use-duration flag (8 bit), duration (32 bit), listen to
global trigger (8 bit), global trigger delay (32 bit). The rest of the map
below follows the same packet layout; it is this project's assumption about the
board (the thesis shows only Table 4.2), and the emulator implements the same map:

========  ==========================  ===================================
address   register                    payload
========  ==========================  ===================================
0x10+i    light i configuration       Table 4.2 (12 bytes)
0x18+i    light i action / state      1 byte: 1 trigger, 0 switch off
0x20+i    camera line i configuration 1 byte listen + 4 bytes delay (µs)
0x28+i    camera line i pulse         1 byte: 1
0x30+k    TTL output k (shutter)      1 byte level
0x40      global trigger              1 byte: 1 fire
0x7F      identification (read)       ASCII
========  ==========================  ===================================

Opcodes: 0x01 write, 0x02 read; the board answers ``opcode | 0x80`` with the
same address (an empty payload for a write, the register for a read) or
``0xFF, address, 1, code`` for an error. Durations and delays count
microseconds; the current index counts steps of ``current_step_ma``.

:func:`decode_packet` and :func:`split_packets` raise only
:class:`~scopetwin.instrument.errors.ProtocolError`.
"""

from __future__ import annotations

import struct
import threading
import time
from dataclasses import dataclass
from typing import Any

from scopetwin.instrument.devices import LightConfig, LightSource, Shutter, TriggerController
from scopetwin.instrument.errors import ControllerError, OutOfRangeError, ProtocolError
from scopetwin.instrument.transport import Link

WRITE, READ, ERROR = 0x01, 0x02, 0xFF
ACK_WRITE, ACK_READ = WRITE | 0x80, READ | 0x80
LIGHT_CONFIG, LIGHT_ACTION, CAMERA_CONFIG, CAMERA_PULSE, TTL_OUTPUT = 0x10, 0x18, 0x20, 0x28, 0x30
GLOBAL_TRIGGER, IDENTIFICATION = 0x40, 0x7F
N_LIGHTS = N_CAMERA_LINES = 4
N_TTL = 4
VALID_OPCODES = {WRITE, READ, ACK_WRITE, ACK_READ, ERROR}
LIGHT_STRUCT = struct.Struct(">HBIBI")  # Table 4.2, bytes 3..14
CAMERA_STRUCT = struct.Struct(">BI")
BOARD_ERRORS = {1: "unknown opcode", 2: "unknown address", 3: "wrong length", 4: "value out of range"}


@dataclass(frozen=True)
class Packet:
    """One board packet: ``opcode, address, len(payload), payload``."""

    opcode: int
    address: int
    payload: bytes = b""

    def encode(self) -> bytes:
        """The packet's bytes (Table 4.2 layout)."""
        return encode_packet(self)


def encode_packet(packet: Packet) -> bytes:
    """Encode a packet; raise ``OutOfRangeError`` for fields that do not fit a byte."""
    for what, value in (("opcode", packet.opcode), ("address", packet.address), ("length", len(packet.payload))):
        if not 0 <= value <= 0xFF:
            raise OutOfRangeError(f"FPGA packet {what} {value} does not fit one byte")
    return bytes([packet.opcode, packet.address, len(packet.payload)]) + bytes(packet.payload)


def decode_packet(data: bytes) -> Packet:
    """Decode exactly one complete packet.

    Raises
    ------
    ProtocolError
        Unknown opcode, or a length byte that disagrees with the data.
    """
    if len(data) < 3:
        raise ProtocolError(f"FPGA packet too short: {bytes(data[:16])!r}")
    opcode, address, length = data[0], data[1], data[2]
    if opcode not in VALID_OPCODES:
        raise ProtocolError(f"FPGA packet with unknown opcode 0x{opcode:02X}")
    if len(data) != 3 + length:
        raise ProtocolError(f"FPGA packet length byte {length} but {len(data) - 3} payload bytes")
    return Packet(opcode, address, bytes(data[3:]))


def split_packets(buffer: bytes) -> tuple[list[Packet], bytes]:
    """Split a byte stream into complete packets and the incomplete rest.

    Raises
    ------
    ProtocolError
        At the first byte that cannot start a packet.
    """
    packets: list[Packet] = []
    i = 0
    while len(buffer) - i >= 3:
        length = buffer[i + 2]
        if len(buffer) - i < 3 + length:
            break
        packets.append(decode_packet(buffer[i : i + 3 + length]))
        i += 3 + length
    if i < len(buffer) and buffer[i] not in VALID_OPCODES:
        raise ProtocolError(f"FPGA stream: unknown opcode 0x{buffer[i]:02X}")
    return packets, bytes(buffer[i:])


def seconds_to_us(seconds: float) -> int:
    """A duration in seconds as the board's 32-bit microsecond count."""
    us = round(float(seconds) * 1e6)
    if not 0 <= us <= 0xFFFFFFFF:
        raise OutOfRangeError(f"duration {seconds} s does not fit the board's 32-bit microsecond counter")
    return us


def encode_light_config(config: LightConfig, current_step_ma: float) -> bytes:
    """The 12 payload bytes of Table 4.2 for ``config``."""
    index = round(config.current_ma / current_step_ma)
    if not 0 <= index <= 0xFFFF:
        raise OutOfRangeError(f"current {config.current_ma} mA is beyond the board's 16-bit current index")
    return LIGHT_STRUCT.pack(
        index,
        int(config.use_duration),
        seconds_to_us(config.duration_s),
        int(config.listen_global_trigger),
        seconds_to_us(config.global_trigger_delay_s),
    )


def decode_light_config(payload: bytes, current_step_ma: float) -> LightConfig:
    """Inverse of :func:`encode_light_config`; raises ``ProtocolError`` on a wrong length or flag."""
    if len(payload) != LIGHT_STRUCT.size:
        raise ProtocolError(f"light configuration of {len(payload)} bytes, expected {LIGHT_STRUCT.size}")
    index, use, duration, listen, delay = LIGHT_STRUCT.unpack(payload)
    if use > 1 or listen > 1:
        raise ProtocolError(f"light configuration flags must be 0 or 1, got {use}, {listen}")
    return LightConfig(
        current_ma=index * current_step_ma,
        duration_s=duration * 1e-6,
        use_duration=bool(use),
        listen_global_trigger=bool(listen),
        global_trigger_delay_s=delay * 1e-6,
    )


class FpgaBoard:
    """The board on a transport: register writes and reads with acknowledgement.

    Parameters
    ----------
    transport
        Open transport (USB serial device or URL).
    timeout_s : float
        Timeout of one exchange.
    current_step_ma : float
        Milliamperes per step of the current index.
    """

    def __init__(
        self, transport: Any, *, timeout_s: float = 1.0, current_step_ma: float = 0.1, name: str = "FPGA board"
    ) -> None:
        self.link = Link(transport, timeout_s=timeout_s, name=name)
        self.current_step_ma = float(current_step_ma)
        self.name = name
        self._users = 0
        self._lock = threading.Lock()

    def _exchange(self, packet: Packet, expect: int) -> bytes:
        with self.link.exchange():
            stale = self.link.cut  # the previous exchange was cut short: its answer may come before this one's
            self.link.write(packet.encode())
            deadline = time.monotonic() + self.link.timeout_s
            reply = self._read_reply(deadline)
            if stale and (reply.opcode, reply.address) != (expect, packet.address):
                reply = self._read_reply(deadline)  # that was the answer of the request cut short: skip it once
            if reply.opcode == ERROR:
                code = reply.payload[0] if reply.payload else 0
                raise ControllerError(
                    f"{self.name}: register 0x{packet.address:02X}: board error {code} "
                    f"({BOARD_ERRORS.get(code, 'unknown')})",
                    code,
                )
            if reply.opcode != expect or reply.address != packet.address:
                raise ProtocolError(
                    f"{self.name}: expected reply 0x{expect:02X}/0x{packet.address:02X}, "
                    f"got 0x{reply.opcode:02X}/0x{reply.address:02X}"
                )
            return reply.payload

    def _read_reply(self, deadline: float) -> Packet:
        """One reply packet (Table 4.2 layout) before ``deadline``."""
        header = self.link.read_exact(3, deadline)
        opcode, _, length = header
        if opcode not in VALID_OPCODES:
            raise ProtocolError(f"{self.name}: reply with unknown opcode 0x{opcode:02X}")
        payload = self.link.read_exact(length, deadline) if length else b""
        return decode_packet(header + payload)

    def write(self, address: int, payload: bytes) -> None:
        """Write a register and wait for the acknowledgement."""
        self._exchange(Packet(WRITE, address, payload), ACK_WRITE)

    def read(self, address: int) -> bytes:
        """Read a register."""
        return self._exchange(Packet(READ, address), ACK_READ)

    def identify(self) -> str:
        """The board's identification string."""
        with self.link.exchange():
            raw = self.read(IDENTIFICATION)
            try:
                return raw.decode("ascii")
            except UnicodeDecodeError as exc:
                raise ProtocolError(f"{self.name}: identification is not ASCII") from exc

    def acquire(self) -> None:
        """Count one more device using the board (the first identifies it)."""
        with self._lock:
            if self._users == 0:
                self.identify()
            self._users += 1

    def release(self) -> None:
        """Count one device less (the transport belongs to whoever opened it and stays open)."""
        with self._lock:
            self._users = max(0, self._users - 1)


def _one_byte(payload: bytes, what: str) -> int:
    if len(payload) != 1:
        raise ProtocolError(f"FPGA board: {what} register of {len(payload)} bytes, expected 1")
    return payload[0]


class FpgaLight(LightSource):
    """Light source channel ``channel`` (0-3) of the board."""

    driver = "fpga-board"

    def __init__(self, name: str, board: FpgaBoard, *, channel: int, max_current_ma: float) -> None:
        super().__init__(name, max_current_ma=max_current_ma)
        if channel not in range(N_LIGHTS):
            raise OutOfRangeError(f"light {name!r}: channel {channel} not in 0..{N_LIGHTS - 1}")
        if round(max_current_ma / board.current_step_ma) > 0xFFFF:
            raise OutOfRangeError(f"light {name!r}: {max_current_ma} mA exceeds the board's current index")
        self.board = board
        self.channel = int(channel)

    def links(self) -> tuple[Link, ...]:
        """The board's serial line (shared by every device on the board)."""
        return (self.board.link,)

    def _do_initialize(self) -> None:
        self.board.acquire()
        self._do_switch_off()

    def _do_shutdown(self) -> None:
        self.board.release()

    def _do_configure(self, config: LightConfig) -> None:
        self.board.write(LIGHT_CONFIG + self.channel, encode_light_config(config, self.board.current_step_ma))

    def read_config(self) -> LightConfig:
        """The configuration as stored on the board."""
        self._require()
        return decode_light_config(self.board.read(LIGHT_CONFIG + self.channel), self.board.current_step_ma)

    def _do_trigger(self) -> None:
        self.board.write(LIGHT_ACTION + self.channel, b"\x01")

    def _do_switch_off(self) -> None:
        self.board.write(LIGHT_ACTION + self.channel, b"\x00")

    def _do_is_on(self) -> bool:
        return bool(_one_byte(self.board.read(LIGHT_ACTION + self.channel), "light state"))


class FpgaShutter(Shutter):
    """Shutter on two TTL outputs: ``open_output`` high opens, ``close_output`` high closes."""

    driver = "fpga-board"

    def __init__(self, name: str, board: FpgaBoard, *, open_output: int = 0, close_output: int = 1) -> None:
        super().__init__(name)
        for output in (open_output, close_output):
            if output not in range(N_TTL):
                raise OutOfRangeError(f"shutter {name!r}: TTL output {output} not in 0..{N_TTL - 1}")
        self.board = board
        self.open_output, self.close_output = int(open_output), int(close_output)

    def links(self) -> tuple[Link, ...]:
        """The board's serial line (shared by every device on the board)."""
        return (self.board.link,)

    def _do_initialize(self) -> None:
        self.board.acquire()

    def _do_shutdown(self) -> None:
        self.board.release()

    def _do_set_open(self, is_open: bool) -> None:
        self.board.write(TTL_OUTPUT + self.close_output, bytes([int(not is_open)]))
        self.board.write(TTL_OUTPUT + self.open_output, bytes([int(is_open)]))

    def _do_is_open(self) -> bool:
        return bool(_one_byte(self.board.read(TTL_OUTPUT + self.open_output), "TTL"))


class FpgaTrigger(TriggerController):
    """Global trigger and camera trigger lines of the board."""

    driver = "fpga-board"

    def __init__(self, name: str, board: FpgaBoard) -> None:
        super().__init__(name, n_camera_lines=N_CAMERA_LINES)
        self.board = board

    def links(self) -> tuple[Link, ...]:
        """The board's serial line (shared by every device on the board)."""
        return (self.board.link,)

    def _do_initialize(self) -> None:
        self.board.acquire()

    def _do_shutdown(self) -> None:
        self.board.release()

    def _do_configure_camera_line(self, line: int, listen: bool, delay_s: float) -> None:
        self.board.write(CAMERA_CONFIG + line, CAMERA_STRUCT.pack(int(listen), seconds_to_us(delay_s)))

    def _do_trigger_camera(self, line: int) -> None:
        self.board.write(CAMERA_PULSE + line, b"\x01")

    def _do_fire(self) -> None:
        self.board.write(GLOBAL_TRIGGER, b"\x01")
