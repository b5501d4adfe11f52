"""Channel registration from images of a Siemens star in a square frame (thesis §5.2.2, Tables 5.1-5.4).

Works on any monochrome image (rendered or a camera frame; numpy/scipy/OpenCV only):

1. **Frame** - the clear square line around the star is found (Otsu threshold, the largest square contour), then
   refined: across each side, profiles perpendicular to it give the line's centre to sub-pixel (background-
   subtracted intensity centroid); a line is fitted to each side (total least squares, corners excluded) and
   adjacent sides are intersected. Centre = mean of the four corners, side = mean corner distance, angle =
   mean side direction modulo 90°.
2. **Magnification** m = side_px x pixel pitch / frame side (Table 5.1); m_x, m_y from the two side pairs.
3. **Offset and tilt** of a channel relative to the reference (NIR) channel: difference of the frame centres
   (px, and µm at the image plane) and of the frame angles (Tables 5.3, 5.4). Tilt is counter-clockwise positive
   as the image is displayed (row 0 at the top).
4. **Resolution** delta_x = pi r_min / N_spokes (thesis §5.2.2): around the star centre the image is sampled on
   circles; the modulation of the N-th angular harmonic (the spokes' fundamental), relative to its value in the
   outer part of the star, is followed inward; r_min is the radius where it first drops below ``threshold``
   (default 0.1, our reading of "the spokes are still separated"). Spurious resolution inside r_min is ignored.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import cv2
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.ndimage import map_coordinates

from scopetwin.scenes.errors import ScopetwinError

Array = NDArray[np.float64]


class ChannelError(ScopetwinError, ValueError):
    """The image does not show a measurable Siemens star in a square frame."""


@dataclass(frozen=True)
class FrameFit:
    """The square frame in continuous pixel coordinates (x = col, y = row; pixel (r, c) spans [c, c+1))."""

    center: tuple[float, float]
    side_px: float
    side_xy_px: tuple[float, float]
    angle_deg: float
    corners: tuple[tuple[float, float], ...]


@dataclass(frozen=True)
class ChannelMeasurement:
    """Frame, magnification and resolution of one channel's image."""

    frame: FrameFit
    magnification: float
    magnification_xy: tuple[float, float]
    r_min_px: float
    r_min_um: float
    delta_x_um: float
    resolved_to_limit: bool

    def to_json(self) -> dict:
        return asdict(self)


