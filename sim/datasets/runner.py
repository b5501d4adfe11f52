"""Where tasks run: in this process or on Dask distributed (an embedded LocalCluster or an existing scheduler).

Shared by the datasets and the studies (docs/contract.md, "Scale"). :func:`run_tasks` yields each task's result or error
as it finishes, so one failed task does not lose the others' results; :func:`init_worker` sets a worker process's
Dr.Jit thread count once.

Security: a Dask scheduler and its workers unpickle what their clients send, so whoever can connect runs code. The
embedded cluster therefore speaks TLS with mutual authentication on credentials made for it alone and held in memory
(:meth:`distributed.security.Security.temporary`): another local user who reaches its port is refused before
anything is deserialised. An existing scheduler is used with Dask's own security configuration
(``distributed.comm.tls.*``, e.g. ``DASK_DISTRIBUTED__COMM__TLS__CA_FILE``): ``--scheduler tls://host:port`` with a
CA file and a client certificate and key; a ``tcp://`` scheduler authenticates nobody, which a warning says.
"""

from __future__ import annotations

import contextlib
import logging
import os
from collections.abc import Callable, Generator, Iterator, Sequence
from typing import Any

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.sim.datasets.config import DatasetError

log = logging.getLogger(__name__)

#: What :func:`init_worker` set in this process (so a second call with the same count does nothing).
_WORKER_STATE: dict[str, Any] = {}


def init_worker(threads: int | None) -> None:
    """Once per worker process: Dr.Jit's thread count and the reconstruction's threads
    (:func:`scopetwin.recon.parallel.limit_cpus`; one per worker on a local cluster; None/0 leaves them), and
    Mitsuba's log at errors only (a worker's warnings — e.g. Mitsuba's own "winding down" on a Ctrl-C that reached
    the worker — would only add lines to the client's one-line report)."""
    if not _WORKER_STATE.get("quiet") and _in_dask_worker():
        from scopetwin.scenes.mitsuba.variant import quiet_warnings, resolve

        quiet_warnings(resolve(None, "mono"))
        _WORKER_STATE["quiet"] = True
    if threads and _WORKER_STATE.get("threads") != threads:
        from scopetwin.recon.parallel import limit_cpus
        from scopetwin.scenes.mitsuba.variant import set_thread_count

        set_thread_count(int(threads))
        limit_cpus(int(threads))
        _WORKER_STATE["threads"] = threads


def _in_dask_worker() -> bool:
    try:
        from distributed import get_worker

        get_worker()
    except (ImportError, ValueError):
        return False
    return True


def default_workers() -> int:
    """One worker per core this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


def check_scheduler(address: str) -> str:
    """Check the syntax of a Dask scheduler address (``tcp://host:8786``) before anything is started or created.

    Raises
    ------
    DatasetError
        ``address`` names no host and port (the message quotes it and shows the expected form).
    """
    expected = "expected e.g. tcp://host:8786"
    try:
        from distributed.comm.addressing import parse_address, parse_host_port

        scheme, location = parse_address(address)
        if scheme in ("tcp", "tls", "ws", "wss"):
            host, port = parse_host_port(location)
            if not host or not 0 < int(port) < 65536:
                raise ValueError("a host and a port in 1..65535 are needed")
    except ImportError:
        return address  # dask_client names the missing package
    except (ValueError, TypeError) as exc:
        raise DatasetError(f"--scheduler {address!r} is not a Dask scheduler address ({exc}); {expected}") from None
    return address


@contextlib.contextmanager
def _quiet_distributed() -> Iterator[None]:
    """Distributed's loggers silenced (a cluster shutting down after an interruption logs connection errors)."""
    loggers = [logging.getLogger(n) for n in ("distributed", "tornado", "asyncio")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL + 1)
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels, strict=True):
            lg.setLevel(level)


def _silence_distributed() -> None:
    """Distributed's loggers off for the rest of this process (the cluster is about to be closed)."""
    for name in ("distributed", "tornado", "asyncio"):
        logging.getLogger(name).setLevel(logging.CRITICAL + 1)


#: Run before the worker's Python: ignore SIGINT and SIGHUP (inherited through ``exec``), then start it.
_TRAP = 'trap "" INT HUP; exec "$0" "$@"'


