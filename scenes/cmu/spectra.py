"""Spectral models of the compact microscope unit (thesis ch. 3-4): fluorophores, light sources, filters, dichroics.

Everything is a function of wavelength in nm on :data:`GRID_NM` (300-1000 nm, 0.5 nm steps). What the thesis
gives is used as given; what it does not give is a stated model with stated parameters:

* **Fluorophores** (§3.3): excitation/emission peaks and quantum yields from the thesis. Band shapes are
  Fraser-Suzuki (skewed log-normal) bands in wavenumber, the empirical shape of Siano & Metzler
  (J. Chem. Phys. 51, 1856, 1969) for absorption and fluorescence bands of dyes; the widths (FWHM in nm) and the
  skew are *our estimates* of the published spectra's shapes (the thesis's Figs. 3.1-3.5 are images), and the
  excitation band is normalised to a peak of 1 (relative absorption; no molar extinction is used).
* **LEDs** (§4.1.1): peak and spectral half width from the thesis, shape after Ohno's LED model
  (Opt. Eng. 44, 111302, 2005): S = (g + 2 g^5)/3 with g a Gaussian of that FWHM. Halogen bulb: a Planck
  radiator at 3100 K (a 150 W halogen lamp's typical colour temperature; not in the thesis) through the fibre.
* **Band-pass filters** (§4.1.3): decoded from the name, ``HQ485/15X`` = centre 485 nm, FWHM 15 nm; flat top
  (transmission 0.90 for HQ/D, 0.93 for ET coatings) with logistic edges of 10-90 % width 1 % of the centre,
  blocking 1e-5 (OD 5) outside. These are models, not the Chroma curves.
* **Dichroic edge filters** (``NNNDCXR``, §4.1.3): high pass in transmission, low pass in reflection, 50 % at
  NNN nm (at 45°), logistic edge of 10-90 % width 1.5 % of NNN, T_max 0.95, R_max 0.98.
* **61002BS** (§4.1.3, Fig. 4.12): a multiband splitter; transmission bands whose edges lie midway between the
  neighbouring excitation and emission bands of Table 3.1 (it "defines the usable excitation and emission
  bands"): T in [405, 478.5], [496.5, 555], [585, 655] and above 735 nm; reflection = the inverse curve.
* **Camera** (§4.1.4, Sony ICX285AL): an approximate quantum-efficiency curve (peak ~0.62 near 500 nm;
  our reading of the data-sheet's relative response, not in the thesis).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scopetwin.scenes.errors import ScopetwinError

Array = NDArray[np.float64]

#: Wavelength grid of every tabulated spectrum, nm.
GRID_NM: Array = np.arange(300.0, 1000.0 + 1e-9, 0.5)
CHANNELS: tuple[str, ...] = ("blue", "green", "red", "nir")

#: Table 3.1 (excitation and emission bands, nm) as (centre, half width).
TABLE_3_1: dict[str, dict[str, tuple[float, float]]] = {
    "blue": {"excitation": (360.0, 20.0), "emission": (455.0, 25.0)},
    "green": {"excitation": (485.0, 8.0), "emission": (525.0, 25.0)},
    "red": {"excitation": (570.0, 10.0), "emission": (620.0, 30.0)},
    "nir": {"excitation": (680.0, 20.0), "emission": (785.0, 15.0)},
}

#: Table 4.1: optical power of the excitation at the object plane, mW.
TABLE_4_1_MW: dict[str, float] = {"blue": 9.13, "green": 1.42, "red": 0.85, "nir": 7.78}


class SpectrumError(ScopetwinError, ValueError):
    """An unknown filter, fluorophore or light source name, or an impossible spectral parameter."""


def _logistic(x: ArrayLike, width_10_90: float) -> Array:
    """Smooth step 0 -> 1 whose 10 %-90 % rise spans ``width_10_90`` (x in the same unit)."""
    k = 2.0 * np.log(9.0) / width_10_90
    return 0.5 * (1.0 + np.tanh(0.5 * k * np.asarray(x, dtype=np.float64)))


# -- fluorophores ---------------------------------------------------------------------------------
def fraser_suzuki(wl_nm: ArrayLike, peak_nm: float, fwhm_nm: float, skew: float) -> Array:
    """Skewed log-normal band in wavenumber (Fraser-Suzuki form), peak 1 at ``peak_nm``.

    f(nu) = exp(-ln2 [ln(1 + 2 b (nu - nu0)/w) / b]^2), nu in 1/nm, w the FWHM converted at the peak
    (w = fwhm/peak^2); b > 0 gives the long tail toward short wavelengths (absorption), b < 0 toward long
    wavelengths (fluorescence). b -> 0 is a Gaussian.
    """
    wl = np.asarray(wl_nm, dtype=np.float64)
    nu = 1.0 / wl
    nu0 = 1.0 / peak_nm
    w = fwhm_nm / peak_nm**2
    if abs(skew) < 1e-9:
        return np.exp(-4.0 * np.log(2.0) * ((nu - nu0) / w) ** 2)
    arg = 1.0 + 2.0 * skew * (nu - nu0) / w
    with np.errstate(divide="ignore", invalid="ignore"):
        out = np.exp(-np.log(2.0) * (np.log(np.where(arg > 0, arg, 1.0)) / skew) ** 2)
    return np.where(arg > 0, out, 0.0)


@dataclass(frozen=True)
class Fluorophore:
    """A fluorophore of thesis §3.3: peaks and quantum yield from the thesis, band widths our estimates."""

    name: str
    excitation_nm: float
    emission_nm: float
    quantum_yield: float
    excitation_fwhm_nm: float
    emission_fwhm_nm: float
    skew: float = 0.2

    def excitation(self, wl_nm: ArrayLike = GRID_NM) -> Array:
        """Relative absorption (peak 1)."""
        return fraser_suzuki(wl_nm, self.excitation_nm, self.excitation_fwhm_nm, self.skew)

    def emission(self, wl_nm: ArrayLike = GRID_NM) -> Array:
        """Emission spectrum normalised to unit area on :data:`GRID_NM` (photons per nm, relative)."""
        e = fraser_suzuki(GRID_NM, self.emission_nm, self.emission_fwhm_nm, -self.skew)
        e /= np.trapezoid(e, GRID_NM)
        return np.interp(np.asarray(wl_nm, dtype=np.float64), GRID_NM, e, left=0.0, right=0.0)


#: Thesis §3.3 (peaks, quantum yields); widths estimated from the published spectra (not in the thesis).
FLUOROPHORES: dict[str, Fluorophore] = {
    "DAPI": Fluorophore("DAPI", 358.0, 461.0, 0.92, 55.0, 95.0),
    "Hoechst 33258": Fluorophore("Hoechst 33258", 350.0, 460.0, 0.6, 55.0, 100.0),
    "EGFP": Fluorophore("EGFP", 488.0, 507.0, 0.6, 40.0, 35.0),
    "mRFP": Fluorophore("mRFP", 584.0, 607.0, 0.25, 45.0, 45.0),
    "mCherry": Fluorophore("mCherry", 587.0, 610.0, 0.22, 50.0, 50.0),
    # §3.3.4: emission 681 nm, 697 nm when intercalated with dsDNA (stained nuclei); QY 0.003-0.004
    "DRAQ5": Fluorophore("DRAQ5", 646.0, 697.0, 0.0035, 90.0, 90.0),
}
#: The fluorophore imaged in each channel (Table 3.1; the cells of §5.2.3 used Hoechst, GFP, mCherry, DRAQ5).
CHANNEL_FLUOROPHORE: dict[str, str] = {"blue": "DAPI", "green": "EGFP", "red": "mCherry", "nir": "DRAQ5"}


def fluorophore(name: str) -> Fluorophore:
    """Look up a fluorophore by name (case-insensitive)."""
    for key, f in FLUOROPHORES.items():
        if key.lower() == name.lower():
            return f
    raise SpectrumError(f"unknown fluorophore {name!r} (known: {', '.join(FLUOROPHORES)})")


# -- light sources --------------------------------------------------------------------------------
def ohno_led(wl_nm: ArrayLike, peak_nm: float, fwhm_nm: float) -> Array:
    """Ohno's LED spectrum model (g + 2 g^5)/3, g Gaussian of FWHM ``fwhm_nm``; peak 1."""
    sigma = fwhm_nm / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    g = np.exp(-0.5 * ((np.asarray(wl_nm, dtype=np.float64) - peak_nm) / sigma) ** 2)
    return (g + 2.0 * g**5) / 3.0


