"""The one error family of scopetwin's world model.

Every error a user can cause with bad input (a setup file, a preset name, an
image file, a geometry that makes no sense) is a :class:`ScopetwinError`. The
command line turns it into one line on stderr and exit code 2.
"""

from __future__ import annotations


class ScopetwinError(Exception):
    """Bad input or an impossible request; the message names the problem."""


class GeometryError(ScopetwinError, ValueError):
    """A frame, camera or pattern whose geometry is invalid."""


class SetupError(ScopetwinError, ValueError):
    """A setup (TOML, preset, override) that cannot be loaded."""


class FileFormatError(ScopetwinError, ValueError):
    """A file that is unreadable or lacks what the contract requires."""