def _normalise(img: ArrayLike) -> Array:
    a = np.asarray(img, dtype=np.float64)
    if a.ndim != 2 or min(a.shape) < 32:
        raise ChannelError(f"need a 2-D image of at least 32x32 pixels, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ChannelError("image contains NaN or infinite values")
    lo, hi = np.percentile(a, [1.0, 99.9])
    if not hi > lo:
        raise ChannelError("image has no contrast")
    return (a - lo) / (hi - lo)


def _coarse_frame(a: Array) -> tuple[np.ndarray, float, float]:
    u8 = np.clip(a * 255, 0, 255).astype(np.uint8)
    _, binary = cv2.threshold(cv2.GaussianBlur(u8, (5, 5), 0), 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    contours, _ = cv2.findContours(binary, cv2.RETR_LIST, cv2.CHAIN_APPROX_NONE)
    best = None
    for c in contours:
        (cx, cy), (w, h), ang = cv2.minAreaRect(c)
        if min(w, h) < 0.15 * min(a.shape) or abs(w - h) > 0.1 * max(w, h):
            continue
        if cv2.contourArea(c) < 0.85 * w * h:  # a square outline encloses (nearly) its whole rectangle
            continue
        if best is None or w * h > best[1] ** 2:
            best = (np.array([cx, cy]), 0.5 * (w + h), ang)
    if best is None:
        raise ChannelError("no square frame found in the image")
    return best


def _fit_side(a: Array, c: np.ndarray, side: float, theta: float, k: int, half_width: float) -> tuple[Array, Array]:
    """Sub-pixel centre points of side k (0..3) of the square; returns (points (n,2), direction)."""
    phi = theta + k * 0.5 * np.pi
    nrm = np.array([np.cos(phi), np.sin(phi)])
    tan = np.array([-nrm[1], nrm[0]])
    tau = np.linspace(-0.38 * side, 0.38 * side, max(32, int(0.76 * side / 2)))
    s = np.linspace(-half_width, half_width, int(4 * half_width) + 1)
    base = c[None, :] + 0.5 * side * nrm[None, :] + tau[:, None] * tan[None, :]
    pts = base[:, None, :] + s[None, :, None] * nrm[None, None, :]
    # pixel centres are at +0.5: sample at (row - 0.5, col - 0.5)
    prof = map_coordinates(a, [pts[..., 1] - 0.5, pts[..., 0] - 0.5], order=1, mode="nearest")
    bg = np.median(np.concatenate([prof[:, :3], prof[:, -3:]], axis=1), axis=1, keepdims=True)
    w = np.clip(prof - bg, 0.0, None)
    w = np.where(w > 0.2 * w.max(axis=1, keepdims=True), w, 0.0)
    tot = w.sum(axis=1)
    ok = tot > 0
    off = (w * s[None, :]).sum(axis=1)[ok] / tot[ok]
    return base[ok] + off[:, None] * nrm[None, :], tan


def _tls_line(p: Array) -> tuple[Array, Array]:
    m = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - m)
    return m, vt[0]


def _intersect(p1: Array, d1: Array, p2: Array, d2: Array) -> Array:
    t = np.linalg.solve(np.column_stack([d1, -d2]), p2 - p1)
    return p1 + t[0] * d1


def fit_frame(img: ArrayLike, iterations: int = 3) -> FrameFit:
    """Find and refine the square frame (sub-pixel centre, side, angle)."""
    a = _normalise(img)
    c, side, ang = _coarse_frame(a)
    theta = np.deg2rad(ang)
    half_width = max(4.0, 0.04 * side)
    corners = []
    for _ in range(iterations):
        lines = []
        for k in range(4):
            pts, _ = _fit_side(a, c, side, theta, k, half_width)
            if len(pts) < 8:
                raise ChannelError("the frame's sides could not be measured")
            lines.append(_tls_line(pts))
        corners = [_intersect(*lines[k], *lines[(k + 1) % 4]) for k in range(4)]
        cc = np.mean(corners, axis=0)
        sides = [np.linalg.norm(corners[(k + 1) % 4] - corners[k]) for k in range(4)]
        dirs = np.array([np.arctan2(ln[1][1], ln[1][0]) for ln in lines])
        theta = float(np.angle(np.mean(np.exp(4j * dirs))) / 4.0)
        c, side = cc, float(np.mean(sides))
        half_width = max(3.0, 0.03 * side)
    sx = 0.5 * (sides[0] + sides[2])
    sy = 0.5 * (sides[1] + sides[3])
    # displayed angle: rows grow downward, so counter-clockwise on screen is -theta in (col, row) axes
    return FrameFit(
        (float(c[0]), float(c[1])),
        float(side),
        (float(sx), float(sy)),
        float(-np.rad2deg(theta)),
        tuple((float(p[0]), float(p[1])) for p in corners),
    )


def spoke_modulation(img: ArrayLike, center: tuple[float, float], radii: ArrayLike, spokes: int) -> Array:
    """Modulation (|N-th angular harmonic| / mean) of the image on circles of ``radii`` (px) about ``center``."""
    a = np.asarray(img, dtype=np.float64)
    r = np.asarray(radii, dtype=np.float64)
    m = max(16 * spokes, 720)
    th = np.arange(m) * 2.0 * np.pi / m
    x = center[0] + r[:, None] * np.cos(th)[None, :]
    y = center[1] + r[:, None] * np.sin(th)[None, :]
    p = map_coordinates(a, [y - 0.5, x - 0.5], order=1, mode="nearest")
    harm = np.abs((p * np.exp(-1j * spokes * th)[None, :]).sum(axis=1)) * 2.0 / m
    return harm / np.maximum(p.mean(axis=1), 1e-12)


def measure_channel(
    img: ArrayLike,
    pixel_um: float,
    frame_side_um: float,
    star_radius_um: float,
    spokes: int = 30,
    threshold: float = 0.1,
    step_px: float = 0.25,
) -> ChannelMeasurement:
    """Frame, magnification and Siemens-star resolution of one image (thesis §5.2.2).

    Parameters
    ----------
    pixel_um : float
        Camera pixel pitch (6.45 µm, §4.1.4).
    frame_side_um, star_radius_um : float
        The target's frame side and star radius at the object, µm.
    threshold : float
        Relative spoke modulation below which the spokes count as no longer separated.
    """
    if pixel_um <= 0 or frame_side_um <= 0 or star_radius_um <= 0:
        raise ChannelError("pixel_um, frame_side_um and star_radius_um must be > 0")
    a = np.asarray(img, dtype=np.float64)
    fr = fit_frame(a)
    m = fr.side_px * pixel_um / frame_side_um
    mxy = (fr.side_xy_px[0] * pixel_um / frame_side_um, fr.side_xy_px[1] * pixel_um / frame_side_um)
    r_star = star_radius_um * m / pixel_um
    radii = np.arange(0.95 * r_star, 2.0, -step_px)
    mod = spoke_modulation(a, fr.center, radii, spokes)
    ref = np.median(mod[(radii > 0.6 * r_star) & (radii < 0.9 * r_star)])
    rel = mod / max(ref, 1e-12)
    below = np.flatnonzero(rel < threshold)
    limited = below.size == 0
    if limited:
        r_min = float(radii[-1])
    else:
        i = below[0]
        if i == 0:
            r_min = float(radii[0])
        else:  # interpolate the crossing between radii[i-1] (above) and radii[i] (below)
            t = (rel[i - 1] - threshold) / (rel[i - 1] - rel[i])
            r_min = float(radii[i - 1] + t * (radii[i] - radii[i - 1]))
    r_min_um = r_min * pixel_um / m
    return ChannelMeasurement(
        fr, float(m), (float(mxy[0]), float(mxy[1])), r_min, float(r_min_um), float(np.pi * r_min_um / spokes), limited
    )


def relative_pose(meas: ChannelMeasurement, reference: ChannelMeasurement, pixel_um: float) -> dict[str, float]:
    """Offset (px and µm at the image plane) and tilt (deg) of a channel relative to the reference (Tables 5.3/5.4)."""
    dx = meas.frame.center[0] - reference.frame.center[0]
    dy = meas.frame.center[1] - reference.frame.center[1]
    dphi = (meas.frame.angle_deg - reference.frame.angle_deg + 45.0) % 90.0 - 45.0
    return {
        "offset_x_px": dx,
        "offset_y_px": dy,
        "offset_x_um": dx * pixel_um,
        "offset_y_um": dy * pixel_um,
        "tilt_deg": dphi,
        "magnification_ratio": meas.magnification / reference.magnification,
    }