def planck(wl_nm: ArrayLike, temperature_k: float) -> Array:
    """Planck spectral radiance shape, normalised to 1 at its maximum over :data:`GRID_NM`."""
    h, c, k = 6.62607015e-34, 2.99792458e8, 1.380649e-23
    lam = np.asarray(wl_nm, dtype=np.float64) * 1e-9
    b = 1.0 / (lam**5 * np.expm1(h * c / (lam * k * temperature_k)))
    ref = 1.0 / ((GRID_NM * 1e-9) ** 5 * np.expm1(h * c / (GRID_NM * 1e-9 * k * temperature_k)))
    return b / ref.max()


@dataclass(frozen=True)
class LightSource:
    """An excitation source of thesis §4.1.1."""

    name: str
    kind: Literal["led", "halogen"]
    peak_nm: float = 0.0
    fwhm_nm: float = 0.0
    temperature_k: float = 3100.0

    def spectrum(self, wl_nm: ArrayLike = GRID_NM) -> Array:
        """Relative spectral power (peak ~1)."""
        if self.kind == "led":
            return ohno_led(wl_nm, self.peak_nm, self.fwhm_nm)
        return planck(wl_nm, self.temperature_k)


#: §4.1.1. The UV LED's peak "between 360 nm and 370 nm" is read as 365 nm, the Rebel Blue's "475-480 nm" as 477.5.
SOURCES: dict[str, LightSource] = {
    "blue": LightSource("Nichia NCSU033B UV LED", "led", 365.0, 9.0),
    "green": LightSource("Luxeon Rebel Blue", "led", 477.5, 20.0),
    "red": LightSource("150 W halogen bulb, fibre NA 0.39, 1 mm core", "halogen", temperature_k=3100.0),
    "nir": LightSource("Luxeon Rebel Deep Red", "led", 662.5, 20.0),
}


