"""Centroid bias: where a marker's spot centroid lies relative to the image of the marker's centre.

A marker is a round spot on the pattern (grey value g = 1 - r/r_m, thesis §1.6.3). Its image is the
disk mapped through the optics: perspective on a tilted target (§2.8.2) and reflection in the bent
substrate (§1.6.5) bend that map, so the grey-weighted centroid of the spot (§1.5.1) is not the
image of the marker's centre. The difference — the bias — reaches 0.05-0.1 px on a calibration
target tilted by 20-40° and several tenths of a pixel on a 40 µm bow (docs/rendering.md, "Centroid bias"), far more
than the photon-noise scatter. This module predicts it from a model, so that calibration and
reconstruction can iterate: estimate the setup -> predict the bias -> correct the centroids ->
estimate again.

How the prediction works
------------------------
:func:`scopetwin.recon.markers.centroids` measures the first moment of the whole spot (its window includes the
faint rim), i.e. up to pixel sampling

    c = ∫ x I(x) dx / ∫ I(x) dx,    I(x) = g(M(x)),

where M maps an image point x to the pattern point its (chief) ray reaches. A rendered pixel is the
box-filtered radiance, and a box filter does not move a first moment. Substituting the pattern point
y = M(x) as the integration variable, with x = P(y) the inverse map and |det DP| its Jacobian,

    c = ∫_disk P(y) g(y) |det DP(y)| dy / ∫_disk g(y) |det DP(y)| dy,

while the image of the marker's centre is P(y_c). For every marker P is fitted, as a cubic
polynomial in the pattern coordinates, to the model's forward trace of 7 x 7 image points that cover
the marker's spot (the model's ``pattern_hits``: camera ray -> target plane, or -> surface ->
reflection -> pattern plane, all in the float64 numpy model of :mod:`scopetwin.scenes`). The integrals are
then evaluated exactly for the polynomial integrand by a polar Gauss-Legendre x trapezoid
quadrature over the marker's disk. No image is rendered, and the prediction has no noise; ~60 rays
per marker are traced. The model is the pinhole camera; a thin lens's symmetric defocus blur does
not move a first moment to first order.

The correction to add to a measured centroid is ``center - centroid``.

Two evaluations of the one model
--------------------------------
* :func:`predict_spots` (above): the continuous first moment, for any model (a plane target,
  :class:`PlaneTarget`, or the deflectometry setup, :func:`model_for_setup`); it serves the
  reconstruction (:func:`scopetwin.recon.reconstruct.centroid_bias_step`) and :func:`correct_centroids`.
* :func:`spot_centroids` / :func:`spot_bias_model`: the same marker (g = 1 - r/r_m) through the same
  pinhole camera onto a plane target, evaluated on the pixels as :func:`scopetwin.recon.markers.centroids` sees
  them: each pixel integrates ``supersample``^2 stratified ray samples (box filter), and the centroid is
  taken over the pixels above a threshold, at pixel centres. It serves the bias-corrected one-shot
  calibration (:func:`scopetwin.calib.oneshot.calibrate_bias_corrected`).

With threshold 0 both predict the whole-spot first moment; they differ by the pixel sampling of the
second (its midpoint rule over the cone's kinks): on the thesis's calibration presets (§2.8.1-§2.9.1,
all markers in view) by 4e-5 px RMS face-on and 1e-4 to 2e-4 px RMS (at most 4.4e-4 px) on the oblique
views, where the bias itself is 0.03-0.07 px RMS. Both are kept, each where it was used, so that the
figures of ``scopetwin run`` and ``scopetwin study thesis`` do not change.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scopetwin.scenes.analytic import AnalyticScene
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.geometry import Array, Frame, intersect_plane
from scopetwin.scenes.pattern import MarkerPattern
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap

log = logging.getLogger(__name__)


class BiasError(ScopetwinError, ValueError):
    """A bias prediction that cannot be made (markers the model does not image)."""


class Model(Protocol):
    """What the bias prediction needs: a camera, a pattern, and where camera rays land on the pattern."""

    camera: Camera
    pattern: MarkerPattern

    def pattern_hits(self, origins: Array, dirs: Array) -> tuple[Array, NDArray[np.bool_]]:
        """Local pattern (x, y), mm, where rays end, and whether they get there."""
        ...


@dataclass(frozen=True)
class PlaneTarget:
    """Camera looking directly at a plane target (a calibration pattern, thesis §2.2, §2.8)."""

    camera: Camera
    pattern: MarkerPattern

    def pattern_hits(self, origins: Array, dirs: Array) -> tuple[Array, NDArray[np.bool_]]:
        """Local (x, y) where rays meet the target plane; True where they reach its front side."""
        return plane_hits(self.pattern.frame, origins, dirs)


def plane_hits(frame: Frame, origins: Array, dirs: Array) -> tuple[Array, NDArray[np.bool_]]:
    """Where rays meet a plane target: local (x, y) in ``frame``, mm, and whether they reach its front side.

    Parameters
    ----------
    frame : Frame
        The target's plane (its local z = 0; the front side faces +N_z).
    origins, dirs : ndarray, (n, 3)
        Rays.

    Returns
    -------
    xy : ndarray, (n, 2)
        Local coordinates of the hits (of the ray origin where the ray does not reach the front side).
    reaches : ndarray of bool, (n,)
        The ray meets the plane ahead of its origin, coming from the front.
    """
    lam = intersect_plane(origins, dirs, frame)
    ok = ((dirs @ frame.nz) < 0) & np.isfinite(lam) & (lam > 0)
    local = frame.to_local(origins + np.where(ok, lam, 0.0)[:, None] * dirs)
    return local[:, :2], ok


def model_for_setup(setup: Setup, heights: HeightMap | None = None, camera: Camera | None = None) -> Model:
    """The numpy ray model of a setup (:class:`scopetwin.scenes.analytic.AnalyticScene`), optionally with another
    camera.

    Parameters
    ----------
    setup : Setup
        Target, mirror or deflectometry setup.
    heights : HeightMap, optional
        Surface (estimate) of the substrate; required for ``deflectometry``.
    camera : Camera, optional
        A calibrated camera to use instead of the setup's.
    """
    scene = AnalyticScene(setup, heights)
    if camera is not None:
        scene.camera = camera
    return scene


@dataclass(frozen=True)
class SpotPrediction:
    """Predicted spot centroids and images of marker centres, continuous pixel coordinates (col, row).

    Attributes
    ----------
    centroid : ndarray, (n, 2)
        First moment of each marker's spot.
    center : ndarray, (n, 2)
        Image of each marker's centre.
    fit_rms : ndarray, (n,)
        RMS residual of the local cubic map fit, px (a check on the prediction).
    reaches : ndarray of bool, (n,)
        All traced rays around the marker reached it (False: the spot is not imaged whole in the model).
    predicted : ndarray of bool, (n,)
        The model's map around the marker could be built (False: its rays meet the model nowhere near, or the map
        is singular there, as at a caustic; its centroid and centre are then the guess, its correction 0).
    """

    centroid: Array
    center: Array
    fit_rms: Array
    reaches: NDArray[np.bool_]
    predicted: NDArray[np.bool_]

    @property
    def correction(self) -> Array:
        """What to add to a measured centroid to get the image of the marker's centre, px."""
        return self.center - self.centroid


