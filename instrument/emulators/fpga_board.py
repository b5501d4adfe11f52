"""Emulator of the FPGA light/trigger board (thesis §4.3.1, Table 4.2 packets) on a pseudo-terminal.

Implements the register map of :mod:`scopetwin.instrument.drivers.fpga_board`. Lights
switch on by their action register or by the global trigger (when listening,
after their delay), and off by the action register or when their duration
ends (``use_duration``). Every switching and trigger pulse is recorded in
:attr:`FpgaBoardEmulator.events` with its time, so tests can check that lights
ended up off and that cameras and lights were triggered together.

The emulator shares the register *addresses* with the driver but not its
encoders: it reads the Table 4.2 payload byte by byte as the thesis's table lays
it out (:func:`read_light_config`), so a field swapped in the driver's struct
cannot pass a round trip through the emulator.
"""

from __future__ import annotations

import time
from typing import Any

from scopetwin.instrument.drivers.fpga_board import (
    ACK_READ,
    ACK_WRITE,
    CAMERA_CONFIG,
    CAMERA_PULSE,
    ERROR,
    GLOBAL_TRIGGER,
    IDENTIFICATION,
    LIGHT_ACTION,
    LIGHT_CONFIG,
    N_CAMERA_LINES,
    N_LIGHTS,
    N_TTL,
    READ,
    TTL_OUTPUT,
    WRITE,
)
from scopetwin.instrument.emulators.base import PtyEmulator, number_in

#: Table 4.2, byte 2: "12 (number of following bytes)".
LIGHT_CONFIG_LENGTH = 12
#: Camera line configuration: listen (byte 3), delay in µs (bytes 4-7, MSB first).
CAMERA_CONFIG_LENGTH = 5


def read_light_config(payload: bytes) -> tuple[int, int, int, int, int]:
    """The fields of a light configuration, read by the byte numbers of thesis Table 4.2.

    Parameters
    ----------
    payload : bytes
        Bytes 3-14 of the packet (the 12 bytes after the length byte).

    Returns
    -------
    tuple of int
        ``(current_index, use_duration, duration_us, listen_global_trigger, global_trigger_delay_us)``.
    """
    b = payload
    current_index = (b[0] << 8) | b[1]  # bytes 3 (MSB), 4 (LSB)
    use_duration = b[2]  # byte 5
    duration_us = (b[3] << 24) | (b[4] << 16) | (b[5] << 8) | b[6]  # bytes 6 (MSB) .. 9 (LSB)
    listen = b[7]  # byte 10
    delay_us = (b[8] << 24) | (b[9] << 16) | (b[10] << 8) | b[11]  # bytes 11 (MSB) .. 14 (LSB)
    return current_index, use_duration, duration_us, listen, delay_us


def read_camera_config(payload: bytes) -> tuple[int, int]:
    """``(listen, delay_us)`` of a camera line configuration (1 byte flag, 32-bit delay, MSB first)."""
    return payload[0], int.from_bytes(payload[1:5], "big")


