"""python-microscope adapters: a rig's devices as ``microscope.abc`` devices (Cockpit and its clients).

Optional dependency: ``pip install microscope``. :func:`microscope_devices` wraps
the devices of an open rig in python-microscope's device classes, in
python-microscope's units: cameras expose in seconds and deliver uint16 frames;
light sources take a power in [0, 1] (the fraction of the light's maximum
current); stages and the focus drive (a one-axis stage named ``z``) move in
micrometres, as Cockpit expects. The wrappers never own the rig's devices:
``shutdown`` switches a light off or stops a camera's acquisition but leaves
the rig device to :func:`scopetwin.instrument.rig.open_rig`. :func:`serve_devices` is the
library function behind ``scopetwin rig RIG serve``: python-microscope's device
server (Pyro) on 127.0.0.1 only.

Security: every Pyro message to and from the server carries an HMAC of a secret key (Pyro4's ``_pyroHmacKey``),
checked before anything in the message is deserialised, so a process without the key — another user on the
machine — is refused before it can send a pickle. :func:`new_key_file` makes a key per server in a file only its
owner can read; :func:`read_key_file` reads one the user gives. Lights and stages are served with Pyro's
``serpent`` serializer, which cannot run code; cameras only with ``pickle``, because python-microscope pushes
frames as numpy arrays, which only pickle carries (``serializer="pickle"`` serves every device with pickle, as
python-microscope's own device server does). :func:`connect` is python-microscope's client with the key
(and, for a camera, its data listener keyed too).

Replays: Pyro's HMAC covers a message, not the moment it is sent, so a recorded message would verify again. Each
connection therefore signs with a key of its own after the handshake: the client sends a fresh nonce in its (keyed)
connect message, the server answers with one of its own, and both sign everything after that with
HMAC(key, both nonces) (``SessionProxy`` and ``KeyedDaemon``). A recorded call played back on a new connection
meets a new server nonce and fails its HMAC before anything in it is read; clients that do not speak this handshake
(Pyro's plain proxy with the key) are refused. Before a connection has signed its handshake it has
:data:`HANDSHAKE_TIMEOUT_S` seconds in all to do so and may send at most :data:`MAX_HANDSHAKE_BYTES`; after it, a
message may be at most :data:`MAX_REQUEST_BYTES` (a camera's listener: a frame). A message declaring more is refused
from its header, before its body is read. What the key does not protect: anyone on the machine can still open
connections and keep the server's workers busy for up to :data:`HANDSHAKE_TIMEOUT_S` each (:func:`connect` retries
for :data:`CONNECT_RETRY_S`), and the messages are not encrypted (127.0.0.1 only).
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import os
import secrets
import socket
import stat
import tempfile
import threading
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from scopetwin.instrument.devices import CameraDevice, FocusDrive, LightSource, Stage
from scopetwin.instrument.errors import InstrumentError, RigError
from scopetwin.instrument.rig import Rig

LOCALHOST = "127.0.0.1"
#: Random bytes of a generated key (written as hex text: the file's stripped text is the key).
KEY_BYTES = 32
#: The fewest bytes a key given by the user may have.
MIN_KEY_BYTES = 16
#: The largest key file read (a key is a line of text).
MAX_KEY_FILE_BYTES = 4096
#: Name of the generated key file inside its private folder.
KEY_FILE_NAME = "hmac.key"
#: ``serve_devices(serializer=...)``: "auto" (serpent for lights and stages, pickle for cameras) or "pickle".
SERIALIZERS = ("auto", "pickle")
#: Seconds a new connection has, in all, to send its signed connect message; then it is closed.
HANDSHAKE_TIMEOUT_S = 3.0
#: The largest connect message a daemon reads (the client's nonce, the object's name and Pyro's framing).
MAX_HANDSHAKE_BYTES = 64 * 1024
#: The largest request a served device reads (a call and its arguments: settings, positions, a listener's URI).
MAX_REQUEST_BYTES = 1024 * 1024
#: Seconds :func:`connect` keeps trying while the server turns connections away (its workers all busy).
CONNECT_RETRY_S = 2 * HANDSHAKE_TIMEOUT_S
#: Random bytes of each side's nonce.
NONCE_BYTES = 16
#: Mixed into each connection's key (with both nonces), so that it is used for nothing else.
SESSION_LABEL = b"scopetwin pyro session v1"
_NOFOLLOW = getattr(os, "O_NOFOLLOW", 0)


def _microscope() -> tuple[Any, Any]:
    try:
        import microscope
        import microscope.abc
    except ImportError as exc:  # pragma: no cover - optional dependency
        raise RigError("python-microscope adapters need the package: pip install microscope") from exc
    return microscope, microscope.abc


def _member(kind: Any, value: Any) -> Any:
    """``value`` as a member of the enum ``kind`` (over serpent an enum arrives as its value); None if it is none."""
    try:
        return kind(value)
    except ValueError:
        return None


def _m() -> Any:
    """The ``microscope`` package (imported on first use)."""
    return _microscope()[0]


def _pyro() -> Any:
    import Pyro4  # type: ignore[import-untyped]  # Pyro4 ships no type information

    return Pyro4


#: The mixins' base for the type checker: python-microscope (untyped, optional) supplies the real base class.
_MixinBase: Any = object


# The adapters' methods live in plain mixins; :func:`make_device_classes` puts each before its python-microscope
# base class (imported only then). Each mixin's docstring is its class's.
class _LightMixin(_MixinBase):
    """A rig light as a python-microscope light source: power = current / maximum current.

    Only software triggering in bulb mode: ``enable`` switches the light on, ``disable`` off.
    """

    def __init__(self, light: LightSource, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.light = light
        self.light.switch_off()

    @property
    def trigger_type(self) -> Any:
        return _m().TriggerType.SOFTWARE

    @property
    def trigger_mode(self) -> Any:
        return _m().TriggerMode.BULB

    def set_trigger(self, ttype: Any, tmode: Any) -> None:
        if _member(_m().TriggerType, ttype) is not _m().TriggerType.SOFTWARE or _member(
            _m().TriggerMode, tmode
        ) is not (_m().TriggerMode.BULB):
            raise _m().UnsupportedFeatureError("scopetwin lights trigger in software, bulb mode only")

    def _do_trigger(self) -> None:
        raise _m().UnsupportedFeatureError("a light in bulb mode is switched by enable/disable")

    def get_status(self) -> list[str]:
        on = "on" if self.light.is_on else "off"
        return [f"{self.light.name}: {on}", f"current {self.light.current_ma:g} mA"]

    def get_is_on(self) -> bool:
        return bool(self.light.is_on)

    def _current_for(self, power: float) -> float:
        return float(power) * self.light.current_range.high

    def _do_get_power(self) -> float:
        if not self.light.is_on:
            return 0.0
        return float(self.light.current_ma / self.light.current_range.high)

    def _do_set_power(self, power: float) -> None:
        if self.light.is_on:
            self.light.switch_on(self._current_for(power))
        else:
            self.light.set_current_ma(self._current_for(power))

    def _do_enable(self) -> bool:
        self.light.switch_on(self._current_for(self.get_set_power()))
        return True

    def _do_disable(self) -> None:
        # python-microscope disables again from __del__, after the rig may have closed (lights off already)
        if self.light.initialized:
            self.light.switch_off()

    def _do_shutdown(self) -> None:
        # python-microscope also shuts down from __del__: never raise, the rig closes the line anyway
        if self.light.initialized:
            with contextlib.suppress(InstrumentError):
                self.light.switch_off()


class _CameraMixin(_MixinBase):
    """A rig camera as a python-microscope camera: software trigger, one frame per trigger."""

    #: The HMAC key of the server that serves this camera (:func:`serve_devices` sets it; None: not served).
    client_key: bytes | None = None

    def __init__(self, camera: CameraDevice, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.camera = camera
        self._triggered = 0
        self._lock = threading.Lock()
        self.add_setting(
            "bit depth",
            "enum",
            lambda: self.camera.bit_depth,
            lambda bits: self.camera.set_bit_depth(int(bits)),
            lambda: list(self.camera.limits.bit_depths),
        )

    @property
    def trigger_type(self) -> Any:
        return _m().TriggerType.SOFTWARE

    @property
    def trigger_mode(self) -> Any:
        return _m().TriggerMode.ONCE

    def set_trigger(self, ttype: Any, tmode: Any) -> None:
        if _member(_m().TriggerType, ttype) is not _m().TriggerType.SOFTWARE or _member(
            _m().TriggerMode, tmode
        ) is not (_m().TriggerMode.ONCE):
            raise _m().UnsupportedFeatureError("the python-microscope adapter triggers in software, once")

    def _do_trigger(self) -> None:
        with self._lock:
            if self._acquiring:
                self._triggered += 1

    def soft_trigger(self) -> None:
        self.trigger()

    def _fetch_data(self) -> Any:
        with self._lock:
            if not (self._acquiring and self._triggered > 0):
                return None
            self._triggered -= 1
        frame = self.camera.grab()
        return np.clip(np.rint(frame), 0, 65535).astype(np.uint16)

    def _do_enable(self) -> bool:
        with self._lock:
            self._triggered = 0
            self._acquiring = True
        return True

    def _do_disable(self) -> None:
        self.abort()

    def abort(self) -> None:
        with self._lock:
            self._acquiring = False
            self._triggered = 0

    def _do_shutdown(self) -> None:
        self.abort()

    def set_client(self, new_client: Any) -> None:
        """Frames go to ``new_client`` (a listener URI); when served, over a proxy that signs with the key."""
        if self.client_key is not None and isinstance(new_client, str | _pyro().core.URI):
            new_client = _keyed_proxy(new_client, self.client_key, "pickle")  # frames: numpy arrays
        super().set_client(new_client)

    def set_exposure_time(self, value: float) -> None:
        self.camera.set_exposure_s(float(value))

    def get_exposure_time(self) -> float:
        return float(self.camera.exposure_s)

    def get_cycle_time(self) -> float:
        return float(self.camera.exposure_s)

    def _get_sensor_shape(self) -> tuple[int, int]:
        rows, cols = self.camera.sensor_shape
        return cols, rows  # python-microscope: (width, height)

    def _get_binning(self) -> Any:
        return _m().Binning(self.camera.binning, self.camera.binning)

    def _set_binning(self, binning: Any) -> bool:
        if binning.h != binning.v:
            raise _m().UnsupportedFeatureError("scopetwin cameras bin square only")
        self.camera.set_binning(int(binning.h))
        return True

    def _get_roi(self) -> Any:
        roi = self.camera.roi
        return _m().ROI(roi.col, roi.row, roi.cols, roi.rows)

    def _set_roi(self, roi: Any) -> bool:
        self.camera.set_roi(int(roi.top), int(roi.left), int(roi.height), int(roi.width))
        return True


class _AxisMixin(_MixinBase):
    """One rig axis in micrometres: a stage (mm inside) or the focus drive (µm inside)."""

    def __init__(self, device: Stage | FocusDrive) -> None:
        super().__init__()
        self.device = device

    @property
    def limits(self) -> Any:
        if isinstance(self.device, Stage):
            return _m().AxisLimits(self.device.travel.low * 1e3, self.device.travel.high * 1e3)
        return _m().AxisLimits(self.device.range.low, self.device.range.high)

    @property
    def position(self) -> float:
        if isinstance(self.device, Stage):
            return float(self.device.position_mm * 1e3)
        return float(self.device.position_um)

    def move_to(self, pos: float) -> None:
        lim = self.limits
        target = min(max(float(pos), lim.lower), lim.upper)  # python-microscope clips to the limits
        if isinstance(self.device, Stage):
            self.device.move_absolute(target * 1e-3)
        else:
            self.device.move_absolute_um(target)

    def move_by(self, delta: float) -> None:
        self.move_to(self.position + float(delta))


class _StageMixin(_MixinBase):
    """Rig axes as one python-microscope stage (µm); never homes on enable."""

    def __init__(self, axes: Mapping[str, Stage | FocusDrive], **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self._axes = {name: _device_classes()["axis"](device) for name, device in axes.items()}

    @property
    def axes(self) -> Mapping[str, Any]:
        return self._axes

    def may_move_on_enable(self) -> bool:
        return False  # the drivers reference at rig initialisation, not on enable

    def move_by(self, delta: Mapping[str, float]) -> None:
        for name, d in delta.items():
            self._axes[name].move_by(d)

    def move_to(self, position: Mapping[str, float]) -> None:
        for name, p in position.items():
            self._axes[name].move_to(p)

    def _do_shutdown(self) -> None:
        """Axes stay where they are."""


_DEVICE_CLASSES: dict[str, type] = {}


def _device_classes() -> dict[str, type]:
    if not _DEVICE_CLASSES:
        _, mabc = _microscope()
        for key, mixin, base in (
            ("light", _LightMixin, mabc.LightSource),
            ("camera", _CameraMixin, mabc.Camera),
            ("stage", _StageMixin, mabc.Stage),
            ("axis", _AxisMixin, mabc.StageAxis),
        ):
            name = {"light": "RigLightSource", "camera": "RigCamera", "stage": "RigStage", "axis": "RigAxis"}[key]
            namespace = {"__module__": __name__, "__doc__": mixin.__doc__, "__qualname__": name}
            _DEVICE_CLASSES[key] = type(base)(name, (mixin, base), namespace)
    return _DEVICE_CLASSES


def make_device_classes() -> dict[str, type]:
    """The adapter classes (python-microscope is imported here): ``light``, ``camera``, ``stage``, ``axis``."""
    return dict(_device_classes())


def microscope_devices(rig: Rig, *, stage_x: str = "x", stage_y: str = "y") -> dict[str, Any]:
    """The rig's cameras, lights, XY stage and focus drive as python-microscope devices.

    Parameters
    ----------
    rig : Rig
        An open rig.
    stage_x, stage_y : str
        The stage axes of the XY stage (``"xy"``: axes ``x`` and ``y``); other stages become
        one-axis stages under their own names.

    Returns
    -------
    dict
        Name -> ``microscope.abc.Device``: every camera and light under its rig name, ``"xy"``
        for the XY stage, and the focus drive under its rig name as a one-axis stage (axis ``z``).
    """
    classes = make_device_classes()
    out: dict[str, Any] = {}
    stages = {d.name: d for d in rig.devices.values() if isinstance(d, Stage)}
    for device in rig.devices.values():
        if isinstance(device, CameraDevice):
            out[device.name] = classes["camera"](device)
        elif isinstance(device, LightSource):
            out[device.name] = classes["light"](device)
        elif isinstance(device, FocusDrive):
            out[device.name] = classes["stage"]({"z": device})
    if stage_x in stages and stage_y in stages:
        out["xy"] = classes["stage"]({"x": stages.pop(stage_x), "y": stages.pop(stage_y)})
    for name, stage in stages.items():
        out[name] = classes["stage"]({name: stage})
    return out


# -- the key -----------------------------------------------------------------------------------------------
def write_key_file(path: str | os.PathLike[str], key: bytes) -> Path:
    """Write ``key`` (text) into a new file only its owner can read (0600; never through a symbolic link).

    Raises
    ------
    RigError
        ``path`` exists already (a file, a folder or a link), or cannot be created.
    """
    dest = Path(path)
    try:
        fd = os.open(dest, os.O_WRONLY | os.O_CREAT | os.O_EXCL | _NOFOLLOW, 0o600)
    except FileExistsError:
        raise RigError(f"key file {dest} exists already; not overwritten") from None
    except OSError as exc:
        raise RigError(f"cannot create the key file {dest}: {exc.strerror or exc}") from None
    try:
        os.write(fd, key + b"\n")
    finally:
        os.close(fd)
    return dest


def new_key_file() -> tuple[bytes, Path]:
    """A fresh key (:data:`KEY_BYTES` random bytes as hex text) in ``hmac.key`` of a new private temporary folder.

    The folder is made by :func:`tempfile.mkdtemp` (mode 0700, a new name: nothing there can be a link someone
    planted) and the file with ``O_EXCL`` and mode 0600. :func:`remove_key_file` removes both.
    """
    key = secrets.token_bytes(KEY_BYTES).hex().encode("ascii")
    folder = Path(tempfile.mkdtemp(prefix="scopetwin-serve-"))
    return key, write_key_file(folder / KEY_FILE_NAME, key)


def remove_key_file(path: Path) -> None:
    """Remove a key file made by :func:`new_key_file` and its folder (quietly: a server stopping)."""
    with contextlib.suppress(OSError):
        path.unlink()
    with contextlib.suppress(OSError):
        path.parent.rmdir()


def read_key_file(path: str | os.PathLike[str]) -> bytes:
    """The key in ``path``: its text without surrounding white space (a file made by :func:`new_key_file`, or e.g.
    ``python -c "import secrets; print(secrets.token_hex(32))" > key; chmod 600 key``).

    Raises
    ------
    RigError
        ``path`` is a symbolic link, not a regular file, readable or writable by others than its owner (POSIX),
        owned by another user (POSIX), larger than :data:`MAX_KEY_FILE_BYTES`, or holds fewer than
        :data:`MIN_KEY_BYTES` bytes of key.
    """
    where = f"key file {path}"
    try:
        fd = os.open(path, os.O_RDONLY | _NOFOLLOW | getattr(os, "O_NONBLOCK", 0))
    except OSError as exc:
        if os.path.islink(path):
            raise RigError(f"{where} is a symbolic link; give the file itself") from None
        raise RigError(f"cannot read the {where}: {exc.strerror or exc}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise RigError(f"{where} is not a regular file")
        if os.name == "posix":
            if info.st_mode & 0o077:
                raise RigError(
                    f"{where} can be read or written by others (mode {info.st_mode & 0o777:o}); chmod 600 it"
                )
            if info.st_uid != os.getuid():
                raise RigError(f"{where} belongs to another user")
        if info.st_size > MAX_KEY_FILE_BYTES:
            raise RigError(f"{where} is {info.st_size} bytes; a key file holds one line (at most {MAX_KEY_FILE_BYTES})")
        key = os.read(fd, MAX_KEY_FILE_BYTES + 1).strip()
    finally:
        os.close(fd)
    if len(key) < MIN_KEY_BYTES:
        raise RigError(f"{where} holds {len(key)} bytes of key; at least {MIN_KEY_BYTES} are needed")
    return key


def _key(key: bytes | str | os.PathLike[str]) -> bytes:
    """A key given as bytes, or as the path of a key file."""
    return key if isinstance(key, bytes) else read_key_file(key)


# -- Pyro with the key -------------------------------------------------------------------------------------------
def _session_key(key: bytes, client_nonce: str, server_nonce: str) -> bytes:
    """The key one connection signs with after its handshake: HMAC-SHA256 of both nonces under the shared key."""
    text = SESSION_LABEL + b"|" + client_nonce.encode("ascii") + b"|" + server_nonce.encode("ascii")
    return hmac.new(key, text, hashlib.sha256).digest()


def _nonce_of(data: Any) -> str | None:
    """The nonce in a handshake's data (``{"nonce": hex digits}``), or None when there is none."""
    nonce = data.get("nonce") if isinstance(data, dict) else None
    if isinstance(nonce, str) and len(nonce) == 2 * NONCE_BYTES and all(c in "0123456789abcdef" for c in nonce):
        return nonce
    return None