# -- polynomial map ----------------------------------------------------------------------------
_EXPONENTS = np.array([(a, d - a) for d in range(4) for a in range(d, -1, -1)])  # cubic, 10 terms


def _powers(v: Array) -> Array:
    """v^0 .. v^3 stacked on a new last axis, by products (np.power with an exponent array is ~10x slower)."""
    v2 = v * v
    return np.stack([np.ones_like(v), v, v2, v2 * v], axis=-1)


def _design(q: Array) -> Array:
    """Monomials q_x^a q_y^b of total degree <= 3, shape (..., 10)."""
    return _powers(q[..., 0])[..., _EXPONENTS[:, 0]] * _powers(q[..., 1])[..., _EXPONENTS[:, 1]]


def _design_grad(q: Array) -> tuple[Array, Array]:
    """Derivatives of the monomials by q_x and q_y, each (..., 10)."""
    a, b = _EXPONENTS[:, 0], _EXPONENTS[:, 1]
    qx, qy = q[..., :1], q[..., 1:2]
    dx = np.where(a > 0, a * qx ** np.maximum(a - 1, 0) * qy**b, 0.0)
    dy = np.where(b > 0, b * qx**a * qy ** np.maximum(b - 1, 0), 0.0)
    return dx, dy


def _quadrature(n_r: int, n_theta: int) -> tuple[Array, Array]:
    """Nodes (k, 2) on the unit disk and weights for ∫ f(q) (1 - |q|) dq (polar Gauss-Legendre x trapezoid)."""
    t, w = np.polynomial.legendre.leggauss(n_r)
    rho = 0.5 * (t + 1.0)
    w_r = 0.5 * w * rho * (1.0 - rho)
    theta = 2.0 * np.pi * np.arange(n_theta) / n_theta
    nodes = (rho[:, None, None] * np.stack([np.cos(theta), np.sin(theta)], axis=-1)[None]).reshape(-1, 2)
    weights = (w_r[:, None] * np.full(n_theta, 2.0 * np.pi / n_theta)[None]).ravel()
    return nodes, weights