@contextlib.contextmanager
def _spawn_ignoring_interrupts() -> Iterator[None]:
    """While the local cluster starts, processes spawned by ``multiprocessing`` ignore SIGINT and SIGHUP from exec on.

    A terminal sends Ctrl-C to the whole process group, a dropped session SIGHUP; a worker that is still starting
    (before its preload, :func:`scopetwin.sim.signals.dask_setup`, runs; even before its ``site`` import) would print a
    KeyboardInterrupt traceback. So for the duration of the start, ``multiprocessing``'s spawn command goes
    through ``/bin/sh -c 'trap "" INT HUP; exec python ...'``: an ignored signal stays ignored across ``exec``,
    and Python keeps an ignored SIGINT ignored. Workers restarted later rely on the preload.
    """
    import shutil
    from multiprocessing import resource_tracker, spawn

    _start_resource_tracker(resource_tracker)
    sh = shutil.which("sh") or "/bin/sh"
    real_cmd = getattr(spawn, "get_command_line", None)
    real_exe = getattr(spawn, "get_executable", None)
    if real_cmd is None or real_exe is None or not os.access(sh, os.X_OK):  # pragma: no cover - unusual platform
        yield
        return

    python = real_exe()
    shell: Any = os.fsencode(sh) if isinstance(python, bytes) else sh  # the same type (3.11 keeps bytes)

    def get_command_line(**kwds: Any) -> list[Any]:
        cmd = list(real_cmd(**kwds))  # [executable, *flags, "-c", prog, ...], executable read from get_executable
        return [shell, "-c", _TRAP, python, *cmd[1:]]

    spawn.get_command_line = get_command_line
    spawn.get_executable = lambda: shell
    try:
        yield
    finally:
        spawn.get_command_line = real_cmd
        spawn.get_executable = real_exe


def _start_resource_tracker(resource_tracker: Any) -> None:
    """Start multiprocessing's resource tracker (if it is not running) with SIGHUP ignored.

    The tracker ignores SIGINT and SIGTERM itself, not SIGHUP: a dropped session's SIGHUP to the process group
    would kill it, and the one relaunched in its place prints a KeyError traceback for every name it never saw.
    """
    import signal
    import threading

    hup = getattr(signal, "SIGHUP", None)  # POSIX only
    if hup is None or threading.current_thread() is not threading.main_thread():
        resource_tracker.ensure_running()
        return
    previous = signal.signal(hup, signal.SIG_IGN)  # inherited by the tracker process
    try:
        resource_tracker.ensure_running()
    finally:
        signal.signal(hup, previous)


#: Seconds each close (the client's, then the local cluster's) may take after an interruption. A signal to the whole
#: process group ends the worker processes at the moment the client stops, and a nanny may be restarting one then:
#: the close must not wait on it without bound (the samples on disk are listed after it either way). Two closes, the
#: 3 s hand-over of finished results and the program's 10 s exit grace stay under the 30 s a batch system (SLURM's
#: KillWait, Kubernetes' grace period) waits between SIGTERM and SIGKILL.
INTERRUPTED_CLOSE_S = 8.0


def _close_quietly(*closables: Any, interrupted: bool) -> None:
    """Close a client and its cluster; after an interruption without distributed's logs or a second error, each
    within :data:`INTERRUPTED_CLOSE_S`."""
    ctx = _quiet_distributed() if interrupted else contextlib.nullcontext()
    with ctx:
        for obj in closables:
            try:
                obj.close(timeout=INTERRUPTED_CLOSE_S) if interrupted else obj.close()
            except Exception:  # noqa: BLE001 - already failing or interrupted: closing must not add an error
                if not interrupted:
                    raise


def _require_distributed() -> None:
    """Raise a :class:`DatasetError` that says what to do when Dask distributed (or, for its TLS credentials,
    cryptography) is not installed."""
    try:
        import cryptography  # noqa: F401  # Security.temporary(): the embedded cluster's TLS credentials
        import dask  # noqa: F401
        from distributed import Client, LocalCluster  # noqa: F401
    except ImportError as exc:
        raise DatasetError(
            f"Dask distributed is not installed ({exc}); install dask[distributed] and cryptography or use "
            "--workers 0 to work in this process"
        ) from None


