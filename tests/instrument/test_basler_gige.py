"""The Basler driver's GigE branches on a fake node map, and Mono12Packed unpacked bit-exact.

The fake node map describes a scout scA1400-30gm (thesis §4.1.4) as pylon presents a GigE camera of that
generation: ``ExposureTimeRaw`` in steps of ``ExposureTimeBaseAbs`` µs, ``GainRaw``, ``BlackLevelRaw``,
``AcquisitionFrameRateAbs``, pixel formats Mono8 / Mono12Packed / Mono16 (no Mono12), and the GigE
transport features ``GevSCPSPacketSize`` and ``GevSCPD``.
"""

from __future__ import annotations

import textwrap

import numpy as np
import pytest

from scopetwin.instrument.drivers.basler import BaslerCamera, unpack_mono12packed
from scopetwin.instrument.errors import OutOfRangeError, ProtocolError
from scopetwin.instrument.rig import load_rig

# two 12-bit pixels in three bytes (GigE Vision Mono12Packed), worked out by hand:
# p0 = 0xAB1, p1 = 0x23C -> AB (p0 11..4), C1 (p1 3..0 | p0 3..0), 23 (p1 11..4)
# p2 = 0x00F, p3 = 0xFF0 -> 00, 0F, FF;   p4 = 0x800, p5 = 0x001 -> 80, 10, 00
PACKED = b"\xab\xc1\x23\x00\x0f\xff\x80\x10\x00"
PIXELS = [0xAB1, 0x23C, 0x00F, 0xFF0, 0x800, 0x001]


class FakeNode:
    """A GenICam feature: value, limits, enumeration entries."""

    def __init__(self, value, low=0, high=0, symbolics=()):
        self.Value, self.Min, self.Max, self.Symbolics = value, low, high, tuple(symbolics)

    def is_available(self):
        return True

    def GetValue(self):  # noqa: N802 - GenICam's names
        return self.Value

    def SetValue(self, value):  # noqa: N802
        self.Value = value


class FakeGigECamera:
    """An InstantCamera-like object whose node map holds only the features given."""

    def __init__(self, formats=("Mono8", "Mono12Packed", "Mono16")):
        nodes = {
            "ExposureTimeRaw": FakeNode(500, 1, 4095),
            "ExposureTimeBaseAbs": FakeNode(20.0, 1.0, 10000.0),
            "GainRaw": FakeNode(300, 300, 850),
            "BlackLevelRaw": FakeNode(32, 0, 255),
            "AcquisitionFrameRateAbs": FakeNode(30.0, 0.1, 30.0),
            "PixelFormat": FakeNode(formats[0], symbolics=formats),
            "HeightMax": FakeNode(1040),
            "WidthMax": FakeNode(1392),
            "Height": FakeNode(1040),
            "Width": FakeNode(1392),
            "OffsetX": FakeNode(0),
            "OffsetY": FakeNode(0),
            "TriggerSelector": FakeNode("FrameStart"),
            "TriggerMode": FakeNode("Off"),
            "TriggerSource": FakeNode("Software"),
            "GevSCPSPacketSize": FakeNode(1500, 220, 16404),
            "GevSCPD": FakeNode(0, 0, 65535),
        }
        object.__setattr__(self, "nodes", nodes)
        object.__setattr__(self, "results", [])

    def __getattr__(self, name):
        try:
            return self.nodes[name]
        except KeyError:
            raise AttributeError(name) from None

    def GetNodeMap(self):  # noqa: N802
        return self

    def GetNode(self, name):  # noqa: N802
        return self.nodes.get(name)

    def RetrieveResult(self, timeout_ms, handling):  # noqa: N802
        return self.results.pop(0)

    def Close(self):  # noqa: N802
        pass


class FakeResult:
    """A grab result carrying raw bytes (packed formats) or an array."""

    def __init__(self, width, height, buffer=b"", array=None):
        self.Width, self.Height, self.PaddingX, self._buffer, self.Array = width, height, 0, buffer, array

    def IsValid(self):  # noqa: N802
        return True

    def GrabSucceeded(self):  # noqa: N802
        return True

    def GetBuffer(self):  # noqa: N802
        return bytearray(self._buffer)

    def Release(self):  # noqa: N802
        pass


def _scout(fake, **kwargs):
    cam = BaslerCamera("scout", **kwargs)
    cam._cam = fake
    cam.configure_from_nodes()
    cam._initialized = True  # what initialize() does after opening the camera
    return cam


# Mono12Packed -------------------------------------------------------------------------------------
def test_unpack_mono12packed_hand_made_buffer():
    frame = unpack_mono12packed(PACKED, 3, 2)  # odd width: row 1 starts in the middle of a group
    np.testing.assert_array_equal(frame, np.array(PIXELS, dtype=np.uint16).reshape(2, 3))
    assert frame.dtype == np.uint16
    np.testing.assert_array_equal(unpack_mono12packed(PACKED[:5], 3, 1), [PIXELS[:3]])  # odd pixel count
    with pytest.raises(ProtocolError):
        unpack_mono12packed(PACKED[:4], 3, 1)


