"""Rigs: a TOML file names each device and its implementation; :func:`open_rig` opens them all.

Format (docs/contract.md, 'Rig files')::

    [rig]
    name = "sim-cmu"

    [devices.x]
    kind = "stage"            # camera | stage | focus | light | shutter | trigger
    driver = "sim"            # sim | pi-gcs | jena-piezo | fpga-board | basler
    travel_mm = [0.0, 150.0]  # limits given here are enforced before anything is sent
    max_velocity_mm_s = 50.0

    [devices.focus]
    kind = "focus"
    driver = "jena-piezo"
    port = "/dev/ttyS0"       # a device path or any pyserial URL (emu://jena-piezo?model=nv40-1 for the emulator)
    model = "nv40-1"          # nv40-1 | nv40-3 | 30dv50: the dialect, default baud rate and XON/XOFF
    range_um = [0.0, 400.0]

Devices on one port share one transport (the FPGA board drives lights, the
shutter and the trigger lines). When simulated devices share a rig with drivers
on in-process emulators (``emu://`` ports), the simulated world probes the
emulators (:func:`connect_emulators`): a simulated camera sees the board's
lights and the stages' and focus drive's positions. An ``emu://`` emulator lives as long as
the rig that opened it: each :func:`open_rig` (each ``scopetwin rig`` command) starts it fresh,
so state such as a stage position does not carry over; ``scopetwin emulate KIND`` runs one in
its own process whose port a rig names like a device path. :func:`open_rig` is a context manager: on every
exit, exception included, it switches every light off, closes shutters, stops
camera acquisition and closes transports; it never moves an axis.

A device that stops answering mid-operation (its port gone, no answer within its
timeout, garbage, a flood) is not tried again on the way out beyond one attempt per
line: every other device is brought to its safe state, and :func:`open_rig` raises one
:class:`~scopetwin.instrument.errors.DeviceLost` whose one-line message names the
device and what is known of its state ("light 'halogen' may still be on").
"""

from __future__ import annotations

import contextlib
import functools
import logging
import math
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from scopetwin.instrument.devices import (
    CameraDevice,
    CameraLimits,
    Device,
    FocusDrive,
    LightSource,
    Range,
    Shutter,
    Stage,
    TriggerController,
)
from scopetwin.instrument.errors import DeviceLost, DisconnectedError, InstrumentError, InstrumentTimeout, RigError
from scopetwin.instrument.interrupts import deferred_signals
from scopetwin.scenes.inputs import InputError, load_toml_input
from scopetwin.shipped import find_rig, rig_names

log = logging.getLogger(__name__)

KINDS = ("camera", "stage", "focus", "light", "shutter", "trigger")
DRIVERS = ("sim", "pi-gcs", "jena-piezo", "fpga-board", "basler")
#: Optical facts a device table may give beside its driver's fields (any driver): they describe the light path for
#: the metadata of acquisitions (OME channel colours and wavelengths, the objective) and limit nothing.
OPTICAL_FIELDS = {"light": ("wavelength_nm", "emission_nm"), "camera": ("numerical_aperture",)}


def _pop_optics(name: str, table: dict[str, Any]) -> dict[str, float]:
    """Take the optical fields of ``table``'s kind out of it (positive numbers), by name."""
    optics = {}
    for key in OPTICAL_FIELDS.get(str(table.get("kind")), ()):
        if key in table:
            value = table.pop(key)
            if isinstance(value, bool) or not isinstance(value, int | float) or not 0 < value < 1e6:
                raise RigError(f"device {name!r}: {key} must be a positive number, got {value!r}")
            optics[key] = float(value)
    return optics


@dataclass
class _Context:
    world: Any = None
    transports: dict[str, Any] = field(default_factory=dict)
    boards: dict[str, Any] = field(default_factory=dict)

    def sim_world(self) -> Any:
        if self.world is None:
            from scopetwin.instrument.simulated.world import VirtualWorld

            self.world = VirtualWorld()
        return self.world

    def transport(self, name: str, table: dict[str, Any], default_baud: int, default_xonxoff: bool = False) -> Any:
        from scopetwin.instrument.transport import open_transport

        port = _take(table, "port", str, name)
        baud = _take(table, "baudrate", int, name, default_baud)
        if not 50 <= baud <= 4_000_000:
            raise RigError(f"device {name!r}: baudrate must be in 50..4000000, got {baud}")
        xonxoff = _take(table, "xonxoff", bool, name, default_xonxoff)
        if port not in self.transports:
            self.transports[port] = open_transport(port, baudrate=baud, timeout_s=0.02, xonxoff=xonxoff)
        return self.transports[port]