_SESSION_CLASSES: dict[str, type] = {}


def _session_classes() -> dict[str, type]:
    """The Pyro proxy and daemon that sign each connection with its own key (built once; Pyro4 imported here)."""
    if _SESSION_CLASSES:
        return _SESSION_CLASSES
    import Pyro4.util  # type: ignore[import-untyped]

    proxy = _session_proxy_class()
    daemon = _keyed_daemon_class(proxy)
    Pyro4.util.SerializerBase.register_dict_to_class(
        "Pyro4.core.SessionProxy", lambda _, d: _session_proxy_from_dict_state(d["state"])
    )
    _SESSION_CLASSES.update(proxy=proxy, daemon=daemon)
    return _SESSION_CLASSES


def _session_proxy_class() -> type:
    """Build ``SessionProxy``: Pyro's proxy with a nonce in its connect message and a session key after it."""
    import Pyro4
    import Pyro4.errors  # type: ignore[import-untyped]

    class SessionProxy(Pyro4.core.Proxy):  # Pyro4 is untyped: a subclass of Any
        """A Pyro proxy that sends a fresh nonce in each connect message and signs the rest of that connection with
        the session key (:func:`_session_key`); the connect message itself is signed with the shared key."""

        @property
        def _pyroHmacKey(self) -> bytes | None:  # noqa: N802 - Pyro4's name
            conn = self.__dict__.get("_pyroConnection")
            key = getattr(conn, "scopetwin_session_key", None) or self.__dict__.get("_Proxy__pyroHmacKey")
            return key if isinstance(key, bytes) else None

        @_pyroHmacKey.setter
        def _pyroHmacKey(self, value: bytes | str | None) -> None:  # noqa: N802
            self.__dict__["_Proxy__pyroHmacKey"] = value.encode("utf-8") if isinstance(value, str) else value

        @property
        def _pyroHandshake(self) -> dict[str, str]:  # noqa: N802 - read once per connect message
            nonce = secrets.token_hex(NONCE_BYTES)
            self.__dict__["scopetwin_nonce"] = nonce
            return {"nonce": nonce}

        @_pyroHandshake.setter
        def _pyroHandshake(self, value: Any) -> None:  # noqa: N802 - a copied or unpickled proxy makes its own
            pass

        def _pyroValidateHandshake(self, response: Any) -> None:  # noqa: N802 - Pyro4's name
            server_nonce = _nonce_of(response)
            base = self.__dict__.get("_Proxy__pyroHmacKey")
            if server_nonce is None or not base:
                raise Pyro4.errors.SecurityError("no session nonce from the server: not a scopetwin device server")
            session = _session_key(base, self.__dict__["scopetwin_nonce"], server_nonce)
            self._pyroConnection.scopetwin_session_key = session

        def __reduce__(self) -> tuple[Any, ...]:  # pickled by its state (the class is built at run time)
            return _session_proxy_from_state, (self.__getstate__(),)

    return SessionProxy


