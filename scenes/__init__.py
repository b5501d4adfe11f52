"""scenes: the physical world of scopetwin.

Geometry (frames, planes, reflection and refraction), the thesis's camera
model, marker patterns, substrates, setup models and presets, the analytic
reference renderer and sensor physics. Pure numpy; Mitsuba lives in
:mod:`scopetwin.scenes.mitsuba` and is only loaded when asked for.
"""

from scopetwin.scenes.errors import FileFormatError, GeometryError, ScopetwinError, SetupError
from scopetwin.scenes.geometry import Frame

__all__ = ["FileFormatError", "Frame", "GeometryError", "ScopetwinError", "SetupError"]
