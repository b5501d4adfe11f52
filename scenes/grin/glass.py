"""Homogeneous glasses of the GRIN objective (thesis §8.3: Schott AF32 substrates, B270 beam-splitter substitute).

Each entry carries the catalogue's n_d (587.56 nm) and Abbe number ν_d, and the index at
other wavelengths comes from a two-term Cauchy model through n_d and n_F - n_C = (n_d-1)/ν_d.
Over 450-660 nm a two-term Cauchy fit through n_d and ν_d reproduces a crown glass's
Sellmeier index to a few 1e-4, far below what matters for 0.16-2 mm plates at near-normal
incidence (a 1e-3 index error moves the image by < 1 µm here).

Sources of the numbers (manufacturer data sheets, values as quoted there):

* AF32 -- SCHOTT AF 32 eco thin glass data sheet: n_d = 1.5099, ν_d = 65.7 (substrates of the
  GRIN arrays, thesis §8.3).
* B270 -- SCHOTT B 270 i "Superwite" data sheet: n_d = 1.5230, ν_d = 58.5 (substitute for the
  beam-splitter polymer, thesis §8.3).
* D263 -- SCHOTT D 263 M cover glass data sheet: n_d = 1.5230, ν_d = 55.0 (the 160 µm cover glass
  of §7.5.2; the thesis does not name its glass, D 263 is the usual cover-glass borosilicate).

The values are the catalogue figures as quoted above; check them against the current data sheets before relying
on a result (the sensitivity of every result to them is printed by ``scopetwin optics grin --sensitivity``).
"""

from __future__ import annotations

from dataclasses import dataclass

from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.grin.profiles import LAMBDA_D_NM, cauchy_slope


@dataclass(frozen=True)
class Glass:
    """A homogeneous glass: n(λ) = n_d + B (1/λ² - 1/λ_d²) (λ in µm), B from ν_d."""

    name: str
    n_d: float
    abbe_d: float
    source: str

    def index(self, wavelength_nm: float) -> float:
        """Refractive index at ``wavelength_nm``."""
        if self.abbe_d == 0.0:
            return self.n_d
        dx = 1.0 / (wavelength_nm / 1000.0) ** 2 - 1.0 / (LAMBDA_D_NM / 1000.0) ** 2
        return self.n_d + cauchy_slope(self.abbe_d, self.n_d - 1.0) * dx


AIR = Glass("AIR", 1.0, 0.0, "vacuum index used for air (the design is specified in air at 1.0)")

CATALOGUE: dict[str, Glass] = {
    "AIR": AIR,
    "AF32": Glass("AF32", 1.5099, 65.7, "SCHOTT AF 32 eco data sheet (n_d, nu_d)"),
    "B270": Glass("B270", 1.5230, 58.5, "SCHOTT B 270 i Superwite data sheet (n_d, nu_d)"),
    "D263": Glass("D263", 1.5230, 55.0, "SCHOTT D 263 M data sheet (n_d, nu_d)"),
}


def glass(name: str) -> Glass:
    """Catalogue entry by name (case-insensitive); a clear error for unknown glasses."""
    key = name.upper().replace(" ", "")
    if key not in CATALOGUE:
        raise SetupError(f"unknown glass {name!r} (known: {', '.join(sorted(CATALOGUE))})")
    return CATALOGUE[key]
