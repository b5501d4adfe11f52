"""Pixel blocks: the decoded display points averaged over b x b pixel tiles before the slope iteration (thesis §1.7).

A pixel block's mean display point, seen along the ray through the block's centre, is one observation of the
surface's gradient at the block's footprint (the ray model of :mod:`scopetwin.recon.fringes.slopes` unchanged). Only
blocks whose b^2 pixels are all decoded are kept: their centre is the mean pixel position exactly. Were the display
point an affine function of the pixel position over a block, the block's mean would be the display point of its
centre. It is not quite: the surface's short-wavelength content (glass's micro-waviness of tens of nm at 1-8 mm)
curves the display-point map f by f_rr ~ 3 µm per pixel^2 along the rows of the §1.10 camera (measured against the
per-pixel truth of rendered cut sheets), and a block of b pixels, each a box of one, averages f over a box of b
pixels: mean = f(centre) + (b^2 / 24)(f_rr + f_cc), about 1 µm at b = 3, a bias along the surface's own detail that
no noise model covers (at two display positions it was the second largest error of the shape on such sheets, 2.3 nm
of 4 nm). The second differences of neighbouring block means along the block rows and columns are b^2 f_rr and
b^2 f_cc (to second order), so :func:`block_centre_values` takes (D_r + D_c) / 24 off each mean: a component of
wavelength 4.4 blocks (1 mm along the rows at b = 3) is then kept to 0.98 instead of 0.91. It raises the block's
noise variance by :data:`CENTRE_VARIANCE_FACTOR` (1.37).

The block size is chosen from what the slope integration resolves: the cubic B-spline of knot spacing s
(:class:`scopetwin.recon.fringes.integration.SlopeIntegrator`) follows no gradient component shorter than a
wavelength of 2 s, and averaging over a footprint w scales a component of wavelength lambda by
sinc(w / lambda). The block's footprint (the geometric mean of its two edges) is at most s / :data:`BLOCKS_PER_KNOT`
= s / 2: at least four blocks in every knot cell, each with two slope equations for the cell's one new
coefficient. On the ``thesis-1.10-fringes`` preset (pixel footprint 39 x 75 µm, geometric mean 54 µm at the image
centre, s = 0.4 mm) that is 3 x 3 pixels, 0.12 x 0.23 mm: a component of wavelength 2 s is kept to 0.88 or better,
one of 4 s to 0.97; 47,000 blocks from 422,000 decoded pixels. On a 4x binned camera (216 µm) every pixel stays its
own observation.

Uncertainty of a block mean: the decoder's per-pixel sigma_u (phase-step residuals, :mod:`.phase`) leaves out any
error that is the same in every frame of a pixel, such as the render's (or a real optical system's) sampling error of
the pixel footprint on the display, which shifts each pixel's display point without a phase residual. The scatter
of a block's display points about their best affine fit in the pixel offsets shows it: with n = b^2 pixels its mean
square, over n - 3 degrees of freedom, estimates the per-pixel variance of everything that is independent from pixel
to pixel. Its ratio to the decoder's variance, pooled over all blocks (per direction, the median with the
chi^2_(n-3) median's correction: a few blocks over an unwrapping slip or an edge do not move it), is the factor
F^2 >= 1 by which every pixel's variance is scaled: sigma_block^2 = F^2 mean_i sigma_i^2 / n. A factor, not an added
constant: the pixels the decoder trusts less (low modulation) scatter more, and an added constant would flatten
their weights (on rendered glass at two display positions, the absolute height's error doubled with it). Where
every pixel stays its own observation (block 1) F is found the same way over 3 x 3 tiles and scales each pixel's
sigma.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from scopetwin.recon.fringes.phase import DisplayCoordinates, FringeDecodingError
from scopetwin.recon.substrate import Substrate2D
from scopetwin.scenes.camera import Camera

#: A block's footprint on the substrate is at most the knot spacing divided by this (module docstring).
BLOCKS_PER_KNOT = 2.0
#: Largest automatic block edge, pixels.
MAX_BLOCK_PX = 8
#: The block mean's second-order term: a box of b pixels (each pixel's own footprint a box of one) has the offset
#: variance b^2 / 12 in pixel units along each axis, so mean = centre + (b^2 / 24) (f_rr + f_cc) for a display-point
#: map f of curvature f_rr, f_cc per pixel^2; the second differences of neighbouring block means are b^2 f'' (module
#: docstring).
SECOND_ORDER_DIVISOR = 24.0
#: Variance of the corrected value relative to the plain mean's: (1 + 4 + 1) / 24^2 more per axis, and the mean's
#: own share in its second differences (-2 / 24 twice) (module docstring).
CENTRE_VARIANCE_FACTOR = (1.0 + 4.0 / 24.0) ** 2 + 4.0 / 24.0**2
#: Tile edge over which the unstated per-pixel noise is found when every pixel stays its own observation, pixels.
NOISE_TILE_PX = 3


@dataclass(frozen=True)
class BlockNoise:
    """How much larger the per-pixel display-point scatter is than the decoder's sigma (u and v; F >= 1)."""

    factor_u: float
    factor_v: float