class _Bounded:
    """A Pyro connection that refuses, from the message's header, a read larger than ``limit`` bytes."""

    def __init__(self, conn: Any, limit: int) -> None:
        self._conn = conn
        self._limit = limit

    def recv(self, size: int) -> bytes:
        if size > self._limit:
            self._conn.close()
            raise _pyro().errors.SecurityError(f"a message part of {size} bytes refused: at most {self._limit}")
        return bytes(self._conn.recv(size))

    def __getattr__(self, name: str) -> Any:
        return getattr(self._conn, name)


def _timed_handshake(handshake: Callable[[Any], Any], conn: Any) -> bool:
    """Run Pyro's ``handshake`` on ``conn`` within :data:`HANDSHAKE_TIMEOUT_S` and :data:`MAX_HANDSHAKE_BYTES`.

    Returns
    -------
    bool
        Whether it succeeded; a dropped, too slow or too large client gives False (its caller closes it).
    """
    watchdog = threading.Timer(HANDSHAKE_TIMEOUT_S, _shut, args=(conn,))
    watchdog.daemon = True
    watchdog.start()
    try:
        conn.timeout = HANDSHAKE_TIMEOUT_S
        ok = bool(handshake(_Bounded(conn, MAX_HANDSHAKE_BYTES)))
    except Exception:  # a dropped, too slow or too large client: its caller closes it, nothing to report
        ok = False
    finally:
        watchdog.cancel()
    return ok


