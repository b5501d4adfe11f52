"""Families of substrate surfaces for tests and studies: each surface's ``substrate.surface`` table drawn from a seed.

A family is a function ``seed -> dict`` (the keys of :class:`scopetwin.scenes.setup.SurfaceSpec`); its parameters are
drawn from the seed alone, so a family's surfaces are fixed before any tuning of the code they test. The families:

* ``gauss``, ``gauss+broadband``, ``abc+broadband``, ``power+broadband`` — the thesis's kind (§1.9 generator,
  8-20 mm correlation, 20-60 µm range) and PSD surfaces of that size, with 1-5 nm of broadband content;
* ``glass`` — like float glass: power-law waviness at 8-80 mm, a bow, 20-100 nm of micro-waviness at 1-8 mm;
* ``cut`` — sheets cut from such glass: the edges roll off (slopes of 6-16 mrad at the edges over 2-6 mm), a few
  local dimples and bumps, 30-70 µm peak to valley;
* ``steep`` — steep and high sheets: 80-200 µm of §1.9 waviness at 10-25 mm plus a bow, slopes of several mrad;
* ``features`` — the thesis's kind or glass with 2-5 local dimples and bumps of 0.5-3 µm over 1-4 mm (full width at
  half maximum).

:func:`dimple_spec` is the one named case of a local feature: the §1.10 surface with a 3 mm wide, 2 µm deep dimple;
:func:`dimple_depth` measures it on any height function.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

#: The families of the thesis's own kind (§1.9 and PSD surfaces of its size).
THESIS_KIND = ("gauss", "gauss+broadband", "abc+broadband", "power+broadband")
#: The hard families: bent glass the reconstruction was not designed on.
HARD = ("glass", "cut", "steep", "features")


def _glass(
    rng: np.random.Generator, seed: int, range_um: tuple[float, float], bow_um: float, micro_nm: tuple[float, float]
) -> dict[str, Any]:
    """Glass-like waviness drawn from ``rng``: power law f^-3 to f^-4, flat below f = 1/40 to 1/80 mm, rolled off by a
    Gaussian of 1-3 mm (so the waviness lies at 8-80 mm), ``range_um``, a bow within +-``bow_um``, micro-waviness of
    ``micro_nm`` RMS at 1-8 mm."""
    return {
        "kind": "psd",
        "spectrum": "power",
        "seed": int(seed),
        "psd_exponent": float(rng.uniform(3.0, 4.0)),
        "correlation_length": float(rng.uniform(40.0, 80.0)),
        "psd_rolloff_mm": float(rng.uniform(1.0, 3.0)),
        "range_um": float(rng.uniform(*range_um)),
        "bow_um": float(rng.uniform(-bow_um, bow_um)),
        "broadband_rms_nm": float(rng.uniform(*micro_nm)),
        "broadband_wavelength_mm": 8.0,
        "broadband_min_wavelength_mm": 1.0,
    }


def glass_spec(seed: int) -> dict[str, Any]:
    """One glass-like surface, like float glass: power-law waviness at 8-80 mm, 14-60 µm of it, a paraboloidal bow of
    up to +-20 µm, 20-100 nm RMS of flat-spectrum micro-waviness at 1-8 mm."""
    return _glass(np.random.default_rng([seed, 2727]), seed, (14.0, 60.0), 20.0, (20.0, 100.0))


def _features(rng: np.random.Generator, count: int) -> list[dict[str, float]]:
    """``count`` dimples and bumps of 0.5-3 µm, 1-4 mm wide (FWHM), inside the part of the ROI the markers see."""
    out = []
    for _ in range(count):
        depth = float(rng.uniform(0.5, 3.0)) * (-1.0 if rng.random() < 0.6 else 1.0)
        out.append(
            {
                "x": float(rng.uniform(-9.0, 9.0)),
                "y": float(rng.uniform(-20.0, 20.0)),
                "width_mm": float(rng.uniform(1.0, 4.0)),
                "height_um": depth,
            }
        )
    return out


def cut_spec(seed: int) -> dict[str, Any]:
    """A sheet cut from glass: glass-like waviness of 20-45 µm and a bow of up to +-15 µm, the four edges rolled off
    over 2-6 mm with a slope of 6-16 mrad at the edge (a quarter of them rising instead), 5-40 nm of micro-waviness,
    0-3 local dimples and bumps."""
    rng = np.random.default_rng([seed, 3434])
    width = float(rng.uniform(2.0, 6.0))
    slope = float(rng.uniform(6e-3, 16e-3))
    sign = -1.0 if rng.random() < 0.25 else 1.0
    return {
        **_glass(rng, seed, (20.0, 45.0), 15.0, (5.0, 40.0)),
        "edge_rolloff_mm": width,
        "edge_rolloff_um": sign * slope * width / 3.0 * 1e3,
        "features": _features(rng, int(rng.integers(0, 4))),
    }


def steep_spec(seed: int) -> dict[str, Any]:
    """A steep, high sheet: 80-200 µm of §1.9 waviness at 10-25 mm, a bow of up to +-40 µm, 1-5 nm of broadband
    content."""
    rng = np.random.default_rng([seed, 4545])
    return {
        "kind": "random",
        "seed": int(seed),
        "correlation_length": float(rng.uniform(10.0, 25.0)),
        "range_um": float(rng.uniform(80.0, 200.0)),
        "bow_um": float(rng.uniform(-40.0, 40.0)),
        "broadband_rms_nm": float(rng.uniform(1.0, 5.0)),
    }


def features_spec(seed: int) -> dict[str, Any]:
    """The thesis's kind (§1.9, 8-20 mm, 20-60 µm) or a glass-like sheet, with 2-5 local dimples and bumps."""
    rng = np.random.default_rng([seed, 5656])
    base = glass_spec(seed) if rng.random() < 0.5 else thesis_spec("gauss", seed)
    return {**base, "features": _features(rng, int(rng.integers(2, 6)))}


