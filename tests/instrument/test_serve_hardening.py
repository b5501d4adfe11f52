"""The keyed Pyro daemon behind ``rig RIG serve`` against a local process without the key: a recorded call played
back, idle connections that never sign, a message declaring 600 MiB, a handshake sent a byte at a time. Real Pyro4
clients and sockets on 127.0.0.1, with the handshake's time limit shortened; each hostile case has a control on
Pyro's plain keyed daemon where the attack works, so a pass is not an artefact of the probe."""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterator

import pytest

Pyro4 = pytest.importorskip("Pyro4")

from scopetwin.instrument import pymicroscope as pm  # noqa: E402

KEY = b"k" * 32


@Pyro4.expose
class Counter:
    """A served object whose calls leave a trace."""

    def __init__(self) -> None:
        self.calls = 0

    def bump(self, payload: object = None) -> int:
        self.calls += 1
        return self.calls


def _serve(daemon: object, counter: Counter) -> str:
    uri = str(daemon.register(counter, objectId="counter"))  # type: ignore[attr-defined]
    threading.Thread(target=daemon.requestLoop, daemon=True).start()  # type: ignore[attr-defined]
    return uri


@pytest.fixture
def keyed(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[str, Counter]]:
    """The project's keyed daemon (serpent) serving a counter, its handshake limited to 0.5 s."""
    monkeypatch.setattr(pm, "HANDSHAKE_TIMEOUT_S", 0.5)
    monkeypatch.setattr(pm, "CONNECT_RETRY_S", 4.0)
    daemon = pm._keyed_daemon(KEY, ("serpent",))
    counter = Counter()
    try:
        yield _serve(daemon, counter), counter
    finally:
        daemon.shutdown()


@pytest.fixture
def plain() -> Iterator[tuple[str, Counter]]:
    """Control: Pyro's own daemon with the same key (as serve ran before)."""
    daemon = Pyro4.Daemon(host="127.0.0.1")
    daemon._pyroHmacKey = KEY
    counter = Counter()
    try:
        yield _serve(daemon, counter), counter
    finally:
        daemon.shutdown()


def _address(uri: str) -> tuple[str, int]:
    u = Pyro4.core.URI(uri)
    return u.host, u.port


def _recording_relay(target: tuple[str, int]) -> tuple[int, bytearray]:
    """A relay on a free port to ``target`` that records what the client sends (what another process on the
    machine could capture); returns its port and the record."""
    listener = socket.create_server(("127.0.0.1", 0))
    record = bytearray()

    def pump(src: socket.socket, dst: socket.socket, keep: bool) -> None:
        while data := src.recv(65536):
            if keep:
                record.extend(data)
            dst.sendall(data)
        dst.close()

    def run() -> None:
        client, _ = listener.accept()
        server = socket.create_connection(target)
        threading.Thread(target=pump, args=(client, server, True), daemon=True).start()
        pump(server, client, False)

    threading.Thread(target=run, daemon=True).start()
    return listener.getsockname()[1], record


def _record_one_call(uri: str, make_proxy: Callable[[str], object]) -> bytes:
    port, record = _recording_relay(_address(uri))
    proxy = make_proxy(uri.replace(f":{_address(uri)[1]}", f":{port}"))
    assert proxy.bump() == 1  # type: ignore[attr-defined]
    proxy._pyroRelease()  # type: ignore[attr-defined]
    return bytes(record)


def _replay(uri: str, recorded: bytes, counter: Counter) -> int:
    """Send the recorded bytes on a new connection (no key needed) and wait for the server; the counter after."""
    with socket.create_connection(_address(uri), timeout=2) as sock:
        sock.sendall(recorded)
        deadline = time.monotonic() + 2
        while time.monotonic() < deadline and counter.calls < 2:
            try:
                if not sock.recv(65536):
                    break  # the server closed the connection
            except OSError:
                break
    return counter.calls


def _plain_proxy(uri: str) -> object:
    proxy = Pyro4.Proxy(uri)
    proxy._pyroHmacKey = KEY
    proxy._pyroSerializer = "serpent"
    return proxy


def test_a_recorded_call_replayed_without_the_key_does_not_run(keyed):
    uri, counter = keyed
    recorded = _record_one_call(uri, lambda u: pm._keyed_proxy(u, KEY, "serpent"))
    assert counter.calls == 1
    assert _replay(uri, recorded, counter) == 1  # the connect message verifies, the call does not: nothing ran


