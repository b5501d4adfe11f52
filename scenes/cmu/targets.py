"""Test objects of the unit (thesis §5.1.2, §5.2.2): the Siemens star with its square frame, and dummy cells.

Both are written once against an array namespace (numpy, or Dr.Jit via :mod:`scopetwin.scenes.mitsuba.cmu`), so the
renderer and the numpy reference evaluate the same function.
"""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.cmu.layout import CellsSpec, TargetSpec

NP = SimpleNamespace(sqrt=np.sqrt, atan2=np.arctan2, sin=np.sin, where=np.where, abs=np.abs, maximum=np.maximum)


def siemens_star(x: Any, y: Any, spec: TargetSpec, xp: Any = NP) -> Any:
    """Transmission of the chrome-on-glass Siemens star with its frame (§5.2.2) at object point (x, y), mm.

    ``spokes`` clear spokes alternate with as many chrome spokes inside ``star_radius`` (30 spokes: the
    period at radius r is 2 pi r / 30, so a spoke is pi r / 30 wide: delta x = pi r_min / N_spokes); a clear square
    line of width ``frame_line`` whose centre line has side ``frame_side`` surrounds it; all else is chrome.
    """
    r2 = x * x + y * y
    theta = xp.atan2(y, x)
    spoke = (r2 <= spec.star_radius**2) & (xp.sin(spec.spokes * theta) > 0)
    cheb = xp.maximum(xp.abs(x), xp.abs(y))
    line = xp.abs(cheb - 0.5 * spec.frame_side) <= 0.5 * spec.frame_line
    return xp.where(spoke | line, 1.0, 0.0)


def dummy_cells(spec: CellsSpec, field: tuple[float, float], texel: float = 0.5e-3) -> tuple[NDArray, float, float]:
    """Raster (row 0 at -y) of ``count`` elliptical cells of length x width (§5.1.2) over the field, seeded.

    Returns (image, x_min, y_min); texel (mm) is the raster step. Cells have a brighter nucleus (half size).
    """
    w, h = field
    nx, ny = int(np.ceil(w / texel)), int(np.ceil(h / texel))
    rng = np.random.default_rng(spec.seed)
    img = np.zeros((ny, nx), dtype=np.float32)
    xs = (np.arange(nx) + 0.5) * texel - 0.5 * w
    ys = (np.arange(ny) + 0.5) * texel - 0.5 * h
    a, b = 0.5 * spec.length, 0.5 * spec.width
    for _ in range(spec.count):
        cx, cy = rng.uniform(-0.5 * w, 0.5 * w), rng.uniform(-0.5 * h, 0.5 * h)
        phi = rng.uniform(0, np.pi)
        c, s = np.cos(phi), np.sin(phi)
        ix = slice(max(0, int((cx - a + 0.5 * w) / texel)), min(nx, int((cx + a + 0.5 * w) / texel) + 1))
        iy = slice(max(0, int((cy - a + 0.5 * h) / texel)), min(ny, int((cy + a + 0.5 * h) / texel) + 1))
        gx, gy = np.meshgrid(xs[ix] - cx, ys[iy] - cy)
        u, v = gx * c + gy * s, -gx * s + gy * c
        q = (u / a) ** 2 + (v / b) ** 2
        img[iy, ix] = np.maximum(img[iy, ix], np.where(q <= 1, np.where(q <= 0.25, 1.0, 0.4), 0.0))
    return img, -0.5 * w, -0.5 * h