def thesis_spec(family: str, seed: int) -> dict[str, Any]:
    """A surface of the thesis's kind: §1.9 or PSD (ABC / power law), 8-20 mm, 20-60 µm, with 1-5 nm of broadband
    content except for ``gauss``."""
    rng = np.random.default_rng([seed, 1414])
    spec: dict[str, Any] = {
        "seed": int(seed),
        "correlation_length": float(rng.uniform(8.0, 20.0)),
        "range_um": float(rng.uniform(20.0, 60.0)),
    }
    bb = float(rng.uniform(1.0, 5.0))
    if family == "gauss":
        spec["kind"] = "random"
    elif family == "gauss+broadband":
        spec.update(kind="random", broadband_rms_nm=bb)
    elif family in ("abc+broadband", "power+broadband"):
        spec.update(
            kind="psd",
            spectrum="abc" if family.startswith("abc") else "power",
            psd_exponent=float(rng.choice([3.0, 4.0])),
            broadband_rms_nm=bb,
        )
    else:
        raise ValueError(f"unknown surface family {family!r} (known: {', '.join(FAMILIES)})")
    return spec


def dimple_spec(depth_um: float = 2.0, width_mm: float = 3.0, at: tuple[float, float] = (2.0, 5.0)) -> dict[str, Any]:
    """The §1.10 surface (§1.9 generator, 12 mm, 40 µm, seed 1) with one dimple of ``depth_um`` and FWHM ``width_mm``
    at ``at`` (mm)."""
    return {
        "kind": "random",
        "seed": 1,
        "correlation_length": 12.0,
        "range_um": 40.0,
        "features": [{"x": at[0], "y": at[1], "width_mm": width_mm, "height_um": -depth_um}],
    }


def dimple_depth(height: Callable[[Any, Any], Any], x: float = 2.0, y: float = 5.0, ring_mm: float = 4.0) -> float:
    """Depth of a dimple at (x, y): the mean height over a ring of ``ring_mm`` around it minus the height there, mm.

    ``height(x, y)`` is any vectorised height function in mm (a height map's, a reconstruction's). The ratio of a
    reconstruction's depth to the true surface's is the share of the dimple (:func:`dimple_spec`) it recovers.
    """
    a = np.linspace(0.0, 2.0 * np.pi, 24, endpoint=False)
    ring = np.asarray(height(x + ring_mm * np.cos(a), y + ring_mm * np.sin(a)), float)
    return float(np.mean(ring) - np.asarray(height(np.array([x]), np.array([y])), float)[0])


_HARD: dict[str, Callable[[int], dict[str, Any]]] = {
    "glass": glass_spec,
    "cut": cut_spec,
    "steep": steep_spec,
    "features": features_spec,
}
#: Every family, by name.
FAMILIES = (*THESIS_KIND, *HARD)


def family_spec(family: str, seed: int) -> dict[str, Any]:
    """The ``substrate.surface`` table of one surface of ``family`` (parameters drawn from ``seed``)."""
    if family in _HARD:
        return _HARD[family](seed)
    return thesis_spec(family, seed)