# -- filters and beam splitters ---------------------------------------------------------------------
_BANDPASS = re.compile(r"^(HQ|ET|D)(\d+(?:\.\d+)?)/(\d+(?:\.\d+)?)([A-Z]*)$")
_DCXR = re.compile(r"^(\d+)DCXR$")


def bandpass(name: str, wl_nm: ArrayLike = GRID_NM) -> Array:
    """Transmission of a Chroma band-pass filter decoded from its name (``HQ360/40M``, ``ET525/50M``, ``D680/40X``)."""
    m = _BANDPASS.match(name.strip().upper())
    if m is None:
        raise SpectrumError(f"cannot decode band-pass filter name {name!r} (expected e.g. HQ485/15X or ET525/50M)")
    coat, centre, width = m.group(1), float(m.group(2)), float(m.group(3))
    t_max = 0.93 if coat == "ET" else 0.90
    edge = 0.01 * centre
    wl = np.asarray(wl_nm, dtype=np.float64)
    t = _logistic(wl - (centre - 0.5 * width), edge) * _logistic((centre + 0.5 * width) - wl, edge)
    return np.maximum(t_max * t, 1e-5)


def dichroic(name: str, mode: Literal["T", "R"], wl_nm: ArrayLike = GRID_NM) -> Array:
    """Transmission (``mode='T'``) or reflection (``'R'``) of ``NNNDCXR`` or ``61002BS`` at 45°."""
    wl = np.asarray(wl_nm, dtype=np.float64)
    key = name.strip().upper()
    if key == "61002BS":
        edges = ((405.0, 478.5), (496.5, 555.0), (585.0, 655.0), (735.0, 2000.0))
        s = np.zeros_like(wl)
        for lo, hi in edges:
            s += _logistic(wl - lo, 0.008 * lo) * _logistic(hi - wl, 0.008 * hi)
        s = np.clip(s, 0.0, 1.0)
    else:
        m = _DCXR.match(key)
        if m is None:
            raise SpectrumError(f"unknown beam splitter {name!r} (expected NNNDCXR or 61002BS)")
        cut = float(m.group(1))
        s = _logistic(wl - cut, 0.015 * cut)
    if mode == "T":
        return 0.95 * s
    if mode == "R":
        return 0.98 * (1.0 - s)
    raise SpectrumError(f"beam splitter mode must be 'T' or 'R', got {mode!r}")


