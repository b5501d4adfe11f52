"""Simulated substrate surfaces (seed §1.9) and analytic test surfaces.

Every generated surface satisfies the a-priori knowledge the reconstruction
relies on (seed §1.4, §1.9): the maxima of both holding-frame regions are 0
(the substrate touches the frame there), and the peak-to-valley range over
the substrate is the requested one.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import brentq

from scenes.errors import GeometryError, SetupError
from scenes.setup import Setup, SubstrateSpec, SurfaceSpec
from scenes.surface import HeightMap

Array = NDArray[np.float64]


def _grid(spec: SurfaceSpec, size: tuple[float, float]) -> tuple[Array, Array]:
    nx, ny = spec.grid
    x = np.linspace(-0.5 * size[0], 0.5 * size[0], nx)
    y = np.linspace(-0.5 * size[1], 0.5 * size[1], ny)
    return np.meshgrid(x, y)


def lowpass_noise(shape: tuple[int, int], spacing: tuple[float, float], correlation_length: float, seed: int) -> Array:
    """White noise in [0, 1] low-pass filtered in the Fourier domain (seed §1.9, Fig. 1.9 a-b).

    The filter is Gaussian, exp(-2 pi^2 sigma^2 |f|^2) with sigma = ``correlation_length``
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


def level_on_frame(z: Array, y: Array, roi_length: float) -> Array:
    """Tilt about the x axis and shift so both frame regions have maximum 0 (seed §1.9, Fig. 1.9 c).

    Solves max_region1(z + a*y) = max_region2(z + a*y) for the tilt a (the difference is
    monotonic in a, so a bracketing root finder is exact), then subtracts the common maximum.
    """
    r1 = y <= -0.5 * roi_length
    r2 = y >= 0.5 * roi_length
    if not (r1.any() and r2.any()):
        raise GeometryError("the height-map grid has no nodes in one of the frame regions")

    def diff(a: float) -> float:
        t = z + a * y
        return float(t[r1].max() - t[r2].max())

    span = float(y.max() - y.min())
    bound = 10.0 * (float(np.ptp(z)) + 1e-300) / max(span, 1e-12)
    a = brentq(diff, -bound, bound, xtol=1e-15, rtol=1e-15) if diff(-bound) * diff(bound) < 0 else 0.0
    t = z + a * y
    return t - t[r1].max()


def scale_to_range(z: Array, range_mm: float) -> Array:
    """Scale heights so max - min = ``range_mm`` (seed §1.9, Fig. 1.9 d); zero stays zero."""
    ptp = float(np.ptp(z))
    if ptp == 0:
        return np.zeros_like(z)
    return z * (range_mm / ptp)


def random_surface(spec: SurfaceSpec, substrate: SubstrateSpec) -> HeightMap:
    """The seed's §1.9 generator: noise -> FFT low-pass -> level on the frame -> scale to range."""
    xx, yy = _grid(spec, substrate.size)
    dy = yy[1, 0] - yy[0, 0]
    dx = xx[0, 1] - xx[0, 0]
    z = lowpass_noise(xx.shape, (dy, dx), spec.correlation_length, spec.seed)
    z = scale_to_range(level_on_frame(z, yy, substrate.roi_length), spec.range_um * 1e-3)
    return HeightMap(z, xx[0, 0], xx[0, -1], yy[0, 0], yy[-1, 0])


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
        z = scale_to_range(level_on_frame(z, yy, substrate.roi_length), spec.range_um * 1e-3)
    return HeightMap(z, xx[0, 0], xx[0, -1], yy[0, 0], yy[-1, 0])


def make_surface(spec: SurfaceSpec, substrate: SubstrateSpec) -> HeightMap:
    """Height map for a surface spec (generated, analytic, or read from an EXR file)."""
    if spec.kind == "file":
        from scenes.io import read_heightmap

        return read_heightmap(spec.path)  # type: ignore[arg-type]
    if spec.kind == "random":
        return random_surface(spec, substrate)
    return analytic_surface(spec, substrate)


def surface_for(setup: Setup) -> HeightMap | None:
    """The substrate height map of a setup (None for scenes without a substrate)."""
    if setup.scene != "deflectometry":
        return None
    if setup.substrate is None:
        raise SetupError("deflectometry setup has no substrate")
    return make_surface(setup.substrate.surface, setup.substrate)
