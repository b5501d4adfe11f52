"""Photon budget of the four channels: electrons per pixel per ms, and the exposure each channel needs.

Why were the thesis's exposures 80 ms (blue) but 4000 / 9800 / 6000 ms (green, red, NIR) (the thesis, §5.2.3)? This
module follows one fluorophore's photons from the source to the camera's electrons, per channel, from the thesis's own
numbers and published fluorophore data. Pure functions of numpy arrays, no Mitsuba.

The model, channel c with fluorophore f (wavelengths in nm on :data:`~scopetwin.scenes.cmu.spectra.GRID_NM`):

* **Excitation** E_c(lambda), mW/nm at the object plane: :func:`~scopetwin.scenes.cmu.spectra.excitation_at_object`
  (the source's spectrum through its excitation path, scaled to the power of Table 4.1). Table 4.1's "illuminated
  area" (0.9 / 0.9 / 1.1 / 0.9 mm, the thesis, §4.1.1) is read as the diameter of a uniformly lit disc (our reading:
  the table gives one length). The photon irradiance is phi(lambda) = E(lambda) lambda / (h c A).
* **Absorption**: the cross-section sigma(lambda) = ln(10) 1000 cm^3/L eps(lambda) / N_A, with eps = the published
  peak molar extinction coefficient (:data:`FLUOROPHORE_DATA`) times the relative absorption band of
  :mod:`~scopetwin.scenes.cmu.spectra` (Fraser-Suzuki bands, peak 1: a simple peak/width parameterisation of the
  published spectra, not the measured curves). Excitations per molecule and second: k = integral sigma phi d lambda;
  emitted photons k QY, with the quantum yield of the thesis, §3.3.
* **Labelling**: rho molecules per µm^2 of object (the column density under a pixel), the same for the four stains
  unless stated; it is the free parameter (:func:`implied_density` gives the one an exposure implies). A pixel sees
  (6.45 µm / 10)^2 = 0.416 µm^2 of object (the thesis, §4.1.2 and §4.1.4).
* **Collection**: the objective (10x / NA 0.45 in air, :class:`~scopetwin.scenes.objective.Objective`) gathers the
  fraction (1 - cos asin NA) / 2 = 0.0535 of isotropic emission; its own transmission is taken as 1 (not in the thesis).
* **Detection**: electrons per collected photon, eta = integral em(lambda) D_c(lambda) d lambda with the emission
  spectrum (unit area) and :func:`~scopetwin.scenes.cmu.spectra.detection_response` (splitters, mirror, band pass and
  the Sony ICX285AL's spectral quantum efficiency).
* **Camera**: the EMVA 1288 model (:class:`~scopetwin.scenes.emva1288.EmvaSensor`: full well 18 ke-, dark noise
  10 e- rms); its flat quantum efficiency is replaced by the spectral one above. SNR = S / sqrt(S + sigma_d^2) for a
  signal of S electrons (shot noise and dark noise; no background or autofluorescence).
* **Photobleaching** (fluorescent proteins only): the published half-life t_half under illumination that makes each
  molecule emit 1000 photons/s means N_b = 1000 t_half / ln 2 photons per molecule before it bleaches; at an emission
  rate k QY the 1/e bleaching time is tau_b = N_b / (k QY). No bleaching number is used for the two DNA dyes.

Every number from outside the thesis carries its source beside it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scopetwin.scenes.cmu import spectra
from scopetwin.scenes.emva1288 import EmvaSensor
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.objective import Objective

Array = NDArray[np.float64]

#: Planck constant, J s (SI 2019, exact).
PLANCK_J_S = 6.62607015e-34
#: Speed of light in vacuum, m/s (exact).
LIGHT_M_S = 2.99792458e8
#: Avogadro constant, 1/mol (SI 2019, exact).
AVOGADRO_PER_MOL = 6.02214076e23

#: The stains of the thesis's cells (§5.2.3: Hoechst 33258, GFP, mCherry, DRAQ5; GFP as the EGFP of §3.3.2).
STAINS: dict[str, str] = {"blue": "Hoechst 33258", "green": "EGFP", "red": "mCherry", "nir": "DRAQ5"}
#: Exposure of each channel's fluorescence image of those cells, ms (the thesis, §5.2.3). The red one was still
#: underexposed "at the maximum exposure time of the camera".
SEED_EXPOSURE_MS: dict[str, float] = {"blue": 80.0, "green": 4000.0, "red": 9800.0, "nir": 6000.0}
#: Table 4.1's illuminated area at the object plane, read as the diameter of a uniformly lit disc, mm (§4.1.1).
ILLUMINATED_DIAMETER_MM: dict[str, float] = {"blue": 0.9, "green": 0.9, "red": 1.1, "nir": 0.9}
#: The longest exposure the camera takes, ms: the thesis's red image at 9800 ms was taken "at the maximum exposure
#: time of the camera" (§5.2.3).
MAX_EXPOSURE_MS = 9800.0


class BudgetError(ScopetwinError, ValueError):
    """A photon-budget parameter that makes no sense (non-positive density, SNR, power or area)."""


@dataclass(frozen=True)
class FluorophoreData:
    """Published photophysics of a stain beyond the thesis's peaks and quantum yields (§3.3).

    Attributes
    ----------
    extinction_m_cm : float
        Peak molar extinction coefficient, 1/(M cm), at the peak of the relative absorption band of
        :data:`~scopetwin.scenes.cmu.spectra.FLUOROPHORES`.
    half_life_s : float or None
        Photobleaching half-life, s, under widefield illumination that makes each molecule emit 1000 photons/s at
        first (the normalisation of Shaner et al., Nat. Methods 2, 905 (2005)); None where no number is used.
    source : str
        Where the numbers come from.
    """

    extinction_m_cm: float
    half_life_s: float | None
    source: str


#: The stains' published numbers (quantum yields and peaks are the thesis's, §3.3, in spectra.FLUOROPHORES).
FLUOROPHORE_DATA: dict[str, FluorophoreData] = {
    # Molecular Probes Handbook (Thermo Fisher, 11th ed.), Table 8.2: Hoechst 33258 bound to DNA, abs. 352 nm,
    # eps = 40,000 /(M cm). Its photobleaching is not modelled (no published number used).
    "Hoechst 33258": FluorophoreData(40_000.0, None, "Molecular Probes Handbook, Table 8.2 (DNA-bound, 352 nm)"),
    # FPbase, EGFP: eps = 55,900 /(M cm) at 488 nm, QY 0.60; half-life 174 s: Shaner, Steinbach & Tsien,
    # Nat. Methods 2, 905 (2005), Table 1 (widefield, 1000 photons/s per molecule at first).
    "EGFP": FluorophoreData(55_900.0, 174.0, "FPbase EGFP; Shaner et al. 2005, Table 1 (photostability)"),
    # FPbase, mCherry (www.fpbase.org/protein/mcherry/): eps = 72,000 /(M cm) at 587 nm, QY 0.22, t1/2 = 68 s
    # (Shu et al. 2006, as FPbase lists it).
    "mCherry": FluorophoreData(72_000.0, 68.0, "FPbase mCherry (EC, QY, t1/2 68 s after Shu et al. 2006)"),
    # Smith et al., Cytometry 40, 280 (2000) and the Biostatus DRAQ5 data sheet: eps = 20,961 /(M cm) at 646 nm
    # (free dye in aqueous buffer; our use for the DNA-bound dye). Photostable; no bleaching number used.
    "DRAQ5": FluorophoreData(20_961.0, None, "Smith et al. 2000 / Biostatus DRAQ5 data sheet (646 nm)"),
}


@dataclass(frozen=True)
class Laser:
    """A laser the thesis proposes for a channel (§5.2.3): line, output power and product."""

    wavelength_nm: float
    power_mw: float
    product: str


#: §5.2.3: 355 nm up to 250 mW (Coherent Genesis CX STM), 488 nm up to 4 W (Genesis CX STM), 568 nm 200 mW
#: (Sapphire 568 LP), 660 nm 100 mW (CUBE 660-100C).
SEED_LASERS: dict[str, Laser] = {
    "blue": Laser(355.0, 250.0, "Coherent Genesis CX STM"),
    "green": Laser(488.0, 4000.0, "Coherent Genesis CX STM"),
    "red": Laser(568.0, 200.0, "Coherent Sapphire 568 LP"),
    "nir": Laser(660.0, 100.0, "Coherent CUBE 660-100C"),
}

#: The camera of every channel (§4.1.4: Basler scA1400-30gm, Sony ICX285AL, 12 bit): the EMVA 1288 defaults
#: (full well 18 ke-, dark noise 10 e-); the quantum efficiency is the spectral one (spectra.camera_qe), so 1 here.
CAMERA = EmvaSensor(quantum_efficiency=1.0)


# -- conversions ------------------------------------------------------------------------------------------------------
def photon_energy_j(wavelength_nm: ArrayLike) -> Array:
    """Energy of one photon, E = h c / lambda, J."""
    return PLANCK_J_S * LIGHT_M_S / (np.asarray(wavelength_nm, dtype=np.float64) * 1e-9)


def photons_per_s(power_mw: ArrayLike, wavelength_nm: ArrayLike) -> Array:
    """Photon flux of a monochromatic beam of ``power_mw`` at ``wavelength_nm``, photons/s."""
    return np.asarray(power_mw, dtype=np.float64) * 1e-3 / photon_energy_j(wavelength_nm)


def cross_section_cm2(extinction_m_cm: ArrayLike) -> Array:
    """Absorption cross-section of one molecule from its molar (decadic) extinction coefficient, cm^2.

    sigma = ln(10) * 1000 cm^3/L * eps / N_A (eps in 1/(M cm)).
    """
    return math.log(10.0) * 1000.0 * np.asarray(extinction_m_cm, dtype=np.float64) / AVOGADRO_PER_MOL


def collection_fraction(na: float, immersion_index: float = 1.0) -> float:
    """Fraction of isotropic emission inside the objective's cone, (1 - cos asin(NA/n)) / 2."""
    if not 0 < na < immersion_index:
        raise BudgetError(f"NA must be in (0, n = {immersion_index}), got {na}")
    return 0.5 * (1.0 - math.cos(math.asin(na / immersion_index)))