#: Reflectance of the flat folding mirrors (§4.1.3 emission paths): a broadband metal mirror, 0.95 (our model).
MIRROR_REFLECTANCE = 0.95


def camera_qe(wl_nm: ArrayLike = GRID_NM) -> Array:
    """Approximate quantum efficiency of the Sony ICX285AL (Basler scA1400-30gm, thesis §4.1.4)."""
    pts = np.array(
        [
            [300, 0.05],
            [350, 0.22],
            [400, 0.45],
            [450, 0.57],
            [500, 0.62],
            [550, 0.60],
            [600, 0.53],
            [650, 0.45],
            [700, 0.36],
            [750, 0.28],
            [800, 0.20],
            [850, 0.13],
            [900, 0.08],
            [1000, 0.02],
        ],
        dtype=np.float64,
    )
    return np.interp(np.asarray(wl_nm, dtype=np.float64), pts[:, 0], pts[:, 1])


# -- the four channels' paths (§4.1.3) ----------------------------------------------------------------
#: Excitation paths: (element, mode) from the source to the objective; "BP" = band-pass filter.
EXCITATION_PATHS: dict[str, tuple[tuple[str, str], ...]] = {
    "blue": (("HQ360/40M", "BP"), ("425DCXR", "R"), ("515DCXR", "R"), ("61002BS", "R")),
    "green": (("HQ485/15X", "BP"), ("425DCXR", "T"), ("515DCXR", "R"), ("61002BS", "R")),
    "red": (("HQ570/20X", "BP"), ("585DCXR", "R"), ("515DCXR", "T"), ("61002BS", "R")),
    "nir": (("D680/40X", "BP"), ("585DCXR", "T"), ("515DCXR", "T"), ("61002BS", "R")),
}
#: Emission paths: from the objective to the camera; "M" = mirror.
EMISSION_PATHS: dict[str, tuple[tuple[str, str], ...]] = {
    "blue": (("61002BS", "T"), ("565DCXR", "R"), ("500DCXR", "R"), ("ET455/50M", "BP")),
    "green": (("61002BS", "T"), ("565DCXR", "R"), ("500DCXR", "T"), ("mirror", "M"), ("ET525/50M", "BP")),
    "red": (("61002BS", "T"), ("565DCXR", "T"), ("770DCXR", "R"), ("mirror", "M"), ("ET620/60M", "BP")),
    "nir": (("61002BS", "T"), ("565DCXR", "T"), ("770DCXR", "T"), ("HQ775/50X", "BP")),
}


def element_curve(name: str, mode: str, wl_nm: ArrayLike = GRID_NM) -> Array:
    """Spectral factor of one path element (``BP`` band pass, ``T``/``R`` splitter, ``M`` mirror)."""
    if mode == "BP":
        return bandpass(name, wl_nm)
    if mode == "M":
        return np.full(np.shape(wl_nm), MIRROR_REFLECTANCE)
    return dichroic(name, mode, wl_nm)  # type: ignore[arg-type]


def path_curve(path: tuple[tuple[str, str], ...], wl_nm: ArrayLike = GRID_NM) -> Array:
    """Product of the spectral factors along a path."""
    out = np.ones(np.shape(wl_nm))
    for name, mode in path:
        out = out * element_curve(name, mode, wl_nm)
    return out


def excitation_at_object(channel: str, wl_nm: ArrayLike = GRID_NM) -> Array:
    """Spectral power of channel's excitation at the object plane, mW/nm, scaled to Table 4.1's power."""
    _check_channel(channel)
    s = SOURCES[channel].spectrum(GRID_NM) * path_curve(EXCITATION_PATHS[channel], GRID_NM)
    s = s * TABLE_4_1_MW[channel] / np.trapezoid(s, GRID_NM)
    return np.interp(np.asarray(wl_nm, dtype=np.float64), GRID_NM, s, left=0.0, right=0.0)