def pixel_footprint_mm(camera: Camera, sub: Substrate2D) -> float:
    """Edge of the square of one pixel's footprint area on the substrate's base plane at the image centre, mm (the
    camera's rays through the centre pixel and its neighbours meet the plane z = 0 of the substrate's frame; the
    footprint is longer along the oblique view than across it, this is the geometric mean of the two)."""
    cx, cy = 0.5 * camera.nx, 0.5 * camera.ny
    px = np.array([[cx, cy], [cx + 1.0, cy], [cx, cy + 1.0]])
    o, d = camera.rays(px)
    o, d = sub.frame.to_local(o), sub.frame.vectors_to_local(d)
    with np.errstate(divide="ignore", invalid="ignore"):
        hit = o - (o[:, 2] / d[:, 2])[:, None] * d
    step = np.hypot(*(hit[1:, :2] - hit[0, :2]).T)
    return float(np.sqrt(step[0] * step[1])) if np.all(np.isfinite(step)) else float("inf")


def block_size(camera: Camera, sub: Substrate2D, knot_spacing_mm: float) -> int:
    """The largest block edge (pixels, 1 to :data:`MAX_BLOCK_PX`) whose footprint on the substrate is at most
    ``knot_spacing_mm`` / :data:`BLOCKS_PER_KNOT` (module docstring)."""
    foot = pixel_footprint_mm(camera, sub)
    if not (np.isfinite(foot) and foot > 0):
        return 1
    return int(np.clip(np.floor(knot_spacing_mm / (BLOCKS_PER_KNOT * foot)), 1, MAX_BLOCK_PX))


def _tiles(a: NDArray[Any], b: int) -> NDArray[Any]:
    """(rows, cols) -> (rows // b, cols // b, b * b): each full b x b tile's pixels on the last axis."""
    r, c = a.shape[0] // b, a.shape[1] // b
    return a[: r * b, : c * b].reshape(r, b, c, b).transpose(0, 2, 1, 3).reshape(r, c, b * b)


def block_centre_values(means: NDArray[Any]) -> NDArray[Any]:
    """The display point of each block's centre ray from the blocks' mean display points (rows, cols; NaN where a
    block is not decoded): the second-order term of the module docstring removed, mean - (D_r + D_c) / 24, with D_r,
    D_c the second differences of the means along the block rows and columns; an axis whose two neighbours are not
    both decoded is left uncorrected."""
    out = means.copy()
    for axis in (0, 1):
        d2 = np.zeros_like(means)
        inner = [slice(None), slice(None)]
        inner[axis] = slice(1, -1)
        lo, hi = list(inner), list(inner)
        lo[axis], hi[axis] = slice(None, -2), slice(2, None)
        d2[tuple(inner)] = means[tuple(hi)] - 2.0 * means[tuple(inner)] + means[tuple(lo)]
        out -= np.where(np.isfinite(d2), d2, 0.0) / SECOND_ORDER_DIVISOR
    return out