def test_control_the_replay_runs_on_pyros_plain_keyed_daemon(plain):
    uri, counter = plain
    recorded = _record_one_call(uri, _plain_proxy)
    assert _replay(uri, recorded, counter) == 2  # Pyro's HMAC has no nonce: the replayed call ran again


def test_a_proxy_without_the_session_handshake_is_refused(keyed):
    uri, counter = keyed
    with pytest.raises(Pyro4.errors.CommunicationError, match="session nonce"):
        _plain_proxy(uri).bump()
    assert counter.calls == 0


def test_idle_connections_without_the_key_do_not_lock_out_a_keyed_client(keyed):
    uri, counter = keyed
    idle = [socket.create_connection(_address(uri), timeout=3) for _ in range(60)]
    try:
        start = time.monotonic()
        proxy = pm._keyed_proxy(uri, KEY, "serpent")
        for _ in range(40):  # the pool may still be full: connect as connect() does (it retries)
            try:
                proxy._pyroBind()
                break
            except Pyro4.errors.ConnectionClosedError:
                proxy._pyroRelease()
                time.sleep(0.1)
        assert proxy.bump() == 1
        assert time.monotonic() - start < 3.0
        proxy._pyroRelease()
        for sock in idle:  # each idle connection was closed by the server after the handshake's time limit
            assert _closed_within(sock, 2.0)
    finally:
        for sock in idle:
            sock.close()


def test_control_idle_connections_block_pyros_plain_keyed_daemon(plain):
    uri, _ = plain
    idle = [socket.create_connection(_address(uri), timeout=3) for _ in range(45)]  # more than its 40 workers
    try:
        proxy = _plain_proxy(uri)
        proxy._pyroTimeout = 1.0
        with pytest.raises(Pyro4.errors.CommunicationError):
            proxy.bump()
    finally:
        for sock in idle:
            sock.close()


def _header(msg_type: int, data_size: int) -> bytes:
    """A Pyro message header declaring ``data_size`` bytes of body, unsigned."""
    from Pyro4 import message, util

    msg = message.Message(msg_type, b"", util.get_serializer("serpent").serializer_id, 0, 1)
    msg.data_size = data_size
    return bytes(msg._Message__header_bytes())


def _closed_within(sock: socket.socket, seconds: float) -> bool:
    sock.settimeout(seconds)
    try:
        while sock.recv(65536):
            pass  # a refusal message may come first
    except TimeoutError:
        return False
    except OSError:
        return True  # reset
    return True


def test_a_600_mib_unsigned_message_is_refused_from_its_header(keyed):
    from Pyro4 import message

    uri, counter = keyed
    with socket.create_connection(_address(uri), timeout=2) as sock:
        sock.sendall(_header(message.MSG_CONNECT, 600 * 2**20) + b"x" * 1024)
        assert _closed_within(sock, 1.5)  # closed after 1 KiB of the declared 600 MiB
    proxy = pm._keyed_proxy(uri, KEY, "serpent")
    assert proxy.bump() == 1  # the server still serves the key's holder


def test_a_request_above_the_limit_is_refused_after_the_handshake(keyed):
    uri, counter = keyed
    proxy = pm._keyed_proxy(uri, KEY, "serpent")
    with pytest.raises(Pyro4.errors.CommunicationError):
        proxy.bump("x" * (pm.MAX_REQUEST_BYTES + 1))
    assert counter.calls == 0


def test_a_handshake_sent_a_byte_at_a_time_is_dropped_at_the_time_limit(keyed):
    from Pyro4 import message

    uri, _ = keyed
    head = _header(message.MSG_CONNECT, 100)
    with socket.create_connection(_address(uri), timeout=2) as sock:
        start = time.monotonic()
        closed = False
        for byte in head:
            try:
                sock.sendall(bytes([byte]))
            except OSError:
                closed = True
                break
            time.sleep(0.1)  # each byte well inside a per-read timeout, the whole far beyond the limit
            if time.monotonic() - start > 1.0:
                break
        assert closed or _closed_within(sock, 1.0)
        assert time.monotonic() - start < 2.5