def _take(table: dict[str, Any], key: str, kind: type, device: str, default: Any = ...) -> Any:
    if key not in table:
        if default is ...:
            raise RigError(f"device {device!r}: missing field {key!r}")
        return default
    value = table.pop(key)
    if kind is float and isinstance(value, int) and not isinstance(value, bool):
        value = float(value)
    if kind is tuple:
        if not isinstance(value, list) or len(value) != 2 or not all(_number(v) for v in value):
            raise RigError(f"device {device!r}: {key} must be a list of two numbers, each finite, got {value!r}")
        return (float(value[0]), float(value[1]))
    if not isinstance(value, kind) or (kind in (int, float) and isinstance(value, bool)):
        raise RigError(f"device {device!r}: {key} must be {kind.__name__}, got {value!r}")
    if kind in (int, float) and not _number(value):
        raise RigError(f"device {device!r}: {key} must be finite and at most {MAX_NUMBER:g} in size, got {value!r}")
    return value


#: Largest magnitude of any number in a rig file (every number finite and in a physical range; the
#: device classes check their own limits, travel and current ranges, within it).
MAX_NUMBER = 1.0e12
#: Longest timeout of one exchange with a device, seconds.
MAX_TIMEOUT_S = 600.0


def _number(value: Any) -> bool:
    """A finite int or float (not a bool) of magnitude at most :data:`MAX_NUMBER`."""
    return (
        isinstance(value, int | float)
        and not isinstance(value, bool)
        and math.isfinite(value)
        and abs(value) <= MAX_NUMBER
    )


def _camera_limits(name: str, t: dict[str, Any]) -> CameraLimits:
    defaults = CameraLimits()
    shape = t.pop("sensor_shape", list(defaults.sensor_shape))
    if not (isinstance(shape, list) and len(shape) == 2 and all(isinstance(v, int) and v > 0 for v in shape)):
        raise RigError(f"camera {name!r}: sensor_shape must be [rows, cols], got {shape!r}")
    exposure = _take(t, "exposure_range_s", tuple, name, (defaults.exposure_s.low, defaults.exposure_s.high))
    return CameraLimits(
        sensor_shape=(shape[0], shape[1]),
        pixel_size_um=_take(t, "pixel_size_um", float, name, defaults.pixel_size_um),
        magnification=_take(t, "magnification", float, name, defaults.magnification),
        exposure_s=Range(exposure[0], exposure[1], "s"),
    )


def _build_sim(name: str, kind: str, t: dict[str, Any], ctx: _Context, timeout_s: float) -> Device:
    """Build a simulated device of ``kind`` on the rig's shared virtual world."""
    from scopetwin.instrument.simulated import devices as simd

    world = ctx.sim_world()
    if kind == "stage":
        return simd.SimStage(
            name,
            world,
            travel_mm=_take(t, "travel_mm", tuple, name),
            max_velocity_mm_s=_take(t, "max_velocity_mm_s", float, name),
            position_mm=_take(t, "position_mm", float, name, None),
            timeout_s=timeout_s,
        )
    if kind == "focus":
        return simd.SimFocus(
            name,
            world,
            range_um=_take(t, "range_um", tuple, name, (0.0, 400.0)),
            position_um=_take(t, "position_um", float, name, None),
            timeout_s=timeout_s,
        )
    if kind == "light":
        return simd.SimLight(
            name,
            world,
            max_current_ma=_take(t, "max_current_ma", float, name),
            shutter=_take(t, "shutter", str, name, None),
            timeout_s=timeout_s,
        )
    if kind == "shutter":
        return simd.SimShutter(name, world, timeout_s=timeout_s)
    if kind == "trigger":
        return simd.SimTrigger(
            name, world, n_camera_lines=_take(t, "n_camera_lines", int, name, 4), timeout_s=timeout_s
        )
    return _build_sim_camera(name, t, world, timeout_s)


