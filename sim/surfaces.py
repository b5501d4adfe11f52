"""Simulated substrate surfaces (thesis §1.9), PSD surfaces of real glass, and analytic test surfaces.

Two random families: the thesis's §1.9 generator (white noise, Gaussian low-pass: exactly band-limited) and
Gaussian random fields drawn from a power spectral density (:func:`psd_noise`) as glass flatness and waviness
are specified — the K-correlation (ABC) model and a power law with roll-off. Either can carry an nm-level
broadband part (:func:`broadband_noise`, flat spectrum over a band of short wavelengths), which decides how
well the surface extrapolates into the frame regions (docs/rendering.md, "Absolute height").

Every generated surface satisfies the a-priori knowledge the reconstruction
relies on (thesis §1.4, §1.9): the maxima of both holding-frame regions are 0
(the substrate touches the frame there), and the peak-to-valley range over
the substrate is the requested one.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray
from scipy.interpolate import RectBivariateSpline
from scipy.optimize import brentq

from scopetwin.scenes.errors import GeometryError, SetupError
from scopetwin.scenes.setup import FeatureSpec, Setup, SubstrateSpec, SurfaceSpec
from scopetwin.scenes.surface import HeightMap

Array = NDArray[np.float64]


def _grid(spec: SurfaceSpec, size: tuple[float, float]) -> tuple[Array, Array]:
    nx, ny = spec.grid
    x = np.linspace(-0.5 * size[0], 0.5 * size[0], nx)
    y = np.linspace(-0.5 * size[1], 0.5 * size[1], ny)
    return np.meshgrid(x, y)


def lowpass_noise(shape: tuple[int, int], spacing: tuple[float, float], correlation_length: float, seed: int) -> Array:
    """White noise in [0, 1] low-pass filtered in the Fourier domain (thesis §1.9, Fig. 1.9 a-b).

    The filter is Gaussian, ``exp(-2 pi^2 sigma^2 |f|^2)`` with sigma = ``correlation_length``
    (mm): the noise is smoothed by a Gaussian kernel of that standard deviation. The
    field is generated on a grid padded by 4 sigma on each side and cropped, so the
    FFT's periodic wrap-around does not correlate opposite edges.

    Parameters
    ----------
    shape : (ny, nx)
        Output grid.
    spacing : (dy, dx)
        Node spacing, mm.
    correlation_length : float
        sigma of the smoothing, mm.
    seed : int
        Seed of the white noise.
    """
    dy, dx = spacing
    pad_y = int(np.ceil(4 * correlation_length / dy))
    pad_x = int(np.ceil(4 * correlation_length / dx))
    ny, nx = shape[0] + 2 * pad_y, shape[1] + 2 * pad_x
    noise = np.random.default_rng(seed).random((ny, nx))
    spectrum = np.fft.rfft2(noise)
    fy = np.fft.fftfreq(ny, d=dy)[:, None]
    fx = np.fft.rfftfreq(nx, d=dx)[None, :]
    spectrum *= np.exp(-2.0 * np.pi**2 * correlation_length**2 * (fx**2 + fy**2))
    smooth = np.fft.irfft2(spectrum, s=(ny, nx))
    return smooth[pad_y : pad_y + shape[0], pad_x : pad_x + shape[1]]


def abc_psd(f: Array, b: float, c: float) -> Array:
    """The K-correlation (ABC) spectrum PSD(f) = 1 / (1 + (B f)^2)^(C/2) (A = 1), f in 1/mm, B in mm."""
    return np.asarray((1.0 + (b * f) ** 2) ** (-0.5 * c), dtype=np.float64)


def power_psd(f: Array, b: float, c: float) -> Array:
    """A power law f^-C rolled off (flat) below f = 1/B: PSD(f) = min(f B, 1)^-C (A = 1)."""
    return np.asarray(np.maximum(b * np.asarray(f), 1.0) ** (-c), dtype=np.float64)


def psd_noise(
    shape: tuple[int, int],
    spacing: tuple[float, float],
    psd: Callable[[Array], Array],
    seed: int | Sequence[int],
    pad: tuple[int, int] = (0, 0),
) -> Array:
    """A Gaussian random field with isotropic power spectral density ``psd(|f|)`` (any scale), by FFT.

    Complex white noise in the Fourier domain of a grid padded by ``pad`` = (rows, cols) on each side is
    weighted by sqrt(PSD) and transformed back; the crop removes the periodic wrap-around of the FFT.

    Parameters
    ----------
    shape : (ny, nx)
        Output grid.
    spacing : (dy, dx)
        Node spacing, mm.
    psd : callable
        PSD as a function of the radial spatial frequency ``|f|``, 1/mm (relative scale only).
    seed : int or sequence of int
        Seed of the white noise (``numpy.random.default_rng``).
    pad : (int, int)
        Padding in nodes on each side.
    """
    dy, dx = spacing
    ny, nx = shape[0] + 2 * pad[0], shape[1] + 2 * pad[1]
    white = np.random.default_rng(seed).standard_normal((ny, nx))
    spectrum = np.fft.rfft2(white)
    fy = np.fft.fftfreq(ny, d=dy)[:, None]
    fx = np.fft.rfftfreq(nx, d=dx)[None, :]
    spectrum *= np.sqrt(psd(np.sqrt(fx**2 + fy**2)))
    field = np.fft.irfft2(spectrum, s=(ny, nx))
    return np.asarray(field[pad[0] : pad[0] + shape[0], pad[1] : pad[1] + shape[1]], dtype=np.float64)


def broadband_noise(
    shape: tuple[int, int], spacing: tuple[float, float], rms_mm: float, band_mm: tuple[float, float], seed: int
) -> Array:
    """Flat-spectrum content at wavelengths in ``band_mm`` = (shortest, longest), mm, with RMS exactly ``rms_mm``.

    The nm-level short-wavelength part of real glass surfaces: it is what an exactly band-limited
    test surface lacks, and what limits the extrapolation into the frame regions.
    """
    if rms_mm <= 0:
        return np.zeros(shape)
    lo, hi = 1.0 / band_mm[1], 1.0 / band_mm[0]

    def flat(f: Array) -> Array:
        return ((f >= lo) & (f <= hi)).astype(np.float64)

    field = psd_noise(shape, spacing, flat, [int(seed), 14], pad=(0, 0))
    field -= field.mean()
    rms = float(np.sqrt(np.mean(field**2)))
    return field * (rms_mm / rms) if rms > 0 else field


def _edge_rows(z: Array, x: Array, y: Array, roi_length: float) -> tuple[Array, Array]:
    """Heights on the lines y = -roi/2 and y = +roi/2 at the x nodes, by the height map's bicubic interpolation."""
    xs, ys = x[0], y[:, 0]
    spline = RectBivariateSpline(ys, xs, z, kx=3, ky=3, s=0)
    half = 0.5 * roi_length
    return spline(-half, xs, grid=True)[0], spline(half, xs, grid=True)[0]


