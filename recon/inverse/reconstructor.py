"""Inverse rendering: the substrate's surface fitted to the whole image through a differentiable render.

The centroid method (:mod:`scopetwin.recon.reconstruct`, thesis §1.4-§1.8) needs every marker's image to be a compact
spot whose centroid follows the image of its centre. Here instead the image itself is the data: the surface (a
uniform cubic B-spline over the base plane, fine enough for 3 mm correlation lengths) is fitted so that a render
of the measurement — the thesis's ray model of §1.6 written in Dr.Jit
(:mod:`scopetwin.scenes.mitsuba.deflectometry_ad`) — matches the camera image pixel by pixel, partial markers included.

Loss (Gauss-Newton / Levenberg-Marquardt on the coefficients c)::

    sum_p (I_p - alpha*R_p(c) - beta)^2 / var_p  +  lambda * |D c|^2,   mean_ROI(h) = H

* ``var_p``: the EMVA 1288 variance of pixel p (:mod:`scopetwin.scenes.emva1288`: K^2 sigma_d^2 + K (I - black) +
  1/12 in DN) for camera images; a constant for noise-free renders;
* ``alpha, beta``: the photometric gain and offset (exposure, black level), solved in closed form each step;
* ``D``: second differences of the coefficient grid (a discrete thin-plate energy): the smoothness prior, which
  also carries the surface into the frame regions, where there are no data;
* the Jacobian dR/dc is sparse (16 coefficients per ray) and exact: per ray, the render returns the derivative
  with respect to a local height/slope perturbation (forward-mode AD), combined with the B-spline basis here;
* coarse to fine from a plane start: first on binned images (b x b pixels each, rendered as one super-pixel: the
  image blurred and decimated, which widens the basin), then on the full-resolution image; from the centroid
  method's surface (already inside the basin) the full-resolution image directly.

From a converged centroid start the coefficients are held to the span of the centroid method's shifted basis
(``surface="start-basis"``: c = P a, P the basis functions as B-splines, :meth:`SplineSurface.span`; its scale was
chosen from the data by :func:`scopetwin.recon.scale.select_sigma`): the prior the centroid method found for this
surface, fitted now to every pixel instead of to the markers' centroids. The free spline (every coefficient,
thin-plate prior) is used from a plane start and where the height is searched.

The absolute height is decided by the frame criterion (thesis §1.4, eqs. 1.3-1.4,
:mod:`scopetwin.recon.frame_criterion`): the fit is constrained to a mean ROI height H; from a centroid start H is
the centroid method's (found by the frame criterion on its Gaussian-process surface, the better extrapolation into
the frame regions), and with ``absolute="frame"`` or from a plane H is searched (secant) until the fitted surface's
maxima over the two frame regions lie on the holding frame (the one bracketed secant of both methods,
:func:`scopetwin.recon.frame_criterion.next_start_height`). ``refine_setup`` adds 12 rigid-motion parameters of
camera and pattern to the unknowns, held near the calibration by a Gaussian prior of the given standard deviations.

This is the one reconstruction module that renders: it imports the renderer (:mod:`scopetwin.scenes.mitsuba`) lazily,
inside its functions (``tests/architecture/test_layers.py`` names it), because a differentiable render of the
measurement is the method. On a real rig the image comes from a camera as for every other recon module.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from numpy.typing import NDArray
from scipy.linalg import null_space

from scopetwin.recon.errors import ReconstructionError
from scopetwin.recon.frame_criterion import FrameCriterion, frame_criterion, frame_distance, next_start_height
from scopetwin.recon.shifted_basis import ShiftedBasis
from scopetwin.recon.spline import SplineSurface
from scopetwin.recon.substrate import Substrate2D
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array, Frame
from scopetwin.scenes.pattern import MarkerPattern
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap

if TYPE_CHECKING:  # the renderer is imported lazily at run time
    from scopetwin.scenes.mitsuba.deflectometry_ad import RayModel, SplineGrid


def _pixel_moments(res: Any, ok: NDArray[np.bool_], spp: int, block: int = 32768) -> tuple[Array, ...]:
    """Per usable pixel: the mean hit point and the moments of the rays' sensitivities about it.

    Returns (xm, ym, ma, mb, mc, m_ax, m_ay, m_bx, m_by, m_cx, m_cy): the means of the hit x, y and of the
    sensitivities a, b, c (to a local height, x-slope and y-slope perturbation), and the means of a, b, c times the
    hit's offset from the pixel's mean hit in x and y. The basis is expanded to second order about the mean hit
    (the rays of a pixel land within ~0.05 knot spacings of each other). Worked in blocks of ``block`` pixels, so
    that the temporaries stay a few tens of MB whatever the image size.
    """
    good = np.flatnonzero(ok)
    out = np.empty((11, len(good)))
    x_all = res.x.reshape(-1, spp)
    y_all = res.y.reshape(-1, spp)
    s_all = [res.sens[k].reshape(-1, spp) for k in range(3)]
    for start in range(0, len(good), block):
        rows = good[start : start + block]
        x, y = x_all[rows], y_all[rows]
        xm, ym = x.mean(axis=1), y.mean(axis=1)
        ddx, ddy = x - xm[:, None], y - ym[:, None]
        sa, sb, sc = (s[rows] for s in s_all)
        part = out[:, start : start + len(rows)]
        part[0], part[1] = xm, ym
        part[2], part[3], part[4] = sa.mean(axis=1), sb.mean(axis=1), sc.mean(axis=1)
        part[5], part[6] = (sa * ddx).mean(axis=1), (sa * ddy).mean(axis=1)
        part[7], part[8] = (sb * ddx).mean(axis=1), (sb * ddy).mean(axis=1)
        part[9], part[10] = (sc * ddx).mean(axis=1), (sc * ddy).mean(axis=1)
    return tuple(out)


# -- configuration and results ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class InverseConfig:
    """Parameters of the inverse reconstruction.

    Attributes
    ----------
    spacing : float
        B-spline knot spacing, mm (0.5 mm resolves the 3 mm correlation length).
    surface : {"start-basis", "spline"}
        The surfaces the fit searches. "start-basis" (from a centroid start): the span of the centroid method's
        shifted basis (its scale chosen from the data by :func:`scopetwin.recon.reconstruct.select_sigma`) as B-splines,
        :meth:`SplineSurface.span` — the prior the centroid method found for this surface, now fitted to every
        pixel; measured (Mitsuba 16 spp, seed 2): with EMVA 1288 noise 0.0012-0.0022 µm shape against the centroid
        method's 0.0016-0.0032 at 5-20 mm / 40 µm, and 3 mm / 60 µm tilt-removed 0.014 µm against 0.060; the free
        spline with its thin-plate prior passes more noise (0.0041 with noise at 12 mm). "spline": every
        coefficient free (always so from a plane start, which has no basis, and with ``absolute="frame"``: the
        basis's extrapolation into the frame regions moved the height searched on it by -28 µm at 3 mm / 60 µm).
    levels : tuple of (int, int)
        Coarse-to-fine schedule: (pixel binning b, rays per super-pixel and axis) per level, coarse first. The
        finest level needs 4 x 4 rays per pixel: with 2 x 2 the midpoint rule's error on the marker cones (measured
        against Mitsuba renders: chi^2 per pixel 1.7e-6 at 2 x 2, 5.8e-7 at 3 x 3, 4.2e-7 at 4 x 4, 3.2e-7 at 8 x 8)
        biases the fit more than the surface's own signal. 6 x 6 jittered rays (``jitter``): shape error at
        5 mm / 40 µm 0.0022 µm against 0.0030-0.0032 µm with 4 x 4 centred or jittered rays. Default 8 x 8: chi^2
        per pixel 3.6e-7 against 5.4e-7 at 6 x 6 on a Mitsuba 16 spp render (its own floor 3.2e-7), shape at
        12 mm / 40 µm 0.00112 against 0.00126 µm (basis span), 28 against 16 s per fit, about twice the memory.
    plane_levels : tuple of (int, int)
        The schedule for a start from a plane (no centroid result): binned levels first, to widen the basin.
    absolute : {"start", "frame"}
        Where the absolute height comes from when the fit starts from the centroid method's surface: "start" keeps
        its mean ROI height (the centroid method's frame criterion, whose Gaussian-process basis extrapolates into
        the frame regions better than the thin-plate prior here: measured -0.025 vs -0.071 µm at 5 mm / 40 µm);
        "frame" searches the start height on the fitted surface (always done for a plane start).
    iterations : tuple of int
        Largest number of Gauss-Newton steps per level (the last entry repeats).
    outer_iterations : int
        Gauss-Newton steps at the finest level for each further start height (warm-started: the surfaces depend
        almost linearly on the start height).
    smoothness : float
        Weight lambda of the thin-plate prior relative to the mean diagonal of J^T W J.
    jitter : bool
        Rays at fixed pseudo-random positions inside the sub-pixels instead of their centres.
    tol_um : float
        A level stops when the RMS coefficient step falls below this, µm.
    criterion : {"level", "delta"}
        Frame criterion of the start-height search (thesis §1.4).
    outer_max : int
        Largest number of start heights tried.
    outer_tol_um : float
        Start-height search stops when ``|criterion|`` falls below this, µm.
    frame_step : float
        Spacing of the evaluation grid over the frame regions, mm.
    noise : {"auto", "emva", "none"}
        Pixel variances: EMVA 1288 (camera images in DN), constant, or chosen from the image (peak > 2: DN).
    refine_setup : bool
        Add camera and pattern rigid motions to the unknowns.
    pose_sigma : (float, float, float, float)
        Prior standard deviations of those motions: camera shift (mm), camera rotation (rad), pattern shift (mm),
        pattern rotation (rad) — the calibration's uncertainties where the setup carries them
        (:func:`pose_sigma_for`, ``[calibration]`` of a setup that ``calibrate-setup`` wrote).
    pose_box : float
        The pose stays within this many of those standard deviations of the setup (each step shortened to keep
        it so): the pixels of an unknown specular surface hardly tell a camera motion from a change of the surface's
        slopes, and on a full Mitsuba image the free fit (the Gaussian prior alone) moved the camera by 2 mm against
        a 27 µm sigma, the shape 1.5 -> 17.7 µm (``benchmarks/refine_setup.py``); within the box the shape is
        1.39 against 1.45 µm unrefined, but the poses run to its walls (camera 69 µm / 274 µrad off, from 27 µm / 71
        µrad): the pose is not identifiable from such an image.
    """

    spacing: float = 0.5
    surface: Literal["spline", "start-basis"] = "start-basis"
    levels: tuple[tuple[int, int], ...] = ((1, 8),)
    plane_levels: tuple[tuple[int, int], ...] = ((4, 4), (2, 4), (1, 8))
    iterations: tuple[int, ...] = (3,)
    absolute: Literal["start", "frame"] = "start"
    outer_iterations: int = 1
    smoothness: float = 1e-3
    jitter: bool = True
    tol_um: float = 2e-3
    criterion: FrameCriterion = "level"
    outer_max: int = 3
    outer_tol_um: float = 2e-3
    frame_step: float = 0.2
    noise: str = "auto"
    refine_setup: bool = False
    pose_sigma: tuple[float, float, float, float] = (0.05, 2e-4, 0.05, 2e-4)
    pose_box: float = 3.0


@dataclass
class InverseStep:
    """One Gauss-Newton step: level, start height, loss (chi^2 per pixel), RMS step, seconds since the start."""

    level: int
    binning: int
    start_height_um: float
    chi2: float
    step_rms_um: float
    pixels: int
    seconds: float


@dataclass
class InverseResult:
    """The fitted surface, the start height found, the iteration history and the (refined) setup."""

    surface: SplineSurface
    substrate: Substrate2D
    start_height_um: float
    criterion_um: float
    delta_h_max_um: float
    history: list[InverseStep]
    outer_iterations: int
    converged: bool
    seconds: float
    camera: Camera
    pattern: MarkerPattern
    shape_std_um: float | None = None
    extras: dict[str, Any] = field(default_factory=dict)

    def heightmap(self, nx: int = 128, ny: int = 288) -> HeightMap:
        return self.surface.heightmap(self.substrate, nx, ny)

    def summary(self) -> dict[str, Any]:
        from dataclasses import asdict

        return {
            "method": "inverse",
            "outer_iterations": self.outer_iterations,
            "inner_iterations": len(self.history),
            "delta_h_max_um": self.delta_h_max_um,
            "start_height_um": self.start_height_um,
            "criterion_um": self.criterion_um,
            "converged": self.converged,
            "seconds": self.seconds,
            "knot_spacing_mm": self.surface.dx,
            "coefficients": int(self.surface.coef.size),
            "shape_std_um": self.shape_std_um,
            "history": [asdict(h) for h in self.history],
            **self.extras,
        }


# -- the fit -------------------------------------------------------------------------------------------------------
def bin_image(image: Array, b: int, rows: tuple[int, int], cols: tuple[int, int]) -> Array:
    """Mean of b x b pixel blocks of ``image[rows, cols]`` (the window is cut to a multiple of b)."""
    r0, r1 = rows
    c0, c1 = cols
    nr, nc = (r1 - r0) // b, (c1 - c0) // b
    crop = np.asarray(image, dtype=np.float64)[r0 : r0 + nr * b, c0 : c0 + nc * b]
    return crop.reshape(nr, b, nc, b).mean(axis=(1, 3))


def pixel_variance(image: Array, setup: Setup, mode: str = "auto") -> Array:
    """EMVA 1288 variance of each pixel of a camera image in DN, or ones for a noise-free render (irradiance).

    var = K^2 sigma_d^2 + K max(I - black, 0) + 1/12 (shot noise, dark noise, quantisation; the EMVA linear model of
    :mod:`scopetwin.scenes.emva1288`). ``mode`` "auto": the EMVA variance when the image peak exceeds 2 (digital
    numbers).
    """
    img = np.asarray(image, dtype=np.float64)
    use = mode == "emva" or (mode == "auto" and float(np.max(img)) > 2.0)
    if not use:
        return np.ones_like(img)
    s = setup.sensor.sensor()
    k = s.gain_dn_per_e
    return k * k * s.dark_noise_e**2 + k * np.maximum(img - s.black_level_dn, 0.0) + 1.0 / 12.0


class _Level:
    """One resolution level: the ray model of the (binned) window's pixels and the binned image with weights."""

    def __init__(
        self,
        camera: Camera,
        pattern: MarkerPattern,
        setup: Setup,
        image: Array,
        var: Array,
        window: tuple[int, int, int, int],
        b: int,
        sub: int,
        variant: str | None,
        jitter: bool = False,
    ) -> None:
        from scopetwin.scenes.mitsuba.deflectometry_ad import RayModel

        r0, r1, c0, c1 = window
        self.b = b
        self.data = bin_image(image, b, (r0, r1), (c0, c1)).ravel()
        # variance of a block mean: mean variance / b^2
        self.var = bin_image(var, b, (r0, r1), (c0, c1)).ravel() / (b * b)
        nr, nc = (r1 - r0) // b, (c1 - c0) // b
        rr, cc = np.meshgrid(np.arange(nr), np.arange(nc), indexing="ij")
        # a super-pixel of b x b pixels: model its rays on a b-times coarser pixel grid
        assert setup.substrate is not None
        self.model: RayModel = RayModel(
            _binned_camera(camera, b, r0, c0),
            pattern,
            setup.pattern.radiance,
            setup.substrate.size,
            setup.substrate.roi_length,
            rr.ravel(),
            cc.ravel(),
            sub,
            variant,
            jitter,
        )