def disc_area_um2(diameter_mm: float) -> float:
    """Area of a disc of diameter ``diameter_mm``, µm^2."""
    if not diameter_mm > 0:
        raise BudgetError(f"illuminated diameter must be > 0, got {diameter_mm}")
    return math.pi * (0.5 * diameter_mm * 1e3) ** 2


def micromolar(density_per_um2: float, thickness_um: float) -> float:
    """The concentration (µM) of ``density_per_um2`` molecules per µm^2 spread through ``thickness_um``: 1 µM is
    N_A 1e-6 mol/L x 1e-15 L/µm^3 = 602.214 molecules/µm^3."""
    if not thickness_um > 0:
        raise BudgetError(f"thickness must be > 0 µm, got {thickness_um}")
    return density_per_um2 / (thickness_um * AVOGADRO_PER_MOL * 1e-21)


def signal_for_snr_e(snr: float, dark_noise_e: float) -> float:
    """Signal S (electrons) whose SNR = S / sqrt(S + sigma_d^2) equals ``snr``: S = (snr^2 + snr sqrt(snr^2 +
    4 sigma_d^2)) / 2."""
    if not snr > 0:
        raise BudgetError(f"SNR must be > 0, got {snr}")
    return 0.5 * (snr * snr + snr * math.sqrt(snr * snr + 4.0 * dark_noise_e**2))


