"""Basler GigE cameras through pypylon (thesis §4.1.4: scA1400-30gm, 12 bit, 1392 x 1040, 6.45 µm).

Optional dependency: ``pip install scopetwin[hardware]`` (pypylon). The driver
probes the feature names of both GenICam generations: ``ExposureTime`` (µs,
SFNC 2), ``ExposureTimeAbs`` (µs, older GigE models such as the scA series) or
``ExposureTimeRaw`` (steps of ``ExposureTimeBaseAbs`` µs); ``Gain`` (dB) or
``GainRaw`` (steps of ``gain_db_per_raw`` dB); ``BlackLevel`` or
``BlackLevelRaw``; ``AcquisitionFrameRate`` or ``AcquisitionFrameRateAbs``;
``TriggerDelay`` or ``TriggerDelayAbs``. Every exposure is triggered
(``TriggerMode=On``): ``Software`` for a software trigger, ``Line1`` for the
FPGA board's camera line.

Pixel formats: ``Mono8`` (8 bit), ``Mono12`` or, on cameras without it such as
the scout scA1400-30gm, ``Mono12Packed`` (12 bit, unpacked here by
:func:`unpack_mono12packed`), and ``Mono16`` (16 bit). GigE transport: the
rig's ``packet_size`` (bytes, ``GevSCPSPacketSize``) and ``inter_packet_delay``
(ticks, ``GevSCPD``) are set at initialisation.

The driver also runs against pylon's camera emulator (``PYLON_CAMEMU=1``),
whose image-file mode (:meth:`BaslerCamera.set_node` ``ImageFilename``) serves
rendered frames; tests drive the GigE branches through a fake node map (every
node object may offer ``is_available()``, which :func:`node_available` asks
before GenICam's ``IsAvailable``).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.instrument.devices import CameraDevice, CameraLimits, Range, Roi, TriggerMode, TriggerType
from scopetwin.instrument.errors import DisconnectedError, InstrumentTimeout, OutOfRangeError, ProtocolError, RigError

#: Pixel format for each bit depth, in order of preference.
PIXEL_FORMATS: dict[int, tuple[str, ...]] = {8: ("Mono8",), 12: ("Mono12", "Mono12Packed"), 16: ("Mono16",)}


def unpack_mono12packed(buffer: bytes | bytearray | memoryview, width: int, height: int) -> NDArray[np.uint16]:
    """Unpack a GigE Vision ``Mono12Packed`` image: two 12-bit pixels in three bytes.

    Byte 0 holds bits 11-4 of the first pixel, byte 1 bits 3-0 of the first pixel in its low
    nibble and bits 3-0 of the second pixel in its high nibble, byte 2 bits 11-4 of the second
    pixel. The packing runs over the whole image (a row of odd width ends mid-group).

    Parameters
    ----------
    buffer : bytes-like
        At least ``ceil(width * height * 3 / 2)`` bytes.
    width, height : int
        Image size in pixels.

    Returns
    -------
    numpy.ndarray
        ``(height, width)`` uint16 array of 12-bit values.

    Raises
    ------
    ProtocolError
        If the buffer is too short.
    """
    n = int(width) * int(height)
    need = (3 * n + 1) // 2
    raw = np.frombuffer(buffer, dtype=np.uint8)
    if raw.size < need:
        raise ProtocolError(f"Mono12Packed: {raw.size} bytes for {width} x {height} pixels, need {need}")
    groups = (n + 1) // 2
    padded = np.zeros(groups * 3, dtype=np.uint16)
    padded[:need] = raw[:need]
    b = padded.reshape(groups, 3)
    out = np.empty((groups, 2), dtype=np.uint16)
    out[:, 0] = (b[:, 0] << 4) | (b[:, 1] & 0x0F)
    out[:, 1] = (b[:, 2] << 4) | (b[:, 1] >> 4)
    return out.reshape(-1)[:n].reshape(int(height), int(width))


def node_available(node: Any) -> bool:
    """Whether a GenICam node exists and is available (a test double may answer ``is_available()``)."""
    if node is None:
        return False
    probe = getattr(node, "is_available", None)
    if callable(probe):
        return bool(probe())
    _, genicam = _pylon()
    return bool(genicam.IsAvailable(node))


def _pylon() -> tuple[Any, Any]:
    try:
        from pypylon import genicam, pylon
    except ImportError as exc:  # pragma: no cover - depends on the optional extra
        raise RigError("the basler driver needs pypylon: pip install 'scopetwin[hardware]'") from exc
    return pylon, genicam


@contextlib.contextmanager
def pylon_errors(name: str) -> Iterator[None]:
    """Map pypylon/GenICam exceptions to the InstrumentError family."""
    pylon, genicam = _pylon()
    try:
        yield
    except genicam.TimeoutException as exc:
        raise InstrumentTimeout(f"camera {name!r}: {str(exc).splitlines()[0][:200]}") from exc
    except genicam.RuntimeException as exc:
        text = str(exc)
        if "removed" in text.lower() or "not open" in text.lower():
            raise DisconnectedError(f"camera {name!r}: {text[:200]}") from exc
        raise ProtocolError(f"camera {name!r}: {text[:200]}") from exc
    except genicam.GenericException as exc:
        raise ProtocolError(f"camera {name!r}: {str(exc)[:200]}") from exc


class BaslerCamera(CameraDevice):
    """A Basler camera via pypylon.

    Parameters
    ----------
    name : str
        Device name.
    serial : str, optional
        Serial number to open (default: the first camera found).
    pixel_size_um : float
        Pixel pitch (not readable from every model).
    magnification : float
        Magnification of the optics in front of the camera (for the sample-side pixel size).
    gain_db_per_raw : float
        dB per ``GainRaw`` step for models without ``Gain`` in dB.
    trigger_line : str
        Input line wired to the FPGA board's camera output.
    packet_size : int, optional
        GigE stream packet size in bytes (``GevSCPSPacketSize``), e.g. 1500 or 9000 with jumbo frames.
    inter_packet_delay : int, optional
        GigE inter-packet delay in timestamp ticks (``GevSCPD``).
    timeout_s : float
        Longest wait for a frame beyond its exposure.
    """

    driver = "basler"

    def __init__(
        self,
        name: str,
        *,
        serial: str | None = None,
        pixel_size_um: float = 6.45,
        magnification: float = 1.0,
        gain_db_per_raw: float = 0.0359,
        trigger_line: str = "Line1",
        packet_size: int | None = None,
        inter_packet_delay: int | None = None,
        timeout_s: float = 2.0,
    ) -> None:
        super().__init__(
            name, limits=CameraLimits(pixel_size_um=pixel_size_um, magnification=magnification), timeout_s=timeout_s
        )
        self.serial = serial
        self.gain_db_per_raw = float(gain_db_per_raw)
        self.trigger_line_name = trigger_line
        for what, value in (("packet_size", packet_size), ("inter_packet_delay", inter_packet_delay)):
            if value is not None and (isinstance(value, bool) or int(value) < 0):
                raise RigError(f"camera {name!r}: {what} must be a non-negative integer, got {value!r}")
        self.packet_size = None if packet_size is None else int(packet_size)
        self.inter_packet_delay = None if inter_packet_delay is None else int(inter_packet_delay)
        self._cam: Any = None
        self._gain_scale = 1.0
        self._pixel_format = ""

    # node helpers ---------------------------------------------------------------------------------
    def _find(self, *names: str) -> tuple[str, Any]:
        nodemap = self._cam.GetNodeMap()
        for n in names:
            node = nodemap.GetNode(n)
            if node_available(node):
                return n, node
        raise ProtocolError(f"camera {self.name!r} has none of the features {names}")

    def _node(self, *names: str) -> Any:
        return self._find(*names)[1]

    def _has(self, name: str) -> bool:
        return node_available(self._cam.GetNodeMap().GetNode(name))

    def set_node(self, name: str, value: Any) -> None:
        """Set any GenICam feature by name (e.g. the emulator's ``ImageFilename``)."""
        self._require()
        with pylon_errors(self.name):
            self._node(name).SetValue(value)

    def get_node(self, name: str) -> Any:
        """Read any GenICam feature by name."""
        self._require()
        with pylon_errors(self.name):
            return self._node(name).GetValue()

    @property
    def pixel_format(self) -> str:
        """The pixel format in use (``Mono8``, ``Mono12``, ``Mono12Packed`` or ``Mono16``)."""
        return self._pixel_format

    # lifecycle ---------------------------------------------------------------------------------------
    def _do_initialize(self) -> None:
        pylon, _ = _pylon()
        with pylon_errors(self.name):
            factory = pylon.TlFactory.GetInstance()
            devices = factory.EnumerateDevices()
            chosen = [d for d in devices if self.serial in (None, d.GetSerialNumber())]
            if not chosen:
                raise DisconnectedError(
                    f"camera {self.name!r}: no Basler camera with serial {self.serial!r} "
                    f"(found {[d.GetSerialNumber() for d in devices]})"
                )
            self._cam = pylon.InstantCamera(factory.CreateDevice(chosen[0]))
            self._cam.Open()
            self.serial = chosen[0].GetSerialNumber()
            self.configure_from_nodes()

    def configure_from_nodes(self) -> None:
        """Read the limits from the node map and apply the rig's settings (called by initialisation).

        Raises
        ------
        ProtocolError
            A feature the driver needs is missing, or the rig asks for a GigE transport setting
            the camera does not offer.
        """
        cam = self._cam
        exposure_name, exposure = self._find("ExposureTime", "ExposureTimeAbs", "ExposureTimeRaw")
        exposure_scale_us = (
            float(self._node("ExposureTimeBaseAbs").Value) if exposure_name == "ExposureTimeRaw" else 1.0
        )
        gain_name, gain = self._find("Gain", "GainRaw")
        gain_scale = 1.0 if gain_name == "Gain" else self.gain_db_per_raw
        black = self._node("BlackLevel", "BlackLevelRaw")
        fps = self._node("AcquisitionFrameRate", "AcquisitionFrameRateAbs")
        symbolics = tuple(cam.PixelFormat.Symbolics)
        depths = tuple(bits for bits, names in PIXEL_FORMATS.items() if any(n in symbolics for n in names))
        binnings = (
            tuple(b for b in (1, 2, 4) if b <= cam.BinningHorizontal.Max) if self._has("BinningHorizontal") else (1,)
        )
        self._exposure_name, self._exposure_scale_us = exposure_name, exposure_scale_us
        self._gain_name, self._gain_scale = gain_name, gain_scale
        self._formats = symbolics
        self.limits = CameraLimits(
            sensor_shape=(int(cam.HeightMax.Value), int(cam.WidthMax.Value)),
            pixel_size_um=self.limits.pixel_size_um,
            magnification=self.limits.magnification,
            exposure_s=Range(exposure.Min * exposure_scale_us * 1e-6, exposure.Max * exposure_scale_us * 1e-6, "s"),
            gain_db=Range(gain.Min * gain_scale, gain.Max * gain_scale, "dB"),
            black_level_dn=Range(float(black.Min), float(black.Max), "DN"),
            fps=Range(max(float(fps.Min), 1e-3), float(fps.Max), "Hz"),
            bit_depths=depths or (8,),
            binnings=binnings,
        )
        self._apply_transport()
        cam.OffsetX.Value = 0
        cam.OffsetY.Value = 0
        cam.Width.Value = cam.WidthMax.Value
        cam.Height.Value = cam.HeightMax.Value
        self._roi = Roi(0, 0, *self.limits.sensor_shape)
        bits = 12 if 12 in self.limits.bit_depths else max(self.limits.bit_depths)  # the thesis's ADC depth
        self._do_set_bit_depth(bits)
        self._bit_depth = bits
        self._exposure_s = float(exposure.Value) * exposure_scale_us * 1e-6
        self._do_set_trigger(TriggerType.SOFTWARE, TriggerMode.ONCE, 0.0)

    def _apply_transport(self) -> None:
        for feature, value in (("GevSCPSPacketSize", self.packet_size), ("GevSCPD", self.inter_packet_delay)):
            if value is None:
                continue
            if not self._has(feature):
                raise ProtocolError(f"camera {self.name!r} has no {feature} (not a GigE camera?)")
            node = self._node(feature)
            if not node.Min <= value <= node.Max:
                raise OutOfRangeError(f"camera {self.name!r}: {feature} {value} outside [{node.Min}, {node.Max}]")
            node.Value = int(value)

    def _do_shutdown(self) -> None:
        if self._cam is not None:
            with contextlib.suppress(Exception):
                self._cam.Close()
            self._cam = None

    def _limits(self) -> dict[str, Any]:
        extra: dict[str, Any] = {}
        if self.packet_size is not None:
            extra["packet_size"] = self.packet_size
        if self.inter_packet_delay is not None:
            extra["inter_packet_delay"] = self.inter_packet_delay
        return {**super()._limits(), **extra}

    # settings --------------------------------------------------------------------------------------
    def _do_get_serial_number(self) -> str:
        return str(self.serial)

    def _apply_roi(self, roi: Roi, binning: int) -> None:
        self._cam.OffsetX.Value = 0
        self._cam.OffsetY.Value = 0
        self._cam.Width.Value = roi.cols // binning
        self._cam.Height.Value = roi.rows // binning
        self._cam.OffsetX.Value = roi.col // binning
        self._cam.OffsetY.Value = roi.row // binning

    def _do_set_roi(self, roi: Roi) -> None:
        with pylon_errors(self.name):
            self._apply_roi(roi, self.binning)

    def _do_set_binning(self, binning: int) -> None:
        with pylon_errors(self.name):
            self._cam.OffsetX.Value = 0
            self._cam.OffsetY.Value = 0
            self._cam.BinningHorizontal.Value = binning
            self._cam.BinningVertical.Value = binning
            self._apply_roi(self.roi, binning)

    def _do_set_bit_depth(self, bits: int) -> None:
        choices = [f for f in PIXEL_FORMATS.get(bits, ()) if f in self._formats]
        if not choices:
            raise OutOfRangeError(f"camera {self.name!r} offers no {bits}-bit pixel format ({self._formats})")
        with pylon_errors(self.name):
            self._cam.PixelFormat.Value = choices[0]
        self._pixel_format = choices[0]

    def _do_set_exposure_s(self, exposure_s: float) -> float:
        with pylon_errors(self.name):
            node = self._node(self._exposure_name)
            steps = exposure_s * 1e6 / self._exposure_scale_us
            node.Value = int(round(steps)) if self._exposure_name == "ExposureTimeRaw" else steps
            return float(node.Value) * self._exposure_scale_us * 1e-6

    def _do_set_gain_db(self, gain_db: float) -> None:
        with pylon_errors(self.name):
            node = self._node(self._gain_name)
            node.Value = gain_db if self._gain_name == "Gain" else int(round(gain_db / self._gain_scale))

    def _do_set_black_level_dn(self, black_level_dn: float) -> None:
        with pylon_errors(self.name):
            node = self._node("BlackLevel", "BlackLevelRaw")
            node.Value = type(node.Value)(black_level_dn)

    def _do_set_fps(self, fps: float) -> None:
        with pylon_errors(self.name):
            if self._has("AcquisitionFrameRateEnable"):
                self._cam.AcquisitionFrameRateEnable.Value = True
            self._node("AcquisitionFrameRate", "AcquisitionFrameRateAbs").Value = fps

    def _do_set_trigger(self, trigger_type: TriggerType, trigger_mode: TriggerMode, delay_s: float) -> None:
        with pylon_errors(self.name):
            cam = self._cam
            cam.TriggerSelector.Value = "FrameStart"
            cam.TriggerMode.Value = "On"
            cam.TriggerSource.Value = "Software" if trigger_type is TriggerType.SOFTWARE else self.trigger_line_name
            if trigger_type is not TriggerType.SOFTWARE and self._has("TriggerActivation"):
                cam.TriggerActivation.Value = "RisingEdge" if trigger_type is TriggerType.RISING_EDGE else "FallingEdge"
            if self._has("ExposureMode"):
                cam.ExposureMode.Value = "TriggerWidth" if trigger_mode is TriggerMode.BULB else "Timed"
            if self._has("TriggerDelay") or self._has("TriggerDelayAbs"):
                self._node("TriggerDelay", "TriggerDelayAbs").Value = delay_s * 1e6

    # acquisition --------------------------------------------------------------------------------------
    def _do_arm(self) -> None:
        pylon, _ = _pylon()
        with pylon_errors(self.name):
            self._cam.StartGrabbing(pylon.GrabStrategy_OneByOne)

    def _do_disarm(self) -> None:
        if self._cam is not None:
            with pylon_errors(self.name):
                self._cam.StopGrabbing()

    def _do_software_trigger(self) -> None:
        pylon, _ = _pylon()
        with pylon_errors(self.name):
            self._cam.WaitForFrameTriggerReady(int(self.timeout_s * 1000), pylon.TimeoutHandling_ThrowException)
            self._cam.ExecuteSoftwareTrigger()

    def frame_from_result(self, result: Any) -> NDArray[np.float32]:
        """The float32 frame of a grab result, unpacking ``Mono12Packed`` (any other format via ``Array``)."""
        if self._pixel_format == "Mono12Packed":
            if int(getattr(result, "PaddingX", 0)):
                raise ProtocolError(f"camera {self.name!r}: Mono12Packed rows with padding are not supported")
            frame = unpack_mono12packed(result.GetBuffer(), int(result.Width), int(result.Height))
            return frame.astype(np.float32)
        return np.asarray(result.Array, dtype=np.float32).copy()

    def _do_read_frame(self, timeout_s: float) -> NDArray[np.float32]:
        pylon, _ = _pylon()
        with pylon_errors(self.name):
            result = self._cam.RetrieveResult(int(timeout_s * 1000), pylon.TimeoutHandling_Return)
            if result is None or not result.IsValid():
                raise InstrumentTimeout(f"camera {self.name!r}: no frame within {timeout_s:.3g} s")
            try:
                if not result.GrabSucceeded():
                    raise ProtocolError(f"camera {self.name!r}: frame lost ({result.GetErrorDescription()})")
                return self.frame_from_result(result)
            finally:
                result.Release()