def _binned_camera(camera: Camera, b: int, r0: int, c0: int) -> Camera:
    """A camera whose pixel (r, c) is the b x b block of ``camera``'s pixels starting at (r0 + b r, c0 + b c)."""
    if b == 1 and r0 == 0 and c0 == 0:
        return camera
    nx_b = camera.nx // b + 2
    ny_b = camera.ny // b + 2
    # pixel grid: u = (x - nx/2) p + x_cs; block c covers x in [c0 + b c, c0 + b (c + 1))
    pitch = camera.pitch * b
    x_cs = camera.r_cs[0] + (c0 - 0.5 * camera.nx) * camera.pitch + 0.5 * nx_b * pitch
    y_cs = camera.r_cs[1] + (0.5 * camera.ny - r0) * camera.pitch - 0.5 * ny_b * pitch
    return camera.with_(nx=nx_b, ny=ny_b, pitch=pitch, r_cs=(x_cs, y_cs))


def spline_grid(surf: SplineSurface) -> SplineGrid:
    """The renderer's description of a spline surface's knot grid (:class:`scopetwin.scenes.mitsuba.deflectometry_ad.
    SplineGrid`)."""
    from scopetwin.scenes.mitsuba.deflectometry_ad import SplineGrid

    ny, nx = surf.shape
    return SplineGrid(surf.x0, surf.y0, surf.dx, surf.dy, nx, ny)


