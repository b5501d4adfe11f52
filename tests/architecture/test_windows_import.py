"""Every scopetwin module imports on Windows: checked here, on POSIX, in a subprocess without POSIX.

The subprocess takes away what Windows lacks before it imports anything of ours: a :data:`sys.meta_path` finder
refuses the POSIX-only modules (``fcntl``, ``termios``, ``tty``, ``pty``, ``resource``, ``grp``, ``pwd``, pyserial's
``serial.serialposix``), the POSIX-only signal names (``SIGHUP``, ``SIGQUIT``, ``SIGUSR1`` ...) and signal
functions are deleted from :mod:`signal`, and the POSIX-only :mod:`os` functions and flags (``openpty``,
``O_NOFOLLOW``, ``pwrite`` ...) from :mod:`os`. Then every module of the package (listed from the folders, as
setup.py maps them; ``__main__`` modules left out) is imported, and every one must import. POSIX-only features
import and say so when used (``scopetwin emulate``, ``emu://`` ports: the one-line test below).

Third-party packages that choose their platform module by ``os.name`` (pyserial) are imported first, as on Windows
they import their Windows module; the POSIX-only modules they pulled in are then dropped from :data:`sys.modules`,
so an import of one of them by our code still fails. ``os.name`` and ``sys.platform`` stay as they are. Two control
modules (one importing ``fcntl``, one reading ``signal.SIGHUP`` at import) prove that the subprocess does refuse.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
LAYERS = ("scenes", "sim", "recon", "calib", "instrument")

#: Run in the subprocess: argv[1] the JSON list of module names, argv[2] the folder of the control modules.
WITHOUT_POSIX = textwrap.dedent(
    """
    import importlib, importlib.abc, json, os, signal, sys, traceback

    POSIX_MODULES = {"fcntl", "termios", "tty", "pty", "resource", "grp", "pwd", "serial.serialposix"}
    WINDOWS_SIGNALS = {"SIGABRT", "SIGBREAK", "SIGFPE", "SIGILL", "SIGINT", "SIGSEGV", "SIGTERM"}
    POSIX_SIGNAL_FUNCTIONS = {
        "alarm", "getitimer", "setitimer", "pause", "pthread_kill", "pthread_sigmask", "sigpending", "sigwait",
        "sigwaitinfo", "sigtimedwait", "siginterrupt", "SIG_BLOCK", "SIG_UNBLOCK", "SIG_SETMASK",
        "ITIMER_REAL", "ITIMER_VIRTUAL", "ITIMER_PROF",
    }
    POSIX_OS = {
        "openpty", "ttyname", "forkpty", "fork", "killpg", "setsid", "getpgid", "getuid", "geteuid", "getgid",
        "pwrite", "pread", "O_NOFOLLOW", "O_DIRECTORY", "O_NONBLOCK", "O_NOCTTY", "sched_getaffinity", "sysconf",
    }

    import serial  # pyserial picks serialposix by os.name; on Windows it imports serialwin32 instead
    try:  # platformdirs (pymmcore-plus imports it) picks its unix module by sys.platform; on Windows, windows
        import platformdirs
    except ImportError:
        pass

    class NoPosix(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name in POSIX_MODULES:
                raise ModuleNotFoundError(f"No module named {name!r} (simulated Windows)", name=name)
            return None

    for name in POSIX_MODULES:
        sys.modules.pop(name, None)
    sys.meta_path.insert(0, NoPosix())
    for name in list(vars(signal)):
        if (name.startswith("SIG") and not name.startswith("SIG_") and name not in WINDOWS_SIGNALS) or (
            name in POSIX_SIGNAL_FUNCTIONS
        ):
            delattr(signal, name)
    for name in POSIX_OS:
        if hasattr(os, name):
            delattr(os, name)

    result = {"control": {}, "failed": {}, "imported": 0}
    sys.path.insert(0, sys.argv[2])
    for control in ("control_fcntl", "control_sighup"):
        try:
            importlib.import_module(control)
            result["control"][control] = "imported"
        except Exception as exc:
            result["control"][control] = type(exc).__name__
    for module in json.loads(sys.argv[1]):
        try:
            importlib.import_module(module)
            result["imported"] += 1
        except BaseException as exc:
            result["failed"][module] = "".join(traceback.format_exception(exc)[-3:])
    print(json.dumps(result))
    """
)


def package_modules() -> list[str]:
    """Every module of the package, named as installed (``recon/markers/indexing.py`` ->
    ``scopetwin.recon.markers.indexing``), ``__main__`` modules left out."""
    names = []
    for folder, package in [("scopetwin", "scopetwin"), *((layer, f"scopetwin.{layer}") for layer in LAYERS)]:
        for path in sorted((ROOT / folder).rglob("*.py")):
            parts = list(path.relative_to(ROOT / folder).with_suffix("").parts)
            if parts[-1] == "__main__":
                continue
            if parts[-1] == "__init__":
                parts = parts[:-1]
            names.append(".".join([package, *parts]))
    return names


def test_the_module_list_covers_every_layer():
    names = package_modules()
    assert "scopetwin.recon.markers.indexing" in names and "scopetwin._version" in names
    assert {f"scopetwin.{layer}" for layer in LAYERS} | {"scopetwin.cli"} <= set(names)
    assert "scopetwin.cli.__main__" not in names
    assert len(names) > 100


@pytest.mark.timeout(600)
def test_every_module_imports_without_posix(tmp_path):
    (tmp_path / "control_fcntl.py").write_text("import fcntl\n")
    (tmp_path / "control_sighup.py").write_text("import signal\n\nHUP = signal.SIGHUP\n")
    names = package_modules()
    proc = subprocess.run(
        [sys.executable, "-c", WITHOUT_POSIX, json.dumps(names), str(tmp_path)],
        cwd=tmp_path,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=580,
    )
    assert proc.returncode == 0, proc.stderr[-4000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    # the subprocess does take POSIX away: a module that imports fcntl, or reads SIGHUP at import, fails there
    assert result["control"] == {"control_fcntl": "ModuleNotFoundError", "control_sighup": "AttributeError"}
    failed = result["failed"]
    assert not failed, "\n".join(f"{name}:\n{text}" for name, text in failed.items())
    assert result["imported"] == len(names)


def test_emulators_say_in_one_line_that_they_need_a_pty(monkeypatch, tmp_path):
    import scopetwin.instrument.emulators.base as base
    from scopetwin.instrument.emulators import PiGcsEmulator
    from scopetwin.instrument.emulators.serve import serve
    from scopetwin.instrument.transport import open_transport

    monkeypatch.setattr(base, "pty_available", lambda: False)
    with pytest.raises(base.EmulatorUnavailable, match=r"^emulators need a POSIX pseudo-terminal \(Linux, macOS\)"):
        PiGcsEmulator().start()
    with pytest.raises(base.EmulatorUnavailable, match=r"^port 'emu://pi-gcs': emulators need a POSIX"):
        open_transport("emu://pi-gcs")
    log = tmp_path / "requests.jsonl"
    with pytest.raises(base.EmulatorUnavailable, match="not available on this platform"):
        serve("jena-piezo", log_path=log)
    assert not log.exists()  # refused before anything was opened


def test_the_cli_prints_the_one_line(monkeypatch, capsys):
    import scopetwin.instrument.emulators.base as base
    from scopetwin.cli import main

    monkeypatch.setattr(base, "pty_available", lambda: False)
    assert main(["emulate", "pi-gcs"]) == 2
    captured = capsys.readouterr()
    assert captured.err == (
        "scopetwin: error: emulators need a POSIX pseudo-terminal (Linux, macOS); not available on this platform\n"
    )
    assert captured.out == ""