def test_unpack_mono12packed_agrees_with_pylon_converter():
    pylon = pytest.importorskip("pypylon.pylon")
    rng = np.random.default_rng(3)
    raw = rng.integers(0, 256, size=3 * 64 * 48 // 2, dtype=np.uint8).tobytes()
    image = pylon.PylonImage()
    image.AttachBytesObject(raw, pylon.PixelType_Mono12packed, 64, 48, 0)
    converter = pylon.ImageFormatConverter()
    converter.OutputPixelFormat = pylon.PixelType_Mono16
    expected = converter.Convert(image).Array
    np.testing.assert_array_equal(unpack_mono12packed(raw, 64, 48), expected)


# the GigE feature names -------------------------------------------------------------------------------
def test_scout_without_mono12_delivers_12_bit_via_mono12packed():
    fake = FakeGigECamera()
    cam = _scout(fake)
    assert cam.limits.bit_depths == (8, 12, 16)
    assert cam.bit_depth == 12 and cam.pixel_format == "Mono12Packed" and fake.PixelFormat.Value == "Mono12Packed"
    assert cam.saturation_dn == 4095
    fake.results.append(FakeResult(3, 2, buffer=PACKED))
    frame = cam._do_read_frame(0.1)
    assert frame.dtype == np.float32
    np.testing.assert_array_equal(frame, np.array(PIXELS, dtype=np.float32).reshape(2, 3))
    cam.set_bit_depth(16)
    assert fake.PixelFormat.Value == "Mono16"
    fake.results.append(FakeResult(2, 1, array=np.array([[65535, 7]], dtype=np.uint16)))
    np.testing.assert_array_equal(cam._do_read_frame(0.1), [[65535.0, 7.0]])
    cam.set_bit_depth(8)
    assert fake.PixelFormat.Value == "Mono8"


def test_camera_with_only_mono8_and_mono16():
    cam = _scout(FakeGigECamera(formats=("Mono8", "Mono16")))
    assert cam.limits.bit_depths == (8, 16) and cam.bit_depth == 16
    with pytest.raises(OutOfRangeError):
        cam.set_bit_depth(12)


def test_exposure_raw_in_steps_of_the_time_base():
    fake = FakeGigECamera()
    cam = _scout(fake)
    assert cam.limits.exposure_s.low == pytest.approx(20e-6) and cam.limits.exposure_s.high == pytest.approx(0.0819)
    assert cam.exposure_s == pytest.approx(0.01)  # 500 steps of 20 us
    cam.set_exposure_s(0.0125)
    assert fake.ExposureTimeRaw.Value == 625 and cam.exposure_s == pytest.approx(0.0125)


def test_gain_raw_scale():
    fake = FakeGigECamera()
    cam = _scout(fake, gain_db_per_raw=0.0359)
    assert cam.limits.gain_db.low == pytest.approx(300 * 0.0359) and cam.limits.gain_db.high == pytest.approx(
        850 * 0.0359
    )
    cam.set_gain_db(20.0)
    assert fake.GainRaw.Value == round(20.0 / 0.0359) == 557
    assert isinstance(fake.GainRaw.Value, int)


def test_packet_size_and_inter_packet_delay():
    fake = FakeGigECamera()
    _scout(fake, packet_size=9000, inter_packet_delay=1000)
    assert fake.GevSCPSPacketSize.Value == 9000 and fake.GevSCPD.Value == 1000
    with pytest.raises(OutOfRangeError):
        _scout(FakeGigECamera(), packet_size=20000)
    fake = FakeGigECamera()
    del fake.nodes["GevSCPD"]
    with pytest.raises(ProtocolError, match="GevSCPD"):
        _scout(fake, inter_packet_delay=10)
    untouched = FakeGigECamera()
    _scout(untouched)
    assert untouched.GevSCPSPacketSize.Value == 1500  # nothing asked, nothing set


def test_rig_toml_carries_gige_settings(tmp_path):
    pytest.importorskip("pypylon")
    rig = tmp_path / "rig.toml"
    rig.write_text(
        textwrap.dedent(
            """
            [devices.cam]
            kind = "camera"
            driver = "basler"
            serial = "21234567"
            packet_size = 8192
            inter_packet_delay = 2500
            gain_db_per_raw = 0.05
            """
        )
    )
    cam = load_rig(rig)["cam"]
    assert isinstance(cam, BaslerCamera)
    assert (cam.packet_size, cam.inter_packet_delay, cam.gain_db_per_raw) == (8192, 2500, 0.05)
    fake = FakeGigECamera()
    cam._cam = fake
    cam.configure_from_nodes()
    assert fake.GevSCPSPacketSize.Value == 8192 and fake.GevSCPD.Value == 2500
