"""Camera sensor physics after the EMVA 1288 linear model.

Rendered images are irradiance in "radiance units" (a white pattern texel seen
directly is 1). A capture turns them into digital numbers:

    mu_p   = irradiance * photons_per_unit_s * exposure_s        (mean photons per pixel)
    n_e    ~ Poisson(QE * mu_p)                                  (shot noise)
    n_e    = min(n_e, full_well_e)                               (saturation of the well)
    y_dn   = black_level_dn + K * (n_e + N(0, sigma_d^2))        (dark noise, system gain K)
    y_dn   = clip(round(y_dn), 0, 2^bits - 1)                    (quantisation, ADC range)

(EMVA Standard 1288, Release 4.0, the linear camera model.) Every capture takes
an explicit seed or generator: the same seed gives the same bytes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scopetwin.scenes.errors import GeometryError


@dataclass(frozen=True)
class EmvaSensor:
    """Linear EMVA 1288 sensor.

    Parameters
    ----------
    quantum_efficiency : float
        eta, electrons per photon (0..1].
    full_well_e : float
        Saturation capacity of a pixel, electrons.
    dark_noise_e : float
        sigma_d, temporal dark noise, electrons RMS.
    gain_dn_per_e : float
        System gain K, digital numbers per electron.
    black_level_dn : float
        Offset of the dark signal, DN.
    bit_depth : int
        ADC resolution (12 for the thesis's cameras, §1.11 and §4.1.4).

    The defaults describe a 12-bit CCD of the thesis's class (Sony ICX205/ICX285 type:
    full well ~ 18 ke-, dark noise ~ 10 e-); K is chosen so the full well just fills the ADC.
    """

    quantum_efficiency: float = 0.55
    full_well_e: float = 18000.0
    dark_noise_e: float = 10.0
    gain_dn_per_e: float = 4000.0 / 18000.0
    black_level_dn: float = 32.0
    bit_depth: int = 12

    def __post_init__(self) -> None:
        if not 0 < self.quantum_efficiency <= 1:
            raise GeometryError(f"quantum_efficiency must be in (0, 1], got {self.quantum_efficiency}")
        for name in ("full_well_e", "gain_dn_per_e"):
            if not getattr(self, name) > 0:
                raise GeometryError(f"sensor {name} must be > 0, got {getattr(self, name)}")
        if self.dark_noise_e < 0 or self.black_level_dn < 0:
            raise GeometryError("sensor dark_noise_e and black_level_dn must be >= 0")
        if int(self.bit_depth) != self.bit_depth or not 1 <= self.bit_depth <= 32:
            raise GeometryError(f"sensor bit_depth must be an integer in 1..32, got {self.bit_depth}")

    @property
    def max_dn(self) -> int:
        """Largest digital number, 2^bits - 1."""
        return 2 ** int(self.bit_depth) - 1

    def mean_dn(self, irradiance: ArrayLike, photons_per_unit_s: float, exposure_s: float) -> NDArray[np.float64]:
        """Expected DN (noise-free, unsaturated, unquantised) for an irradiance image."""
        mu_e = self.quantum_efficiency * np.asarray(irradiance, dtype=np.float64) * photons_per_unit_s * exposure_s
        return self.black_level_dn + self.gain_dn_per_e * mu_e

    def exposure_for(self, peak_irradiance: float, photons_per_unit_s: float, fraction: float = 0.7) -> float:
        """Exposure time (s) that fills ``fraction`` of the full well at ``peak_irradiance``."""
        if not peak_irradiance > 0 or not photons_per_unit_s > 0:
            raise GeometryError("peak irradiance and photons_per_unit_s must be > 0 to choose an exposure")
        return fraction * self.full_well_e / (self.quantum_efficiency * peak_irradiance * photons_per_unit_s)

    def capture(
        self,
        irradiance: ArrayLike,
        photons_per_unit_s: float,
        exposure_s: float,
        rng: np.random.Generator | int | None = 0,
    ) -> NDArray[np.float32]:
        """Digital numbers (float32 array) of one exposure, with shot noise, dark noise, saturation, ADC.

        Parameters
        ----------
        irradiance : array_like
            Rendered image, radiance units, >= 0.
        photons_per_unit_s : float
            Photons per pixel per second at irradiance 1.
        exposure_s : float
            Exposure time, s.
        rng : numpy Generator or int seed
            Source of the noise (an int is used as a seed).
        """
        e = np.asarray(irradiance, dtype=np.float64)
        if np.any(~np.isfinite(e)) or np.any(e < 0):
            raise GeometryError("irradiance image must be finite and >= 0")
        if not exposure_s >= 0 or not photons_per_unit_s >= 0:
            raise GeometryError("exposure_s and photons_per_unit_s must be >= 0")
        gen = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
        electrons = gen.poisson(self.quantum_efficiency * e * photons_per_unit_s * exposure_s).astype(np.float64)
        electrons = np.minimum(electrons, self.full_well_e)
        electrons += gen.normal(0.0, self.dark_noise_e, size=e.shape)
        dn = np.rint(self.black_level_dn + self.gain_dn_per_e * electrons)
        return np.clip(dn, 0, self.max_dn).astype(np.float32)