def _keyed_daemon_class(session_proxy: type) -> type:
    """Build ``KeyedDaemon``: Pyro's daemon with per-connection session keys; it hands out ``session_proxy``s."""
    import Pyro4
    import Pyro4.errors

    class KeyedDaemon(Pyro4.Daemon):  # Pyro4 is untyped: a subclass of Any
        """A Pyro daemon whose connections each sign with a session key after a handshake signed with the shared
        key and finished within :data:`HANDSHAKE_TIMEOUT_S`; messages are bounded before they are read."""

        def __init__(self, *args: Any, max_message_bytes: int = MAX_REQUEST_BYTES, **kwargs: Any) -> None:
            self._session = threading.local()  # a connection lives in one worker thread: handshake and requests
            self._max_message_bytes = int(max_message_bytes)
            self.scopetwin_serializers: tuple[str, ...] = ("serpent",)
            super().__init__(*args, **kwargs)

        @property
        def _pyroHmacKey(self) -> bytes | None:  # noqa: N802 - Pyro4's name
            key = getattr(self._session, "key", None) or self.__dict__.get("_Daemon__pyroHmacKey")
            return key if isinstance(key, bytes) else None

        @_pyroHmacKey.setter
        def _pyroHmacKey(self, value: bytes | str | None) -> None:  # noqa: N802
            self.__dict__["_Daemon__pyroHmacKey"] = value.encode("utf-8") if isinstance(value, str) else value

        def proxyFor(self, objectOrId: Any, nat: bool = True) -> Any:  # noqa: N802,N803 - Pyro4's names
            plain = super().proxyFor(objectOrId, nat)
            proxy: Any = session_proxy(plain._pyroUri)
            proxy._pyroHmacKey = self.__dict__.get("_Daemon__pyroHmacKey")  # the shared key, not this connection's
            proxy._pyroSerializer = self.scopetwin_serializers[0]
            return proxy

        def _handshake(self, conn: Any, denied_reason: str | None = None) -> bool:
            self._session.key = None
            self._session.pending = None
            if denied_reason:  # all workers busy: close at once rather than wait for this client in the accept loop
                return False
            ok = _timed_handshake(super()._handshake, conn)
            if ok and self._session.pending:
                self._session.key = self._session.pending
                conn.timeout = None  # a keyed client may hold its connection as long as it likes
                return True
            return False

        def validateHandshake(self, conn: Any, data: Any) -> Any:  # noqa: N802 - Pyro4's name
            client_nonce = _nonce_of(data)
            if client_nonce is None:
                raise Pyro4.errors.SecurityError("this server needs a session nonce: connect with scopetwin's client")
            server_nonce = secrets.token_hex(NONCE_BYTES)
            self._session.pending = _session_key(self.__dict__["_Daemon__pyroHmacKey"], client_nonce, server_nonce)
            return {"nonce": server_nonce}

        def handleRequest(self, conn: Any) -> Any:  # noqa: N802 - Pyro4's name
            if not getattr(self._session, "key", None):  # no handshake on this worker: nothing is served
                raise Pyro4.errors.SecurityError("no session")
            return super().handleRequest(_Bounded(conn, self._max_message_bytes))

    return KeyedDaemon