def snr_of(signal_e: ArrayLike, dark_noise_e: float) -> Array:
    """SNR = S / sqrt(S + sigma_d^2) of a signal of S electrons."""
    s = np.asarray(signal_e, dtype=np.float64)
    return s / np.sqrt(s + dark_noise_e**2)


# -- the excitation ---------------------------------------------------------------------------------------------------
def laser_line(laser: Laser, channel: str, fwhm_nm: float = 1.0) -> Array:
    """Spectral power at the object plane (mW/nm on GRID_NM) of a laser sent through ``channel``'s excitation path.

    A Gaussian line of ``fwhm_nm`` (a stand-in for a single-line laser) times the path's modelled transmission (its
    band pass and dichroics, :data:`~scopetwin.scenes.cmu.spectra.EXCITATION_PATHS`); the beam is taken as expanded to
    the channel's illuminated disc.
    """
    if not laser.power_mw > 0:
        raise BudgetError(f"laser power must be > 0, got {laser.power_mw}")
    wl = spectra.GRID_NM
    sigma = fwhm_nm / (2.0 * math.sqrt(2.0 * math.log(2.0)))
    line = np.exp(-0.5 * ((wl - laser.wavelength_nm) / sigma) ** 2)
    line *= laser.power_mw / np.trapezoid(line, wl)
    return line * spectra.path_curve(spectra.EXCITATION_PATHS[channel], wl)


