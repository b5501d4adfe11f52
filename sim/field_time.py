"""Time per field and per slide: the four-channel unit against a sequential microscope (the thesis, §3.4, ch. 6).

The thesis's claim (§3.4.1, ch. 6): with four channels at once and no filter wheel, "the rate of analysis ... only
depends on the exposure time and the time needed to move to different positions", and the focus map of Part I
removes the focus search, "the most time-consuming factor in microscopy" (§1.1). This module puts numbers on it,
stop-and-go over a raster of fields, each term with its source (:data:`TERM_SOURCES`):

* **the unit (CMU)**: per field, the XY move to the next field (trapezoidal velocity profile, then the settle) while
  the piezo goes to the focus map's height and the previous frames read out; then one exposure, the longest channel's
  (all four cameras at once).
* **a sequential microscope**: the same stages, camera and channels, one camera behind a filter wheel: the move,
  an autofocus search (frames over the piezo range, each a settle, an exposure of the brightest channel and a
  readout), then the four channels one after the other, each exposure followed by a filter change (the previous
  frame reads out meanwhile); the wheel's last change, back to the first filter, overlaps the next move.

A slide is a serpentine raster of ``columns x rows`` fields of the camera's field of view (0.8978 x 0.6708 mm,
the thesis, §5.1.2): per field, (columns - 1) / columns of a move along x by one field width and 1 / columns of a
move along y by one field height. Times in s, lengths in mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from scopetwin.scenes.errors import ScopetwinError


class FieldTimeError(ScopetwinError, ValueError):
    """A timing parameter that makes no sense (non-positive velocity, acceleration, field or count)."""


@dataclass(frozen=True)
class Axis:
    """A motorised stage axis: trapezoidal velocity profile, then a settle time.

    Attributes
    ----------
    name : str
        The stage.
    velocity_mm_s : float
        Top speed, mm/s.
    acceleration_mm_s2 : float
        Acceleration and deceleration, mm/s^2.
    settle_s : float
        Time to settle within the positioning tolerance after the profile ends, s.
    """

    name: str
    velocity_mm_s: float
    acceleration_mm_s2: float
    settle_s: float

    def __post_init__(self) -> None:
        if not (self.velocity_mm_s > 0 and self.acceleration_mm_s2 > 0 and self.settle_s >= 0):
            raise FieldTimeError(f"axis {self.name}: velocity and acceleration must be > 0, settle >= 0")

    def move_s(self, distance_mm: float) -> float:
        """Time of a move of ``distance_mm`` including the settle, s."""
        return move_time_s(distance_mm, self.velocity_mm_s, self.acceleration_mm_s2) + self.settle_s


def move_time_s(distance_mm: float, velocity_mm_s: float, acceleration_mm_s2: float) -> float:
    """Duration of a point-to-point move with a trapezoidal velocity profile, s.

    A short move never reaches the top speed v (triangular profile): t = 2 sqrt(d / a) for d <= v^2 / a; else
    t = d / v + v / a.
    """
    d = abs(distance_mm)
    if d == 0:
        return 0.0
    if d <= velocity_mm_s**2 / acceleration_mm_s2:
        return 2.0 * math.sqrt(d / acceleration_mm_s2)
    return d / velocity_mm_s + velocity_mm_s / acceleration_mm_s2


#: Where each number of :class:`TimingModel` comes from.
TERM_SOURCES: dict[str, str] = {
    "field": "the thesis, §5.1.2: 1392 x 1040 px of 0.645 µm = 0.8978 x 0.6708 mm",
    "x": "the thesis, §4.2.2: PI M-404.6PD, 50 mm/s (rigs/sim-cmu.toml); acceleration and settle: our assumption",
    "y": "the thesis, §4.2.2: PI M-414.3PD, 100 mm/s (rigs/sim-cmu.toml); acceleration and settle: our assumption",
    "piezo": "the thesis, §4.2.3: MIPOS500, 0-400 µm; its settle after a small step: our assumption",
    "readout": "the thesis, §4.1.4: Basler scA1400-30gm, 30 frames/s at full frame (its model name): 1/30 s",
    "filter": "our assumption: a fast motorised filter wheel, adjacent positions (not in the thesis)",
    "autofocus": "the thesis, §1.1: the bending is 50-100 depths of field and a focus search 'can last seconds'; "
    "our search: 20 frames (coarse-to-fine over 50 depths of field), each at the brightest channel's exposure",
    "exposure": "the thesis, §5.2.3 (80 / 4000 / 9800 / 6000 ms) or the photon budget (scenes/cmu/photon_budget.py)",
}


@dataclass(frozen=True)
class TimingModel:
    """The stages, focus drive, camera and slide of the timing comparison (sources: :data:`TERM_SOURCES`)."""

    field_mm: tuple[float, float] = (0.8978, 0.6708)
    x: Axis = field(default_factory=lambda: Axis("PI M-404.6PD", 50.0, 200.0, 0.1))
    y: Axis = field(default_factory=lambda: Axis("PI M-414.3PD", 100.0, 200.0, 0.1))
    piezo_settle_s: float = 0.02
    readout_s: float = 1.0 / 30.0
    filter_change_s: float = 0.05
    autofocus_frames: int = 20
    columns: int = 80
    rows: int = 25

    def __post_init__(self) -> None:
        if not (min(self.field_mm) > 0 and self.columns >= 1 and self.rows >= 1 and self.autofocus_frames >= 0):
            raise FieldTimeError("field sizes must be > 0, columns and rows >= 1, autofocus frames >= 0")
        if min(self.piezo_settle_s, self.readout_s, self.filter_change_s) < 0:
            raise FieldTimeError("settle, readout and filter-change times must be >= 0")

    @property
    def fields(self) -> int:
        """Fields per slide."""
        return self.columns * self.rows

    def move_s(self) -> float:
        """Mean XY move (with settle) per field of the serpentine raster, s."""
        tx = self.x.move_s(self.field_mm[0])
        ty = self.y.move_s(self.field_mm[1])
        return ((self.columns - 1) * tx + ty) / self.columns


def _check_exposures(exposures_ms: dict[str, float]) -> None:
    if not exposures_ms or any(not (t > 0 and math.isfinite(t)) for t in exposures_ms.values()):
        raise FieldTimeError(f"exposures must be finite and > 0 ms, got {exposures_ms}")


def cmu_field_s(model: TimingModel, exposures_ms: dict[str, float]) -> dict[str, float]:
    """Time of one field with the four-channel unit, by term, s (``total`` their sum).

    The piezo's step to the focus map's height and the previous frames' readout run during the move; only what
    outlasts the move adds to it.
    """
    _check_exposures(exposures_ms)
    move = model.move_s()
    terms = {
        "move": move,
        "focus": max(0.0, model.piezo_settle_s - move),
        "exposure": max(exposures_ms.values()) * 1e-3,
        "filters_readout": max(0.0, model.readout_s - move),
    }
    return terms | {"total": sum(terms.values())}


def sequential_field_s(
    model: TimingModel,
    exposures_ms: dict[str, float],
    autofocus_exposure_ms: float | None = None,
    focus_map: bool = False,
) -> dict[str, float]:
    """Time of one field with a sequential microscope (filter wheel, autofocus search), by term, s.

    ``autofocus_exposure_ms`` defaults to the shortest channel exposure (the brightest channel focuses fastest).
    With ``focus_map`` the microscope has Part I's focus map instead of the search: the piezo goes to the map's height
    during the move, as in the unit.
    """
    _check_exposures(exposures_ms)
    t_af = (autofocus_exposure_ms if autofocus_exposure_ms is not None else min(exposures_ms.values())) * 1e-3
    move = model.move_s()
    search = model.autofocus_frames * (model.piezo_settle_s + t_af + model.readout_s)
    terms = {
        "move": move,
        "focus": max(0.0, model.piezo_settle_s - move) if focus_map else search,
        "exposure": sum(exposures_ms.values()) * 1e-3,
        "filters_readout": (len(exposures_ms) - 1) * max(model.filter_change_s, model.readout_s),
    }
    return terms | {"total": sum(terms.values())}


def slide_h(model: TimingModel, per_field: dict[str, float]) -> float:
    """Hours for the whole slide at ``per_field["total"]`` seconds a field."""
    return model.fields * per_field["total"] / 3600.0


def comparison(
    model: TimingModel, scenarios: dict[str, dict[str, float]]
) -> dict[str, dict[str, dict[str, float] | float]]:
    """For each scenario (a name and its four exposures, ms): the field time by term of the unit (``cmu_s``), of a
    sequential microscope with Part I's focus map (``sequential_map_s``) and with a focus search (``sequential_s``),
    their slide times (h, ``*_slide_h``) and the speed-ups of the unit over the two (``speedup_map``,
    ``speedup``)."""
    out: dict[str, dict[str, dict[str, float] | float]] = {}
    for name, exposures in scenarios.items():
        runs = {
            "cmu": cmu_field_s(model, exposures),
            "sequential_map": sequential_field_s(model, exposures, focus_map=True),
            "sequential": sequential_field_s(model, exposures),
        }
        row: dict[str, dict[str, float] | float] = {}
        for key, terms in runs.items():
            row[f"{key}_s"] = terms
            row[f"{key}_slide_h"] = slide_h(model, terms)
        row["speedup_map"] = runs["sequential_map"]["total"] / runs["cmu"]["total"]
        row["speedup"] = runs["sequential"]["total"] / runs["cmu"]["total"]
        out[name] = row
    return out
