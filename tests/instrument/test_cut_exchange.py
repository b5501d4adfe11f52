"""An exchange with the FPGA board cut short by a signal (CI, stop 31: SIGHUP during ``rig acquire`` left the
halogen on): the board's answer to the cut request arrives late, after the clean-up's "light off" went out, and
must not be taken for the clean-up's answer.

The board's bytes are written literally (thesis Table 4.2 layout: opcode, address, length, payload; write 0x01, read
0x02, their acknowledgements with bit 7 set; light 2's on/off register at 0x18 + 2 = 0x1A)."""

from __future__ import annotations

import pytest

from scopetwin.instrument.drivers.fpga_board import FpgaBoard
from scopetwin.instrument.errors import ProtocolError

READ_STATE_2 = b"\x02\x1a\x00"  # read light 2's on/off register
ANSWER_ON = b"\x82\x1a\x01\x01"  # ... it is on
SWITCH_OFF_2 = b"\x01\x1a\x01\x00"  # write 0 to it: off
ACK_OFF = b"\x81\x1a\x00"


class _LateBoard:
    """A line whose board answers each request only after the next request arrived (the first read is cut)."""

    def __init__(self, answers: dict[bytes, bytes], cut_first_read: bool) -> None:
        self.answers, self.cut_first_read = answers, cut_first_read
        self.timeout, self.is_open = 0.0, True
        self.requests: list[bytes] = []
        self.waiting = bytearray()
        self._late = b""

    @property
    def in_waiting(self) -> int:
        return len(self.waiting)

    def write(self, data: bytes) -> int:
        self.requests.append(bytes(data))
        self.waiting += self._late  # the previous request's answer comes now, after the input was dropped
        self._late = self.answers[bytes(data)]
        if not self.cut_first_read or len(self.requests) > 1:
            self.waiting += self._late
            self._late = b""
        return len(data)

    def read(self, n: int) -> bytes:
        if self.cut_first_read and len(self.requests) == 1:
            raise KeyboardInterrupt  # the signal arrives while the driver waits for the first answer
        out, self.waiting[:n] = bytes(self.waiting[:n]), b""
        return out

    def reset_input_buffer(self) -> None:
        self.waiting.clear()

    def flush(self) -> None:
        pass


def test_the_answer_of_a_cut_exchange_is_not_taken_for_the_next_ones():
    line = _LateBoard({READ_STATE_2: ANSWER_ON, SWITCH_OFF_2: ACK_OFF}, cut_first_read=True)
    board = FpgaBoard(line, timeout_s=0.05)
    with pytest.raises(KeyboardInterrupt):
        board.read(0x1A)
    assert board.link.cut
    board.write(0x1A, b"\x00")  # the clean-up's "off": its own acknowledgement, after the stale answer
    assert line.requests == [READ_STATE_2, SWITCH_OFF_2]
    assert not board.link.cut and board.link.lost is None


def test_a_wrong_answer_to_an_exchange_nobody_cut_is_still_a_protocol_error():
    line = _LateBoard({SWITCH_OFF_2: ANSWER_ON}, cut_first_read=False)
    board = FpgaBoard(line, timeout_s=0.05)
    with pytest.raises(ProtocolError, match="expected reply 0x81/0x1A, got 0x82/0x1A"):
        board.write(0x1A, b"\x00")
