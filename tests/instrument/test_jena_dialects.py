"""The three piezosystem jena dialects, byte for byte as the vendor documents them.

The expected bytes are written out here literally (not produced by the driver's encoder), from the command
forms of piezosystem jena's documentation and its own Micro-Manager adapters (PSJ NV40/1, NV40/3, 30DV50):

- NV40/1 CLE: ``i1`` remote on, ``cl`` / ``ol`` loop, ``wr,12.500`` set, ``rd`` read answered
  ``rd,12.500`` CR LF; 9600 baud, no handshake.
- NV40/3: ``setk,0,1`` remote on channel 0, ``cloop,0,1`` closed loop, ``set,0,12.500`` set, ``rk,0`` read
  answered ``rk,0,12.500`` CR; 19200 baud, XON/XOFF.
- 30DV50: ``cl,1`` closed loop, ``set,12.500000`` set, ``mess`` read answered ``mess,12.500`` CR LF;
  115200 baud, XON/XOFF.
"""

from __future__ import annotations

import time

import pytest
import serial

from scopetwin.instrument import open_rig
from scopetwin.instrument.drivers.jena_piezo import DIALECTS, JenaPiezoFocus, decode_reply
from scopetwin.instrument.emulators import JenaPiezoEmulator
from scopetwin.instrument.errors import ControllerError, ProtocolError


def _exchange(port: serial.Serial, request: bytes, expect: int, timeout_s: float = 1.0) -> bytes:
    """Send raw bytes and collect ``expect`` bytes of answer (or what came within the timeout)."""
    port.reset_input_buffer()
    port.write(request)
    out = b""
    deadline = time.monotonic() + timeout_s
    while len(out) < expect and time.monotonic() < deadline:
        out += port.read(expect - len(out))
    return out


@pytest.fixture(params=["nv40-1", "nv40-3", "30dv50"])
def line(request):
    """An emulator of one model and a raw serial port to it."""
    emulator = JenaPiezoEmulator(model=request.param)
    emulator.start()
    port = serial.Serial(emulator.port, baudrate=DIALECTS[request.param].baudrate, timeout=0.05)
    try:
        yield request.param, emulator, port
    finally:
        port.close()
        emulator.stop()


# the emulator answers the documented examples -------------------------------------------------------
def test_nv40_1_documented_exchange():
    with JenaPiezoEmulator(model="nv40-1") as emulator:
        port = serial.Serial(emulator.port, 9600, timeout=0.05)
        try:
            assert _exchange(port, b"i1\r", 1, 0.1) == b""  # set commands are silent
            assert _exchange(port, b"cl\r", 1, 0.1) == b""
            assert _exchange(port, b"wr,12.500\r", 1, 0.1) == b""
            assert _exchange(port, b"rd\r", len(b"rd,12.500\r\n")) == b"rd,12.500\r\n"
            assert _exchange(port, b"ol\r", 1, 0.1) == b""
            assert _exchange(port, b"wr,55.000\r", 1, 0.1) == b""  # open loop: volts
            assert _exchange(port, b"rd\r", len(b"rd,55.000\r\n")) == b"rd,55.000\r\n"
            assert _exchange(port, b"xyz\r", len(b"err,1\r\n")) == b"err,1\r\n"
            assert _exchange(port, b"i0\r", 1, 0.1) == b""
            assert _exchange(port, b"wr,1.000\r", len(b"err,1\r\n")) == b"err,1\r\n"  # no remote control
        finally:
            port.close()


def test_nv40_3_documented_exchange():
    with JenaPiezoEmulator(model="nv40-3") as emulator:
        port = serial.Serial(emulator.port, 19200, timeout=0.05, xonxoff=True)
        try:
            assert _exchange(port, b"setk,0,1\r", 1, 0.1) == b""
            assert _exchange(port, b"cloop,0,1\r", 1, 0.1) == b""
            assert _exchange(port, b"cloop,0\r", len(b"cloop,0,1\r")) == b"cloop,0,1\r"
            assert _exchange(port, b"set,0,12.500\r", 1, 0.1) == b""
            assert _exchange(port, b"rk,0\r", len(b"rk,0,12.500\r")) == b"rk,0,12.500\r"
            assert _exchange(port, b"rk,1\r", len(b"rk,1,0.000\r")) == b"rk,1,0.000\r"  # channel 1 untouched
            assert _exchange(port, b"set,1,3.000\r", len(b"err,1\r")) == b"err,1\r"  # channel 1 not remote
        finally:
            port.close()