def detection_response(channel: str, wl_nm: ArrayLike = GRID_NM, include_splitters: bool = True) -> Array:
    """Electrons per emitted photon entering the emission path at wavelength: path transmission x camera QE.

    With ``include_splitters=False`` only the fixed parts in front of the camera (band pass, QE): the splitters and
    the folding mirrors are then applied ray by ray in the renderer (:mod:`scopetwin.scenes.mitsuba.cmu` models both as
    plates, the mirrors with :data:`MIRROR_REFLECTANCE`).
    """
    _check_channel(channel)
    path = EMISSION_PATHS[channel]
    if not include_splitters:
        path = tuple(p for p in path if p[1] == "BP")
    return path_curve(path, wl_nm) * camera_qe(wl_nm)


def band_limits(curve: ArrayLike, wl_nm: ArrayLike = GRID_NM, level: float = 0.5) -> tuple[float, float]:
    """Wavelengths where a single-band curve crosses ``level`` x its maximum (the usable band, nm)."""
    c = np.asarray(curve, dtype=np.float64)
    wl = np.asarray(wl_nm, dtype=np.float64)
    above = np.flatnonzero(c >= level * c.max())
    return float(wl[above[0]]), float(wl[above[-1]])


def _check_channel(channel: str) -> None:
    if channel not in CHANNELS:
        raise SpectrumError(f"unknown channel {channel!r} (channels: {', '.join(CHANNELS)})")


# -- crosstalk --------------------------------------------------------------------------------------
def excitation_rates(fluorophores: dict[str, str] | None = None) -> Array:
    """A[i, j]: photons absorbed by channel j's fluorophore under channel i's source (relative units).

    A_ij = integral E_i(lambda) eps_j(lambda) lambda d lambda, with E_i the object-plane excitation of
    Table 4.1 (mW/nm) and eps_j the relative absorption (peak 1); lambda converts power to photon flux.
    """
    fl = fluorophores or CHANNEL_FLUOROPHORE
    out = np.zeros((4, 4))
    for i, ci in enumerate(CHANNELS):
        e = excitation_at_object(ci)
        for j, cj in enumerate(CHANNELS):
            out[i, j] = np.trapezoid(e * fluorophore(fl[cj]).excitation(GRID_NM) * GRID_NM, GRID_NM)
    return out


def excitation_crosstalk(fluorophores: dict[str, str] | None = None) -> Array:
    """4x4 excitation crosstalk X[i, j] = A_ij / A_jj: how strongly source i excites fluorophore j relative to
    fluorophore j's own source (rows: sources blue..nir, columns: fluorophores of blue..nir). Diagonal = 1.
    Normalising per fluorophore cancels the unknown molar extinction coefficients."""
    a = excitation_rates(fluorophores)
    return a / np.diag(a)[None, :]


def emission_crosstalk(fluorophores: dict[str, str] | None = None) -> Array:
    """B[j, k]: electrons in camera k per electron in camera j from fluorophore j (emission bleed-through)."""
    fl = fluorophores or CHANNEL_FLUOROPHORE
    out = np.zeros((4, 4))
    for j, cj in enumerate(CHANNELS):
        em = fluorophore(fl[cj]).emission(GRID_NM)
        for k, ck in enumerate(CHANNELS):
            out[j, k] = np.trapezoid(em * detection_response(ck), GRID_NM)
    return out / np.diag(out)[:, None]


def channel_signal_matrix(fluorophores: dict[str, str] | None = None) -> Array:
    """S[i, k]: signal in camera k with only source i on, all four fluorophores present in equal amounts
    (absorption x quantum yield x detection), normalised to each camera's own source (S[k, k] = 1)."""
    fl = fluorophores or CHANNEL_FLUOROPHORE
    a = excitation_rates(fl)
    det = np.zeros((4, 4))
    for j, cj in enumerate(CHANNELS):
        f = fluorophore(fl[cj])
        for k, ck in enumerate(CHANNELS):
            det[j, k] = f.quantum_yield * np.trapezoid(f.emission(GRID_NM) * detection_response(ck), GRID_NM)
    s = a @ det
    return s / np.diag(s)[None, :]
