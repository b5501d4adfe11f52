"""The files shipped beside the code: the rigs and the examples the documentation's commands use.

``rigs/`` holds the rig TOMLs (``sim-cmu.toml``, ``sim-deflectometry.toml``, ``sim-deflectometry-stage.toml``,
``emulated-hardware.toml``) and their Micro-Manager configurations (``*.cfg``); ``examples/`` the dataset configs
(``examples/datasets/*.toml``) and an MDA sequence (``examples/mda/*.json``). In the checkout they are the folders at
the repository root; an installed wheel holds them as package data, ``scopetwin/rigs/`` and ``scopetwin/examples/``
(setup.py), found through :func:`importlib.resources.files`.

An input path that exists is read as it is. One that does not exist, relative and naming a shipped file, reads the
shipped file: ``rigs/sim-cmu.toml`` and ``examples/datasets/01-deflectometry-small.toml`` work from any folder, and a
rig's bare name (``sim-cmu``) names the shipped rig.

Examples
--------
>>> from scopetwin.shipped import find_rig, rig_names
>>> rig_names()
['emulated-hardware', 'sim-cmu', 'sim-deflectometry', 'sim-deflectometry-stage']
>>> find_rig("sim-cmu").name
'sim-cmu.toml'
"""

from __future__ import annotations

import functools
from importlib.resources import files
from pathlib import Path

#: The shipped folders (each beside the package's code: ``scopetwin/<folder>`` in a wheel, the checkout's root
#: otherwise).
FOLDERS = ("rigs", "examples")


@functools.cache
def root() -> Path:
    """The folder holding ``rigs/`` and ``examples/``: the installed package's own folder, else (an editable install
    of the checkout) the checkout's root beside ``scopetwin/``."""
    package = Path(str(files("scopetwin")))
    if (package / "rigs").is_dir():
        return package
    checkout = package.parent
    return checkout if (checkout / "rigs").is_dir() and (checkout / "setup.py").is_file() else package


def shipped(path: str | Path) -> Path | None:
    """The shipped file a relative ``path`` names (``rigs/sim-cmu.toml``), or ``None`` (absolute, ``..``, not
    shipped)."""
    p = Path(path)
    if p.is_absolute() or ".." in p.parts or not p.parts or p.parts[0] not in FOLDERS:
        return None
    candidate = root() / p
    return candidate if candidate.is_file() else None


def find_input(path: str | Path) -> Path:
    """``path`` itself when it exists (or cannot name a shipped file), else the shipped file it names.

    A path that names nothing is given back as it is, so that the reader's own error names it.
    """
    p = Path(path)
    if p.exists():
        return p
    return shipped(p) or p


def rig_names() -> list[str]:
    """The bare names of the shipped rigs (``sim-cmu`` for ``rigs/sim-cmu.toml``), sorted."""
    folder = root() / "rigs"
    return sorted(p.stem for p in folder.glob("*.toml")) if folder.is_dir() else []


def find_rig(path: str | Path) -> Path:
    """The rig file ``path`` names: itself when it exists; else a shipped one, by its relative path
    (``rigs/sim-cmu.toml``) or its bare name (``sim-cmu`` or ``sim-cmu.toml``); else ``path`` as it is."""
    p = Path(path)
    if p.exists():
        return p
    found = shipped(p)
    if found is None and len(p.parts) == 1 and p.name not in ("", ".", ".."):
        name = p.name if p.suffix == ".toml" else f"{p.name}.toml"
        found = shipped(Path("rigs") / name)
    return found or p


def shipped_rig_name(path: str | Path) -> str | None:
    """The bare name of the shipped rig at ``path`` (a resolved file in the shipped ``rigs/``), else ``None``."""
    p = Path(path).resolve()
    folder = (root() / "rigs").resolve()
    return p.stem if p.parent == folder and p.suffix == ".toml" and p.is_file() else None
