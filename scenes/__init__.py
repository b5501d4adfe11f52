"""scenes: the physical world of scopetwin.

Geometry (frames, planes, reflection and refraction), the thesis's camera
model, marker patterns, substrates, setup models and presets, the analytic
reference renderer and sensor physics. Pure numpy; Mitsuba lives in
:mod:`scopetwin.scenes.mitsuba` and is only loaded when asked for.
"""

from __future__ import annotations

if __name__ == "scenes":  # the bare folder, from the checkout's root: a second copy of scopetwin.scenes
    raise ImportError(
        "scenes is part of scopetwin: import scopetwin.scenes (install with `make setup` or `pip install -e .`)"
    )

from typing import TYPE_CHECKING, Any

from scopetwin.scenes.errors import FileFormatError, GeometryError, ScopetwinError, SetupError

if TYPE_CHECKING:
    from scopetwin.scenes.geometry import Frame

__all__ = ["FileFormatError", "Frame", "GeometryError", "ScopetwinError", "SetupError"]


def __getattr__(name: str) -> Any:
    """``Frame`` from :mod:`scopetwin.scenes.geometry`, imported on first use: the errors, which every command of the
    command line uses, load without numpy."""
    if name == "Frame":
        from scopetwin.scenes.geometry import Frame

        return Frame
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
