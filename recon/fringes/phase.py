"""Phase-shift decoding of fringe images: wrapped phase, background, modulation and temporal unwrapping.

Phase-measuring deflectometry replaces the marker pattern of the thesis's §1.10 setup by a display showing sinusoidal
fringes. A frame of direction d in {x, y}, period p (mm) and shift delta (rad) is ideally

    I = A + B cos(2 pi u_d / p + delta)

with u_d the display coordinate (mm, the pattern plane's own T_x / T_y from its centre) seen by the pixel. N >= 4
shifts delta_k = 2 pi k / N of one period give, per pixel (the N-step least-squares estimate)

    C = sum_k I_k cos(delta_k) = N B cos(phi) / 2,   S = sum_k I_k sin(delta_k) = -N B sin(phi) / 2,
    phi = atan2(-S, C),   B = 2 sqrt(C^2 + S^2) / N,   A = mean_k I_k,

and, for independent image noise of standard deviation sigma_I, the phase noise sigma_phi = sqrt(2 / N) sigma_I / B.

Temporal multi-frequency unwrapping: the coarsest period exceeds the display, so its phase is unambiguous and gives
u directly; each finer period's fringe order is the one that agrees with the coarser estimate, and the finest
period's phase sets u and its uncertainty. A pixel is valid where its modulation is high enough, every period
agrees with the coarser one within ``max_disagreement`` of its period, and u lies on the display.

Everything is vectorised over pixels; images are float arrays (N, rows, cols) in any linear unit (DN).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import nnls

from scopetwin.recon.errors import ReconstructionError
from scopetwin.recon.parallel import thread_map
from scopetwin.scenes.geometry import Array

#: Fewest phase steps per period: with N >= 4 the fit of (A, B, phi) leaves a residual to estimate the noise from.
MIN_STEPS = 4


class FringeDecodingError(ReconstructionError):
    """Fringe images that cannot be decoded (too few steps, mismatched shapes, periods that cannot be unwrapped)."""


@dataclass(frozen=True)
class PhaseMap:
    """The N-step estimate of one period's frames, per pixel.

    Attributes
    ----------
    phase : ndarray
        Wrapped phase phi in (-pi, pi], rad.
    background : ndarray
        A, the images' unit.
    modulation : ndarray
        B, the images' unit.
    phase_std : ndarray
        sigma_phi = sqrt(2/N) sigma_I / B, rad (inf where B = 0).
    noise_std : ndarray
        sigma_I used, the images' unit (given, or from the noise model fitted to the residuals).
    """

    phase: Array
    background: Array
    modulation: Array
    phase_std: Array
    noise_std: Array


@dataclass(frozen=True)
class NoiseModel:
    """Image noise variance as an affine function of the signal: sigma_I^2 = read + shot * A (EMVA 1288 linear model,
    :mod:`scopetwin.scenes.emva1288`: dark noise plus photon noise proportional to the mean signal).

    Attributes
    ----------
    read : float
        Signal-independent variance, (image unit)^2.
    shot : float
        Variance per unit of signal, image unit.
    """

    read: float
    shot: float

    def std(self, signal: ArrayLike) -> Array:
        """sigma_I at mean signal ``signal``."""
        return np.sqrt(np.clip(self.read + self.shot * np.asarray(signal, dtype=np.float64), 1e-30, None))


def phase_shifts(n_steps: int) -> Array:
    """The shifts delta_k = 2 pi k / N, k = 0..N-1, rad."""
    return 2.0 * np.pi * np.arange(n_steps) / n_steps


def _check_stack(images: ArrayLike) -> Array:
    stack = np.asarray(images)
    if stack.dtype not in (np.float32, np.float64):
        stack = stack.astype(np.float64)
    if stack.ndim < 2:
        raise FringeDecodingError(f"a phase-shift stack needs shape (N, ...) with N >= {MIN_STEPS}, got {stack.shape}")
    if stack.shape[0] < MIN_STEPS:
        raise FringeDecodingError(f"phase shifting needs at least {MIN_STEPS} steps per period, got {stack.shape[0]}")
    if not np.all(np.isfinite(stack)):
        raise FringeDecodingError("fringe images hold non-finite values (NaN or inf)")
    return stack


def _fit(stack: Array) -> tuple[Array, Array, Array, Array]:
    """(phi, A, B, residual sum of squares) of the N-step fit, per pixel.

    Accumulated one frame at a time in float64 (a float32 stack is not copied whole); the shifts whose cosine or
    sine is zero add nothing and are skipped. 1, cos(delta_k), sin(delta_k) are orthogonal over the N steps
    (sum cos^2 = sum sin^2 = N/2), so the residual is the frames' energy less the fitted part's:
    rss = sum_k I_k^2 - N A^2 - (2/N)(C^2 + S^2).
    """
    n = stack.shape[0]
    delta = phase_shifts(n)
    cos, sin = np.cos(delta), np.sin(delta)
    c = np.zeros(stack.shape[1:])
    s = np.zeros(stack.shape[1:])
    a = np.zeros(stack.shape[1:])
    sq = np.zeros(stack.shape[1:])
    buf = np.empty(stack.shape[1:])
    for k in range(n):
        f = stack[k]  # float32 or float64: the ufuncs below compute into float64 outputs without a converted copy
        a += f
        np.multiply(f, f, out=buf, dtype=np.float64)
        sq += buf
        for acc, w in ((c, cos[k]), (s, sin[k])):  # in place: no temporary per frame
            if abs(w) <= 1e-12:
                continue
            if w == 1.0:
                acc += f
            elif w == -1.0:
                acc -= f
            else:
                np.multiply(f, w, out=buf, dtype=np.float64)
                acc += buf
    a /= n
    phi = np.arctan2(-s, c)
    b = 2.0 * np.hypot(c, s) / n
    rss = np.maximum(sq - n * a * a - (2.0 / n) * (c * c + s * s), 0.0)
    return phi, a, b, rss


def fit_noise_model(stacks: Sequence[ArrayLike], mask: ArrayLike | None = None) -> NoiseModel:
    """The image noise model sigma_I^2 = read + shot * A from the residuals of the N-step fits (pooled over pixels).

    Each pixel's residual sum of squares over its N frames has expectation (N - 3) sigma_I^2 (three parameters
    fitted); regressing rss / (N - 3) on the background A over all pixels (of ``mask``) gives the affine model.

    Parameters
    ----------
    stacks : sequence of array_like, each (N_i, ...)
        Phase-shift stacks of the same pixels (each period and direction).
    mask : array_like of bool, optional
        The pixels to pool (default: all).

    Raises
    ------
    FringeDecodingError
        No pixels to pool, or a stack with fewer than four steps.
    """
    pooled = []
    for images in stacks:
        stack = _check_stack(images)
        _, a, _, rss = _fit(stack)
        sel = np.ones(a.shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
        pooled.append((a[sel], rss[sel] / (stack.shape[0] - 3)))
    return _noise_model(pooled)


def _noise_model(pooled: Sequence[tuple[Array, Array]]) -> NoiseModel:
    """:func:`fit_noise_model` from (background A, rss / (N - 3)) of the pooled pixels of each stack."""
    x = np.concatenate([p[0] for p in pooled])
    y = np.concatenate([p[1] for p in pooled])
    if y.size < 10:
        raise FringeDecodingError("too few pixels to estimate the image noise from the fringe fits")
    # both terms non-negative (non-negative least squares): over a narrow range of signal the split between them is
    # ill-determined, but their sum at the signals seen is not
    scale = max(float(np.mean(x)), 1e-30)
    # on the 2 x 2 triangle R of the design (the same minimiser: |X b - y|^2 = |R b - R^-T X^T y|^2 + const), R from
    # the Cholesky factor of X^T X (five sums over the 10^5-10^6 rows, not their QR: 0.2 s of a 2 s reconstruction);
    # where all rows have one signal (X^T X singular), R from the QR
    xs = x / scale
    gram = np.array([[float(x.size), float(xs.sum())], [float(xs.sum()), float(xs @ xs)]])
    try:
        r = np.linalg.cholesky(gram).T
        qty = np.linalg.solve(r.T, np.array([float(y.sum()), float(xs @ y)]))
    except np.linalg.LinAlgError:
        q, r = np.linalg.qr(np.column_stack([np.ones_like(xs), xs]))
        qty = q.T @ y
    (read, shot), _ = nnls(r, qty)
    return NoiseModel(float(read), float(shot) / scale)


def phase_shift(images: ArrayLike, noise: float | ArrayLike | NoiseModel) -> PhaseMap:
    """N-step phase retrieval of one period's frames (module docstring), per pixel.

    Parameters
    ----------
    images : array_like, (N, ...)
        The N >= 4 frames of shifts 2 pi k / N, in order.
    noise : float, array_like or NoiseModel
        sigma_I: one value, one per pixel, or the affine model (evaluated at each pixel's A).

    Returns
    -------
    PhaseMap

    Raises
    ------
    FringeDecodingError
        Fewer than four frames, non-finite values, or a negative noise.
    """
    stack = _check_stack(images)
    return _phase_map(_fit(stack), stack.shape[0], noise)


def _phase_map(fit: tuple[Array, Array, Array, Array], n: int, noise: float | ArrayLike | NoiseModel) -> PhaseMap:
    """The :class:`PhaseMap` of an N-step fit (:func:`_fit`) with the image noise ``noise``."""
    phi, a, b, _ = fit
    if isinstance(noise, NoiseModel):
        sigma = noise.std(a)
    else:
        sigma = np.broadcast_to(np.asarray(noise, dtype=np.float64), a.shape)
        if np.any(~(sigma >= 0)):
            raise FringeDecodingError("the image noise sigma_I must be >= 0")
    with np.errstate(divide="ignore"):
        std = np.where(b > 0, np.sqrt(2.0 / n) * sigma / np.where(b > 0, b, 1.0), np.inf)
    return PhaseMap(phi, a, b, std, np.asarray(sigma, dtype=np.float64))


@dataclass(frozen=True)
class Unwrapped:
    """The display coordinate along one direction, per pixel, after temporal unwrapping.

    Attributes
    ----------
    coordinate : ndarray
        u (mm), NaN where invalid.
    std : ndarray
        Its standard uncertainty, mm (from the finest period's phase noise).
    consistent : ndarray of bool
        Every period agreed with the coarser estimate within ``max_disagreement`` of its period.
    modulation_ok : ndarray of bool
        The modulation of every period reaches the threshold.
    """

    coordinate: Array
    std: Array
    consistent: NDArray[np.bool_]
    modulation_ok: NDArray[np.bool_]


def unwrap_temporal(
    maps: Sequence[PhaseMap],
    periods: Sequence[float],
    min_modulation: float = 0.0,
    max_disagreement: float = 0.25,
) -> Unwrapped:
    """Temporal multi-frequency unwrapping: the display coordinate from phases of several periods.

    The coarsest period p_0 exceeds the display (its phase in (-pi, pi] maps u in (-p_0/2, p_0/2] one to one):
    u_0 = p_0 phi_0 / (2 pi). For each finer period p_k the fringe order is
    m = round((2 pi u_{k-1} / p_k - phi_k) / (2 pi)) and u_k = p_k (phi_k + 2 pi m) / (2 pi); the pixel is
    inconsistent where |u_{k-1} - u_k| > ``max_disagreement`` p_k (the coarser estimate was off by a fringe's
    fraction that makes the order uncertain). u is the finest period's, sigma_u = p sigma_phi / (2 pi).

    Parameters
    ----------
    maps : sequence of PhaseMap
        The phase maps, in the order of ``periods``.
    periods : sequence of float
        Periods, mm, strictly decreasing (coarsest first).
    min_modulation : float
        Smallest modulation B of a valid pixel (every period), the images' unit.
    max_disagreement : float
        Largest |u_{k-1} - u_k| as a fraction of p_k.

    Raises
    ------
    FringeDecodingError
        Periods not positive and strictly decreasing, or a count that differs from the maps'.
    """
    p = np.asarray(periods, dtype=np.float64)
    if len(maps) != len(p) or len(p) == 0:
        raise FringeDecodingError(f"{len(maps)} phase maps for {len(p)} periods: give one map per period")
    if np.any(~(p > 0)) or np.any(np.diff(p) >= 0):
        raise FringeDecodingError(f"fringe periods must be positive and strictly decreasing (coarsest first), got {p}")
    u = p[0] * maps[0].phase / (2.0 * np.pi)
    consistent = np.ones(u.shape, dtype=bool)
    mod_ok = maps[0].modulation >= min_modulation
    std = p[0] * maps[0].phase_std / (2.0 * np.pi)
    for pk, m in zip(p[1:], maps[1:], strict=True):
        order = np.round((2.0 * np.pi * u / pk - m.phase) / (2.0 * np.pi))
        uk = pk * (m.phase + 2.0 * np.pi * order) / (2.0 * np.pi)
        consistent &= np.abs(uk - u) <= max_disagreement * pk
        mod_ok &= m.modulation >= min_modulation
        u, std = uk, pk * m.phase_std / (2.0 * np.pi)
    return Unwrapped(u, std, consistent, mod_ok)


@dataclass(frozen=True)
class DisplayCoordinates:
    """The display point (u, v) each camera pixel sees, with uncertainty and validity (rows, cols).

    Attributes
    ----------
    u, v : ndarray
        Display coordinates along the pattern plane's T_x, T_y from its centre, mm (NaN where not ``valid``).
    u_std, v_std : ndarray
        Standard uncertainties, mm.
    valid : ndarray of bool
        Decoded: modulation high enough, unwrapping consistent, on the display.
    low_modulation, inconsistent, off_display : ndarray of bool
        Why a pixel is not valid (a pixel may have several reasons).
    block : int
        1: one entry per camera pixel; b > 1: one per b x b pixel tile, the tile's mean display point seen along the
        ray through its centre (:func:`scopetwin.recon.fringes.blocks.block_average`).
    """

    u: Array
    v: Array
    u_std: Array
    v_std: Array
    valid: NDArray[np.bool_]
    low_modulation: NDArray[np.bool_]
    inconsistent: NDArray[np.bool_]
    off_display: NDArray[np.bool_]
    block: int = 1

    @property
    def shape(self) -> tuple[int, ...]:
        return tuple(self.u.shape)

    @classmethod
    def from_arrays(
        cls, uv: ArrayLike, uv_std: ArrayLike | float, valid: ArrayLike | None = None
    ) -> DisplayCoordinates:
        """From a (rows, cols, 2) map of (u, v), mm (NaN: not seen), and its standard uncertainty (mm).

        For display points known otherwise (a truth map, another decoder).
        """
        a = np.asarray(uv, dtype=np.float64)
        if a.ndim != 3 or a.shape[2] != 2:
            raise FringeDecodingError(f"display coordinates need shape (rows, cols, 2), got {a.shape}")
        s = np.broadcast_to(np.asarray(uv_std, dtype=np.float64), a.shape).copy()
        ok = np.all(np.isfinite(a), axis=-1) & np.all(np.isfinite(s) & (s > 0), axis=-1)
        if valid is not None:
            ok &= np.asarray(valid, dtype=bool)
        no = np.zeros(ok.shape, dtype=bool)
        return cls(
            np.where(ok, a[..., 0], np.nan), np.where(ok, a[..., 1], np.nan), s[..., 0], s[..., 1], ok, no, no, no
        )


def _phase_maps(stacks: list[Array], noise: float | ArrayLike | NoiseModel | None) -> list[PhaseMap]:
    """The phase map of every stack, the stacks side by side in threads; each stack fitted once (the noise model,
    fitted where ``noise`` is None, and the phases share the fits)."""
    fits = thread_map(_fit, stacks)
    if noise is None:
        b_first = fits[0][2]
        sel = b_first > 0.1 * float(b_first.max())
        noise = _noise_model([(f[1][sel], f[3][sel] / (s.shape[0] - 3)) for f, s in zip(fits, stacks, strict=True)])
    sigma_i = noise
    return thread_map(lambda k: _phase_map(fits[k], stacks[k].shape[0], sigma_i), range(len(stacks)))


def decode_display(
    frames_x: Sequence[ArrayLike],
    frames_y: Sequence[ArrayLike],
    periods: Sequence[float],
    display_size: tuple[float, float],
    noise: float | ArrayLike | NoiseModel | None = None,
    min_modulation: float | None = None,
    max_disagreement: float = 0.25,
) -> DisplayCoordinates:
    """The display point of every pixel from phase-shifted fringe frames in x and y at several periods.

    Parameters
    ----------
    frames_x, frames_y : sequence of array_like, each (N, rows, cols)
        One phase-shift stack per period (in the order of ``periods``) with fringes along the display's T_x
        (``frames_x``: I = A + B cos(2 pi u / p + delta)) and along T_y.
    periods : sequence of float
        Fringe periods, mm, coarsest first; the coarsest must exceed the display's extent in both directions.
    display_size : (float, float)
        The display's extent along T_x and T_y, mm (centred on the pattern frame's origin).
    noise : float, array_like, NoiseModel or None
        sigma_I of the images; None: fitted from the N-step residuals of all stacks (:func:`fit_noise_model`,
        over the pixels whose modulation exceeds a tenth of the largest).
    min_modulation : float, optional
        Smallest modulation of a valid pixel; default 5 sigma_I (there the phase noise is below 0.15 rad at N = 4).
    max_disagreement : float
        See :func:`unwrap_temporal`.

    Returns
    -------
    DisplayCoordinates

    Raises
    ------
    FringeDecodingError
        Stacks missing or of different pixel shapes, a display extent not positive, or a coarsest period that
        does not exceed the display (the phase would be ambiguous).
    """
    sx, sy = (float(v) for v in display_size)
    if not (sx > 0 and sy > 0):
        raise FringeDecodingError(f"the display size must be positive, got {display_size}")
    if len(frames_x) != len(periods) or len(frames_y) != len(periods):
        raise FringeDecodingError(
            f"give one stack per period in each direction: {len(periods)} periods, "
            f"{len(frames_x)} x-stacks, {len(frames_y)} y-stacks"
        )
    stacks = [_check_stack(f) for f in (*frames_x, *frames_y)]
    shapes = {s.shape[1:] for s in stacks}
    if len(shapes) != 1:
        raise FringeDecodingError(f"fringe stacks of different image shapes: {sorted(shapes)}")
    if not float(periods[0]) > max(sx, sy):
        raise FringeDecodingError(
            f"the coarsest period {periods[0]} mm must exceed the display ({sx} x {sy} mm) to be unambiguous"
        )
    maps = _phase_maps(stacks, noise)
    maps_x, maps_y = maps[: len(periods)], maps[len(periods) :]
    if min_modulation is None:
        min_modulation = 5.0 * float(np.median(maps_x[0].noise_std))
    level = min_modulation
    ux, uy = thread_map(lambda m: unwrap_temporal(m, periods, level, max_disagreement), [maps_x, maps_y])
    low = ~(ux.modulation_ok & uy.modulation_ok)
    inconsistent = ~(ux.consistent & uy.consistent)
    off = ~((np.abs(ux.coordinate) <= 0.5 * sx) & (np.abs(uy.coordinate) <= 0.5 * sy))
    valid = ~(low | inconsistent | off)
    return DisplayCoordinates(
        np.where(valid, ux.coordinate, np.nan),
        np.where(valid, uy.coordinate, np.nan),
        ux.std,
        uy.std,
        valid,
        low,
        inconsistent & ~low,
        off & ~low,
    )