def _shut(conn: Any) -> None:
    """Wake a read that still waits for a handshake (a shut socket returns at once)."""
    with contextlib.suppress(OSError, AttributeError):
        conn.sock.shutdown(socket.SHUT_RDWR)


def _session_proxy_from_state(state: tuple[Any, ...]) -> Any:
    """A ``SessionProxy`` from a pickled proxy's state."""
    cls: Any = _session_classes()["proxy"]
    proxy = cls.__new__(cls)
    proxy.__setstate__(state)
    return proxy


def _session_proxy_from_dict_state(state: Any) -> Any:
    """A ``SessionProxy`` from its serpent form (as Pyro's own proxy: URI, metadata, key)."""
    cls: Any = _session_classes()["proxy"]
    proxy = cls.__new__(cls)
    proxy.__setstate_from_dict__(state)
    return proxy


def __getattr__(name: str) -> Any:
    """``SessionProxy`` and ``KeyedDaemon``, built when first asked for (Pyro4 is imported then)."""
    if name in ("SessionProxy", "KeyedDaemon"):
        return _session_classes()["proxy" if name == "SessionProxy" else "daemon"]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _keyed_proxy(uri: Any, key: bytes, serializer: str) -> Any:
    """A Pyro proxy of ``uri`` that signs its connect message with ``key`` and the rest of each connection with that
    connection's session key, speaking ``serializer``."""
    proxy = _session_classes()["proxy"](uri)
    proxy._pyroHmacKey = key
    proxy._pyroSerializer = serializer
    return proxy


