"""Radial gradient-index profiles n(r, lambda) and their derivatives (thesis §7.5.1).

A *monochromatic* profile (:class:`RadialProfile`) gives the index ``n`` and its
derivative ``dn/d(r^2)`` as functions of ``r2 = x^2 + y^2`` (mm^2). Working in r^2
keeps every profile regular on the axis (no division by r) and gives the
Sharma-Kumar-Ghatak right-hand side directly: ½∇(n²) = 2 n (dn/dr²) (x, y).

Every profile is written once against a tiny array namespace ``xp`` (``sqrt``,
``tanh``, ``cosh``, ``where``, ``maximum``), so the same formula runs on numpy float64
arrays (the reference integrator, :mod:`scopetwin.scenes.grin.rkn`) and on Dr.Jit arrays (the
Mitsuba tracer, :mod:`scopetwin.scenes.mitsuba.grin`).

Profiles
--------
* :class:`PolynomialProfile` -- the GrinTech Taylor form n = n0 + nr2 r² + nr4 r⁴ (+ nr6 r⁶)
  of thesis §7.5.1 (defaults n0 = 1.62893, nr2 = -0.077 mm⁻², nr4 = 0.00315 mm⁻⁴).
* :class:`SechProfile` -- n = n0 sech(g r), the ideal profile the Taylor form approximates
  (§7.5.1); its meridional rays are exactly periodic with period 2π/g.
* :class:`ParabolicN2Profile` -- n² = n0² (1 - g² r²), whose rays (skew ones included) are
  exact sinusoids in the Sharma parameter t.
* :class:`FunctionProfile` -- any profile given as a function with its derivative.

Dispersion (:class:`GradientDispersion`) follows the GRIN literature's convention of
giving every profile coefficient its own Abbe number (a GRADIENT-5 style model where
each coefficient c_k(λ) is a Cauchy-type function of 1/λ²).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any

import numpy as np

from scopetwin.scenes.errors import SetupError

#: numpy namespace for profile formulas (float64 arrays).
NP = SimpleNamespace(
    sqrt=np.sqrt,
    tanh=np.tanh,
    cosh=np.cosh,
    where=np.where,
    maximum=np.maximum,
    floor=np.floor,
    abs=np.abs,
    minimum=np.minimum,
)

#: Fraunhofer F and C lines and the helium d line (nm), for Abbe numbers.
LAMBDA_F_NM = 486.13
LAMBDA_C_NM = 656.27
LAMBDA_D_NM = 587.56


def cauchy_slope(abbe: float, contrast: float) -> float:
    """Slope B of c(λ) = c_ref + B (1/λ² - 1/λ_ref²) (λ in µm) with Abbe number ``abbe``.

    ``contrast`` is the quantity whose F-C difference is ``contrast/abbe``: ``n_d - 1`` for a
    homogeneous glass or the base index, the coefficient itself for a gradient term
    (the GRIN convention ν_k = c_k,d / (c_k,F - c_k,C)).
    """
    span = 1.0 / (LAMBDA_F_NM / 1000.0) ** 2 - 1.0 / (LAMBDA_C_NM / 1000.0) ** 2
    return contrast / abbe / span


class RadialProfile(ABC):
    """A monochromatic radial index profile n(r²) with its derivative dn/d(r²)."""

    @abstractmethod
    def index(self, r2: Any, xp: Any = NP) -> Any:
        """Refractive index at r² (mm²)."""

    @abstractmethod
    def dn_dr2(self, r2: Any, xp: Any = NP) -> Any:
        """Derivative dn/d(r²) (mm⁻²) at r²."""

    @property
    @abstractmethod
    def n0(self) -> float:
        """Index on the axis."""

    @property
    def g(self) -> float:
        """Paraxial gradient constant g (mm⁻¹): n ≈ n0 (1 - g² r² / 2) near the axis."""
        slope = float(self.dn_dr2(np.zeros(1))[0])
        if slope >= 0:
            raise SetupError(f"profile has no focusing gradient on the axis (dn/dr² = {slope:g} >= 0)")
        return float(np.sqrt(-2.0 * slope / self.n0))

    def sharma(self, r2: Any, xp: Any = NP) -> tuple[Any, Any]:
        """(n², k) with ½∇(n²) = k (x, y): the Sharma-Kumar-Ghatak right-hand side (one evaluation)."""
        n = self.index(r2, xp)
        return n * n, 2.0 * n * self.dn_dr2(r2, xp)

    def check(self, radius: float, samples: int = 2001) -> None:
        """Reject a profile that is not a physical index inside the rod of ``radius`` (mm).

        Raises
        ------
        SetupError
            If n is not finite or n < 1 anywhere in 0 <= r <= radius (the message gives r and n).
        """
        r = np.linspace(0.0, radius, samples)
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            n = np.asarray(self.index(r * r), dtype=np.float64) * np.ones_like(r)
            dn = np.asarray(self.dn_dr2(r * r), dtype=np.float64) * np.ones_like(r)
        bad = ~np.isfinite(n) | ~np.isfinite(dn)
        if bad.any():
            raise SetupError(f"profile is not finite at r = {r[bad][0]:.4g} mm inside the rod (radius {radius} mm)")
        low = n < 1.0
        if low.any():
            i = int(np.argmax(low))
            raise SetupError(
                f"profile gives n = {n[i]:.5f} < 1 at r = {r[i]:.4g} mm inside the rod (radius {radius} mm)"
            )


@dataclass(frozen=True)
class PolynomialProfile(RadialProfile):
    """n = n0 + nr2 r² + nr4 r⁴ + nr6 r⁶ (thesis §7.5.1, GrinTech's Taylor form; mm units)."""

    n0_: float = 1.62893
    nr2: float = -0.077
    nr4: float = 0.00315
    nr6: float = 0.0

    @property
    def n0(self) -> float:
        return self.n0_

    def index(self, r2: Any, xp: Any = NP) -> Any:
        return self.n0_ + r2 * (self.nr2 + r2 * (self.nr4 + r2 * self.nr6))

    def dn_dr2(self, r2: Any, xp: Any = NP) -> Any:
        return self.nr2 + r2 * (2.0 * self.nr4 + 3.0 * self.nr6 * r2)


@dataclass(frozen=True)
class SechProfile(RadialProfile):
    """n = n0 sech(g r): meridional rays are periodic with period exactly 2π/g (thesis §7.5.1)."""

    n0_: float
    g_: float

    @property
    def n0(self) -> float:
        return self.n0_

    @property
    def g(self) -> float:
        return self.g_

    def index(self, r2: Any, xp: Any = NP) -> Any:
        return self.n0_ / xp.cosh(self.g_ * xp.sqrt(r2))

    def dn_dr2(self, r2: Any, xp: Any = NP) -> Any:
        # dn/dr = -n0 g sech(x) tanh(x), x = g r; dn/dr² = dn/dr / (2 r) = -(n0 g²/2) sech(x) tanh(x)/x.
        x = self.g_ * xp.sqrt(r2)
        xs = xp.maximum(x, 1e-6)
        tanh_over_x = xp.where(x > 1e-4, xp.tanh(xs) / xs, 1.0 - x * x / 3.0)
        return -0.5 * self.n0_ * self.g_ * self.g_ * tanh_over_x / xp.cosh(x)


@dataclass(frozen=True)
class ParabolicN2Profile(RadialProfile):
    """n² = n0² (1 - g² r²): x(t) = x0 cos(n0 g t) + T_x0/(n0 g) sin(n0 g t) exactly, skew rays included."""

    n0_: float
    g_: float

    @property
    def n0(self) -> float:
        return self.n0_

    @property
    def g(self) -> float:
        return self.g_

    def index(self, r2: Any, xp: Any = NP) -> Any:
        return self.n0_ * xp.sqrt(1.0 - self.g_ * self.g_ * r2)

    def dn_dr2(self, r2: Any, xp: Any = NP) -> Any:
        return -0.5 * self.n0_ * self.g_ * self.g_ / xp.sqrt(1.0 - self.g_ * self.g_ * r2)

    def sharma(self, r2: Any, xp: Any = NP) -> tuple[Any, Any]:
        k = -self.n0_ * self.n0_ * self.g_ * self.g_
        return self.n0_ * self.n0_ * (1.0 - self.g_ * self.g_ * r2), k + 0.0 * r2


@dataclass(frozen=True)
class FunctionProfile(RadialProfile):
    """Any radial profile given as two functions of (r², xp): the index and dn/d(r²).

    The functions must use only arithmetic and ``xp.sqrt/tanh/cosh/where/maximum`` so that
    they run on numpy and on Dr.Jit arrays alike.
    """

    index_fn: Callable[[Any, Any], Any]
    dn_dr2_fn: Callable[[Any, Any], Any]

    @property
    def n0(self) -> float:
        return float(np.asarray(self.index_fn(np.zeros(1), NP)).ravel()[0])

    def index(self, r2: Any, xp: Any = NP) -> Any:
        return self.index_fn(r2, xp)

    def dn_dr2(self, r2: Any, xp: Any = NP) -> Any:
        return self.dn_dr2_fn(r2, xp)


@dataclass(frozen=True)
class GradientDispersion:
    """Dispersion of a polynomial GRIN profile: each coefficient with its own Abbe number.

    c_k(λ) = c_k(λ_ref) + B_k (1/λ² - 1/λ_ref²), λ in µm, with B_0 from ν_0 and (n0 - 1) and
    B_k (k >= 1) from ν_r and c_k itself (the GRIN convention ν = c_d / (c_F - c_C)).

    Parameters
    ----------
    wavelength_ref_nm : float
        Wavelength at which the catalogue coefficients hold.
    abbe_n0 : float
        Abbe number of the base (axial) index.
    abbe_gradient : float
        Abbe number of the gradient coefficients nr2, nr4, nr6 (positive: the index
        contrast grows towards the blue).
    """

    wavelength_ref_nm: float
    abbe_n0: float
    abbe_gradient: float

    def apply(self, profile: PolynomialProfile, wavelength_nm: float) -> PolynomialProfile:
        """The profile's coefficients at ``wavelength_nm``."""
        dx = 1.0 / (wavelength_nm / 1000.0) ** 2 - 1.0 / (self.wavelength_ref_nm / 1000.0) ** 2
        n0 = profile.n0_ + cauchy_slope(self.abbe_n0, profile.n0_ - 1.0) * dx
        scale = 1.0 + cauchy_slope(self.abbe_gradient, 1.0) * dx
        return PolynomialProfile(n0, profile.nr2 * scale, profile.nr4 * scale, profile.nr6 * scale)
