"""``--scheduler`` at an address that is not a Dask scheduler (a web server that waits for a request, a service that
answers with text, a port that says nothing) is one line, exit 2, within seconds, with no dataset folder left; a
real scheduler passes the probe; the embedded cluster keeps no web page (dashboard, info, JSON) open to anyone."""

from __future__ import annotations

import http.server
import socket
import socketserver
import threading
import time
from collections.abc import Iterator

import pytest

pytest.importorskip("distributed")

from scopetwin.cli import main  # noqa: E402
from scopetwin.sim.datasets import runner  # noqa: E402
from scopetwin.sim.datasets.config import DatasetError  # noqa: E402
from tests.sim.test_dataset_common import write_tiny  # noqa: E402


def _serving(server: socketserver.BaseServer) -> Iterator[str]:
    """``server`` run in a thread for one test; its address as Dask would be given it."""
    server.daemon_threads = True  # type: ignore[attr-defined]
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield f"tcp://127.0.0.1:{server.server_address[1]}"
    finally:
        server.shutdown()
        server.server_close()


@pytest.fixture
def web_server() -> Iterator[str]:
    """A tiny HTTP server in a thread (it waits for a request, as web servers do)."""
    yield from _serving(http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler))


class _Talker(socketserver.BaseRequestHandler):
    def handle(self) -> None:
        self.request.sendall(b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n")


@pytest.fixture
def talker() -> Iterator[str]:
    """A server that answers every connection with text at once (Dask's client reads it as a frame length)."""
    yield from _serving(socketserver.ThreadingTCPServer(("127.0.0.1", 0), _Talker))


def test_a_web_server_as_scheduler_is_one_line_within_seconds(tmp_path, capsys, monkeypatch, web_server):
    monkeypatch.setattr(runner, "SCHEDULER_PROBE_S", 1.0)
    tiny = write_tiny(tmp_path, count=2)
    start = time.monotonic()
    code = main(["dataset", "generate", str(tiny), "--out", str(tmp_path / "set"), "--scheduler", web_server])
    elapsed = time.monotonic() - start
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and "not a Dask scheduler" in err and "Traceback" not in err, err
    assert elapsed < 5
    assert not (tmp_path / "set").exists()


def test_a_service_that_answers_with_text_is_not_read_as_a_length(talker):
    with pytest.raises(DatasetError, match="does not speak Dask's protocol.*HTTP/1.1"):
        runner.probe_scheduler(talker, timeout=1.0)


def test_a_closed_port_is_one_line(tmp_path):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed when the block ends: nothing listens there
    with pytest.raises(DatasetError, match="cannot connect to the Dask scheduler"):
        runner.probe_scheduler(f"tcp://127.0.0.1:{port}", timeout=1.0)


def test_a_real_scheduler_passes_the_probe():
    from distributed import LocalCluster

    with LocalCluster(n_workers=0, processes=False, protocol="tcp://", host="127.0.0.1", dashboard_address=None) as c:
        assert c.scheduler_address.startswith("tcp://127.0.0.1:")
        runner.probe_scheduler(c.scheduler_address, timeout=2.0)


def _listening_ports() -> set[int]:
    import psutil

    return {c.laddr.port for c in psutil.Process().net_connections(kind="tcp") if c.status == psutil.CONN_LISTEN}


def _answers_http(port: int) -> bool:
    try:
        with socket.create_connection(("127.0.0.1", port), timeout=2) as sock:
            sock.sendall(b"GET /json/counts.json HTTP/1.0\r\nHost: 127.0.0.1\r\n\r\n")
            return sock.recv(16).startswith(b"HTTP/")
    except OSError:
        return False


def test_the_embedded_cluster_serves_no_web_page():
    with runner.dask_client(workers=1) as client:
        scheduler_port = int(client.scheduler.address.rsplit(":", 1)[1])
        here = _listening_ports()
        assert scheduler_port in here
        assert not any(_answers_http(p) for p in here)  # the scheduler runs in this process
        in_workers = client.run(_listening_ports)
        assert in_workers and not any(_answers_http(p) for ports in in_workers.values() for p in ports)