def level_on_frame(z: Array, y: Array, roi_length: float, x: Array | None = None) -> Array:
    """Tilt about the x axis and shift so both frame regions have maximum 0 (thesis §1.9, Fig. 1.9 c).

    Solves max_region1(z + a*y) = max_region2(z + a*y) for the tilt a (the difference is
    monotonic in a, so a bracketing root finder is exact), then subtracts the common maximum.
    With the x grid ``x``, each region's maximum also covers its inner edge y = -+roi/2 as the height map
    interpolates it (bicubic, which reproduces the tilt exactly): the regions start there, between two nodes, and
    a surface rising toward the ROI has its frame maximum on that edge — without it the truth's frame maxima
    lie up to ~0.05 µm above the frame (node spacing x slope) and every absolute-height error carries that.
    """
    r1 = y <= -0.5 * roi_length
    r2 = y >= 0.5 * roi_length
    if not (r1.any() and r2.any()):
        raise GeometryError("the height-map grid has no nodes in one of the frame regions")
    v1, v2 = z[r1], z[r2]
    y1, y2 = y[r1], y[r2]
    if x is not None:
        e1, e2 = _edge_rows(z, x, y, roi_length)
        half = 0.5 * roi_length
        v1, y1 = np.concatenate([v1, e1]), np.concatenate([y1, np.full(len(e1), -half)])
        v2, y2 = np.concatenate([v2, e2]), np.concatenate([y2, np.full(len(e2), half)])

    def diff(a: float) -> float:
        return float((v1 + a * y1).max() - (v2 + a * y2).max())

    span = float(y.max() - y.min())
    bound = 10.0 * (float(np.ptp(z)) + 1e-300) / max(span, 1e-12)
    a = brentq(diff, -bound, bound, xtol=1e-15, rtol=1e-15) if diff(-bound) * diff(bound) < 0 else 0.0
    return np.asarray(z + a * y - float((v1 + a * y1).max()))