def _trace(model: Model, px: Array) -> tuple[Array, NDArray[np.bool_]]:
    o, d = model.camera.rays(px.reshape(-1, 2))
    xy, ok = model.pattern_hits(o, d)
    return xy.reshape(px.shape), ok.reshape(px.shape[:-1])


def _start(model: Model, ij: NDArray) -> Array:
    """First guess of the image of marker centres: direct view, or the plane mirror z = 0."""
    pts = model.pattern.centers(ij)
    direct = model.camera.project(pts)
    if isinstance(model, PlaneTarget) or getattr(getattr(model, "setup", None), "scene", "target") == "target":
        return direct
    return model.camera.project(pts * np.array([1.0, 1.0, -1.0]))


def _fit_local_map(
    model: Model, x0: Array, c_loc: Array, radius: Array, grid: Array
) -> tuple[Array, Array, NDArray[np.bool_], NDArray[np.bool_]]:
    """Cubic map P(q) (n, 10, 2) fitted to rays traced over each marker's spot around ``x0``, its RMS, reach, and
    where it could be fitted (elsewhere the map is NaN: :func:`predict_spots` keeps the guess there).

    ``grid`` holds the unit-radius pattern offsets the fit points are aimed at (through the local Jacobian at
    ``x0``); q is the pattern offset from the marker centre ``c_loc`` in marker radii.
    """
    unit = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    # local Jacobian d(pattern)/d(pixel) at x0, to place the fit points over the spot
    y3, _ = _trace(model, x0[:, None, :] + unit[None])
    jac = np.stack([y3[:, 1] - y3[:, 0], y3[:, 2] - y3[:, 0]], axis=-1)  # (n, 2 pattern, 2 pixel)
    with np.errstate(invalid="ignore"):
        det = np.linalg.det(jac)
    fitted = np.isfinite(det) & (np.abs(det) > 1e-300)  # a ray that does not converge: NaN
    inv = np.linalg.inv(np.where(fitted[:, None, None], jac, np.eye(2)))
    target = c_loc[:, None, :] + radius[:, None, None] * grid[None]
    px = x0[:, None, :] + (target - np.where(fitted[:, None], y3[:, 0], c_loc)[:, None]) @ inv.transpose(0, 2, 1)
    y, ok = _trace(model, px)
    q = (y - c_loc[:, None, :]) / radius[:, None, None]
    reaches = np.all(ok | (np.hypot(q[..., 0], q[..., 1]) > 1.0), axis=1)
    use = ok | (ok.sum(axis=1, keepdims=True) < 16)  # fit the rays that reach, if there are enough
    a = _design(q)  # (n, k, 10)
    aw = a * use[..., None]
    awt = aw.transpose(0, 2, 1)  # batched products by matmul (einsum's unoptimised loops are ~5x slower here)
    coef = _solve_each(awt @ a, awt @ px, fitted)
    fitted &= np.all(np.isfinite(coef), axis=(1, 2))
    res = np.sum((a @ coef - px) ** 2, axis=-1)
    fit_rms = np.sqrt(np.sum(res * use, axis=1) / use.sum(axis=1))
    return coef, fit_rms, reaches, fitted


def _solve_each(lhs: Array, rhs: Array, fitted: NDArray[np.bool_]) -> Array:
    """The normal equations of each marker where ``fitted`` (at once; one by one where one of them is singular,
    too few rays reaching the pattern near a caustic); NaN elsewhere."""
    coef = np.full(rhs.shape[:1] + lhs.shape[-1:] + rhs.shape[-1:], np.nan)
    k = np.flatnonzero(fitted)
    with np.errstate(invalid="ignore", over="ignore"):
        try:
            coef[k] = np.linalg.solve(lhs[k], rhs[k])
        except np.linalg.LinAlgError:
            for i in k:
                try:
                    coef[i] = np.linalg.solve(lhs[i], rhs[i])
                except np.linalg.LinAlgError:
                    continue  # stays NaN: predict_spots leaves this marker uncorrected
    return coef


