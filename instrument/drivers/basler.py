"""Basler GigE cameras through pypylon (seed §4.1.4: scA1400-30gm, 12 bit, 1392 x 1040, 6.45 µm).

Optional dependency: ``pip install scopetwin[hardware]`` (pypylon). The driver
probes the feature names of both GenICam generations: ``ExposureTime`` (µs,
SFNC 2) or ``ExposureTimeAbs`` (µs, older GigE models such as the scA series),
``Gain`` (dB) or ``GainRaw``, ``BlackLevel`` or ``BlackLevelRaw``,
``AcquisitionFrameRate`` or ``AcquisitionFrameRateAbs``, ``TriggerDelay`` or
``TriggerDelayAbs``. Every exposure is triggered (``TriggerMode=On``):
``Software`` for a software trigger, ``Line1`` for the FPGA board's camera line.
The driver also runs against pylon's camera emulator (``PYLON_CAMEMU=1``),
whose image-file mode (:meth:`BaslerCamera.set_node` ``ImageFilename``) serves
rendered frames.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import numpy as np
from numpy.typing import NDArray

from instrument.devices import Camera, CameraLimits, Range, Roi, TriggerMode, TriggerType
from instrument.errors import DisconnectedError, InstrumentTimeout, ProtocolError, RigError


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


class BaslerCamera(Camera):
    """A Basler camera via pypylon.

    Parameters
    ----------
    name : str
        Device name.
    serial : str, optional
        Serial number to open (default: the first camera found).
    pixel_size_um : float
        Pixel pitch (not readable from every model).
    gain_db_per_raw : float
        dB per ``GainRaw`` step for models without ``Gain`` in dB.
    trigger_line : str
        Input line wired to the FPGA board's camera output.
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
        gain_db_per_raw: float = 0.0359,
        trigger_line: str = "Line1",
        timeout_s: float = 2.0,
    ) -> None:
        super().__init__(name, limits=CameraLimits(pixel_size_um=pixel_size_um), timeout_s=timeout_s)
        self.serial = serial
        self.gain_db_per_raw = float(gain_db_per_raw)
        self.trigger_line_name = trigger_line
        self._cam: Any = None

    # node helpers ---------------------------------------------------------------------------------
    def _node(self, *names: str) -> Any:
        _, genicam = _pylon()
        nodemap = self._cam.GetNodeMap()
        for n in names:
            node = nodemap.GetNode(n)
            if node is not None and genicam.IsAvailable(node):
                return node
        raise ProtocolError(f"camera {self.name!r} has none of the features {names}")

    def _has(self, name: str) -> bool:
        _, genicam = _pylon()
        node = self._cam.GetNodeMap().GetNode(name)
        return node is not None and genicam.IsAvailable(node)

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
            exposure = self._node("ExposureTime", "ExposureTimeAbs")
            gain = self._node("Gain", "GainRaw")
            gain_scale = 1.0 if gain.GetNode().GetName() == "Gain" else self.gain_db_per_raw
            black = self._node("BlackLevel", "BlackLevelRaw")
            fps = self._node("AcquisitionFrameRate", "AcquisitionFrameRateAbs")
            formats = [f for f in self._cam.PixelFormat.Symbolics if f in ("Mono8", "Mono12")]
            binnings = (
                tuple(b for b in (1, 2, 4) if b <= self._cam.BinningHorizontal.Max)
                if self._has("BinningHorizontal")
                else (1,)
            )
            self.limits = CameraLimits(
                sensor_shape=(int(self._cam.HeightMax.Value), int(self._cam.WidthMax.Value)),
                pixel_size_um=self.limits.pixel_size_um,
                exposure_s=Range(exposure.Min * 1e-6, exposure.Max * 1e-6, "s"),
                gain_db=Range(gain.Min * gain_scale, gain.Max * gain_scale, "dB"),
                black_level_dn=Range(float(black.Min), float(black.Max), "DN"),
                fps=Range(max(float(fps.Min), 1e-3), float(fps.Max), "Hz"),
                bit_depths=tuple(sorted(int(f[4:]) for f in formats)) or (8,),
                binnings=binnings,
            )
            self._gain_scale = gain_scale
            self._cam.OffsetX.Value = 0
            self._cam.OffsetY.Value = 0
            self._cam.Width.Value = self._cam.WidthMax.Value
            self._cam.Height.Value = self._cam.HeightMax.Value
            self._roi = Roi(0, 0, *self.limits.sensor_shape)
            self._do_set_bit_depth(max(self.limits.bit_depths))
            self._bit_depth = max(self.limits.bit_depths)
            self._exposure_s = float(exposure.Value) * 1e-6
            self._do_set_trigger(TriggerType.SOFTWARE, TriggerMode.ONCE, 0.0)

    def _do_shutdown(self) -> None:
        if self._cam is not None:
            with contextlib.suppress(Exception):
                self._cam.Close()
            self._cam = None

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
        with pylon_errors(self.name):
            self._cam.PixelFormat.Value = f"Mono{bits}"

    def _do_set_exposure_s(self, exposure_s: float) -> float:
        with pylon_errors(self.name):
            node = self._node("ExposureTime", "ExposureTimeAbs")
            node.Value = exposure_s * 1e6
            return float(node.Value) * 1e-6

    def _do_set_gain_db(self, gain_db: float) -> None:
        with pylon_errors(self.name):
            node = self._node("Gain", "GainRaw")
            node.Value = gain_db if self._gain_scale == 1.0 else int(round(gain_db / self._gain_scale))

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

    def _do_read_frame(self, timeout_s: float) -> NDArray[np.float32]:
        pylon, _ = _pylon()
        with pylon_errors(self.name):
            result = self._cam.RetrieveResult(int(timeout_s * 1000), pylon.TimeoutHandling_Return)
            if result is None or not result.IsValid():
                raise InstrumentTimeout(f"camera {self.name!r}: no frame within {timeout_s:.3g} s")
            try:
                if not result.GrabSucceeded():
                    raise ProtocolError(f"camera {self.name!r}: frame lost ({result.GetErrorDescription()})")
                return np.asarray(result.Array, dtype=np.float32).copy()
            finally:
                result.Release()