def block_average(coords: DisplayCoordinates, block: int) -> tuple[DisplayCoordinates, BlockNoise]:
    """The display points averaged over full ``block`` x ``block`` pixel tiles, with the uncertainty of the module
    docstring (``block`` 1: every pixel kept, its sigma scaled by the factor found over 3 x 3 tiles).

    Returns
    -------
    DisplayCoordinates
        One entry per tile (rows // block, cols // block), ``block`` set: entry (r, c) is the tile of pixels
        [r b, (r + 1) b) x [c b, (c + 1) b), seen along the ray through its centre.
    BlockNoise
        The pooled factors F of the per-pixel sigma.

    Raises
    ------
    FringeDecodingError
        A block edge below 1, coordinates already averaged, or an image smaller than one block.
    """
    if block < 1:
        raise FringeDecodingError(f"the pixel block must be at least 1 pixel, got {block}")
    if coords.block != 1:
        raise FringeDecodingError(f"the display coordinates are already averaged over {coords.block}-pixel blocks")
    if coords.shape[0] < max(block, NOISE_TILE_PX) or coords.shape[1] < max(block, NOISE_TILE_PX):
        raise FringeDecodingError(f"an image of {coords.shape} pixels is smaller than one {block}-pixel block")
    if block == 1:  # every pixel its own observation: the unstated noise from 3 x 3 tiles, added to each pixel's
        _, noise = _averaged(coords, NOISE_TILE_PX)
        return replace(coords, u_std=noise.factor_u * coords.u_std, v_std=noise.factor_v * coords.v_std), noise
    return _averaged(coords, block)


def _averaged(coords: DisplayCoordinates, block: int) -> tuple[DisplayCoordinates, BlockNoise]:
    """:func:`block_average` for ``block`` >= 2."""
    n = block * block
    full = np.all(_tiles(coords.valid, block), axis=-1)
    off = np.arange(block, dtype=np.float64) - 0.5 * (block - 1)
    dy, dx = (g.reshape(n) for g in np.meshgrid(off, off, indexing="ij"))
    design = np.column_stack([np.ones(n), dx, dy])
    residual_map = np.eye(n) - design @ np.linalg.pinv(design)  # I - H: the affine fit's residuals
    median_factor = float(chi2.median(n - 3) / (n - 3))
    means, stds, factors = [], [], []
    for value, std in ((coords.u, coords.u_std), (coords.v, coords.v_std)):
        tiles = np.where(full[..., None], _tiles(np.where(coords.valid, value, 0.0), block), 0.0)
        var = _tiles(np.where(coords.valid, std, 0.0) ** 2, block).mean(axis=-1)
        means.append(block_centre_values(np.where(full, tiles.mean(axis=-1), np.nan)))
        if full.any():
            scatter = np.einsum("...i,ji->...j", tiles[full], residual_map)
            ms = np.sum(scatter * scatter, axis=-1) / (n - 3)
            ratio = max(float(np.median(ms / np.maximum(var[full], 1e-300))) / median_factor, 1.0)
        else:
            ratio = 1.0
        factors.append(np.sqrt(ratio))
        stds.append(np.sqrt(ratio * var / n * CENTRE_VARIANCE_FACTOR))
    no = np.zeros(full.shape, dtype=bool)
    low = np.any(_tiles(coords.low_modulation, block), axis=-1) & ~full
    averaged = DisplayCoordinates(
        np.where(full, means[0], np.nan),
        np.where(full, means[1], np.nan),
        np.where(full, stds[0], np.inf),
        np.where(full, stds[1], np.inf),
        full,
        low,
        no,
        ~full & ~low,
        block,
    )
    return averaged, BlockNoise(float(factors[0]), float(factors[1]))