def _map_first_moment(coef: Array, n_r: int, n_theta: int) -> Array:
    """First moment of the cone marker through the cubic maps ``coef``: the quadrature of the module docstring."""
    nodes, weights = _quadrature(n_r, n_theta)
    basis = _design(nodes)  # (k, 10)
    dx, dy = _design_grad(nodes)
    pos = basis @ coef  # (n, k, 2)
    jx = dx @ coef  # dP/dq_x, (n, k, 2)
    jy = dy @ coef
    jdet = np.abs(jx[..., 0] * jy[..., 1] - jx[..., 1] * jy[..., 0])
    wk = weights[None] * jdet
    return (wk[:, None, :] @ pos)[:, 0, :] / wk.sum(axis=1, keepdims=True)


def predict_spots(
    model: Model,
    ij: ArrayLike,
    guess_px: ArrayLike | None = None,
    n_fit: int = 7,
    span: float = 1.15,
    passes: int = 2,
    n_r: int = 8,
    n_theta: int = 24,
    max_unpredicted: float = 0.05,
) -> SpotPrediction:
    """Predict the spot centroid and the image of the centre of markers ``ij`` from a model (module docstring).

    Parameters
    ----------
    model : Model
        Camera + plane target (:class:`PlaneTarget`) or camera + surface + pattern
        (:func:`model_for_setup`).
    ij : array_like, (n, 2)
        Marker indices (docs/contract.md, "Marker indices").
    guess_px : array_like, (n, 2), optional
        Where the spots are roughly (e.g. the measured centroids); default: the image through a flat
        mirror z = 0 or the direct view.
    n_fit : int
        The local map is fitted to n_fit x n_fit traced points.
    span : float
        The fitted points cover ±span marker radii around the centre.
    passes : int
        Re-centre the fit on the predicted centre image this often.
    n_r, n_theta : int
        Quadrature nodes along the radius and around.
    max_unpredicted : float
        The largest fraction of the markers whose map cannot be built (a ray of the model that does not converge, a
        singular map near a caustic): those keep the guess as centroid and centre (no correction; ``predicted``
        False). One marker's ray should not decide a whole reconstruction.

    Raises
    ------
    BiasError
        The model does not image more than ``max_unpredicted`` of the markers (rays miss the pattern, singular
        maps), or a marker has no start position.
    """
    ij = np.asarray(ij, dtype=np.int64).reshape(-1, 2)
    n = len(ij)
    pattern = model.pattern
    c_loc = pattern.centers_local(ij)
    radius = pattern.radii(ij)
    x0 = _start(model, ij) if guess_px is None else np.asarray(guess_px, dtype=np.float64).reshape(n, 2).copy()
    if not np.all(np.isfinite(x0)):
        raise BiasError("the model does not image every requested marker (no start position)")
    g = np.linspace(-span, span, n_fit)
    grid = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)  # unit-radius pattern offsets
    guess = x0.copy()
    for _ in range(max(1, passes)):
        coef, fit_rms, reaches, fitted = _fit_local_map(model, x0, c_loc, radius, grid)
        x0 = np.where(fitted[:, None], coef[:, 0, :], x0)  # P(y_c): the monomial 1 is the only one not vanishing at 0
    missing = n - int(fitted.sum())
    if missing > max_unpredicted * n:
        raise BiasError(
            f"the model's map around {missing} of {n} markers could not be fitted (rays that miss the pattern or a "
            f"singular map; at most {max_unpredicted:.0%} may be left uncorrected)"
        )
    if missing:
        log.debug("bias model: %d of %d markers left uncorrected (their map could not be built)", missing, n)
    centroid, center = guess.copy(), guess.copy()
    centroid[fitted] = _map_first_moment(coef[fitted], n_r, n_theta)
    center[fitted] = coef[fitted, 0, :]
    return SpotPrediction(centroid=centroid, center=center, fit_rms=fit_rms, reaches=reaches, predicted=fitted)


