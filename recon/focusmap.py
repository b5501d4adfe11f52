"""Focus maps: from the reconstructed substrate heights to piezo focus positions per stage position.

This is why Part I exists (thesis §1.1): the bent cover glass deforms by 50-100 times the
depth of field, so without a map the microscope must search the focus at every position.
With the height map h(x, y) of the substrate (thesis §1.4), every field of view of the
microscope gets its focus position in advance: focus = reference + sign * (h(x, y) - h_ref).

Depth of field and field of view come from the one model of the objective,
:class:`scopetwin.scenes.objective.Objective` (10x, NA 0.45, air; DOF = lambda n / NA^2 + n e / (M NA)).
Defaults: that objective, green emission (520 nm), the MIPOS500 piezo drive's 0-400 µm range.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.geometry import Array
from scopetwin.scenes.objective import Objective

__all__ = ["FocusMap", "FocusMapError", "Objective", "focus_map"]


class FocusMapError(ScopetwinError, ValueError):
    """A focus map that cannot be made (empty ROI, focus outside the drive's range)."""


@dataclass(frozen=True)
class FocusMap:
    """Focus position for every stage position of a raster over the ROI.

    Attributes
    ----------
    x_mm, y_mm : ndarray
        Field centres in substrate coordinates, mm (stage position = centre + ``stage_offset``).
    focus_um : ndarray
        Piezo position for each field, µm.
    spread_um : ndarray
        Height range (max - min) inside each field, µm: one focus plane serves the field when it
        is below the depth of field.
    depth_of_field_um : float
        The objective's depth of field, µm.
    std_um : ndarray or None
        Standard uncertainty of the height in each field (the largest over its samples), µm, when the height map
        came with one (:class:`scopetwin.recon.reconstruct.Uncertainty`).
    """

    x_mm: Array
    y_mm: Array
    stage_x_mm: Array
    stage_y_mm: Array
    focus_um: Array
    spread_um: Array
    depth_of_field_um: float
    std_um: Array | None = None

    @property
    def in_focus(self) -> NDArray[np.bool_]:
        """True where the whole field lies within the depth of field around its focus."""
        return self.spread_um <= self.depth_of_field_um

    @property
    def interval_in_dof(self) -> NDArray[np.bool_]:
        """True where the field's 95 % interval stays in the depth of field: spread/2 + 1.96 u <= DOF/2.

        The focus is set on the field's centre height; the true heights of the field lie, with 95 % probability,
        within half its spread plus 1.96 standard uncertainties of it. Without an uncertainty: :attr:`in_focus`.
        """
        if self.std_um is None:
            return self.in_focus
        return 0.5 * self.spread_um + 1.96 * self.std_um <= 0.5 * self.depth_of_field_um

    def to_csv(self) -> str:
        """The table a rig executes: index, stage x/y (mm), focus (µm), spread (µm), whole field in focus."""
        buf = io.StringIO()
        w = csv.writer(buf, lineterminator="\n")
        head = ["index", "stage_x_mm", "stage_y_mm", "focus_um", "spread_um", "field_in_focus"]
        w.writerow(head + (["std_um", "interval_in_dof"] if self.std_um is not None else []))
        for k in range(len(self.x_mm)):
            row = [
                k,
                f"{self.stage_x_mm[k]:.4f}",
                f"{self.stage_y_mm[k]:.4f}",
                f"{self.focus_um[k]:.3f}",
                f"{self.spread_um[k]:.3f}",
                int(self.in_focus[k]),
            ]
            if self.std_um is not None:
                row += [f"{self.std_um[k]:.4f}", int(self.interval_in_dof[k])]
            w.writerow(row)
        return buf.getvalue()

    def summary(self) -> dict:
        return {
            "fields": int(len(self.x_mm)),
            "depth_of_field_um": self.depth_of_field_um,
            "focus_range_um": float(np.ptp(self.focus_um)) if len(self.focus_um) else 0.0,
            "fields_in_focus": int(self.in_focus.sum()),
            "height_range_over_dof": float(np.ptp(self.focus_um) / self.depth_of_field_um),
            **(
                {
                    "std_max_um": float(self.std_um.max()) if len(self.std_um) else 0.0,
                    "fields_interval_leaves_dof": int((~self.interval_in_dof).sum()),
                }
                if self.std_um is not None
                else {}
            ),
        }


def _serpentine_raster(
    x_range: tuple[float, float], y_range: tuple[float, float], fov: tuple[float, float], step: tuple[float, float]
) -> tuple[Array, Array]:
    """Centres (x, y) of the fields of a serpentine raster, centred in the ROI; every other row runs backwards."""
    sx, sy = step
    (x0, x1), (y0, y1) = x_range, y_range
    nx = int(np.floor((x1 - x0 - fov[0]) / sx + 1e-9)) + 1
    ny = int(np.floor((y1 - y0 - fov[1]) / sy + 1e-9)) + 1
    if nx < 1 or ny < 1:
        raise FocusMapError(f"the region {x_range} x {y_range} mm holds no {fov[0]:.3f} x {fov[1]:.3f} mm field")
    xc = 0.5 * (x0 + x1) + (np.arange(nx) - 0.5 * (nx - 1)) * sx
    yc = 0.5 * (y0 + y1) + (np.arange(ny) - 0.5 * (ny - 1)) * sy
    xx, yy = np.meshgrid(xc, yc)
    xx[1::2] = xx[1::2, ::-1]  # serpentine: every other row runs backwards
    return xx.ravel(), yy.ravel()


def _check_travel(focus: Array, piezo_range_um: tuple[float, float]) -> None:
    """Raise :class:`FocusMapError` when a focus position lies outside the drive's travel."""
    lo, hi = piezo_range_um
    bad = (focus < lo) | (focus > hi)
    if bad.any():
        raise FocusMapError(
            f"{int(bad.sum())} focus positions fall outside the drive's {lo}-{hi} µm travel "
            f"(range {focus.min():.1f}-{focus.max():.1f} µm); change the reference position"
        )


def focus_map(
    height,
    x_range: tuple[float, float],
    y_range: tuple[float, float],
    objective: Objective | None = None,
    step_mm: tuple[float, float] | None = None,
    reference_um: float = 200.0,
    sign: float = 1.0,
    stage_offset_mm: tuple[float, float] = (0.0, 0.0),
    piezo_range_um: tuple[float, float] = (0.0, 400.0),
    samples: int = 5,
    height_std: Callable[[Array, Array], Array] | None = None,
) -> FocusMap:
    """Focus positions over a serpentine raster of fields covering the ROI.

    Parameters
    ----------
    height : callable
        h(x, y) in mm (e.g. ``SBFSurface.height`` or ``HeightMap.height``).
    x_range, y_range : (float, float)
        The region of interest, mm (fields lie fully inside it).
    objective : Objective, optional
        Depth of field and field of view.
    step_mm : (float, float), optional
        Raster step; default the field of view (abutting fields).
    reference_um : float
        Piezo position focused on the height 0 (the holding frame plane), µm.
    sign : float
        +1 when a higher surface needs a larger piezo position, -1 otherwise.
    stage_offset_mm : (float, float)
        Stage position of the substrate origin.
    piezo_range_um : (float, float)
        Travel of the focus drive; a focus outside it is an error.
    samples : int
        Height samples per field side for the spread.
    height_std : callable, optional
        u(x, y), the height's standard uncertainty in mm (e.g. ``ReconstructionResult.std_heightmap().height``):
        each field carries the largest over its samples, and :attr:`FocusMap.interval_in_dof` flags fields whose
        95 % interval leaves the depth of field.

    Raises
    ------
    FocusMapError
        The ROI holds no field, or a focus position falls outside the drive's travel.
    """
    obj = objective or Objective()
    fov = obj.field_of_view_mm
    sx, sy = step_mm if step_mm is not None else fov
    xf, yf = _serpentine_raster(x_range, y_range, fov, (sx, sy))
    t = np.linspace(-0.5, 0.5, samples)
    ox, oy = np.meshgrid(t * fov[0], t * fov[1])
    hs = np.asarray(height(xf[:, None] + ox.ravel()[None], yf[:, None] + oy.ravel()[None]), dtype=np.float64)
    centre = np.asarray(height(xf, yf), dtype=np.float64)
    focus = reference_um + sign * centre * 1e3
    _check_travel(focus, piezo_range_um)
    std = None
    if height_std is not None:
        std = np.max(np.asarray(height_std(xf[:, None] + ox.ravel()[None], yf[:, None] + oy.ravel()[None])), axis=1)
        std = np.clip(std, 0.0, None) * 1e3
    return FocusMap(
        xf,
        yf,
        xf + stage_offset_mm[0],
        yf + stage_offset_mm[1],
        focus,
        np.ptp(hs, axis=1) * 1e3,
        obj.depth_of_field_um,
        std,
    )