def _tls_configured() -> bool:
    """Whether Dask's configuration gives a client TLS credentials (``distributed.comm.tls.*``)."""
    from distributed.security import Security

    return Security().get_connection_args("client").get("ssl_context") is not None


#: Seconds to reach a ``--scheduler`` address and hear its first message before Dask's client is started on it.
SCHEDULER_PROBE_S = 5.0
#: The largest first message (Dask's handshake) a scheduler may announce; a larger length is not Dask's framing.
MAX_HANDSHAKE_BYTES = 1 << 20


def probe_scheduler(address: str, timeout: float | None = None) -> None:
    """Check that ``tcp://`` or ``tls://`` ``address`` speaks like a Dask scheduler before a client is started on it.

    A Dask server speaks first: on a new connection it sends its handshake, framed by an 8-byte little-endian
    length. Something else at the address — a web server, which waits for a request, or a service that answers
    with text — would leave Dask's client waiting without a limit or reading its text as a length (an allocation
    of exbibytes); the probe reads those 8 bytes within ``timeout`` seconds (default :data:`SCHEDULER_PROBE_S`)
    instead. Other schemes (``ws``, ``inproc``) are left to Dask.

    Raises
    ------
    DatasetError
        Nothing answers, nothing is said within ``timeout``, or what is said is not Dask's framing (one line).
    """
    import socket
    import ssl
    import struct

    from distributed.comm.addressing import parse_address, parse_host_port

    scheme, location = parse_address(address)
    if scheme not in ("tcp", "tls"):
        return
    host, port = parse_host_port(location)
    limit = SCHEDULER_PROBE_S if timeout is None else timeout
    where = f"the Dask scheduler {address}"
    try:
        with socket.create_connection((host, port), timeout=limit) as raw:
            sock: socket.socket = raw
            if scheme == "tls":
                from distributed.security import Security

                ctx = Security().get_connection_args("client").get("ssl_context")
                sock = ctx.wrap_socket(raw, server_hostname=host if ctx.check_hostname else None)
            head = b""
            while len(head) < 8:
                chunk = sock.recv(8 - len(head))
                if not chunk:
                    raise DatasetError(f"{where} closed the connection without a word: not a Dask scheduler")
                head += chunk
    except TimeoutError:
        raise DatasetError(f"{where} said nothing within {limit:g} s: not a Dask scheduler, or not answering") from None
    except ssl.SSLError as exc:
        raise DatasetError(f"cannot connect to {where}: TLS failed ({exc.reason or exc})") from None
    except OSError as exc:
        raise DatasetError(f"cannot connect to {where}: {exc.strerror or exc}") from None
    (length,) = struct.unpack("<Q", head)
    if not 0 < length <= MAX_HANDSHAKE_BYTES:
        shown = head.decode("ascii", "replace") if head.isascii() else head.hex()
        raise DatasetError(f"{where} does not speak Dask's protocol (it began with {shown!r}): not a Dask scheduler")


def _connect(scheduler: str) -> Any:
    """A client of the existing cluster at ``scheduler`` (its address checked, and probed, first)."""
    from distributed import Client

    check_scheduler(scheduler)
    scheme = scheduler.split("://", 1)[0].lower() if "://" in scheduler else "tcp"
    if scheme in ("tls", "wss") and not _tls_configured():
        raise DatasetError(
            f"--scheduler {scheduler}: TLS needs a CA file and a client certificate and key in Dask's configuration "
            "(distributed.comm.tls.ca-file, .client.cert, .client.key; e.g. DASK_DISTRIBUTED__COMM__TLS__CA_FILE)"
        )
    probe_scheduler(scheduler)
    try:
        client = Client(scheduler, timeout="30s")
    except (OSError, TimeoutError, ValueError, MemoryError) as exc:
        raise DatasetError(f"cannot connect to the Dask scheduler {scheduler}: {exc}") from None
    if scheme not in ("tls", "wss", "inproc"):
        log.warning(
            "the Dask scheduler %s authenticates nobody: whoever reaches it runs code on its workers; prefer "
            "tls:// with Dask's TLS configuration",
            scheduler,
        )
    return client