def _build_sim_camera(name: str, t: dict[str, Any], world: Any, timeout_s: float) -> Device:
    """Build a simulated camera: its limits, EMVA 1288 sensor and renderer from the table."""
    from scopetwin.instrument.simulated import devices as simd
    from scopetwin.instrument.simulated.renderers import make_renderer
    from scopetwin.scenes.emva1288 import EmvaSensor

    limits = _camera_limits(name, t)
    try:  # the rig's ``sensor`` table: the fields of the EMVA 1288 model
        emva = EmvaSensor(**t.pop("sensor", {}))
    except TypeError as exc:
        raise RigError(f"camera {name!r}: bad sensor field ({exc})") from exc
    renderer = make_renderer(t.pop("renderer", {"kind": "texture"}), camera=name)
    return simd.SimCamera(
        name,
        world,
        renderer=renderer,
        emva=emva,
        limits=limits,
        photons_per_unit_s=_take(t, "photons_per_unit_s", float, name, 1.0e6),
        trigger_line=_take(t, "trigger_line", int, name, 0),
        seed=_take(t, "seed", int, name, 0),
        serial_number=_take(t, "serial", str, name, f"SIM-{name}"),
        timeout_s=timeout_s,
    )


def _build_pi_stage(name: str, t: dict[str, Any], ctx: _Context, timeout_s: float) -> Device:
    """Build a stage axis on a PI GCS controller."""
    from scopetwin.instrument.drivers.pi_gcs import PiGcsStage

    transport = ctx.transport(name, t, 115200)
    return PiGcsStage(
        name,
        transport,
        axis=str(t.pop("axis", "1")),
        travel_mm=_take(t, "travel_mm", tuple, name),
        max_velocity_mm_s=_take(t, "max_velocity_mm_s", float, name, None),  # None: read from the controller
        velocity_mm_s=_take(t, "velocity_mm_s", float, name, None),
        reference=_take(t, "reference", bool, name, True),
        timeout_s=timeout_s,
    )


def _build_jena_focus(name: str, t: dict[str, Any], ctx: _Context, timeout_s: float) -> Device:
    """Build a focus drive on a piezosystem jena amplifier of the table's model."""
    from scopetwin.instrument.drivers.jena_piezo import JenaPiezoFocus, dialect_of

    dialect = dialect_of(_take(t, "model", str, name, "nv40-1"))  # the model sets baud rate and XON/XOFF
    transport = ctx.transport(name, t, dialect.baudrate, dialect.xonxoff)
    return JenaPiezoFocus(
        name,
        transport,
        model=dialect.model,
        channel=_take(t, "channel", int, name, 0),
        range_um=_take(t, "range_um", tuple, name, (0.0, 400.0)),
        voltage_range_v=_take(t, "voltage_range_v", tuple, name, (-20.0, 130.0)),
        closed_loop=_take(t, "closed_loop", bool, name, True),
        timeout_s=timeout_s,
    )


def _build_fpga(name: str, kind: str, t: dict[str, Any], ctx: _Context, timeout_s: float) -> Device:
    """Build a light, shutter or trigger on the FPGA board of the table's port (one board per port)."""
    from scopetwin.instrument.drivers.fpga_board import FpgaBoard, FpgaLight, FpgaShutter, FpgaTrigger

    port = str(t.get("port"))
    transport = ctx.transport(name, t, 115200)
    step = _take(t, "current_step_ma", float, name, 0.1)
    if port not in ctx.boards:
        ctx.boards[port] = FpgaBoard(transport, timeout_s=timeout_s, current_step_ma=step)
    board = ctx.boards[port]
    if kind == "light":
        return FpgaLight(
            name,
            board,
            channel=_take(t, "channel", int, name),
            max_current_ma=_take(t, "max_current_ma", float, name),
        )
    if kind == "shutter":
        return FpgaShutter(
            name,
            board,
            open_output=_take(t, "open_output", int, name, 0),
            close_output=_take(t, "close_output", int, name, 1),
        )
    return FpgaTrigger(name, board)