def _keyed_daemon(
    key: bytes,
    serializers: tuple[str, ...],
    host: str = LOCALHOST,
    port: int = 0,
    *,
    max_message_bytes: int = MAX_REQUEST_BYTES,
) -> Any:
    """A Pyro daemon that refuses every message without ``key``'s HMAC (checked before deserialising; after the
    handshake, the connection's session key), accepts only ``serializers`` and messages of at most
    ``max_message_bytes``; the proxies it hands out (a stage's axes) carry the key and the serializer."""
    import Pyro4.util
    from Pyro4.socketserver.threadpoolserver import SocketServer_Threadpool  # type: ignore[import-untyped]

    daemon = _session_classes()["daemon"](host=host, port=port, max_message_bytes=max_message_bytes)
    if not isinstance(daemon.transportServer, SocketServer_Threadpool):  # the session key is kept per worker thread
        daemon.shutdown()
        raise RigError("the device server needs Pyro's thread pool server (PYRO_SERVERTYPE=thread)")
    daemon.scopetwin_serializers = tuple(serializers)
    daemon._pyroHmacKey = key  # set before its request loop runs: no message is read without it
    # Pyro4 reads the accepted serializers from its global config once, here per daemon (its private set)
    daemon._Daemon__serializer_ids = {Pyro4.util.get_serializer(name).serializer_id for name in serializers}
    return daemon


