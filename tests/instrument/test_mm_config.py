"""Micro-Manager configuration files that a plain ``UniMMCore`` loads with nothing of scopetwin
called first; the shipped ``rigs/*.cfg`` are what ``scopetwin rig RIG mm-config`` writes; a fresh core snaps,
switches the Channel presets and runs a useq MDA through ``core.mda`` into pymmcore-plus's own OME writers; and
pymmcore-widgets (Qt offscreen) opens a configuration."""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys

import pytest

useq = pytest.importorskip("useq", reason="useq-schema (optional extra 'mm') is not installed")
pytest.importorskip("pymmcore_plus", reason="pymmcore-plus (optional extra 'mm') is not installed")

from pymmcore_plus.experimental.unicore import UniMMCore  # noqa: E402

from scopetwin.cli import main  # noqa: E402
from scopetwin.instrument.micromanager import config_text  # noqa: E402
from scopetwin.instrument.rig import load_rig  # noqa: E402
from tests.instrument.cli_processes import ROOT  # noqa: E402

SHIPPED = ("sim-cmu", "sim-deflectometry", "emulated-hardware")
SEQUENCE = {
    "stage_positions": [{"x": 1000.0, "y": 1000.0, "z": 100.0}, {"x": 1250.0, "y": 1050.0, "z": 120.0}],
    "channels": [{"config": "uv", "exposure": 10.0}, {"config": "deep_red", "exposure": 20.0}],
    "z_plan": {"range": 4.0, "step": 2.0},
    "axis_order": "pcz",
}


@pytest.mark.parametrize("name", SHIPPED)
def test_shipped_configuration_is_what_mm_config_writes(name, tmp_path, capsys):
    out = tmp_path / f"{name}.cfg"
    assert main(["rig", str(ROOT / "rigs" / f"{name}.toml"), "mm-config", "--out", str(out)]) == 0
    assert out.read_text() == (ROOT / "rigs" / f"{name}.cfg").read_text()
    assert "Channel presets" in capsys.readouterr().out
    assert f"#py Property,Camera,Rig,{name}\n" in out.read_text()  # a shipped rig: its bare name, found anywhere


def test_a_rig_of_ones_own_is_named_by_its_absolute_path(tmp_path, monkeypatch):
    """A configuration means the same rig from every folder: a rig that is not shipped is named absolutely."""
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "lab.toml").write_text((ROOT / "rigs" / "sim-cmu.toml").read_text())
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "lab.cfg"
    assert main(["rig", "mine/lab.toml", "mm-config", "--out", str(out), "-q"]) == 0
    assert f"#py Property,Camera,Rig,{tmp_path / 'mine' / 'lab.toml'}\n" in out.read_text()