def correct_centroids(centroids: ArrayLike, ij: ArrayLike, model: Model, **kwargs) -> tuple[Array, SpotPrediction]:
    """Bias-corrected centroids: measured + (predicted centre image - predicted centroid).

    Parameters
    ----------
    centroids : array_like, (n, 2)
        Measured centroids (:func:`scopetwin.recon.markers.centroids`, whole-spot first moments).
    ij : array_like, (n, 2)
        Their marker indices.
    model : Model
        Current estimate of the setup.
    **kwargs
        Passed to :func:`predict_spots`.
    """
    c = np.asarray(centroids, dtype=np.float64).reshape(-1, 2)
    pred = predict_spots(model, ij, guess_px=c, **kwargs)
    return c + pred.correction, pred


# -- the pixel-sampled evaluation on a plane target (the bias-corrected calibration) ----------
def _window_groups(lo: NDArray, hi: NDArray, s: int, chunk: int) -> list[NDArray]:
    """Markers grouped, by increasing window size, so that one group's samples stay about within ``chunk``."""
    n = len(lo)
    order = np.argsort((hi - lo).prod(axis=1))
    groups: list[NDArray] = []
    start = 0
    while start < n:
        # group markers with windows of one size so that one array holds them
        k = order[start]
        wx, wy = hi[k] - lo[k]
        group = [k]
        total = wx * wy * s * s
        j = start + 1
        while j < n and total < chunk:
            group.append(order[j])
            total += wx * wy * s * s
            j += 1
        start = j
        groups.append(np.asarray(group))
    return groups


def _target_hits(camera: Camera, px: Array) -> tuple[Array, NDArray[np.bool_]]:
    """:func:`plane_hits` of the target plane z = 0 (the target's own coordinates) for the pinhole rays through
    pixels ``px`` (n, 2), without forming the rays: with d = -b N_z + u T_x + v T_y (the undistorted sensor point,
    thesis §1.6.2) and the centre c, the hit is c + (-c_z / d_z) d (the same point as the unit ray's, to rounding);
    it is reached where d_z < 0 and the hit lies ahead (c_z > 0)."""
    uv = camera.undistort(camera.pixel_to_sensor(px))
    f, c = camera.frame, camera.center
    u, v = uv[:, 0], uv[:, 1]
    dz = u * f.tx[2] + v * f.ty[2] - camera.b * f.nz[2]
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -c[2] / dz
    ok = (dz < 0) & np.isfinite(lam) & (lam > 0)
    lam = np.where(ok, lam, 0.0)
    x = c[0] + lam * (u * f.tx[0] + v * f.ty[0] - camera.b * f.nz[0])
    y = c[1] + lam * (u * f.tx[1] + v * f.ty[1] - camera.b * f.nz[1])
    return np.stack([x, y], axis=-1), ok


def _group_centroids(
    camera: Camera,
    xy: Array,
    radii: Array,
    lo: NDArray,
    hi: NDArray,
    off: Array,
    threshold: float,
    background: float,
    radiance: float,
) -> Array:
    """Thresholded centroids (m, 2) of one group of markers (centres ``xy``, mm) in pixel windows from ``lo``."""
    m, ss = len(xy), len(off)
    size = (hi - lo).max(axis=0)
    cols = np.arange(size[0])
    rows = np.arange(size[1])
    cc, rr = np.meshgrid(cols, rows)  # (H, W)
    base = np.stack([cc, rr], -1).reshape(-1, 2).astype(np.float64)  # (P, 2) pixel corners
    pix = lo[:, None, None, :] + base[None, :, None, :] + off[None, None, :, :]  # (m, P, S, 2)
    hit, reaches = _target_hits(camera, pix.reshape(-1, 2))
    hit = hit.reshape(m, -1, 2) - xy[:, None, :]
    r = np.hypot(hit[..., 0], hit[..., 1]) / radii[:, None]
    grey = radiance * np.clip(1.0 - r, 0.0, 1.0)
    grey = np.where(reaches.reshape(m, -1), grey, 0.0)
    val = grey.reshape(m, -1, ss).mean(axis=2)  # (m, P) pixel values
    w = np.where(val > threshold, val - background, 0.0)
    centres = base + 0.5
    mass = w.sum(axis=1)
    c = (w @ centres) / np.where(mass > 0, mass, np.nan)[:, None]
    return c + lo