def _build_basler(name: str, t: dict[str, Any], timeout_s: float) -> Device:
    """Build a Basler GigE camera."""
    from scopetwin.instrument.drivers.basler import BaslerCamera

    return BaslerCamera(
        name,
        serial=_take(t, "serial", str, name, None),
        pixel_size_um=_take(t, "pixel_size_um", float, name, 6.45),
        magnification=_take(t, "magnification", float, name, 1.0),
        gain_db_per_raw=_take(t, "gain_db_per_raw", float, name, 0.0359),
        trigger_line=_take(t, "trigger_input", str, name, "Line1"),
        packet_size=_take(t, "packet_size", int, name, None),  # GevSCPSPacketSize, bytes
        inter_packet_delay=_take(t, "inter_packet_delay", int, name, None),  # GevSCPD, ticks
        timeout_s=timeout_s,
    )


def _build(name: str, table: dict[str, Any], ctx: _Context) -> Device:
    """Build the device one rig-file table describes; every field must be used."""
    t = dict(table)
    kind = _take(t, "kind", str, name)
    driver = _take(t, "driver", str, name)
    if kind not in KINDS:
        raise RigError(f"device {name!r}: unknown kind {kind!r}; choose from {KINDS}")
    if driver not in DRIVERS:
        raise RigError(f"device {name!r}: unknown driver {driver!r}; choose from {DRIVERS}")
    timeout_s = _take(t, "timeout_s", float, name, 1.0)
    if not 0.0 < timeout_s <= MAX_TIMEOUT_S:
        raise RigError(f"device {name!r}: timeout_s must be in (0, {MAX_TIMEOUT_S:g}] s, got {timeout_s}")
    device: Device
    key = (kind, driver)
    if driver == "sim":
        device = _build_sim(name, kind, t, ctx, timeout_s)
    elif key == ("stage", "pi-gcs"):
        device = _build_pi_stage(name, t, ctx, timeout_s)
    elif key == ("focus", "jena-piezo"):
        device = _build_jena_focus(name, t, ctx, timeout_s)
    elif driver == "fpga-board" and kind in ("light", "shutter", "trigger"):
        device = _build_fpga(name, kind, t, ctx, timeout_s)
    elif key == ("camera", "basler"):
        device = _build_basler(name, t, timeout_s)
    else:
        raise RigError(f"device {name!r}: driver {driver!r} does not provide a {kind!r}")
    t.pop("description", None)
    if t:
        raise RigError(f"device {name!r}: unknown field(s) {sorted(t)} for a {driver} {kind}")
    return device