def without_plane(x: Array, y: Array, values: Array) -> Array:
    """``values`` (points, ...) less their least-squares plane a + b x + c y over the points (x, y)."""
    plane = np.column_stack([np.ones(len(x)), x, y])
    return values - plane @ np.linalg.lstsq(plane, values, rcond=None)[0]


def _shape_rms_um(s_mat: Array, cov: Array) -> float:
    """sqrt(tr(S C S^T) / m) in µm: the RMS over m points of the variance of S w (mm) for w of covariance C."""
    return float(np.sqrt(max(float(np.sum(s_mat * (s_mat @ cov))), 0.0) / s_mat.shape[0])) * 1e3


def _box_fraction(pose: Array, step: Array, bound: Array) -> float:
    """Largest f in [0, 1] with |pose + f step| <= bound componentwise (pose itself inside the box)."""
    out = np.abs(step) > 0
    room = np.where(step > 0, bound - pose, bound + pose)
    with np.errstate(divide="ignore", invalid="ignore"):
        limits = np.where(out, np.maximum(room, 0.0) / np.abs(step), np.inf)
    return float(min(1.0, np.min(limits)))


def _pose_update(camera: Camera, pattern: MarkerPattern, p: Array) -> tuple[Camera, MarkerPattern]:
    """Apply a rigid-motion step (camera shift, rotation vector; pattern shift, rotation vector) exactly."""
    from scipy.spatial.transform import Rotation

    def moved(frame: Frame, shift: Array, rot: Array) -> Frame:
        r = Rotation.from_rotvec(rot).as_matrix()
        return Frame(frame.origin + shift, r @ frame.tx, r @ frame.ty, r @ frame.nz)

    cam = camera.with_(frame=moved(camera.frame, p[0:3], p[3:6]))
    pf = moved(pattern.frame, p[6:9], p[9:12])
    return cam, replace(pattern, frame=pf)


def _warm_start(
    values: list[tuple[float, float]], surfaces: list[SplineSurface], h_new: float, surf: SplineSurface
) -> SplineSurface:
    """The start for the next start height ``h_new``: the last two fits extrapolated linearly in H (the surfaces
    depend almost linearly on it), or ``surf`` where they do not determine the line."""
    if len(values) >= 2 and values[-1][1] != values[-2][1] and values[-1][0] != values[-2][0]:
        (ha, _), (hb, _) = values[-2], values[-1]
        wgt = (h_new - hb) / (hb - ha)
        return surfaces[-1].with_coef(surfaces[-1].coef + wgt * (surfaces[-1].coef - surfaces[-2].coef))
    return surf


@dataclass
class _PoseBlocks:
    """The pose's blocks of one step's normal equations: prior sigmas (12), A_pp, A_pc (pose x coefficients), g_p."""

    sig: Array
    a_pp: Array
    a_pc: sp.csr_matrix
    g_p: Array


@dataclass
class _NormalEquations:
    """One Gauss-Newton step's linearisation: the model and data on the usable pixels ``ok``, the photometric gain
    and offset, residuals, the normal equations A x = g with the mean-height row, lambda, the pose blocks and the
    chi^2 at the current coefficients."""

    vals: Array
    ok: NDArray[np.bool_]
    data: Array
    wgt: Array
    alpha: float
    beta: float
    r: Array
    a: sp.csr_matrix
    g: Array
    m_row: Array
    lam: float
    pose: _PoseBlocks | None
    chi2_old: float


@dataclass
class _Trial:
    """One damped trial step: its surface, coefficient and pose steps, chi^2 and the pixels usable on both sides."""

    surf: SplineSurface
    dc: Array
    dp: Array | None
    chi2: float
    both: NDArray[np.bool_]