def excitation_rate_per_s(excitation_mw_nm: ArrayLike, area_um2: float, stain: str) -> float:
    """Excitations per molecule per second: integral sigma(lambda) phi(lambda) d lambda.

    Parameters
    ----------
    excitation_mw_nm : array_like
        Spectral power at the object plane on :data:`~scopetwin.scenes.cmu.spectra.GRID_NM`, mW/nm.
    area_um2 : float
        The illuminated area it spreads over (uniformly), µm^2.
    stain : str
        A fluorophore of :data:`FLUOROPHORE_DATA` (its band from :data:`~scopetwin.scenes.cmu.spectra.FLUOROPHORES`).
    """
    if not area_um2 > 0:
        raise BudgetError(f"illuminated area must be > 0, got {area_um2}")
    wl = spectra.GRID_NM
    photons_um2 = photons_per_s(excitation_mw_nm, wl) / area_um2  # photons/(s µm^2 nm)
    sigma_um2 = (
        cross_section_cm2(FLUOROPHORE_DATA[stain].extinction_m_cm) * 1e8 * spectra.fluorophore(stain).excitation(wl)
    )
    return float(np.trapezoid(sigma_um2 * photons_um2, wl))


def detection_e_per_photon(channel: str, stain: str) -> float:
    """Electrons per emitted photon that enters the emission path: integral em(lambda) D_c(lambda) d lambda."""
    wl = spectra.GRID_NM
    em = spectra.fluorophore(stain).emission(wl)
    return float(np.trapezoid(em * spectra.detection_response(channel, wl), wl))


# -- the budget -------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ChannelBudget:
    """One channel's photon budget (see the module docstring for the model).

    Attributes
    ----------
    channel, stain, source : str
        The channel, its fluorophore and its excitation source.
    power_mw : float
        Excitation power at the object plane, mW.
    area_um2 : float
        Illuminated area, µm^2.
    excitation_per_s : float
        Excitations per molecule per second, k.
    emission_per_s : float
        Photons emitted per molecule per second, k QY.
    collection : float
        Fraction of the emission the objective collects.
    detection_e_per_photon : float
        Electrons per collected photon (emission path and spectral quantum efficiency).
    molecules_per_px : float
        Labelled molecules in the object area of one pixel.
    e_per_px_per_ms : float
        Photoelectrons per pixel per ms.
    exposure_ms : float
        Exposure that gives the stated SNR, ms.
    snr : float
        That SNR.
    saturation_ms : float
        Exposure that fills the full well, ms.
    bleach_tau_s : float or None
        1/e photobleaching time at this illumination, s (None: not modelled for this stain).
    """

    channel: str
    stain: str
    source: str
    power_mw: float
    area_um2: float
    excitation_per_s: float
    emission_per_s: float
    collection: float
    detection_e_per_photon: float
    molecules_per_px: float
    e_per_px_per_ms: float
    exposure_ms: float
    snr: float
    saturation_ms: float
    bleach_tau_s: float | None

    def electrons(self, exposure_ms: float) -> float:
        """Mean photoelectrons per pixel in an exposure of ``exposure_ms`` (unsaturated)."""
        return self.e_per_px_per_ms * exposure_ms

    def bleached_fraction(self, exposure_ms: float) -> float | None:
        """Fraction of the molecules bleached during an exposure (None where bleaching is not modelled)."""
        if self.bleach_tau_s is None:
            return None
        return float(-math.expm1(-exposure_ms * 1e-3 / self.bleach_tau_s))


def pixel_area_um2(objective: Objective | None = None) -> float:
    """Object area one camera pixel sees, (pixel pitch / M)^2, µm^2 (0.416 µm^2 for the thesis's 6.45 µm at 10x)."""
    p_um = (objective or Objective()).object_pixel_mm * 1e3
    return p_um * p_um


def _excitation(channel: str, laser: Laser | None) -> tuple[Array, str]:
    """The object-plane excitation spectrum (mW/nm) of a channel and the name of its source."""
    if laser is None:
        return spectra.excitation_at_object(channel), f"{spectra.SOURCES[channel].name} (Table 4.1)"
    return laser_line(laser, channel), f"{laser.wavelength_nm:g} nm laser, {laser.power_mw:g} mW ({laser.product})"


