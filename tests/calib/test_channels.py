"""Truth tests of calib.channels: a synthetic Siemens star + frame with known magnification, offset, tilt and
Gaussian blur (numpy only), and the error paths."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter
from scipy.optimize import brentq

from scopetwin.calib.channels import ChannelError, measure_channel, relative_pose, spoke_modulation
from scopetwin.scenes.cmu.layout import TargetSpec
from scopetwin.scenes.cmu.targets import siemens_star

PIXEL_UM = 6.45
SPEC = TargetSpec()


def star_image(
    m: float,
    center: tuple[float, float],
    tilt_deg: float,
    sigma_px: float,
    size: int = 860,
    ss: int = 3,
    noise: float = 0.0,
    seed: int = 0,
) -> np.ndarray:
    """Box-integrated image (ss x ss samples per pixel) of the target at magnification m, content rotated by
    +tilt (counter-clockwise as displayed) about ``center`` (x = col, y = row), then a Gaussian blur."""
    off = (np.arange(ss) + 0.5) / ss
    img = np.zeros((size, size))
    col = np.arange(size)[None, :]
    row = np.arange(size)[:, None]
    a = np.deg2rad(tilt_deg)
    for oy in off:
        for ox in off:
            u = (col + ox - center[0]) * PIXEL_UM / m * 1e-3
            v = -(row + oy - center[1]) * PIXEL_UM / m * 1e-3
            x = np.cos(a) * u + np.sin(a) * v
            y = -np.sin(a) * u + np.cos(a) * v
            img += siemens_star(x, y, SPEC)
    img = gaussian_filter(img / ss**2, sigma_px) if sigma_px > 0 else img / ss**2
    if noise:
        img = img + np.random.default_rng(seed).normal(0, noise, img.shape)
    return img


def test_magnification_offset_tilt_recovered() -> None:
    ref = measure_channel(star_image(10.0, (430.3, 428.9), 0.0, 1.0), PIXEL_UM, 500.0, 200.0)
    img = star_image(9.82, (418.6, 441.15), 0.13, 1.5, noise=0.01)
    meas = measure_channel(img, PIXEL_UM, 500.0, 200.0)
    assert meas.magnification == pytest.approx(9.82, rel=0.002)
    assert ref.magnification == pytest.approx(10.0, rel=0.002)
    rel = relative_pose(meas, ref, PIXEL_UM)
    assert rel["offset_x_px"] == pytest.approx(418.6 - 430.3, abs=0.5)
    assert rel["offset_y_px"] == pytest.approx(441.15 - 428.9, abs=0.5)
    assert rel["offset_x_um"] == pytest.approx(rel["offset_x_px"] * PIXEL_UM)
    assert rel["tilt_deg"] == pytest.approx(0.13, abs=0.02)


def _truth_r_min(sigma_px: float, m: float, threshold: float) -> float:
    """Radius (px) where Gaussian x pixel-box x supersampling MTF of the spokes' fundamental equals threshold,
    relative to its value at 0.75 r_star (what measure_channel normalises by)."""
    n = SPEC.spokes

    def mtf(r: float) -> float:
        f = n / (2 * np.pi * r)  # cycles per pixel
        return np.exp(-2 * (np.pi * sigma_px * f) ** 2) * np.sinc(f) ** 1

    r_star = SPEC.star_radius * 1e3 * m / PIXEL_UM
    ref = mtf(0.75 * r_star)
    return brentq(lambda r: mtf(r) / ref - threshold, 1.0, r_star)


@pytest.mark.parametrize("sigma_px", [2.0, 4.0])
def test_resolution_recovered_for_known_blur(sigma_px: float) -> None:
    m = 9.9
    img = star_image(m, (430.0, 430.0), 0.0, sigma_px, noise=0.003)
    meas = measure_channel(img, PIXEL_UM, 500.0, 200.0)
    r_true = _truth_r_min(sigma_px, m, 0.1)
    assert meas.r_min_px == pytest.approx(r_true, rel=0.06)
    assert meas.delta_x_um == pytest.approx(np.pi * r_true * PIXEL_UM / meas.magnification / SPEC.spokes, rel=0.06)
    assert not meas.resolved_to_limit


def test_sharp_star_resolves_to_pixel_scale() -> None:
    meas = measure_channel(star_image(10.0, (430.0, 430.0), 0.0, 0.0), PIXEL_UM, 500.0, 200.0)
    assert meas.delta_x_um < 1.0  # the NIR channel of Table 5.2: "< 1 µm"


def test_spoke_modulation_of_pure_harmonic() -> None:
    yy, xx = np.mgrid[0:200, 0:200] + 0.5
    th = np.arctan2(yy - 100, xx - 100)
    img = 1.0 + 0.5 * np.cos(30 * th)
    mod = spoke_modulation(img, (100.0, 100.0), [60.0, 80.0], 30)
    assert mod == pytest.approx([0.5, 0.5], rel=0.02)


def test_errors() -> None:
    with pytest.raises(ChannelError):
        measure_channel(np.zeros((100, 100)), PIXEL_UM, 500.0, 200.0)
    with pytest.raises(ChannelError):
        measure_channel(np.random.default_rng(0).random((100, 100)), PIXEL_UM, 500.0, 200.0)
    with pytest.raises(ChannelError):
        measure_channel(np.ones((10, 10)), PIXEL_UM, 500.0, 200.0)