def scale_to_range(z: Array, range_mm: float) -> Array:
    """Scale heights so max - min = ``range_mm`` (thesis §1.9, Fig. 1.9 d); zero stays zero."""
    ptp = float(np.ptp(z))
    if ptp == 0:
        return np.zeros_like(z)
    return z * (range_mm / ptp)


def _finish(z: Array, xx: Array, yy: Array, spec: SurfaceSpec, substrate: SubstrateSpec) -> HeightMap:
    """Level on the frame, scale to range (§1.9, Fig. 1.9 c-d); add the broadband part, level and scale again;
    add the bow, the edge roll-off and the local features and level once more.

    The second scaling differs from 1 by the broadband part's share of the range (~1e-4 for nm-level content), so
    the range is exact and the broadband RMS is the requested one to that relative precision.
    """
    z = scale_to_range(level_on_frame(z, yy, substrate.roi_length, xx), spec.range_um * 1e-3)
    if spec.broadband_rms_nm > 0:
        dy, dx = yy[1, 0] - yy[0, 0], xx[0, 1] - xx[0, 0]
        band = (spec.broadband_min_wavelength_mm, spec.broadband_wavelength_mm)
        z = z + broadband_noise(z.shape, (dy, dx), spec.broadband_rms_nm * 1e-6, band, spec.seed)
        z = scale_to_range(level_on_frame(z, yy, substrate.roi_length, xx), spec.range_um * 1e-3)
    extra = bow(xx, yy, spec.bow_um * 1e-3) if spec.bow_um != 0 else 0.0
    if spec.edge_rolloff_um != 0:
        extra = extra - edge_rolloff(xx, yy, spec.edge_rolloff_um * 1e-3, spec.edge_rolloff_mm)
    if spec.features:
        extra = extra + local_features(xx, yy, spec.features)
    if spec.bow_um != 0 or spec.edge_rolloff_um != 0 or spec.features:
        z = level_on_frame(z + extra, yy, substrate.roi_length, xx)
    return HeightMap(z, xx[0, 0], xx[0, -1], yy[0, 0], yy[-1, 0])


def edge_rolloff(x: Array, y: Array, depth: float, width: float) -> Array:
    """How far a cut sheet's edges roll off, mm: ``depth`` x (1 - d / ``width``)^3 within ``width`` (mm) of each edge
    of the grid ``x``, ``y`` (d: the distance from that edge), the bands along x and along y added (a corner rolls off
    twice). Its slope at an edge is 3 ``depth`` / ``width``; it is twice continuously differentiable inside."""

    def band(d: Array) -> Array:
        return np.asarray(np.clip(1.0 - d / width, 0.0, None) ** 3)

    dx = np.minimum(x - x.min(), x.max() - x)
    dy = np.minimum(y - y.min(), y.max() - y)
    return np.asarray(depth * (band(dx) + band(dy)))


def local_features(x: Array, y: Array, features: Sequence[FeatureSpec]) -> Array:
    """Local dimples and bumps on the grid ``x``, ``y``, mm: Gaussians of full width at half maximum ``width_mm``."""
    z = np.zeros(np.shape(x))
    for f in features:
        s2 = (f.width_mm / (2.0 * np.sqrt(2.0 * np.log(2.0)))) ** 2
        z += f.height_um * 1e-3 * np.exp(-((x - f.x) ** 2 + (y - f.y) ** 2) / (2.0 * s2))
    return z