@dataclass
class _Information:
    """The Fisher information of a fit's pixels (:meth:`InverseReconstructor._information`): ``fisher`` J^T W J of
    the coefficients (k x k, J scaled by the photometric gain where the image is in its own units), ``cross`` J^T W V
    (k x 2) and ``photometric`` V^T W V (2 x 2) with V = d(alpha v + beta)/d(alpha, beta) = [v, 1] per pixel."""

    fisher: sp.csc_matrix
    cross: Array
    photometric: Array


@dataclass
class _HeightSearch:
    """The start-height search's end: the start height, criterion, frame maxima, heights tried, converged."""

    h: float
    crit: float
    m1: float
    m2: float
    tried: int
    converged: bool


class InverseReconstructor:
    """Fits the substrate's surface to one deflectometry image through the differentiable render (module doc).

    Parameters
    ----------
    setup : Setup
        The (calibrated) deflectometry setup.
    image : ndarray (ny, nx)
        The camera image (irradiance or DN).
    config : InverseConfig, optional
    variant : str, optional
        Renderer backend (default: ``cuda`` when a GPU is usable, else ``llvm``).
    window : (row0, row1, col0, col1), optional
        The pixels fitted (default: the image of the region of interest).
    """

    def __init__(
        self,
        setup: Setup,
        image: NDArray[Any],
        config: InverseConfig | None = None,
        variant: str | None = None,
        window: tuple[int, int, int, int] | None = None,
    ) -> None:
        if setup.scene != "deflectometry" or setup.substrate is None:
            raise ReconstructionError(f"setup {setup.name} is a {setup.scene!r} scene, not a deflectometry setup")
        cam = setup.camera_model
        img = np.asarray(image, dtype=np.float64)
        if img.shape != (cam.ny, cam.nx):
            raise ReconstructionError(
                f"image is {img.shape[1]} x {img.shape[0]} px, the camera has {cam.nx} x {cam.ny}"
            )
        self.setup = setup
        self.image = img
        self.config = config or InverseConfig()
        self.variant = variant
        self.sub = Substrate2D.from_setup(setup)
        self.camera = cam
        self.pattern = setup.marker_pattern
        self.var = pixel_variance(img, setup, self.config.noise)
        self.window: tuple[int, int, int, int] = (
            self._window() if window is None else (int(window[0]), int(window[1]), int(window[2]), int(window[3]))
        )
        self.history: list[InverseStep] = []
        self._t0 = time.perf_counter()
        self.pose = np.zeros(12)
        fx, fy = self.sub.frame_grid(1, self.config.frame_step)
        gx, gy = self.sub.frame_grid(2, self.config.frame_step)
        self._frame_pts = ((fx, fy), (gx, gy))
        #: spline coefficients of the start's basis (columns) when the fit keeps to its span, else None
        self._span: Array | None = None

    def _window(self) -> tuple[int, int, int, int]:
        """Pixel window of the ROI's image (its corners and edges projected, at the frame height), padded."""
        sub = self.sub
        t = np.linspace(-1.0, 1.0, 64)
        hx, hy = 0.5 * sub.size_x, 0.5 * sub.roi_length
        edge = np.concatenate(
            [np.stack([hx * t, np.full_like(t, s * hy)], -1) for s in (-1, 1)]
            + [np.stack([np.full_like(t, s * hx), hy * t], -1) for s in (-1, 1)]
        )
        pts = np.concatenate([edge, np.zeros((len(edge), 1))], axis=1)
        px = self.camera.project(pts)
        if not np.all(np.isfinite(px)):
            raise ReconstructionError("the substrate's region of interest is not in front of the camera")
        c0, r0 = np.floor(px.min(axis=0)).astype(int) - 8
        c1, r1 = np.ceil(px.max(axis=0)).astype(int) + 8
        c0, r0 = max(int(c0), 0), max(int(r0), 0)
        c1, r1 = min(int(c1), self.camera.nx), min(int(r1), self.camera.ny)
        if c1 - c0 < 8 or r1 - r0 < 8:
            raise ReconstructionError("the camera does not see the substrate's region of interest")
        return (r0, r1, c0, c1)

    # -- one level --------------------------------------------------------------------------------------------
    def _level(self, b: int, sub: int) -> _Level:
        return _Level(
            self.camera,
            self.pattern,
            self.setup,
            self.image,
            self.var,
            self.window,
            b,
            sub,
            self.variant,
            self.config.jitter,
        )

    def _linearise(
        self, lev: _Level, surf: SplineSurface, need_jac: bool = True
    ) -> tuple[Array, NDArray[np.bool_], sp.csr_matrix | None, Array | None]:
        """Model pixel values, usable-pixel mask, sparse Jacobian (usable pixels x coefficients), pose Jacobian."""
        model = lev.model
        res = model.trace(
            spline_grid(surf), surf.coef, sensitivities=need_jac, pose=need_jac and self.config.refine_setup
        )
        vals, ok = model.pixel_values(res)
        if not need_jac:
            return vals, ok, None, None
        assert res.sens is not None
        npix = int(ok.sum())
        xm, ym, ma, mb, mc, max_, may, mbx, mby, mcx, mcy = _pixel_moments(res, ok, model.spp)
        idx, w, wx, wy, (wxx, wxy, wyy) = surf.basis_rows_second(xm, ym)
        col = lambda v: v[:, None]  # noqa: E731
        data = (
            col(ma) * w
            + col(max_ + mb) * wx
            + col(may + mc) * wy
            + col(mbx) * wxx
            + col(mby + mcx) * wxy
            + col(mcy) * wyy
        )
        rows = np.repeat(np.arange(npix), 16)
        jac = sp.csr_matrix((data.ravel(), (rows, idx.ravel())), shape=(npix, surf.coef.size))
        jpose = None
        if res.pose is not None:
            jpose = res.pose.reshape(12, -1, model.spp).mean(axis=2)[:, ok].T
        return vals, ok, jac, jpose

    def _photometric(self, vals: Array, data: Array, w: Array) -> tuple[float, float]:
        """Gain and offset (alpha, beta) minimising sum w (data - alpha vals - beta)^2."""
        a = np.stack([vals, np.ones_like(vals)], axis=1)
        sw = np.sqrt(w)
        sol, *_ = np.linalg.lstsq(a * sw[:, None], data * sw, rcond=None)
        return float(sol[0]), float(sol[1])

    def fit_level(self, lev: _Level, surf: SplineSurface, h: float, iterations: int, index: int) -> SplineSurface:
        """Gauss-Newton steps at one level with mean ROI height fixed to ``h``; returns the new surface.

        Each step: the normal equations at the current surface (:meth:`_normal_equations`), then Levenberg-Marquardt
        trials of growing damping until one lowers chi^2 (:meth:`_damped_step`); the level ends when none does, when
        the RMS coefficient step falls below ``tol_um`` or after ``iterations`` steps.
        """
        cfg = self.config
        d = surf.smoothness()
        dtd = (d.T @ d).tocsr()
        mean_row = self._mean_row(surf)
        lam = None
        mu = 1e-3
        c = surf.coef.ravel().copy()
        # enforce the constraint exactly at the start: shift the surface to mean height h
        c += h - float(mean_row @ c)
        surf = surf.with_coef(c)
        for _ in range(iterations):
            ne = self._normal_equations(lev, surf, c, dtd, mean_row, lam)
            lam = ne.lam
            trial, mu = self._damped_step(lev, surf, c, ne, dtd, mu)
            if trial is None:
                self._record(index, lev, h, ne.chi2_old / max(len(ne.r), 1), 0.0, len(ne.r))
                break
            c = c + trial.dc
            if trial.dp is not None:
                self.pose = self.pose + trial.dp
            surf = trial.surf
            step_um = float(np.sqrt(np.mean(trial.dc**2))) * 1e3
            self._record(index, lev, h, trial.chi2 / max(int(trial.both.sum()), 1), step_um, int(trial.both.sum()))
            if step_um < cfg.tol_um:
                break
        return surf

    def _mean_row(self, surf: SplineSurface) -> Array:
        """The row m of the mean ROI height the fit holds: m @ c is the mean of ``surf`` over the ROI's grid."""
        xs, ys = self.sub.roi_grid(max(surf.dx, 0.5))
        return np.asarray(surf.design(xs, ys).mean(axis=0)).ravel()

    def _prior_weight(self, info: sp.spmatrix, dtd: sp.spmatrix) -> float:
        """The thin-plate prior's weight lambda: ``smoothness`` relative to the mean diagonals of J^T W J and D^T D."""
        return self.config.smoothness * float(info.diagonal().mean()) / max(float(dtd.diagonal().mean()), 1e-300)

    def _normal_equations(
        self, lev: _Level, surf: SplineSurface, c: Array, dtd: sp.csr_matrix, mean_row: Array, lam: float | None
    ) -> _NormalEquations:
        """The Gauss-Newton normal equations of one step at ``surf`` (coefficients ``c``), photometry solved.

        ``lam``: the thin-plate prior's weight, None at a level's first step (then set relative to the mean diagonal
        of J^T W J). Where the fit keeps to a span, the equations are in the span's coordinates; with
        ``refine_setup`` the pose blocks are added (:meth:`_pose_blocks`).
        """
        vals, ok, jac, jpose = self._linearise(lev, surf)
        assert jac is not None
        data, wgt = lev.data[ok], 1.0 / lev.var[ok]
        alpha, beta = self._photometric(vals[ok], data, wgt)
        r = data - alpha * vals[ok] - beta
        ja = jac * alpha
        jtw = ja.T.multiply(wgt[None, :]).tocsr()
        jtj = (jtw @ ja).tocsr()
        if lam is None:
            lam = self._prior_weight(jtj, dtd)
        g = jtw @ r - lam * (dtd @ c)
        a = (jtj + lam * dtd).tocsr()
        m_row = mean_row
        span = self._span
        if span is not None:  # the surfaces c + P da: the normal equations in the span's coordinates
            a, g, m_row = sp.csr_matrix(span.T @ (a @ span)), span.T @ g, span.T @ mean_row
        pose = None if jpose is None else self._pose_blocks(jpose * alpha, wgt, ja, r)  # rows of the usable pixels
        chi2_old = float(np.sum(wgt * r * r) + lam * c @ (dtd @ c))
        return _NormalEquations(vals, ok, data, wgt, alpha, beta, r, a, g, m_row, lam, pose, chi2_old)

    def _pose_blocks(self, jp: Array, wgt: Array, ja: sp.csr_matrix, r: Array) -> _PoseBlocks:
        """The 12 pose parameters' blocks of the normal equations, their Gaussian prior about the setup included.

        ``jp``: the pose Jacobian of the usable pixels scaled by the photometric gain, ``ja`` the coefficients' one.
        """
        span = self._span
        sig = np.repeat(np.asarray(self.config.pose_sigma, dtype=np.float64), 3)  # (shift, rotation) x 3 per device
        prior = 1.0 / np.maximum(sig, 1e-12) ** 2
        jpw = jp.T * wgt[None, :]
        a_pp = jpw @ jp + np.diag(prior)
        a_pc = sp.csr_matrix(jpw @ ja if span is None else (jpw @ ja) @ span)
        g_p = jpw @ r - prior * self.pose
        return _PoseBlocks(sig, a_pp, a_pc, g_p)

    def _kkt_step(self, ne: _NormalEquations, mu: float) -> tuple[Array, Array | None]:
        """The damped step (coefficients, pose or None) from the KKT system of the mean-height constraint.

        Damping ``mu`` times the diagonal (Levenberg-Marquardt); the joint step is shortened so that the pose stays
        within ``pose_box`` standard deviations of the setup.
        """
        a, m_row, pb = ne.a, ne.m_row, ne.pose
        damp = a + mu * sp.diags(a.diagonal() + 1e-300)
        blocks = [[damp, m_row[:, None]], [m_row[None, :], None]]
        rhs = [ne.g, np.zeros(1)]
        npose = 0
        if pb is not None:
            npose = 12
            blocks = [
                [damp, pb.a_pc.T, m_row[:, None]],
                [pb.a_pc, sp.csr_matrix(pb.a_pp * (1 + mu)), None],
                [m_row[None, :], None, None],
            ]
            rhs = [ne.g, pb.g_p, np.zeros(1)]
        kkt = sp.bmat(blocks, format="csc")
        step = spla.spsolve(kkt, np.concatenate(rhs))
        k = len(m_row)
        frac = 1.0
        dp = step[k : k + npose] if npose else None
        if dp is not None:  # the joint step shortened so that the pose stays within pose_box sigma
            assert pb is not None
            frac = _box_fraction(self.pose, dp, self.config.pose_box * pb.sig)
            dp = dp * frac
        dc = frac * (step[:k] if self._span is None else self._span @ step[:k])
        return dc, dp

    def _trial(
        self, lev: _Level, surf: SplineSurface, c: Array, ne: _NormalEquations, dtd: sp.csr_matrix, mu: float
    ) -> tuple[_Trial, float, tuple[Camera, MarkerPattern] | None]:
        """One damped trial step: its surface (the level's rays moved with the pose), chi^2 and the reference chi^2.

        Both chi^2 on the pixels usable before and after the step. Returns the trial, the reference chi^2 and the
        level's (camera, pattern) before the pose step (None without one), to restore if the trial is rejected.
        """
        dc, dp = self._kkt_step(ne, mu)
        lam = ne.lam
        trial = surf.with_coef(c + dc)
        saved: tuple[Camera, MarkerPattern] | None = None
        if dp is not None:
            saved = (lev.model.camera, lev.model.pattern)
            self._apply_pose(lev, dp)
        tv, tok, _, _ = self._linearise(lev, trial, need_jac=False)
        both = ne.ok & tok
        ta, tb = self._photometric(tv[both], lev.data[both], 1.0 / lev.var[both])
        tr = lev.data[both] - ta * tv[both] - tb
        chi2_new = float(np.sum(tr * tr / lev.var[both]) + lam * (c + dc) @ (dtd @ (c + dc)))
        # compare on the common pixels
        r_common = (ne.data - ne.alpha * ne.vals[ne.ok] - ne.beta)[both[ne.ok]]
        chi2_ref = float(np.sum(r_common**2 * ne.wgt[both[ne.ok]]) + lam * c @ (dtd @ c))
        return _Trial(trial, dc, dp, chi2_new, both), chi2_ref, saved

    def _damped_step(
        self, lev: _Level, surf: SplineSurface, c: Array, ne: _NormalEquations, dtd: sp.csr_matrix, mu: float
    ) -> tuple[_Trial | None, float]:
        """Up to four trials, the damping tenfold after each rejected one; the accepted trial (or None) and mu."""
        for _ in range(4):
            trial, chi2_ref, saved = self._trial(lev, surf, c, ne, dtd, mu)
            if trial.chi2 <= chi2_ref or not np.isfinite(chi2_ref):
                mu = max(mu / 3.0, 1e-7)
                return trial, mu
            if saved is not None:  # the pose step's rays undone
                lev.model.camera, lev.model.pattern = saved
                self._rebuild_rays(lev)
            mu *= 10.0
        return None, mu

    def _apply_pose(self, lev: _Level, dp: Array) -> None:
        cam, pat = _pose_update(self.camera, self.pattern, self.pose + dp)
        lev.model.camera = _binned_camera(cam, lev.b, self.window[0], self.window[2])
        lev.model.pattern = pat
        self._rebuild_rays(lev)

    @staticmethod
    def _rebuild_rays(lev: _Level) -> None:
        from scopetwin.scenes.mitsuba.deflectometry_ad import RayModel

        m = lev.model
        fresh = RayModel(m.camera, m.pattern, m.radiance, m.size, m.roi_length, m.rows, m.cols, m.sub, None, m.jitter)
        fresh.m = m.m
        lev.model = fresh

    def _record(self, index: int, lev: _Level, h: float, chi2: float, step_um: float, pixels: int) -> None:
        self.history.append(InverseStep(index, lev.b, h * 1e3, chi2, step_um, pixels, time.perf_counter() - self._t0))

    def shape_std_um(
        self,
        surf: SplineSurface,
        var: Any = None,
        sub: int = 3,
        probes: int = 32,
        level: _Level | None = None,
        fisher: sp.csc_matrix | None = None,
    ) -> float:
        """Standard deviation of the ROI shape (RMS over the ROI, mean removed) from the Fisher information, µm.

        The covariance of the coefficients is the inverse of J^T W J + lambda D^T D (the render's Jacobian at
        ``surf`` with W = 1/var, the fit's thin-plate prior), with the mean ROI height held fixed as in the fit;
        with the true pixel variances it is the Cramér-Rao bound of the pixel data (plus prior) on the shape.
        sqrt(mean diag(A C A^T)) over the ROI heights A (mean removed) is traced by ``probes`` Hutchinson probes.
        ``var``: pixel variances of the full image in the render's units (irradiance); default: those of the fit,
        in the image's units (DN for a camera), the Jacobian then scaled by the photometric gain alpha of the
        loss. ``level``: the fit's own full-resolution level to reuse (with the fit's variances), instead of
        building a second ray model. Where the fit keeps to a basis's span (``surface="start-basis"``) the
        covariance is that of the span's coordinates and the trace exact. ``fisher``: J^T W J already formed
        (:meth:`_fisher` on the same ``var``, ``sub`` and ``level``).
        """
        if fisher is None:
            fisher = self._fisher(surf, var, sub, level)
        d = surf.smoothness()
        dtd = d.T @ d
        lam = self._prior_weight(fisher, dtd)
        xs, ys = self.sub.roi_grid(0.5)
        design = surf.design(xs, ys)
        m = np.asarray(design.mean(axis=0)).ravel()
        if self._span is not None:  # the span's few coordinates: the trace exactly, with dense algebra
            p = self._span
            a = p.T @ ((fisher + lam * dtd) @ p)
            q = null_space((p.T @ m)[None, :])  # coordinates that keep the mean ROI height, as in the fit
            a_q = q.T @ a @ q
            scale = 1.0 / np.sqrt(np.abs(np.diag(a_q)) + 1e-300)  # equilibrated: DN images have a huge J^T W J
            cov = q @ (scale[:, None] * np.linalg.inv(scale[:, None] * a_q * scale[None, :]) * scale[None, :]) @ q.T
            dc = np.asarray(design @ p)
            return _shape_rms_um(dc - dc.mean(axis=0), cov)  # mean removed: the shape
        kkt = sp.bmat([[fisher + lam * dtd, m[:, None]], [m[None, :], None]], format="csc")
        lu = spla.splu(kkt)
        rng = np.random.default_rng(0)
        n = surf.coef.size
        acc = 0.0
        for _ in range(probes):
            z = rng.choice([-1.0, 1.0], size=design.shape[0])
            z -= z.mean()  # mean removed: the shape
            v = np.asarray(design.T @ z).ravel()
            x = lu.solve(np.concatenate([v, [0.0]]))[:n]
            acc += float(v @ x)
        return float(np.sqrt(max(acc, 0.0) / probes / design.shape[0])) * 1e3

    def start_height_term_um(
        self,
        lev: _Level,
        surf: SplineSurface,
        h: float,
        absolute_std_um: float,
        information: _Information | None = None,
    ) -> float:
        """The start height's uncertainty carried into the shape, µm (RMS over the ROI).

        The rays are traced through a surface at the start height H, so an error of H tilts and bends the fitted
        shape (thesis §1.4; the centroid method's
        :meth:`scopetwin.recon.reconstruct.Reconstructor._start_height_sensitivity`). The fit's response dc/dH at
        its solution is that of its Gauss-Newton normal equations to the held mean ROI height, the photometric gain
        and offset (alpha, beta) answering with the coefficients: the KKT system
        [[F + lambda D^T D, C, m], [C^T, B, 0], [m^T, 0, 0]] [dc; d(alpha, beta); nu] = [0; 0; 1], with the Fisher
        information F at the fit, C and B its blocks with the photometric parameters (``information``,
        :meth:`_information` on ``lev``), the thin-plate weight lambda and the ROI mean row m as the fit sets them.
        The term is sqrt(mean((d contrast/dH * u_abs)^2)) over the ROI, contrast = height minus its ROI mean. With
        ``refine_setup`` the pose answers too: one more Gauss-Newton pass at H + 0.2 µm from the fit, by finite
        difference (:meth:`_start_height_term_fd`).
        """
        if self.config.refine_setup:
            return self._start_height_term_fd(lev, surf, h, absolute_std_um)
        if information is None:
            information = self._information(surf, None, lev.model.sub, lev)
        xs, ys = self.sub.roi_grid(0.5)
        sens = np.asarray(surf.design(xs, ys) @ self._height_response(surf, information)).ravel()
        return float(np.sqrt(np.mean(((sens - sens.mean()) * absolute_std_um) ** 2)))

    def _height_response(self, surf: SplineSurface, information: _Information) -> Array:
        """dc/dH: the coefficients' first-order response to the mean ROI height the fit holds (its KKT system at
        ``surf``, undamped, :meth:`start_height_term_um`; equilibrated by its diagonal, which leaves dc unchanged)."""
        fisher, cross = information.fisher, information.cross
        d = surf.smoothness()
        dtd = (d.T @ d).tocsr()
        lam = self._prior_weight(fisher, dtd)
        m_row = self._mean_row(surf)
        a = (fisher + lam * dtd).tocsr()
        if self._span is not None:  # the span's coordinates, as the fit's normal equations
            a, m_row = sp.csr_matrix(self._span.T @ (a @ self._span)), self._span.T @ m_row
            cross = self._span.T @ cross
        k = len(m_row)
        diag = np.concatenate([a.diagonal(), np.diag(information.photometric)])
        scale = 1.0 / np.sqrt(np.maximum(np.abs(diag), 1e-300))
        s_c, s_p = scale[:k], scale[k:]
        c_s = sp.csr_matrix(s_c[:, None] * cross * s_p[None, :])
        m_s = (s_c * m_row)[:, None]
        kkt = sp.bmat(
            [
                [sp.diags(s_c) @ a @ sp.diags(s_c), c_s, m_s],
                [c_s.T, sp.csr_matrix(s_p[:, None] * information.photometric * s_p[None, :]), None],
                [m_s.T, None, None],
            ],
            format="csc",
        )
        rhs = np.zeros(k + 3)
        rhs[-1] = 1.0
        dc = s_c * spla.spsolve(kkt, rhs)[:k]
        return dc if self._span is None else self._span @ dc

    def _start_height_term_fd(self, lev: _Level, surf: SplineSurface, h: float, absolute_std_um: float) -> float:
        """:meth:`start_height_term_um` by one more Gauss-Newton pass at H + 0.2 µm (the pose re-fitted with it)."""
        dh = 2e-4  # mm
        n = len(self.history)
        try:
            other = self.fit_level(lev, surf, h + dh, max(self.config.outer_iterations, 1), -1)
        finally:
            del self.history[n:]  # not a step of the fit
        xs, ys = self.sub.roi_grid(0.5)
        c1, c2 = surf.height(xs, ys), other.height(xs, ys)
        sens = ((c2 - c2.mean()) - (c1 - c1.mean())) / dh
        return float(np.sqrt(np.mean((sens * absolute_std_um) ** 2)))

    def _fisher(self, surf: SplineSurface, var: Any, sub: int, level: _Level | None) -> sp.csc_matrix:
        """J^T W J of the full-resolution render at ``surf`` (:meth:`shape_std_um` on ``var`` and ``level``)."""
        return self._information(surf, var, sub, level).fisher

    def _information(self, surf: SplineSurface, var: Any, sub: int, level: _Level | None) -> _Information:
        """:meth:`_fisher` with the photometric parameters' blocks beside it (one linearisation)."""
        if level is not None and var is None and level.b == 1 and level.model.sub == sub:
            lev = level
        else:
            saved = self.var
            if var is not None:
                self.var = np.asarray(var, dtype=np.float64)
            try:
                lev = self._level(1, sub)
            finally:
                self.var = saved
        vals, ok, jac, _ = self._linearise(lev, surf)
        assert jac is not None
        w = 1.0 / lev.var[ok]
        if var is None:  # the image's own units (DN for a camera): the render scaled by the photometric gain
            jac = jac * self._photometric(vals[ok], lev.data[ok], w)[0]
        jtw = jac.T.multiply(w[None, :]).tocsr()
        photometric = np.stack([vals[ok], np.ones(int(ok.sum()))], axis=1)  # d(alpha v + beta)/d(alpha, beta)
        return _Information(
            (jtw @ jac).tocsc(), np.asarray(jtw @ photometric), photometric.T @ (w[:, None] * photometric)
        )

    def shape_bayes_bound_um(
        self, surf: SplineSurface, prior: Array, var: Any = None, sub: int = 3, untilted: bool = False
    ) -> float:
        """Bayesian Cramér-Rao (Van Trees) bound on the ROI shape RMS under a Gaussian prior of the surface, µm.

        ``prior``: the square root X (n, r) of the prior covariance X X^T of the spline coefficients (e.g. the
        centred coefficients of r draws of the surface family, over sqrt(r - 1): :func:`family_prior`). With the
        Fisher information F = J^T W J of the pixels at ``surf`` (``var`` as in :meth:`shape_std_um`), the
        coefficients c = c_mean + X w have the information I + X^T F X in w; the bound is sqrt(tr(S C S^T) / m)
        with C its inverse and S the shape (mean removed; ``untilted``: best-fit plane removed) of the columns of
        X at the m ROI points. The mean ROI height is known in it (the prior conditioned on it, as the fit holds
        it): without the frame criterion the pixels leave height and tilt nearly interchangeable (thesis §1.4), and
        a bound given more information still bounds every estimator, the centroid method's included, on the
        Bayesian mean-square error over the family (F taken at this surface instead of averaged over it).
        """
        x = np.asarray(prior, dtype=np.float64)
        if x.ndim != 2 or x.shape[0] != surf.coef.size:
            raise ReconstructionError(f"prior square root is {x.shape}, the spline has {surf.coef.size} coefficients")
        fisher = self._fisher(surf, var, sub, None)
        xs, ys = self.sub.roi_grid(0.5)
        design = surf.design(xs, ys)
        heights = np.asarray(design @ x)
        q = null_space(heights.mean(axis=0)[None, :])  # w = Q u: the draws of the known mean ROI height
        xq = x @ q
        info = np.eye(q.shape[1]) + xq.T @ np.asarray(fisher @ xq)
        s_mat = heights @ q
        s_mat = without_plane(xs, ys, s_mat) if untilted else s_mat - s_mat.mean(axis=0)  # the shape
        return _shape_rms_um(s_mat, np.linalg.inv(info))

    def frame_maxima(self, surf: SplineSurface) -> tuple[float, float]:
        """Maxima of the surface over frame region 1 and 2, mm (thesis eq. 1.3)."""
        (ax, ay), (bx, by) = self._frame_pts
        return float(np.max(surf.height(ax, ay))), float(np.max(surf.height(bx, by)))

    def run(self, initial: Any = None, absolute_std_um: float | None = None) -> InverseResult:
        """Coarse-to-fine fit with the start-height search (module docstring).

        ``initial``: a surface with ``height(x, y)`` to start from (the centroid method's), or None (a plane at the
        frame height). ``absolute_std_um``: the standard uncertainty of the start height held (the centroid
        method's); its part of the shape uncertainty is added (:meth:`start_height_term_um`).
        """
        cfg = self.config
        t0 = self._t0 = time.perf_counter()
        surf = self._start_surface(initial)
        xs, ys = self.sub.roi_grid(0.5)
        h = float(np.mean(surf.height(xs, ys)))
        schedule = cfg.levels if initial is not None else cfg.plane_levels
        levels = [self._level(b, s) for b, s in schedule]
        search = initial is None or cfg.absolute == "frame"
        surf = self._coarse_to_fine(levels, surf, h)
        fine = levels[-1]
        surf, found = self._height_search(fine, surf, h, len(levels) - 1, search)
        return self._result(surf, found, fine, schedule[-1][1], search, absolute_std_um, t0)

    def _start_surface(self, initial: Any) -> SplineSurface:
        """The start's spline: a plane at the frame height, or ``initial`` fitted; the span to keep to, if any."""
        cfg = self.config
        self._span = None
        if initial is None:
            return SplineSurface.covering(self.sub, cfg.spacing, self.sub.frame_z)
        surf = SplineSurface.fit(initial.height, self.sub, cfg.spacing)
        basis = getattr(initial, "basis", None)
        if cfg.surface == "start-basis" and cfg.absolute == "start" and isinstance(basis, ShiftedBasis):
            self._span = SplineSurface.span(basis, self.sub, cfg.spacing)
        return surf

    def _coarse_to_fine(self, levels: list[_Level], surf: SplineSurface, h: float) -> SplineSurface:
        """The levels in turn at the first start height ``h``, each from the surface (and pose) of the one before."""
        cfg = self.config
        its = list(cfg.iterations) + [cfg.iterations[-1]] * len(levels)
        for k, lev in enumerate(levels):
            if cfg.refine_setup and self.pose.any():  # the pose found at the coarser level
                self._apply_pose(lev, np.zeros(12))
            surf = self.fit_level(lev, surf, h, its[k], k)
        return surf

    def _height_search(
        self, fine: _Level, surf: SplineSurface, h: float, index: int, search: bool
    ) -> tuple[SplineSurface, _HeightSearch]:
        """The start-height search on the finest level (secant on the frame criterion, thesis §1.4).

        ``surf``: the fit at the first start height ``h``; without ``search`` only its criterion is evaluated.
        """
        cfg = self.config
        values: list[tuple[float, float]] = []
        surfaces: list[SplineSurface] = []
        converged = False
        crit = float("nan")
        m1 = m2 = float("nan")
        for outer in range(cfg.outer_max):
            if outer > 0:
                surf = self.fit_level(fine, surf, h, cfg.outer_iterations, index)
            m1, m2 = self.frame_maxima(surf)
            crit = frame_criterion(m1, m2, self.sub.frame_z, cfg.criterion)
            values.append((h, crit))
            surfaces.append(surf)
            if abs(crit) * 1e3 <= cfg.outer_tol_um or not search:
                converged = True
                break
            d_min = frame_distance(m1, m2, self.sub.frame_z)
            h_new = next_start_height(values, h - (d_min if cfg.criterion == "delta" else crit))
            surf = _warm_start(values, surfaces, h_new, surf)
            h = float(h_new)
        return surf, _HeightSearch(h, crit, m1, m2, len(values), converged)

    def _result(
        self,
        surf: SplineSurface,
        found: _HeightSearch,
        fine: _Level,
        sub_rays: int,
        search: bool,
        absolute_std_um: float | None,
        t0: float,
    ) -> InverseResult:
        """The result of :meth:`run`: the refined setup and the shape uncertainty (start-height term included)."""
        cfg = self.config
        h = found.h
        cam, pat = (
            _pose_update(self.camera, self.pattern, self.pose) if cfg.refine_setup else (self.camera, self.pattern)
        )
        # shape uncertainty: the Fisher information at the fit, scaled by the reduced chi^2 (the residuals' own
        # variance where the pixel variances are only known up to a factor, as for a noise-free render)
        chi2 = self.history[-1].chi2 if self.history else 1.0
        info = self._information(surf, None, sub_rays, fine)  # one linearisation for both terms
        shape_std = self.shape_std_um(surf, None, sub_rays, level=fine, fisher=info.fisher) * float(
            np.sqrt(max(chi2, 0.0))
        )
        span_terms = None if self._span is None else int(self._span.shape[1])
        height_term = None
        if absolute_std_um is not None and not search:
            height_term = self.start_height_term_um(fine, surf, h, float(absolute_std_um), information=info)
            shape_std = float(np.hypot(shape_std, height_term))
        return InverseResult(
            surf,
            self.sub,
            h * 1e3,
            found.crit * 1e3,
            (found.m1 - found.m2) * 1e3,
            self.history,
            found.tried,
            found.converged,
            time.perf_counter() - t0,
            cam,
            pat,
            shape_std,
            {
                "surface": "spline" if self._span is None else "start-basis",
                "span_terms": span_terms,
                "start_height_term_um": height_term,
            },
        )