def spot_centroids(
    camera: Camera,
    xy: ArrayLike,
    radii: ArrayLike,
    threshold: float,
    background: float = 0.0,
    radiance: float = 1.0,
    supersample: int = 4,
    chunk: int = 1 << 18,
) -> Array:
    """Predicted centroids of fading round markers on the target plane z = 0 (thesis §1.5.1, §1.6.3).

    Each marker (grey value g = 1 - r/r_m, thesis §1.6.3) is imaged through ``camera`` (pinhole,
    distortion; rays meet the target as in :class:`PlaneTarget`, :func:`plane_hits`) into a pixel
    window; pixels integrate their area (``supersample``^2 stratified points, box filter); the
    centroid is then taken as :func:`scopetwin.recon.markers.centroids` takes it: pixels above ``threshold``
    weighted by their value minus ``background``, at pixel centres.

    Parameters
    ----------
    camera : Camera
        The camera in target coordinates.
    xy : array_like (n, 2)
        Marker centres, mm.
    radii : array_like (n,)
        Marker radii, mm.
    threshold, background, radiance : float
        Spot threshold and background level of the image, and the radiance of a marker centre.
    supersample : int
        Sample points per pixel and axis.
    chunk : int
        Samples (markers x window pixels x ``supersample``^2) of one group of markers computed at once: 2^18 keeps
        the temporaries within a few MB (with 2 million, a calibration's calls spent most of their time on fresh
        memory: 2.9 -> 1.7 s over the four calls of ``scopetwin run``).

    Returns
    -------
    ndarray (n, 2)
        Centroids, continuous px (NaN for markers not wholly in front of the camera).
    """
    xy = np.asarray(xy, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    n = len(xy)
    t = np.linspace(0.0, 2.0 * np.pi, 48, endpoint=False)
    rim = np.concatenate(
        [xy[:, None, :] + radii[:, None, None] * np.stack([np.cos(t), np.sin(t)], -1), np.zeros((n, len(t), 1))],
        axis=-1,
    )
    rim_px = camera.project(rim)
    lo = np.floor(np.nanmin(rim_px, axis=1)).astype(int) - 1
    hi = np.ceil(np.nanmax(rim_px, axis=1)).astype(int) + 1
    out = np.full((n, 2), np.nan)
    s = supersample
    sub = (np.arange(s) + 0.5) / s
    off = np.stack(np.meshgrid(sub, sub), -1).reshape(-1, 2)  # (s*s, 2) within a pixel
    for g_idx in _window_groups(lo, hi, s, chunk):
        out[g_idx] = _group_centroids(
            camera, xy[g_idx], radii[g_idx], lo[g_idx], hi[g_idx], off, threshold, background, radiance
        )
    return out


def spot_bias_model(
    xy: ArrayLike,
    radii: ArrayLike,
    threshold: float = 0.0,
    background: float = 0.0,
    radiance: float = 1.0,
    supersample: int | None = None,
) -> Callable[[Camera], Array]:
    """The centroid bias of a plane target as a function of the camera: centroid minus image of the centre, px.

    The ``predict_bias`` of :func:`scopetwin.calib.oneshot.calibrate_bias_corrected`: for a camera (in target
    coordinates) it returns :func:`spot_centroids` minus the image of each marker's centre, the
    pixel-sampled evaluation of this module's model (module docstring).

    Parameters
    ----------
    xy : array_like (n, 2)
        Marker centres in target coordinates (the target plane z = 0), mm.
    radii : array_like (n,)
        Marker radii, mm.
    threshold, background, radiance : float
        As in :func:`spot_centroids`; the defaults (threshold 0) model the whole-spot first moment of
        :func:`scopetwin.recon.markers.centroids`.
    supersample : int, optional
        Points per pixel side; None: enough for about 40 samples across a spot radius (2 to 8).

    Returns
    -------
    callable
        ``predict(camera) -> ndarray (n, 2)``, the bias of each marker, px.
    """
    xy = np.asarray(xy, dtype=np.float64)
    radii = np.asarray(radii, dtype=np.float64)
    X = np.column_stack([xy, np.zeros(len(xy))])

    def predict(camera: Camera) -> Array:
        s = supersample
        if s is None:
            d = float(np.median(-(X - camera.center) @ camera.frame.nz))
            r_px = float(np.min(radii)) * camera.b / d / camera.pitch
            s = int(np.clip(np.ceil(40.0 / max(r_px, 1e-3)), 2, 8))
        return spot_centroids(camera, xy, radii, threshold, background, radiance, s) - camera.project(X)

    return predict