def _start_local_cluster(workers: int | None) -> tuple[Any, Any]:
    """Start the embedded LocalCluster and its client (see :func:`dask_client`), holding signals until both run."""
    import dask

    from scopetwin.sim.signals import deferred_signals

    # A signal while the cluster starts is held (an interrupted start leaves half-started nannies that log
    # tracebacks at exit) and raised once the cluster can be closed; distributed's logs are off from then on.
    shield = deferred_signals(on_signal=lambda signum: _silence_distributed())
    with (
        shield,
        _spawn_ignoring_interrupts(),
        dask.config.set(
            {
                # no web pages (dashboard, task and worker info, JSON, metrics): they answer anyone without credentials
                "distributed.scheduler.http.routes": [],
                "distributed.worker.http.routes": [],
                "distributed.worker.multiprocessing-method": "spawn",
                "distributed.scheduler.allowed-failures": 5,
                "distributed.worker.memory.terminate": False,
                "distributed.worker.preload": ["scopetwin.sim.signals"],  # a worker restarted later ignores them too
            }
        ),
    ):
        client, cluster = _new_local_cluster(workers, shield)
        stop = shield.interruption()
        if stop is not None:
            _close_quietly(client, cluster, interrupted=True)
            raise stop
    return client, cluster


def _new_local_cluster(workers: int | None, shield: Any) -> tuple[Any, Any]:
    """Create the LocalCluster and its client; a failed start closes what started, then raises (a held signal first)."""
    from distributed import Client, LocalCluster
    from distributed.security import Security

    cluster: Any = None
    try:
        cluster = LocalCluster(
            n_workers=workers or default_workers(),
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            protocol="tls://",  # mutual TLS on credentials made for this cluster alone, held in memory
            security=Security.temporary(),
            dashboard_address=None,
            # Dask starts an HTTP server whatever the options: on a free local port, without routes, and stopped
            # below, so that nothing answers on it
            scheduler_kwargs={"dashboard_address": "127.0.0.1:0", "dashboard": False},
            silence_logs=logging.CRITICAL,  # a closing cluster logs errors (heartbeats) in every worker
        )
        client = Client(cluster)
        client.run_on_scheduler(_stop_http_server)
        client.run(_stop_http_server)
    except Exception:
        if cluster is not None:
            _close_quietly(cluster, interrupted=True)
        stop = shield.interruption()
        if stop is not None:  # e.g. SIGTERM to the process group killed the starting workers
            raise stop from None
        raise
    return client, cluster


def _stop_http_server(dask_scheduler: Any = None, dask_worker: Any = None) -> None:
    """Stop listening on the HTTP port of the scheduler or worker this runs on (Dask always opens one)."""
    server = getattr(dask_scheduler or dask_worker, "http_server", None)
    if server is not None:
        server.stop()


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None) -> Iterator[Any]:
    """A Dask client: on ``scheduler`` (an existing cluster, unchanged) or on an embedded LocalCluster.

    The local cluster has ``workers`` worker processes (default: one per core) with one thread each,
    started with ``spawn`` (Mitsuba's plugin registry is per thread and does not survive ``fork``),
    and listens on 127.0.0.1 only, without a dashboard or any other web page (no HTTP port stays open), speaking TLS
    with credentials made for it alone
    (:meth:`~distributed.security.Security.temporary`): a client without them is refused. Its workers ignore
    SIGINT and SIGHUP (:func:`scopetwin.sim.signals.dask_setup`, a worker preload): the client handles an
    interruption, cancels its work and closes the cluster without distributed's logs, so Ctrl-C prints no worker
    tracebacks.

    Parameters
    ----------
    scheduler : str, optional
        Address of an existing scheduler (``tls://host:8786`` with Dask's TLS configuration, or ``tcp://host:8786``);
        None starts an embedded local cluster.
    workers : int, optional
        Worker processes of the local cluster (default: :func:`default_workers`).

    Yields
    ------
    distributed.Client
        The client; on exit it is closed, and so is the local cluster (quietly after a Ctrl-C).

    Raises
    ------
    DatasetError
        Dask is not installed, or the scheduler address is malformed, does not answer or is not a Dask scheduler
        (:func:`probe_scheduler`, within :data:`SCHEDULER_PROBE_S`), or a ``tls://`` scheduler has no credentials in
        Dask's configuration.
    """
    _require_distributed()
    if scheduler:
        client = _connect(scheduler)
        closables: tuple[Any, ...] = (client,)
    else:
        client, cluster = _start_local_cluster(workers)
        closables = (client, cluster)
    interrupted = False
    try:
        yield client
    except BaseException as exc:
        interrupted = isinstance(exc, KeyboardInterrupt)
        raise
    finally:
        _close_quietly(*closables, interrupted=interrupted)