_TYPES_REGISTERED: list[bool] = []


def _register_microscope_types() -> None:
    """python-microscope's exceptions keep their type over serpent (its enums arrive as their values: serpent's
    own rule, which the adapters accept)."""
    if _TYPES_REGISTERED:
        return
    import microscope
    from Pyro4.util import SerializerBase

    for name, obj in vars(microscope).items():
        if isinstance(obj, type) and obj.__module__ == "microscope" and issubclass(obj, Exception):
            SerializerBase.register_dict_to_class(
                f"microscope.{name}", lambda _, d, cls=obj: SerializerBase.make_exception(cls, d)
            )
    _TYPES_REGISTERED.append(True)


def _serializer_for(device: Any, serializer: str, mabc: Any) -> str:
    """pickle for a camera (its frames are numpy arrays) or when asked; serpent (it cannot run code) otherwise."""
    return "pickle" if serializer == "pickle" or isinstance(device, mabc.DataDevice) else "serpent"


def serve_devices(
    devices: Mapping[str, Any],
    *,
    key: bytes,
    port: int = 8000,
    stop: threading.Event | None = None,
    ready: Callable[[dict[str, str]], None] | None = None,
    serializer: str = "auto",
) -> dict[str, str]:
    """Expose ``devices`` through Pyro (python-microscope's transport) on 127.0.0.1 until ``stop`` is set.

    Each device gets its own daemon on ``port``, ``port + 1``, ... (the layout of python-microscope's
    device server, one port per device; ``port = 0``: a free port each). ``ready`` receives name -> Pyro
    URI once the daemons run, so a client (:func:`connect`) can connect. Without ``stop`` it serves until the
    process ends. Returns the URIs.

    Every daemon checks each message's HMAC with ``key`` before it deserialises anything: a client without the
    key is refused. ``serializer`` "auto": cameras speak pickle (python-microscope sends frames as numpy arrays),
    lights and stages only serpent (which cannot run code); "pickle": every device pickle (python-microscope's
    device server, Cockpit).

    Raises
    ------
    RigError
        A port outside 0..65535 (for the last device), a port already in use, a key shorter than
        :data:`MIN_KEY_BYTES`, or an unknown ``serializer``.
    """
    _, mabc = _microscope()
    import Pyro4

    if not isinstance(key, bytes) or len(key) < MIN_KEY_BYTES:
        raise RigError(f"the device server needs a key of at least {MIN_KEY_BYTES} bytes")
    if serializer not in SERIALIZERS:
        raise RigError(f"serializer {serializer!r}: one of {', '.join(SERIALIZERS)}")
    Pyro4.config.REQUIRE_EXPOSE = False  # as python-microscope's device server: every public member is remote
    _register_microscope_types()
    uris: dict[str, str] = {}
    daemons = []
    try:
        if int(port) < 0 or int(port) + len(devices) - 1 > 65535:
            raise RigError(f"device server ports {port}..{int(port) + len(devices) - 1} are outside 0..65535")
        for i, (name, device) in enumerate(devices.items()):
            wire = _serializer_for(device, serializer, mabc)
            try:
                daemon = _keyed_daemon(key, (wire,), port=int(port) + i if port else 0)
            except OSError as exc:
                raise RigError(f"cannot serve {name!r} on {LOCALHOST}:{int(port) + i}: {exc.strerror or exc}") from None
            daemons.append(daemon)
            if hasattr(device, "client_key"):
                device.client_key = key  # a camera's frames go to its client's listener signed with the key
            uris[name] = str(daemon.register(device, objectId=name))
            if isinstance(device, mabc.Stage):  # as python-microscope's device server: axes travel as proxies
                for axis in device.axes.values():
                    daemon.register(axis)
        for d in daemons:
            threading.Thread(target=d.requestLoop, daemon=True, name="pyro-daemon").start()
        if ready is not None:
            ready(dict(uris))
        (stop or threading.Event()).wait()
    finally:
        for d in daemons:
            d.shutdown()
    return uris