def pose_sigma_for(
    setup: Setup, default: tuple[float, float, float, float] | None = None
) -> tuple[float, float, float, float]:
    """The prior standard deviations of ``--refine-setup`` (:class:`InverseConfig` ``pose_sigma``) for a setup.

    A setup written by ``calibrate-setup`` carries its calibration's uncertainties (``[calibration]``: camera and
    pattern, shift mm and rotation rad, thesis §2.7); other setups get ``default`` (that of :class:`InverseConfig`).
    """
    cal = setup.calibration
    if cal is None:
        return default or InverseConfig().pose_sigma
    return (cal.camera.shift_mm, cal.camera.rotation_rad, cal.pattern.shift_mm, cal.pattern.rotation_rad)


def reconstruct_inverse(
    setup: Setup,
    image: NDArray[Any],
    initial: Any = None,
    config: InverseConfig | None = None,
    variant: str | None = None,
    absolute_std_um: float | None = None,
) -> InverseResult:
    """Fit the substrate's surface to a deflectometry image through the differentiable render (module docstring).

    Parameters
    ----------
    setup : Setup
        The (calibrated) deflectometry setup.
    image : ndarray, (ny, nx)
        The camera image.
    initial : object with ``height(x, y)``, optional
        Start surface (the centroid method's); None: a plane at the frame height.
    config : InverseConfig, optional
    variant : str, optional
        Backend of the render (``cuda`` when a GPU is usable, else ``llvm``).
    absolute_std_um : float, optional
        Standard uncertainty of the start height held (the centroid method's), µm: its part of the shape
        uncertainty is added.
    """
    return InverseReconstructor(setup, image, config, variant).run(initial, absolute_std_um)
