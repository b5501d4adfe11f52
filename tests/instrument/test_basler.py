"""The Basler driver against pylon's camera emulator (PYLON_CAMEMU=1), fed with simulated frames."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("pypylon", reason="pypylon (optional extra 'hardware') is not installed")

from instrument_suites import CameraSuite  # noqa: E402

from scopetwin.instrument.drivers.basler import BaslerCamera  # noqa: E402
from scopetwin.instrument.simulated.renderers import FlatTextureRenderer  # noqa: E402
from scopetwin.instrument.simulated.world import WorldState  # noqa: E402
from scopetwin.scenes.emva1288 import EmvaSensor  # noqa: E402


class _CountingProxy:
    """Wraps the pylon camera object and counts every attribute access (= camera I/O)."""

    def __init__(self, target):
        object.__setattr__(self, "_target", target)
        object.__setattr__(self, "count", 0)

    def __getattr__(self, name):
        object.__setattr__(self, "count", self.count + 1)
        return getattr(self._target, name)

    def __setattr__(self, name, value):
        setattr(self._target, name, value)


@pytest.fixture
def emulated_camera():
    cam = BaslerCamera("basler", timeout_s=0.5)
    try:
        cam.initialize()
    except Exception as exc:  # pragma: no cover - depends on the machine
        pytest.skip(f"pylon camera emulator unavailable: {exc}")
    cam._cam = _CountingProxy(cam._cam)
    yield cam
    cam.shutdown()


class TestBaslerOnPylonEmulator(CameraSuite):
    @pytest.fixture
    def device(self, emulated_camera):
        return emulated_camera

    @pytest.fixture
    def io_count(self, emulated_camera):
        return lambda: emulated_camera._cam.count


def test_driver_grabs_rendered_frames(emulated_camera, tmp_path):
    """A simulated 12-bit frame served by the emulator's image-file mode comes back bit-exact."""
    cv2 = pytest.importorskip("cv2")
    rows, cols = 64, 80
    state = WorldState("basler", (rows, cols), 0.01, {"x": 0.0, "y": 0.0}, {}, {"led": 1.0})
    irradiance = FlatTextureRenderer(peak=1.0)(state)
    dn = EmvaSensor().capture(irradiance, 1.0e6, 0.02, rng=5).astype(np.uint16)
    assert dn.max() > 1000  # a real exposure, not a black frame
    path = tmp_path / "frame.png"
    cv2.imwrite(str(path), dn << 4)  # Mono12 from a 16-bit file takes the upper 12 bits
    cam = emulated_camera
    cam.set_roi(0, 0, rows, cols)
    cam.set_bit_depth(12)
    cam.set_node("ImageFilename", str(path))
    cam.set_node("ImageFileMode", "On")
    cam.set_node("TestImageSelector", "Off")
    frame = cam.grab()
    np.testing.assert_array_equal(frame, dn.astype(np.float32))


def test_exposure_feature_is_probed(emulated_camera):
    cam = emulated_camera
    cam.set_exposure_s(0.0125)
    probed = next(n for n in ("ExposureTime", "ExposureTimeAbs") if cam._has(n))
    assert cam.get_node(probed) == pytest.approx(12500.0)
    assert cam.exposure_s == pytest.approx(0.0125)