def test_30dv50_documented_exchange():
    with JenaPiezoEmulator(model="30dv50") as emulator:
        port = serial.Serial(emulator.port, 115200, timeout=0.05, xonxoff=True)
        try:
            assert _exchange(port, b"cl,1\r", 1, 0.1) == b""
            assert _exchange(port, b"set,12.500000\r", 1, 0.1) == b""
            assert _exchange(port, b"mess\r", len(b"mess,12.500\r\n")) == b"mess,12.500\r\n"
        finally:
            port.close()


# the driver sends the documented bytes ------------------------------------------------------------------
EXPECTED_WIRE = {
    "nv40-1": (b"i1\rrd\r", b"cl\rrd\r", b"wr,12.500\rrd\r", b"rd\r", b"ol\rrd\r", b"wr,55.000\rrd\r", b"i0\rrd\r"),
    "nv40-3": (
        b"setk,0,1\rrk,0\r",
        b"cloop,0,1\rrk,0\r",
        b"set,0,12.500\rrk,0\r",
        b"rk,0\r",
        b"cloop,0,0\rrk,0\r",
        b"set,0,55.000\rrk,0\r",
        b"setk,0,0\rrk,0\r",
    ),
    "30dv50": (
        b"cl,1\rmess\r",
        b"set,12.500000\rmess\r",
        b"mess\r",
        b"cl,0\rmess\r",
        b"set,55.000000\rmess\r",
    ),
}


def test_driver_sends_documented_bytes(line):
    model, emulator, port = line
    focus = JenaPiezoFocus("focus", port, model=model, settle_timeout_s=0.5)
    focus.initialize()
    focus.move_absolute_um(12.5, wait=False)
    assert focus.position_um == pytest.approx(12.5, abs=1e-3)
    focus.set_closed_loop(False)
    # open loop: 200 um of 0-400 um is 55 V of -20..130 V, and the read (volts) comes back as um
    focus.move_absolute_um(200.0, wait=False)
    assert focus.read_volts() == pytest.approx(55.0, abs=1e-3)
    assert focus.position_um == pytest.approx(200.0, abs=1e-2)
    focus.shutdown()
    wire = emulator.received
    expected = EXPECTED_WIRE[model]
    at = 0
    for chunk in expected:  # every documented command appears, in order
        found = wire.find(chunk, at)
        assert found >= 0, f"{chunk!r} not on the wire after byte {at}: {wire[at : at + 80]!r}"
        at = found + len(chunk)


@pytest.mark.parametrize(
    ("model", "raw", "value"),
    [("nv40-1", b"rd,12.500", 12.5), ("nv40-3", b"rk,2,-3.250", -3.25), ("30dv50", b"mess,80.000000", 80.0)],
)
def test_decode_documented_replies(model, raw, value):
    channel = 2 if model == "nv40-3" else 0
    assert decode_reply(raw, DIALECTS[model], channel) == pytest.approx(value)


@pytest.mark.parametrize(
    ("model", "raw"),
    [("nv40-1", b"aw,12.5"), ("nv40-3", b"rk,1,12.5"), ("nv40-3", b"rk,12.5"), ("30dv50", b"rd,1.0")],
)
def test_decode_refuses_other_dialects(model, raw):
    with pytest.raises(ProtocolError):
        decode_reply(raw, DIALECTS[model], 0)


def test_error_reply_is_a_controller_error():
    with pytest.raises(ControllerError) as info:
        decode_reply(b"err,4", DIALECTS["nv40-1"])
    assert info.value.code == 4


# a rig with model = ... opens and moves the focus ------------------------------------------------------------
@pytest.mark.parametrize("model", ["nv40-1", "nv40-3", "30dv50"])
def test_rig_with_model_opens_and_moves_focus(tmp_path, model):
    rig = tmp_path / "rig.toml"
    rig.write_text(
        f"""
[devices.focus]
kind = "focus"
driver = "jena-piezo"
port = "emu://jena-piezo?model={model}"
model = "{model}"
range_um = [0.0, 400.0]
"""
    )
    with open_rig(rig) as r:
        focus = r.focus()
        transport = focus.link.transport
        assert transport.baudrate == DIALECTS[model].baudrate and transport.xonxoff == DIALECTS[model].xonxoff
        focus.move_absolute_um(150.0)
        assert focus.position_um == pytest.approx(150.0, abs=1e-3)
        emulator = transport.emulator
        assert emulator.channels[0].position_um == pytest.approx(150.0) and emulator.channels[0].closed_loop
    assert not emulator.channels[0].remote or model == "30dv50"  # released on close
