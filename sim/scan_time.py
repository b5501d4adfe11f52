"""Scan-time models of the parallel microscope (thesis §7.2-7.4) and the objective count of the demonstrator (§8.2.2).

All lengths in mm, times in s, velocities in mm/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from scopetwin.scenes.errors import ScopetwinError


class ScanTimeError(ScopetwinError, ValueError):
    """Parameters of a scan-time model that make no sense (non-positive sizes, no field of view left)."""


def _positive(**values: float) -> None:
    for name, v in values.items():
        if not (v > 0 and math.isfinite(v)):
            raise ScanTimeError(f"{name} must be a positive number, got {v!r}")


def classic_time(
    width: float, height: float, d_w: float, d_h: float, exposure_s: float, velocity: float
) -> dict[str, float]:
    """Stop-and-go acquisition with one objective (thesis §7.2): T_I, T_M and T = T_I + T_M.

    T_I = (W/d_w) τ_e (H/d_h), T_M = ((W/d_w) H + W) / v.
    """
    _positive(width=width, height=height, d_w=d_w, d_h=d_h, exposure_s=exposure_s, velocity=velocity)
    t_i = width / d_w * exposure_s * height / d_h
    t_m = (width / d_w * height + width) / velocity
    return {"t_i_s": t_i, "t_m_s": t_m, "t_s": t_i + t_m}


def scan_time(width: float, height: float, w_fov: float, v_scan: float, n: int = 1) -> float:
    """Line-scan time with N objectives side by side (thesis §7.3): T_N = (1/N)(H/v)(W/w_FOV) + (1/N)(W/v)."""
    _positive(width=width, height=height, w_fov=w_fov, v_scan=v_scan, n=n)
    return (height / v_scan * width / w_fov + width / v_scan) / n


def scan_time_parallel(d_l: float, w_fov: float, height: float, v_scan: float, n_y: int = 1) -> float:
    """Eq. 7.1/7.2: T = (1/N_y)(D_L/w_FOV)(H/v_scan), the x-direction filled with N_x = W/D_L objectives."""
    _positive(d_l=d_l, w_fov=w_fov, height=height, v_scan=v_scan, n_y=n_y)
    return d_l / w_fov * height / v_scan / n_y


def scans_needed(d_l: float, w_fov: float) -> float:
    """N_scans = D_L / w_FOV (thesis §7.3)."""
    _positive(d_l=d_l, w_fov=w_fov)
    return d_l / w_fov


@dataclass(frozen=True)
class ScalingModel:
    """Spot radius r_s = A + B r_l² of the unscaled system (eq. 7.3) and the diffraction limit λ/NA (§7.4)."""

    a: float
    b: float
    wavelength: float
    na: float
    magnification: float

    def r_max(self, s: float) -> float:
        """Largest diffraction-limited lens radius of the system scaled by s: s √((λ/(s NA) - A)/B)."""
        _positive(s=s)
        inner = (self.wavelength / (s * self.na) - self.a) / self.b
        if inner <= 0:
            raise ScanTimeError(
                f"at scale {s:g} the aberration A·s = {self.a * s:g} mm already exceeds the "
                f"diffraction limit λ/NA = {self.wavelength / self.na:g} mm: no field is left"
            )
        return s * math.sqrt(inner)

    def w_fov(self, s: float) -> float:
        """w_FOV,s = 2 r_max,s / m (§7.4)."""
        return 2.0 * self.r_max(s) / self.magnification

    def scan_time(
        self, s: float, d_l: float, height: float, v_scan: float, n_y: float, pack_rows: bool = True
    ) -> float:
        """Eq. 7.5 (N_y fixed, T ~ √s for small A) or, with ``pack_rows``, N_y ~ 1/s (eq. 7.6, T ~ s^1.5)."""
        rows = n_y / s if pack_rows else n_y
        return s * d_l / self.w_fov(s) * height / v_scan / rows


def objective_count(s: float, d_l_diameter: float, d_l: float, m: float, fov: float) -> int:
    """Eq. 8.1: N = floor((S + D_L - d_L) / (m FOV + d_L - D_L)) objectives on a sensor side S (§8.2.2)."""
    _positive(s=s, d_l_diameter=d_l_diameter, d_l=d_l, m=m, fov=fov)
    if d_l < d_l_diameter:
        raise ScanTimeError(f"axis spacing d_L = {d_l} mm is smaller than the lens diameter D_L = {d_l_diameter} mm")
    return int(math.floor((s + d_l_diameter - d_l) / (m * fov + d_l - d_l_diameter) + 1e-12))


def objective_count_max(s: float, m: float, fov: float) -> int:
    """Eq. 8.2: N_max = floor(S / (m FOV)) with touching lenses (d_L = D_L)."""
    _positive(s=s, m=m, fov=fov)
    return int(math.floor(s / (m * fov) + 1e-12))


def spacing_max(s: float, d_l_diameter: float, m: float, fov: float) -> float:
    """d_L,max = (S - N_max m FOV) / (N_max - 1) + D_L (§8.2.2)."""
    n = objective_count_max(s, m, fov)
    if n < 2:
        raise ScanTimeError(
            f"only {n} objective fits on the sensor (S = {s} mm, m FOV = {m * fov:g} mm): no spacing to choose"
        )
    return (s - n * m * fov) / (n - 1) + d_l_diameter


def demonstrator_geometry(
    s: float = 4.28, d_l_diameter: float = 2.0, m: float = 4.29, fov: float = 0.4, d_l: float = 2.25
) -> dict[str, float]:
    """The §8.2.2 figures: N_max, d_L,max and N at the chosen d_L (the thesis: N_max = 2, d_L,max = 2.848 mm)."""
    return {
        "n_max": objective_count_max(s, m, fov),
        "d_l_max_mm": spacing_max(s, d_l_diameter, m, fov),
        "n_at_d_l": objective_count(s, d_l_diameter, d_l, m, fov),
        "d_l_mm": d_l,
    }