class Rig:
    """The devices of one rig, by name, plus the safe-exit logic.

    Attributes
    ----------
    name : str
        Rig name.
    devices : dict
        Devices by name, in file order.
    world : VirtualWorld or None
        The shared world when any device is simulated.
    ports : dict
        Device name -> the ``port`` its table names (devices on a serial line only).
    """

    def __init__(
        self,
        name: str,
        devices: dict[str, Device],
        world: Any = None,
        transports: dict | None = None,
        path: str = "",
        ports: dict[str, str] | None = None,
        optics: dict[str, dict[str, float]] | None = None,
    ) -> None:
        self.name = name
        self.devices = devices
        self.world = world
        self.path = path
        self.ports = dict(ports or {})
        self._transports = transports or {}
        #: Device name -> its optical fields (:data:`OPTICAL_FIELDS`), for devices whose table gives any.
        self.optics = {name: dict(fields) for name, fields in (optics or {}).items() if fields}

    def emulated_ports(self) -> dict[str, str]:
        """Devices on ``emu://`` ports: in-process emulators that start fresh with every :func:`open_rig`."""
        return {name: port for name, port in self.ports.items() if port.lower().startswith("emu://")}

    def __getitem__(self, name: str) -> Device:
        if name not in self.devices:
            raise RigError(f"rig {self.name!r} has no device {name!r}; devices: {sorted(self.devices)}")
        return self.devices[name]

    def of_kind(self, kind: str) -> list[Device]:
        """All devices of ``kind`` (``"camera"``, ``"stage"``, ``"focus"``, ``"light"``, ...), in file order."""
        return [d for d in self.devices.values() if d.kind == kind]

    def lights(self) -> list[LightSource]:
        """Every light source, in file order."""
        return [d for d in self.devices.values() if isinstance(d, LightSource)]

    def shutters(self) -> list[Shutter]:
        """Every shutter, in file order."""
        return [d for d in self.devices.values() if isinstance(d, Shutter)]

    def _one(self, kind: str, name: str | None, what: str) -> Device:
        if name is not None:
            device = self[name]
            if device.kind != kind:
                raise RigError(f"device {name!r} of rig {self.name!r} is a {device.kind}, not a {what}")
            return device
        found = self.of_kind(kind)
        if not found:
            raise RigError(f"rig {self.name!r} has no {what}")
        return found[0]

    def camera(self, name: str | None = None) -> CameraDevice:
        """A camera by name (default: the first)."""
        device = self._one("camera", name, "camera")
        if not isinstance(device, CameraDevice):
            raise RigError(f"device {device.name!r} says it is a camera but is a {type(device).__name__}")
        return device

    def stage(self, name: str) -> Stage:
        """A stage axis by name."""
        device = self._one("stage", name, "stage")
        if not isinstance(device, Stage):
            raise RigError(f"device {device.name!r} says it is a stage but is a {type(device).__name__}")
        return device

    def focus(self, name: str | None = None) -> FocusDrive:
        """The focus drive (default: the first)."""
        device = self._one("focus", name, "focus drive")
        if not isinstance(device, FocusDrive):
            raise RigError(f"device {device.name!r} says it is a focus drive but is a {type(device).__name__}")
        return device

    def light(self, name: str | None = None) -> LightSource:
        """A light by name (default: the first)."""
        device = self._one("light", name, "light")
        if not isinstance(device, LightSource):
            raise RigError(f"device {device.name!r} says it is a light but is a {type(device).__name__}")
        return device

    def trigger(self, name: str | None = None) -> TriggerController:
        """The trigger controller (default: the first)."""
        device = self._one("trigger", name, "trigger controller")
        if not isinstance(device, TriggerController):
            raise RigError(f"device {device.name!r} says it is a trigger controller but is a {type(device).__name__}")
        return device

    def initialize(self) -> None:
        """Initialize every device in file order."""
        for device in self.devices.values():
            device.initialize()

    def _lost_lines(self) -> set[int]:
        """Identities of the transports whose last exchange failed (a device on them stopped answering)."""
        return {id(link.transport) for d in self.devices.values() for link in d.links() if link.lost is not None}

    @staticmethod
    def _on(device: Device, lines: set[int]) -> bool:
        return any(id(link.transport) in lines for link in device.links())

    def lights_off(self) -> list[str]:
        """Switch every light off and close every shutter; return the failures (never raises).

        A line that fails here is not tried again for the other devices on it, so each line that stopped answering
        costs at most one timeout.
        """
        failures = []
        failed: set[int] = set()
        for device in [*self.lights(), *self.shutters()]:
            if not device.initialized:
                continue
            if self._on(device, failed):
                failures.append(f"{device.name}: not tried, its line stopped answering")
                continue
            try:
                if isinstance(device, LightSource):
                    device.switch_off()
                elif isinstance(device, Shutter):
                    device.close()
            except InstrumentError as exc:
                failures.append(f"{device.name}: {exc}")
                failed |= {id(link.transport) for link in device.links() if link.lost is not None}
        return failures

    def close(self) -> list[str]:
        """Lights off, then shut every device down in reverse order and close transports (never raises).

        Devices on a line that stopped answering are abandoned (:meth:`Device.abandon`), not shut down: nothing more
        is sent to them, and what is known of their state stays for :meth:`lost_message`.
        """
        failures = self.lights_off()
        lost = self._lost_lines()
        for device in reversed(list(self.devices.values())):
            if self._on(device, lost):
                device.abandon()
                continue
            try:
                device.shutdown()
            except Exception as exc:  # noqa: BLE001 - closing must reach every device
                failures.append(f"{device.name}: {exc}")
                lost |= {id(link.transport) for link in device.links() if link.lost is not None}
        for transport in self._transports.values():
            with contextlib.suppress(Exception):
                transport.close()
        return failures

    def lost_devices(self) -> list[Device]:
        """The devices whose line stopped answering (its last exchange failed), in file order."""
        lost = self._lost_lines()
        return [d for d in self.devices.values() if self._on(d, lost)]

    def lost_message(self, failures: list[str]) -> str | None:
        """One line on the devices that stopped answering: which, why, what is known of their state, and whether every
        other device reached its safe state (``failures``: what :meth:`close` returned); ``None`` if none did."""
        lost = self.lost_devices()
        if not lost:
            return None
        parts = []
        for link in {id(link): link for d in lost for link in d.links() if link.lost is not None}.values():
            on_line = [d for d in lost if any(own.transport is link.transport for own in d.links())]
            port = next((self.ports[d.name] for d in on_line if d.name in self.ports), "its port")
            who = link.name if len(on_line) == 1 else f"{link.name} ({', '.join(d.name for d in on_line)})"
            why = str(link.lost).removeprefix(f"{link.name}: ")
            parts.append(f"{who} on {port} stopped answering ({why})")
        unsafe = [d.known_state() for d in lost if not d.state_is_safe()]
        state = "; ".join(unsafe) if unsafe else "no light was left on and no axis was moving"
        names = {d.name for d in lost}
        others = [f for f in failures if f.split(":", 1)[0] not in names]
        rest = f"; also: {'; '.join(others)}" if others else "; every other device is in its safe state"
        return f"{'; '.join(parts)}: {state}{rest}"

    def describe(self) -> dict[str, Any]:
        """Rig name and each device's description (JSON-ready)."""
        devices = []
        for name, device in self.devices.items():
            entry = device.describe()
            if name in self.ports:
                entry["port"] = self.ports[name]
            entry.update(self.optics.get(name, {}))
            devices.append(entry)
        return {"rig": self.name, "path": self.path, "devices": devices}