# -- python-microscope's client with the key ---------------------------------------------------------------------
_CLIENT_CLASSES: dict[str, type] = {}


def _client_classes() -> dict[str, type]:
    """python-microscope's Client and DataClient, signing with a key (built once; microscope imported here)."""
    if _CLIENT_CLASSES:
        return _CLIENT_CLASSES
    _microscope()
    import inspect
    import itertools
    import queue

    from microscope.clients import Client, DataClient

    class KeyedClient(Client):
        """python-microscope's :class:`~microscope.clients.Client` whose proxy signs with a key; it speaks serpent
        where the server accepts it, else pickle."""

        def __init__(self, url: str, key: bytes) -> None:
            self._key = key
            super().__init__(url)

        def _connect(self) -> None:
            self._proxy = _negotiated_proxy(self._url, self._key)
            # from here as python-microscope's Client._connect: the remote methods and properties as attributes
            mine = [m[0] for m in inspect.getmembers(self, predicate=inspect.ismethod)]
            methods = set(self._proxy._pyroMethods).difference(mine)
            my_properties = [m[0] for m in inspect.getmembers(self.__class__, predicate=inspect.isdatadescriptor)]
            properties = set(self._proxy._pyroAttrs).difference(my_properties)
            for attr in itertools.chain(methods, properties):
                setattr(self, attr, getattr(self._proxy, attr))

    class KeyedDataClient(KeyedClient):
        """python-microscope's :class:`~microscope.clients.DataClient` with the key on both sides: its own listener
        (127.0.0.1, a free port) takes frames only from the keyed server."""

        def __init__(self, url: str, key: bytes) -> None:
            super().__init__(url, key)
            self._buffer: queue.Queue[Any] = queue.Queue()
            width, height = self.get_sensor_shape()  # a frame's message: its uint16 pixels (twice over) and framing
            limit = 4 * int(width) * int(height) + MAX_REQUEST_BYTES
            self._listener = _keyed_daemon(key, ("pickle",), max_message_bytes=limit)
            threading.Thread(target=self._listener.requestLoop, daemon=True, name="pyro-listener").start()
            self._client_uri = self._listener.register(self)

        enable = DataClient.enable
        receiveData = DataClient.receiveData  # noqa: N815 - python-microscope's name (exposed, one-way)
        trigger_and_wait = DataClient.trigger_and_wait

        def close(self) -> None:
            """Stop the listener."""
            self._listener.shutdown()

    _CLIENT_CLASSES.update(client=KeyedClient, data=KeyedDataClient)
    return _CLIENT_CLASSES


def _negotiated_proxy(url: str, key: bytes) -> Any:
    """A keyed proxy of ``url``, connected: serpent first, pickle when the server serves this device with pickle.

    A connection closed before the handshake's answer (the server's workers all busy, e.g. with connections that
    never sign) is tried again for :data:`CONNECT_RETRY_S` seconds."""
    import Pyro4.errors

    _register_microscope_types()
    deadline = time.monotonic() + CONNECT_RETRY_S
    wires = ["serpent", "pickle"]
    while True:
        proxy = _keyed_proxy(url, key, wires[0])
        try:
            proxy._pyroGetMetadata()
        except Pyro4.errors.ConnectionClosedError:
            proxy._pyroRelease()
            if time.monotonic() > deadline:
                raise
            time.sleep(0.05)
            continue
        except Pyro4.errors.CommunicationError as exc:
            proxy._pyroRelease()
            if wires[0] == "serpent" and "serializer that is not accepted" in str(exc):
                wires.pop(0)
                continue
            raise
        return proxy


def connect(uri: str, key: bytes | str | os.PathLike[str], *, data: bool = False) -> Any:
    """python-microscope's client of one served device, signing with ``key`` (bytes, or a key file's path).

    ``data=True`` gives a :class:`~microscope.clients.DataClient` (a camera: ``enable()``, ``trigger_and_wait()``
    returns ``(frame, timestamp)``); its listener takes frames only from a server with the key.

    Raises
    ------
    RigError
        A key file that :func:`read_key_file` refuses.
    Pyro4.errors.CommunicationError
        The server is not there, or refused the key (``SecurityError``).
    """
    return _client_classes()["data" if data else "client"](uri, _key(key))