class FpgaBoardEmulator(PtyEmulator):
    """The board: four current-controlled light outputs, four camera lines, TTL outputs, global trigger.

    Parameters
    ----------
    max_current_index : int
        Largest current index the light outputs accept (error 4 beyond).
    """

    protocol = "fpga-board"
    terminator = b""

    def __init__(
        self, *, max_current_index: int = 0xFFFF, seed: int = 0, fault: str = "none", fault_after: int = 0
    ) -> None:
        super().__init__(seed=seed, fault=fault, fault_after=fault_after)
        index = number_in(max_current_index, "max_current_index", 1, 0xFFFF)
        if index != int(index):
            raise ValueError(f"max_current_index must be an integer in [1, 65535], got {max_current_index!r}")
        self.max_current_index = int(index)
        self.light_config = {i: bytes(LIGHT_CONFIG_LENGTH) for i in range(N_LIGHTS)}
        self.camera_config = {i: bytes(CAMERA_CONFIG_LENGTH) for i in range(N_CAMERA_LINES)}
        self.ttl = dict.fromkeys(range(N_TTL), 0)
        self._on_from = dict.fromkeys(range(N_LIGHTS), float("inf"))
        self._on_until = dict.fromkeys(range(N_LIGHTS), float("-inf"))
        self.events: list[tuple[float, str, int]] = []

    # state ------------------------------------------------------------------------------------
    def light_on(self, channel: int, now: float | None = None) -> bool:
        """Whether light ``channel`` emits at time ``now`` (monotonic clock)."""
        t = time.monotonic() if now is None else now
        return self._on_from[channel] <= t < self._on_until[channel]

    def any_light_on(self) -> bool:
        """Whether any light output is on now."""
        return any(self.light_on(i) for i in range(N_LIGHTS))

    def lights_on(self) -> list[int]:
        """The channels that emit now."""
        return [i for i in range(N_LIGHTS) if self.light_on(i)]

    def light_level(self, channel: int, current_step_ma: float, max_current_ma: float) -> float:
        """Relative output of light ``channel`` now: its current over ``max_current_ma``, 0 when off.

        This is what a simulated camera of the same rig sees (the world's light probe).
        """
        with self._lock:
            if not self.light_on(channel):
                return 0.0
            index = read_light_config(self.light_config[channel])[0]
        return index * float(current_step_ma) / float(max_current_ma)

    def state(self) -> dict[str, Any]:
        """``lights_on`` (channels that emit now), the TTL outputs and each light's configuration."""
        with self._lock:
            configs = {ch: read_light_config(raw) for ch, raw in self.light_config.items()}
            return {
                "lights_on": self.lights_on(),
                "ttl": [self.ttl[k] for k in range(N_TTL)],
                "lights": {
                    str(ch): {
                        "current_index": c[0],
                        "use_duration": bool(c[1]),
                        "duration_us": c[2],
                        "listen_global_trigger": bool(c[3]),
                        "global_trigger_delay_us": c[4],
                    }
                    for ch, c in configs.items()
                },
            }

    def _switch_on(self, channel: int, start: float) -> None:
        _, use, duration_us, _, _ = read_light_config(self.light_config[channel])
        self._on_from[channel] = start
        self._on_until[channel] = start + duration_us * 1e-6 if use else float("inf")
        self.events.append((start, "light-on", channel))

    # protocol -----------------------------------------------------------------------------------
    def split(self, buffer: bytes) -> tuple[list[bytes], bytes]:
        requests: list[bytes] = []
        i = 0
        while len(buffer) - i >= 3:
            n = 3 + buffer[i + 2]
            if len(buffer) - i < n:
                break
            requests.append(buffer[i : i + n])
            i += n
        return requests, buffer[i:]

    @staticmethod
    def _error(address: int, code: int) -> bytes:
        return bytes([ERROR, address, 1, code])

    def handle(self, request: bytes) -> bytes:
        opcode, address, payload = request[0], request[1], request[3:]
        now = time.monotonic()
        if opcode == READ:
            value = self._read_register(address, now)
            return self._error(address, 2) if value is None else bytes([ACK_READ, address, len(value)]) + value
        if opcode != WRITE:
            return self._error(address, 1)
        code = self._write_register(address, bytes(payload), now)
        return self._error(address, code) if code else bytes([ACK_WRITE, address, 0])

    def _read_register(self, address: int, now: float) -> bytes | None:
        if address == IDENTIFICATION:
            return b"scopetwin FPGA board emulator 1.0"
        if LIGHT_CONFIG <= address < LIGHT_CONFIG + N_LIGHTS:
            return self.light_config[address - LIGHT_CONFIG]
        if LIGHT_ACTION <= address < LIGHT_ACTION + N_LIGHTS:
            return bytes([int(self.light_on(address - LIGHT_ACTION, now))])
        if CAMERA_CONFIG <= address < CAMERA_CONFIG + N_CAMERA_LINES:
            return self.camera_config[address - CAMERA_CONFIG]
        if TTL_OUTPUT <= address < TTL_OUTPUT + N_TTL:
            return bytes([self.ttl[address - TTL_OUTPUT]])
        return None

    def _write_register(self, address: int, payload: bytes, now: float) -> int:
        if LIGHT_CONFIG <= address < LIGHT_CONFIG + N_LIGHTS:
            if len(payload) != LIGHT_CONFIG_LENGTH:
                return 3
            index, use, _, listen, _ = read_light_config(payload)
            if index > self.max_current_index or use > 1 or listen > 1:
                return 4
            self.light_config[address - LIGHT_CONFIG] = payload
            return 0
        if LIGHT_ACTION <= address < LIGHT_ACTION + N_LIGHTS:
            if len(payload) != 1 or payload[0] > 1:
                return 3 if len(payload) != 1 else 4
            channel = address - LIGHT_ACTION
            if payload[0]:
                self._switch_on(channel, now)
            else:
                self._on_from[channel], self._on_until[channel] = float("inf"), float("-inf")
                self.events.append((now, "light-off", channel))
            return 0
        if CAMERA_CONFIG <= address < CAMERA_CONFIG + N_CAMERA_LINES:
            if len(payload) != CAMERA_CONFIG_LENGTH:
                return 3
            if payload[0] > 1:
                return 4
            self.camera_config[address - CAMERA_CONFIG] = payload
            return 0
        if CAMERA_PULSE <= address < CAMERA_PULSE + N_CAMERA_LINES:
            if payload != b"\x01":
                return 3 if len(payload) != 1 else 4
            self.events.append((now, "camera-pulse", address - CAMERA_PULSE))
            return 0
        if TTL_OUTPUT <= address < TTL_OUTPUT + N_TTL:
            if len(payload) != 1 or payload[0] > 1:
                return 3 if len(payload) != 1 else 4
            self.ttl[address - TTL_OUTPUT] = payload[0]
            return 0
        if address == GLOBAL_TRIGGER:
            if payload != b"\x01":
                return 3 if len(payload) != 1 else 4
            self.events.append((now, "global-trigger", 0))
            for ch in range(N_LIGHTS):
                _, _, _, listen, delay_us = read_light_config(self.light_config[ch])
                if listen:
                    self._switch_on(ch, now + delay_us * 1e-6)
            for line in range(N_CAMERA_LINES):
                listen, delay_us = read_camera_config(self.camera_config[line])
                if listen:
                    self.events.append((now + delay_us * 1e-6, "camera-pulse", line))
            return 0
        return 2

    def garbage(self, n: int) -> bytes:
        """A reply whose opcode byte no packet may start with."""
        body = self._rng.integers(0, 0x100, size=max(n - 1, 2), dtype="uint8").tobytes()
        return bytes([0xA5]) + body