def read_rig_toml(path: str | Path) -> dict[str, Any]:
    """The parsed rig TOML: a regular file of at most 16 MiB, nested at most 64 levels
    (:mod:`scopetwin.scenes.inputs`). A path that does not exist may name a shipped rig
    (:func:`scopetwin.shipped.find_rig`: ``sim-cmu``, ``rigs/sim-cmu.toml``).

    Raises
    ------
    RigError
        Missing, not a regular file (a FIFO, a device), too large, too deep, or not valid TOML.
    """
    p = find_rig(path)
    try:
        return load_toml_input(p, "rig")
    except InputError as exc:
        hint = "" if p.exists() else f" (the shipped rigs: {', '.join(rig_names())})"
        raise RigError(f"{exc}{hint}") from None


def load_rig(path: str | Path) -> Rig:
    """Read a rig TOML and build its devices (no I/O yet except opening serial ports).

    ``path`` is a rig file, or names a shipped one (:func:`scopetwin.shipped.find_rig`): ``sim-cmu`` or
    ``rigs/sim-cmu.toml`` from any folder; the rig's ``path`` is then the shipped file's.

    Raises
    ------
    RigError
        Unreadable file, unknown kind/driver/field, or a bad limit.
    """
    p = find_rig(path)
    data = read_rig_toml(p)
    tables = data.get("devices")
    if not isinstance(tables, dict) or not tables:
        raise RigError(f"rig file {str(p)!r} has no [devices.NAME] tables")
    ctx = _Context()
    devices: dict[str, Device] = {}
    optics: dict[str, dict[str, float]] = {}
    ports = {name: str(table["port"]) for name, table in tables.items() if isinstance(table, dict) and "port" in table}
    try:
        for name, table in tables.items():
            if not isinstance(table, dict):
                raise RigError(f"rig file {str(p)!r}: devices.{name} is not a table")
            table = dict(table)
            optics[name] = _pop_optics(name, table)
            devices[name] = _build(name, table, ctx)
    except Exception:
        for transport in ctx.transports.values():
            with contextlib.suppress(Exception):
                transport.close()
        raise
    if ctx.world is not None:
        connect_emulators(ctx.world, devices)
    rig_name = str(data.get("rig", {}).get("name", p.stem))
    return Rig(rig_name, devices, ctx.world, ctx.transports, str(p), ports, optics)


