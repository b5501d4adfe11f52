"""The microscope unit's objective: 10x / NA 0.45 in air, with its camera (thesis §4.1.2, §4.1.4).

The one model of that objective, used by the focus map (:mod:`scopetwin.recon.focusmap`: depth of field, field of view)
and by the widefield renderer (:mod:`scopetwin.scenes.mitsuba.widefield`: the thin-lens aperture that gives the NA, the
geometric blur disc of a defocus). Pure Python (no Mitsuba), so recon may use it.

Depth of field (the usual wave-optical plus detector term):

    DOF = lambda * n / NA^2 + n * e / (M * NA)

with wavelength lambda, immersion index n, numerical aperture NA, lateral magnification M and camera pixel pitch
e. A point ``dz`` away from the plane in focus is blurred, geometrically, into a disc of radius
``|dz| tan(asin NA)``; a thin lens at distance ``d`` above the plane in focus has that NA with the aperture radius
``d tan(asin NA)``. Defaults: §4.1.2 (10x, NA 0.45, air), green emission (520 nm), the Basler scA1400-30gm's
1392 x 1040 pixels of 6.45 µm (§4.1.4).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from scopetwin.scenes.errors import SetupError


@dataclass(frozen=True)
class Objective:
    """Microscope objective and camera (defaults: thesis §4.1.2 / §4.1.4, 10x / NA 0.45, 6.45 µm pixels).

    Parameters
    ----------
    magnification : float
        Lateral magnification M.
    na : float
        Object-side numerical aperture.
    wavelength_nm : float
        Wavelength of the depth of field, nm.
    immersion_index : float
        Index n of the object space (1: air).
    pixel_pitch_um : float
        Camera pixel pitch e, µm.
    sensor_px : (int, int)
        Camera pixels (columns, rows).
    """

    magnification: float = 10.0
    na: float = 0.45
    wavelength_nm: float = 520.0
    immersion_index: float = 1.0
    pixel_pitch_um: float = 6.45
    sensor_px: tuple[int, int] = (1392, 1040)

    def __post_init__(self) -> None:
        if not (
            self.magnification > 0
            and 0 < self.na < self.immersion_index
            and self.wavelength_nm > 0
            and self.pixel_pitch_um > 0
        ):
            raise SetupError("objective needs magnification > 0, 0 < NA < n, wavelength > 0 and pixel pitch > 0")

    @property
    def depth_of_field_um(self) -> float:
        """DOF = lambda n / NA^2 + n e / (M NA), µm."""
        lam_um = self.wavelength_nm * 1e-3
        n = self.immersion_index
        return lam_um * n / self.na**2 + n * self.pixel_pitch_um / (self.magnification * self.na)

    @property
    def object_pixel_mm(self) -> float:
        """A camera pixel in the object plane, e / M, mm."""
        return self.pixel_pitch_um * 1e-3 / self.magnification

    @property
    def field_of_view_mm(self) -> tuple[float, float]:
        """Object-side field (x, y), mm."""
        w, h = self.sensor_px
        scale = self.object_pixel_mm
        return w * scale, h * scale

    @property
    def half_angle_tan(self) -> float:
        """tan(asin(NA)): the slope of the marginal ray in object space (air)."""
        return math.tan(math.asin(self.na))

    def blur_radius_mm(self, defocus_mm: float) -> float:
        """Radius of the geometric blur disc of a point ``defocus_mm`` away from the plane in focus, mm."""
        return abs(defocus_mm) * self.half_angle_tan

    def aperture_radius_mm(self, distance_mm: float) -> float:
        """Radius of a thin-lens aperture ``distance_mm`` above the plane in focus that gives this NA, mm."""
        return distance_mm * self.half_angle_tan
