"""Beam-splitter plates with height maps (thesis §5.1.1, Fig. 5.1) and the glass they are made of.

The measured maps of Fig. 5.1 are images in the thesis; here a plate's coated surface is a *modelled* map: a
spherical bow whose range (max - min over the whole 25.5 x 36 mm plate) is the thesis's measured range (3.6, 9.4,
10.2 µm), plus a smooth residual (Gaussian-filtered white noise, correlation ~5 mm, given RMS, seeded). A
measured or reconstructed map (the deflectometry part's output, a height-map EXR of docs/contract.md in plate-local mm)
replaces the model when ``height_map`` is given.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy.ndimage import gaussian_filter

from scopetwin.scenes.cmu.layout import ElementSpec, PlateSpec
from scopetwin.scenes.surface import HeightMap

#: Node spacing of the modelled maps, mm.
NODE_MM = 0.5


def bow_radius(range_um: float, width: float, height: float) -> float:
    """Radius of curvature (mm) of a centred sphere whose sag range over a width x height plate is ``range_um``.

    Paraxial sag z = r^2/(2R); the largest r^2 is at the corners: R = ((w/2)^2 + (h/2)^2) / (2 range).
    """
    if range_um <= 0:
        return float("inf")
    return ((0.5 * width) ** 2 + (0.5 * height) ** 2) / (2.0 * range_um * 1e-3)


def plate_heightmap(spec: ElementSpec, plate: PlateSpec) -> HeightMap:
    """Height map (plate-local mm) of the coated surface: bow + residual, or the EXR map named by the spec.

    The bow is concave toward the incident light (``spec.concave``): h = +r^2/(2R) - mean, so the plate acts as a
    weak converging mirror, which makes the refocused images smaller (thesis Table 5.1).
    """
    if spec.height_map is not None:
        from scopetwin.scenes.io import read_heightmap

        return read_heightmap(spec.height_map)
    hw, hh = 0.5 * plate.width, 0.5 * plate.height
    nx = int(round(plate.width / NODE_MM)) + 1
    ny = int(round(plate.height / NODE_MM)) + 1
    x = np.linspace(-hw, hw, nx)
    y = np.linspace(-hh, hh, ny)
    xx, yy = np.meshgrid(x, y)
    r = bow_radius(spec.bow_range_um, plate.width, plate.height)
    z = np.zeros_like(xx) if not np.isfinite(r) else (xx**2 + yy**2) / (2.0 * r)
    if not spec.concave:
        z = -z
    if spec.residual_rms_um > 0:
        rng = np.random.default_rng(spec.residual_seed)
        noise = gaussian_filter(rng.standard_normal(xx.shape), sigma=5.0 / NODE_MM, mode="reflect")
        noise -= noise.mean()
        z = z + noise * (spec.residual_rms_um * 1e-3 / noise.std())
    return HeightMap(z - z.mean(), -hw, hw, -hh, hh)


def fused_silica_index(wl_nm: ArrayLike) -> np.ndarray:
    """Refractive index of fused silica, Malitson's Sellmeier formula (J. Opt. Soc. Am. 55, 1205, 1965)."""
    l2 = (np.asarray(wl_nm, dtype=np.float64) * 1e-3) ** 2
    b = (0.6961663, 0.4079426, 0.8974794)
    c = (0.0684043**2, 0.1162414**2, 9.896161**2)
    return np.sqrt(1.0 + sum(bi * l2 / (l2 - ci) for bi, ci in zip(b, c, strict=True)))