def channel_budget(
    channel: str,
    density_per_um2: float,
    snr: float = 10.0,
    laser: Laser | None = None,
    stain: str | None = None,
    objective: Objective | None = None,
    camera: EmvaSensor = CAMERA,
) -> ChannelBudget:
    """The photon budget of one channel at a labelling density.

    Parameters
    ----------
    channel : str
        ``blue``, ``green``, ``red`` or ``nir``.
    density_per_um2 : float
        Labelled molecules per µm^2 of object.
    snr : float
        The SNR the exposure must reach.
    laser : Laser, optional
        Excite with this laser through the channel's excitation path instead of the thesis's source (§5.2.3).
    stain : str, optional
        The fluorophore (default :data:`STAINS`).
    objective : Objective, optional
        The objective and camera pixel (default 10x / 0.45, 6.45 µm).
    camera : EmvaSensor
        Full well and dark noise (its quantum efficiency is not used: the spectral one is in the detection).
    """
    if channel not in spectra.CHANNELS:
        raise BudgetError(f"unknown channel {channel!r} (channels: {', '.join(spectra.CHANNELS)})")
    if not density_per_um2 > 0:
        raise BudgetError(f"labelling density must be > 0 molecules/µm², got {density_per_um2}")
    stain = stain or STAINS[channel]
    obj = objective or Objective()
    exc, source = _excitation(channel, laser)
    area = disc_area_um2(ILLUMINATED_DIAMETER_MM[channel])
    k = excitation_rate_per_s(exc, area, stain)
    k_em = k * spectra.fluorophore(stain).quantum_yield
    coll = collection_fraction(obj.na, obj.immersion_index)
    eta = detection_e_per_photon(channel, stain)
    n_px = density_per_um2 * pixel_area_um2(obj)
    rate = n_px * k_em * coll * eta * 1e-3
    half = FLUOROPHORE_DATA[stain].half_life_s
    tau_b = None if half is None else 1000.0 * half / math.log(2.0) / k_em
    return ChannelBudget(
        channel=channel,
        stain=stain,
        source=source,
        power_mw=float(np.trapezoid(exc, spectra.GRID_NM)),
        area_um2=area,
        excitation_per_s=k,
        emission_per_s=k_em,
        collection=coll,
        detection_e_per_photon=eta,
        molecules_per_px=n_px,
        e_per_px_per_ms=rate,
        exposure_ms=signal_for_snr_e(snr, camera.dark_noise_e) / rate,
        snr=snr,
        saturation_ms=camera.full_well_e / rate,
        bleach_tau_s=tau_b,
    )


def budget(
    density_per_um2: float | dict[str, float],
    snr: float = 10.0,
    lasers: dict[str, Laser] | None = None,
    objective: Objective | None = None,
) -> dict[str, ChannelBudget]:
    """:func:`channel_budget` of the four channels (one density for all, or one per channel); ``lasers`` replaces the
    thesis's sources by those lasers (e.g. :data:`SEED_LASERS`)."""
    out = {}
    for ch in spectra.CHANNELS:
        rho = density_per_um2[ch] if isinstance(density_per_um2, dict) else density_per_um2
        out[ch] = channel_budget(ch, rho, snr, (lasers or {}).get(ch), objective=objective)
    return out


def implied_density(channel: str, exposure_ms: float, snr: float = 10.0, laser: Laser | None = None) -> float:
    """The labelling density (molecules/µm^2) at which ``channel`` reaches ``snr`` in ``exposure_ms``."""
    if not exposure_ms > 0:
        raise BudgetError(f"exposure must be > 0 ms, got {exposure_ms}")
    unit = channel_budget(channel, 1.0, snr, laser)
    return unit.exposure_ms / exposure_ms


def seed_comparison(snr: float = 10.0, reference: str = "blue") -> dict[str, dict[str, float]]:
    """The thesis's exposures (§5.2.3) against the budget at the density the ``reference`` channel's exposure implies.

    Returns, per channel: ``seed_ms``, ``predicted_ms`` (at that density), ``ratio`` (predicted / thesis; 1 where the
    channel follows from the reference), ``implied_density_per_um2`` (the density the channel's own thesis exposure
    implies) and ``density_ratio`` (that density over the reference's: how much more or less stain the channel
    needed for its exposure).
    """
    rho = implied_density(reference, SEED_EXPOSURE_MS[reference], snr)
    table = budget(rho, snr)
    out = {}
    for ch, b in table.items():
        own = implied_density(ch, SEED_EXPOSURE_MS[ch], snr)
        out[ch] = {
            "seed_ms": SEED_EXPOSURE_MS[ch],
            "predicted_ms": b.exposure_ms,
            "ratio": b.exposure_ms / SEED_EXPOSURE_MS[ch],
            "implied_density_per_um2": own,
            "density_ratio": own / rho,
        }
    return out