class TaskFailure(ScopetwinError):
    """A task raised on a worker; the message is the original exception's type and message."""


def _guarded(func: Callable[..., Any], *args: Any) -> tuple[bool, Any]:
    """Run a task and hand its exception back as a value (no worker-log traceback, always unpicklable-safe)."""
    try:
        return True, func(*args)
    except Exception as exc:  # noqa: BLE001 - handed to the client
        return False, f"{type(exc).__name__}: {exc}"


def failure_text(err: BaseException) -> str:
    """'Type: message' of a task's error."""
    return str(err) if isinstance(err, TaskFailure) else f"{type(err).__name__}: {err}"


def run_tasks(
    func: Callable[..., Any],
    args: Sequence[tuple],
    client: Any | None,
    keys: Sequence[str] | None = None,
    on_abandon: Callable[[int, Any], None] | None = None,
) -> Generator[tuple[int, Any, BaseException | None], None, None]:
    """Run ``func(*a)`` for every ``a`` in ``args``; yield (position, result, error) as each finishes.

    ``client`` None runs in this process, in order. Errors are yielded, not raised, so one bad
    task does not lose the others' results. When the caller stops early (an interruption, or
    ``close()`` on the iterator), the tasks still queued are given up (released), and ``on_abandon(position,
    result)`` is called for each task that had already finished but was not yet yielded (within a
    few seconds; the others are left to the caller's own recovery).
    """
    if client is None:
        for k, a in enumerate(args):
            try:
                yield k, func(*a), None
            except Exception as exc:  # noqa: BLE001 - handed to the caller
                yield k, None, exc
        return
    from distributed import as_completed

    futures = [
        client.submit(_guarded, func, *a, key=None if keys is None else keys[k], pure=False) for k, a in enumerate(args)
    ]
    position = {f.key: k for k, f in enumerate(futures)}
    seen: set[int] = set()
    finished = False
    try:
        for fut in as_completed(futures):
            k = position[fut.key]
            seen.add(k)
            try:
                ok, value = fut.result()
            except Exception as exc:  # noqa: BLE001 - e.g. KilledWorker after repeated worker deaths
                yield k, None, exc
                continue
            yield (k, value, None) if ok else (k, None, TaskFailure(value))
            fut.release()
        finished = True
    finally:
        if not finished:
            _abandon(futures, seen, on_abandon)


def _abandon(futures: Sequence[Any], seen: set[int], on_abandon: Callable[[int, Any], None] | None) -> None:
    """Give up the unfinished futures; hand the finished, unseen ones' results to ``on_abandon`` (3 s at most).

    An unfinished future is released, not cancelled: the release is a message to the scheduler and never waits (a
    cancel is a round trip that may wait without bound on a scheduler whose workers were just ended by the same
    signal), and the scheduler drops a task no client wants, queued or running, as a cancel would; a task another
    client also wants keeps running for that client.
    """
    import time

    from scopetwin.sim.signals import deferred_signals

    with deferred_signals(), _quiet_distributed():
        done = [(k, f) for k, f in enumerate(futures) if k not in seen and f.status == "finished"]
        for k, f in enumerate(futures):
            if k not in seen and f.status != "finished":
                with contextlib.suppress(Exception):
                    f.release()
        deadline = time.monotonic() + 3.0
        for k, f in done:
            left = deadline - time.monotonic()
            if on_abandon is None or left <= 0:
                break
            try:
                ok, value = f.result(timeout=left)
            except Exception:  # noqa: BLE001 - its worker is gone: the caller's recovery finds the sample
                continue
            if ok:
                on_abandon(k, value)
        for _, f in done:
            with contextlib.suppress(Exception):
                f.release()