def bow(x: Array, y: Array, sagitta: float) -> Array:
    """A paraboloidal bow on the grid ``x``, ``y`` (mm): ``sagitta`` (mm) at the centre above the corners, zero at
    the corners (a substrate bent like a shallow dome for a positive sagitta, a bowl for a negative one)."""
    r2 = float(np.max(x**2 + y**2))
    return np.asarray(sagitta * (1.0 - (x**2 + y**2) / r2))


def random_surface(spec: SurfaceSpec, substrate: SubstrateSpec) -> HeightMap:
    """The thesis's §1.9 generator: noise -> FFT low-pass -> level on the frame -> scale to range (+ broadband)."""
    xx, yy = _grid(spec, substrate.size)
    dy = yy[1, 0] - yy[0, 0]
    dx = xx[0, 1] - xx[0, 0]
    z = lowpass_noise(xx.shape, (dy, dx), spec.correlation_length, spec.seed)
    return _finish(z, xx, yy, spec, substrate)


def psd_surface(spec: SurfaceSpec, substrate: SubstrateSpec) -> HeightMap:
    """A Gaussian random surface from the spec's PSD (ABC or power law), levelled and scaled like §1.9.

    The field is drawn on a grid padded by 4 B on each side (B = ``correlation_length``), so the FFT's periodic
    wrap-around does not correlate opposite edges; deterministic per ``seed``.
    """
    xx, yy = _grid(spec, substrate.size)
    dy = yy[1, 0] - yy[0, 0]
    dx = xx[0, 1] - xx[0, 0]
    b, c, s = spec.correlation_length, spec.psd_exponent, spec.psd_rolloff_mm
    model = abc_psd if spec.spectrum == "abc" else power_psd

    def psd(f: Array) -> Array:
        return model(f, b, c) * np.exp(-4.0 * np.pi**2 * s**2 * f**2)

    pad = (int(np.ceil(4 * b / dy)), int(np.ceil(4 * b / dx)))
    z = psd_noise(xx.shape, (dy, dx), psd, [int(spec.seed), 9], pad)
    return _finish(z, xx, yy, spec, substrate)


def analytic_surface(spec: SurfaceSpec, substrate: SubstrateSpec) -> HeightMap:
    """Analytic test surfaces, levelled on the frame and scaled to ``range_um``.

    * ``plane``: h = 0.
    * ``sphere``: a spherical bow sagging in the middle, h ~ -(x^2 + y^2).
    * ``cylinder``: a cylindrical bow along y, h ~ -y^2.
    * ``saddle``: h ~ x^2 - y^2.
    """
    xx, yy = _grid(spec, substrate.size)
    shapes = {
        "plane": lambda x, y: np.zeros_like(x),
        "sphere": lambda x, y: -(x**2 + y**2),
        "cylinder": lambda x, y: -(y**2) + 0.0 * x,
        "saddle": lambda x, y: x**2 - y**2,
    }
    z = shapes[spec.kind](xx, yy)
    if spec.kind != "plane":
        z = scale_to_range(level_on_frame(z, yy, substrate.roi_length, xx), spec.range_um * 1e-3)
    return HeightMap(z, xx[0, 0], xx[0, -1], yy[0, 0], yy[-1, 0])


def make_surface(spec: SurfaceSpec, substrate: SubstrateSpec) -> HeightMap:
    """Height map for a surface spec (generated, analytic, or read from an EXR file)."""
    if spec.kind == "file":
        from scopetwin.scenes.io import check_surface, read_heightmap

        # it must cover the substrate, heights in a physical range
        return check_surface(read_heightmap(spec.path), substrate.size, f"surface file {spec.path}")  # type: ignore[arg-type]
    if spec.kind == "random":
        return random_surface(spec, substrate)
    if spec.kind == "psd":
        return psd_surface(spec, substrate)
    return analytic_surface(spec, substrate)


def surface_for(setup: Setup) -> HeightMap | None:
    """The substrate height map of a setup (None for scenes without a substrate)."""
    if setup.scene != "deflectometry":
        return None
    if setup.substrate is None:
        raise SetupError("deflectometry setup has no substrate")
    return make_surface(setup.substrate.surface, setup.substrate)