def test_a_plain_unimmcore_loads_the_file_in_a_fresh_process(tmp_path):
    """Nothing of scopetwin imported first: the '#py pyDevice' lines import the module themselves."""
    code = (
        "import sys\n"
        "from pymmcore_plus.experimental.unicore import UniMMCore\n"
        "assert not [m for m in sys.modules if m.startswith('scopetwin')]\n"
        "core = UniMMCore()\n"
        "core.loadSystemConfiguration(sys.argv[1])\n"
        "core.setConfig('Channel', 'uv'); core.snapImage(); lit = core.getImage().mean()\n"
        "core.setConfig('Channel', 'deep_red'); core.snapImage()\n"
        "bits = (core.getProperty('Camera', 'BitDepth'), core.getImageBitDepth())\n"
        "print(core.getLoadedDevices(), core.getPixelSizeUm(), *bits, lit)\n"
    )
    cfg = ROOT / "rigs" / "emulated-hardware.cfg"
    done = subprocess.run(
        [sys.executable, "-c", code, str(cfg)], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    devices, pixel, bits, image_bits, lit = done.stdout.strip().rsplit(" ", 4)
    assert "'Camera', 'XY', 'Z', 'Light'" in devices and float(pixel) == pytest.approx(6.45)
    assert int(bits) == 12 and float(lit) > 200  # the rig file was found from another folder (the checkout)
    assert int(image_bits) == 12  # the camera's ADC depth, not its uint16 buffer's 16 (widgets scale by it)


_PLAIN_CORE = """
import sys
from pymmcore_plus import CMMCorePlus
for cfg in sys.argv[1:]:
    core = CMMCorePlus()
    core.loadSystemConfiguration(cfg)
    print(cfg, list(core.getLoadedDevices()), core.getCameraDevice() or "-", core.getAvailablePixelSizeConfigs())
    # each core taken down before the next: several left to the interpreter's exit abort it about one run in three
    # (MMCore's threads, "FATAL: exception not rethrown"), after the files have loaded
    core.unloadAllDevices()
    del core
"""


def test_a_plain_cmmcoreplus_loads_the_files_without_the_python_devices(tmp_path):
    """pymmcore-plus's C++-only core skips every '#py' line (devices, presets, the pixel size of the Python camera)
    and loads the rest; in a process of its own, as ``mmcore run --config`` would."""
    written = tmp_path / "rig.cfg"
    assert main(["rig", str(ROOT / "rigs" / "emulated-hardware.toml"), "mm-config", "--out", str(written)]) == 0
    files = [written, *(ROOT / "rigs" / f"{name}.cfg" for name in SHIPPED)]
    done = subprocess.run(
        [sys.executable, "-c", _PLAIN_CORE, *map(str, files)], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.strip().splitlines()
    assert len(lines) == len(files)
    for line in lines:
        assert line.endswith(" ['Core'] - ()"), line  # the Core device alone, no camera, no pixel-size preset


def test_a_unimmcore_has_the_pixel_size_preset_and_the_bit_depth(tmp_path):
    written = tmp_path / "rig.cfg"
    assert main(["rig", str(ROOT / "rigs" / "emulated-hardware.toml"), "mm-config", "--out", str(written)]) == 0
    text = written.read_text()
    assert "\n#py ConfigPixelSize,scopetwin,Core,Camera,\n#py PixelSize_um,scopetwin,6.45\n" in text
    core = UniMMCore()
    core.loadSystemConfiguration(str(written))
    try:
        assert core.getAvailablePixelSizeConfigs() == ("scopetwin",)
        assert core.getCurrentPixelSizeConfig() == "scopetwin" and core.getPixelSizeUm() == pytest.approx(6.45)
        assert core.getImageBitDepth() == 12 and core.getBytesPerPixel() == 2
        core.snapImage()
        assert int(core.getImage().max()) <= 4095
    finally:
        core.unloadAllDevices()


def _mda_through_pymmcore_plus(core, out):
    core.mda.run(useq.MDASequence(**SEQUENCE), output=str(out))  # pymmcore-plus's own writer (ome-writers)


def test_fresh_core_snaps_switches_presets_and_runs_an_mda(tmp_path):
    rig = tmp_path / "rig.toml"
    rig.write_text((ROOT / "rigs" / "emulated-hardware.toml").read_text())
    written = tmp_path / "rig.cfg"
    assert main(["rig", str(rig), "mm-config", "--out", str(written), "--light", "deep_red"]) == 0
    for cfg in (written, ROOT / "rigs" / "emulated-hardware.cfg"):
        core = UniMMCore()
        core.loadSystemConfiguration(str(cfg))
        try:
            assert core.getChannelGroup() == "Channel" and core.getCameraDevice() == "Camera"
            assert set(core.getAvailableConfigs("Channel")) == {"uv", "blue_led", "halogen", "deep_red"}
            assert core.getPropertyUpperLimit("Camera", "Exposure") == pytest.approx(10000.0)  # the rig's 10 s
            with pytest.raises(ValueError, match="allowed range"):
                core.setProperty("Camera", "Exposure", 1e12)
            for preset in ("uv", "halogen"):
                core.setConfig("Channel", preset)
                assert core.getProperty("Light", "Lamp") == preset
                core.snapImage()
                assert core.getImage().shape == (128, 128)
            out = tmp_path / f"{cfg.stem}-{len(list(tmp_path.iterdir()))}.ome.zarr"
            _mda_through_pymmcore_plus(core, out)
            assert {p.name for p in out.iterdir()} >= {"0", "1", "zarr.json"}  # one image per position
            meta = json.loads((out / "0" / "zarr.json").read_text())["attributes"]["ome"]
            assert [c["label"] for c in meta["omero"]["channels"]] == ["uv", "deep_red"]
        finally:
            core.unloadAllDevices()  # the last device closes the rig the configuration opened


def test_unloading_closes_the_rig_and_an_unknown_device_is_named(tmp_path):
    rig = load_rig(ROOT / "rigs" / "emulated-hardware.toml")
    try:
        text = config_text(rig)
    finally:
        rig.close()
    bad = tmp_path / "bad.cfg"
    bad.write_text(text.replace("Property,Camera,Device,camera", "Property,Camera,Device,nope"))
    core = UniMMCore()
    core.loadSystemConfiguration(str(bad))
    assert core.getDeviceInitializationState("Camera").name == "InitializationFailed"
    core.unloadAllDevices()
    from scopetwin.instrument.micromanager import _OPEN

    assert not _OPEN  # every device shut down: the rig the file opened is closed


@pytest.mark.slow
@pytest.mark.mitsuba
@pytest.mark.parametrize("name", ["sim-cmu", "sim-deflectometry"])
def test_fresh_core_loads_the_rendered_rigs(name, tmp_path):
    core = UniMMCore()
    core.loadSystemConfiguration(str(ROOT / "rigs" / f"{name}.cfg"))
    try:
        presets = core.getAvailableConfigs("Channel")
        for preset in presets[:2]:
            core.setConfig("Channel", preset)
            core.snapImage()
            assert core.getImage().size > 0
        if name == "sim-cmu":
            core.setConfig("Channel", "uv")
            core.snapImage()
            assert core.getImage().mean() > 100  # cam_blue sees the uv LED
            sequence = dict(SEQUENCE, stage_positions=[{"x": 75000.0, "y": 150000.0, "z": 200.0}])
            core.mda.run(useq.MDASequence(**sequence), output=str(tmp_path / "x.ome.tif"))
            assert (tmp_path / "x.ome.tif").stat().st_size > 0
    finally:
        core.unloadAllDevices()


_WIDGETS_SCRIPT = """
import os, sys
os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
os.environ["PYMM_SIGNALS_BACKEND"] = "qt"
import superqt.iconify as iconify

def offline(*key, **kw):
    raise OSError("icons are not fetched in tests (no network here)")

# the widgets draw icons that superqt would download from a public server: never try, use its text fallback
iconify.svg_path = offline
from qtpy.QtCore import QEvent
from qtpy.QtWidgets import QApplication
from pymmcore_plus.experimental.unicore import UniMMCore
from pymmcore_widgets import ChannelWidget, ConfigurationWidget, ExposureWidget, PropertyBrowser

app = QApplication.instance() or QApplication([])
core = UniMMCore()
loader = ConfigurationWidget(mmcore=core)
loader.cfg_LineEdit.setText(sys.argv[1])
loader.load_cfg_Button.click()
app.processEvents()
assert core.getCameraDevice() == "Camera" and "Light" in core.getLoadedDevices()
channel = ChannelWidget(mmcore=core)
channel.channel_wdg._combo.setCurrentText("halogen")  # as a user picks the preset
app.processEvents()
assert core.getCurrentConfig("Channel") == "halogen" and core.getProperty("Light", "Lamp") == "halogen"
exposure = ExposureWidget(mmcore=core)
exposure.spinBox.setValue(25.0)
assert abs(core.getExposure() - 25.0) < 1e-9
browser = PropertyBrowser(mmcore=core)
core.snapImage()
assert core.getImage().shape == (128, 128)
print("widgets ok", flush=True)
# the widgets go first: a widget still listening would react to the unload (ChannelWidget re-selects its group)
for widget in (loader, channel, exposure, browser):
    widget.close()
    widget.deleteLater()
# deleted now (processEvents leaves deferred deletions to a running event loop): their connections go with them
app.sendPostedEvents(None, QEvent.Type.DeferredDelete)
app.processEvents()
core.unloadAllDevices()
app.processEvents()
print("unloaded", flush=True)
# pymmcore-plus's core, still referenced by the widgets' connections, is destroyed only at interpreter exit, after Qt's
# signaller, and its C++ destructor then aborts (with PYMM_SIGNALS_BACKEND=qt; a plain core exits cleanly): leave here
os._exit(0)
"""


@pytest.mark.slow
def test_pymmcore_widgets_open_the_configuration(tmp_path):
    """Qt offscreen, in a process of its own (Qt's objects and pymmcore-plus's signal threads never share the test
    session's process): pymmcore-widgets' own 'load configuration' widget, the channel, exposure and property widgets,
    a snap. (The stage widget fetches its icons from the internet, out of reach here.)"""
    # found, not imported: importing pymmcore-widgets sets PYMM_SIGNALS_BACKEND=qt in this process's environment,
    # which every later subprocess of the session would inherit (a CLI test's stderr then carries its warning)
    for module in ("superqt", "qtpy", "pymmcore_widgets"):
        if importlib.util.find_spec(module) is None:
            pytest.skip(f"{module} (optional extra) is not installed")
    env = dict(os.environ, QT_QPA_PLATFORM=os.environ.get("QT_QPA_PLATFORM", "offscreen"))
    done = subprocess.run(
        [sys.executable, "-c", _WIDGETS_SCRIPT, str(ROOT / "rigs" / "emulated-hardware.cfg")],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.split() == ["widgets", "ok", "unloaded"]
