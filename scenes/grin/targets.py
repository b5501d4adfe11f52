"""The chrome-mask test targets of the demonstrator (thesis §8.5, Fig. 8.12-8.16).

Each pattern fills a disk of 400 µm diameter (the field of view) centred on an objective's
optical axis; the four objectives of the demonstrator each see one copy (§8.5). Chrome
(transmission 0) forms the features and everything outside the pattern disk; the glass between
the features is clear (transmission 1). The thesis does not say which polarity its masks have;
this choice only inverts the images.

* ``dots-25``  -- dots of 10 µm diameter on a 25 µm square grid (Fig. 8.12)
* ``grid-25``  -- grid of 2 µm lines, 25 µm period (Fig. 8.13)
* ``grid-12.5`` -- grid of 2 µm lines, 12.5 µm period (Fig. 8.14)
* ``lines-8``  -- lines of 4 µm width, 8 µm period (125 line pairs/mm, Fig. 8.15)

Transmission functions are written against an array namespace ``xp`` so that they evaluate on
numpy arrays and, inside the renderer, on Dr.Jit arrays.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.grin.profiles import NP

Pattern = Literal["dots", "grid", "lines"]


class TargetError(ScopetwinError, ValueError):
    """A target that is unknown or does not fit in the field of view."""


@dataclass(frozen=True)
class Target:
    """A periodic chrome pattern in a disk (all lengths mm, in the object plane relative to the objective axis)."""

    name: str
    pattern: Pattern
    period: float
    feature: float
    diameter: float = 0.4
    offset: tuple[float, float] = (0.0, 0.0)

    def check_field(self, field_radius: float) -> None:
        """Raise :class:`TargetError` when the pattern disk reaches outside the field of view."""
        reach = (self.offset[0] ** 2 + self.offset[1] ** 2) ** 0.5 + 0.5 * self.diameter
        if reach > field_radius * (1 + 1e-9):
            raise TargetError(
                f"target {self.name!r} reaches {reach * 1e3:.1f} µm from the axis, outside the field "
                f"of view (radius {field_radius * 1e3:.1f} µm)"
            )

    def transmission(self, x: Any, y: Any, xp: Any = NP) -> Any:
        """1 on clear glass, 0 on chrome, at object-plane points (x, y) relative to the objective axis."""
        u = x - self.offset[0]
        v = y - self.offset[1]
        inside = u * u + v * v <= (0.5 * self.diameter) ** 2
        p = self.period
        fu = u - p * xp.floor(u / p + 0.5)
        fv = v - p * xp.floor(v / p + 0.5)
        half = 0.5 * self.feature
        if self.pattern == "dots":
            chrome = fu * fu + fv * fv <= half * half
        elif self.pattern == "grid":
            chrome = (xp.abs(fu) <= half) | (xp.abs(fv) <= half)
        else:
            chrome = xp.abs(fu) <= half
        return xp.where(inside & ~chrome, 1.0, 0.0)


TARGETS: dict[str, Target] = {
    "dots-25": Target("dots-25", "dots", 0.025, 0.010),
    "grid-25": Target("grid-25", "grid", 0.025, 0.002),
    "grid-12.5": Target("grid-12.5", "grid", 0.0125, 0.002),
    "lines-8": Target("lines-8", "lines", 0.008, 0.004),
}


def target(name: str, offset: tuple[float, float] = (0.0, 0.0), diameter: float | None = None) -> Target:
    """A §8.5 target by name, optionally shifted/resized (then check it with :meth:`Target.check_field`)."""
    if name not in TARGETS:
        raise TargetError(f"unknown target {name!r} (known: {', '.join(TARGETS)})")
    t = TARGETS[name]
    return Target(t.name, t.pattern, t.period, t.feature, t.diameter if diameter is None else diameter, offset)