def _emulator_of(transport: Any) -> Any:
    return getattr(transport, "emulator", None)


def connect_emulators(world: Any, devices: dict[str, Device]) -> list[str]:
    """Let the simulated world see drivers that talk to in-process emulators; return the names connected.

    A light on an FPGA board emulator becomes a light probe (its relative current while the
    board says it is on), a PI stage on a GCS emulator a stage probe (its position, mid-move
    included), a jena focus drive on its emulator a focus probe. Devices on real ports are
    left alone: the world cannot see real hardware.
    """
    from scopetwin.instrument.drivers.fpga_board import FpgaLight
    from scopetwin.instrument.drivers.jena_piezo import JenaPiezoFocus
    from scopetwin.instrument.drivers.pi_gcs import PiGcsStage
    from scopetwin.instrument.emulators import FpgaBoardEmulator, JenaPiezoEmulator, PiGcsEmulator

    connected = []
    for name, device in devices.items():
        if isinstance(device, FpgaLight):
            board = _emulator_of(device.board.link.transport)
            if isinstance(board, FpgaBoardEmulator):
                world.light_probes[name] = functools.partial(
                    board.light_level, device.channel, device.board.current_step_ma, device.current_range.high
                )
                connected.append(name)
        elif isinstance(device, PiGcsStage):
            controller = _emulator_of(device.controller.link.transport)
            if isinstance(controller, PiGcsEmulator) and device.axis in controller.axes:
                world.stage_probes[name] = functools.partial(controller.position_mm, device.axis)
                connected.append(name)
        elif isinstance(device, JenaPiezoFocus):
            piezo = _emulator_of(device.link.transport)
            if isinstance(piezo, JenaPiezoEmulator):
                channel = piezo.channels[device.channel]
                world.focus_probes[name] = lambda c=channel: c.position_um
                connected.append(name)
    return connected


@contextlib.contextmanager
def open_rig(path: str | Path, on_close: Callable[[list[str]], None] | None = None) -> Iterator[Rig]:
    """Open a rig as a context manager: devices initialized on entry; on every exit lights off,
    shutters closed, acquisition stopped, transports closed (axes stay where they are).

    A signal (SIGINT, SIGTERM, SIGHUP) that arrives while the rig closes is held until it is closed.

    ``on_close`` receives the list of failures while closing (normally empty).

    Raises
    ------
    DeviceLost
        A device stopped answering: the block raised an :class:`~scopetwin.instrument.errors.InstrumentError` while a
        device's line had failed (or a timeout or lost connection of its own), or the block ended normally but a light
        or shutter could not be made safe on the way out. The message (one line) names the device and what is known of
        its state; every other device is in its safe state. After a signal or another error the same line is logged as
        a warning and that error goes on.
    """
    rig = load_rig(path)
    error: BaseException | None = None
    try:
        rig.initialize()
        yield rig
    except BaseException as exc:
        error = exc
        raise
    finally:
        with deferred_signals():  # a SIGINT/SIGTERM/SIGHUP now waits until every light is off
            failures = rig.close()
        if on_close is not None:
            on_close(failures)
        _raise_if_lost(rig, failures, error)


def _raise_if_lost(rig: Rig, failures: list[str], error: BaseException | None) -> None:
    """Turn a device that stopped answering into one :class:`DeviceLost` (see :func:`open_rig`)."""
    if isinstance(error, DeviceLost):
        return
    message = rig.lost_message(failures)
    if message is None and isinstance(error, InstrumentTimeout | DisconnectedError):
        rest = f"also: {'; '.join(failures)}" if failures else "every other device is in its safe state"
        message = f"{error}; {rest}"
    if message is None or (error is None and not failures):
        return
    lost = DeviceLost(message, tuple(d.name for d in rig.lost_devices()))
    if error is None or isinstance(error, InstrumentError):
        raise lost from error
    log.warning("%s", lost)
