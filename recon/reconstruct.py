"""Non-stereoscopic deflectometric height reconstruction: the nested start-height iteration (seed §1.4).

Inner loop (self-consistent surface for a start height H, §1.4 and Fig. 1.4): start
with the plane z = H (or the previous outer run's surface moved to H); trace every
marker's camera ray to the current surface (secant iteration, §1.6.4,
:func:`scopetwin.scenes.surface.secant_intersection`), form the
normal from the camera ray and the ray to the marker centre (§1.7.1), turn it into a
gradient (§1.7.3), fit the shifted basis functions (§1.8) and set the bias so that the
surface's mean height over the region of interest is H (eq. 1.5). Stop when the RMS
height change over the ROI falls below a threshold. An optional centroid-bias step
(any callable) replaces the measured marker positions by bias-corrected ones in every
inner iteration.

Outer loop (start height, eq. 1.3-1.4): evaluate the maxima of the reconstructed
surface over the two holding-frame regions, where there are no data and the surface
is extrapolated. Criteria (:func:`scopetwin.recon.frame_criterion.frame_criterion`):

* ``"delta"`` — the seed's Delta h_max = max_region1 - max_region2 = 0 (eq. 1.3);
* ``"level"`` — both maxima at the frame position: (max_1 + max_2)/2 = z_frame. The
  start height moves the ROI almost as a pure offset but Delta h_max only at about half
  that rate, so an extrapolation error in the frame regions costs roughly twice as much
  absolute height with ``"delta"`` as with ``"level"`` (see benchmarks/thesis_1_10.py).

Searches: ``"thesis"`` is eq. 1.4, H_{i+1} = H_i - d_min (d_min: the frame maximum
closest to the frame position, with its sign); its fixed point is d_min = 0 (one maximum
on the frame), not Delta h_max = 0, so on this setup it stalls with Delta h_max != 0.
``"secant"`` is a root search on the criterion (secant, kept inside the bracket once the
root is bracketed), started with the thesis step. Each outer run is warm-started from the
previous surfaces extrapolated linearly in H (the response to H is nearly linear).

Default basis (beyond the seed): Gaussians on a grid overhanging the substrate, ridge
damping and plane terms — the Gaussian-process prior of the §1.9 surfaces, which is what
controls the extrapolation into the frame regions. Its scale is chosen from the data
(:func:`select_sigma`, after a first pass with ``sigma``: converged, or not converged because that scale cannot
fit the surface, as a 12 mm basis on a 3 mm correlated glass). After convergence the
frame condition that was not searched on is checked (``consistency_um``), so a mis-indexed
image or a wrong setup raises instead of giving a smooth, tilted, wrong map.

Nothing here imports Mitsuba or sim: input is a setup (camera, pattern, substrate
geometry) and marker observations (index + image position).
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scopetwin.recon.frame_criterion import FrameCriterion, frame_criterion, frame_distance
from scopetwin.recon.gradients import marker_gradients
from scopetwin.recon.shifted_basis import BasisKind, SBFSurface, ShiftedBasis, fit_gradients
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.geometry import Array, Frame
from scopetwin.scenes.pattern import MarkerPattern
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap, secant_intersection

#: A centroid-bias step: (current surface, marker indices (n, 2), measured image positions (n, 2) px)
#: -> corrected image positions of the marker centres (n, 2) px.
BiasStep = Callable[[SBFSurface, NDArray[np.int64], Array], Array]


class ReconstructionError(ScopetwinError, ValueError):
    """The reconstruction cannot be done with this input; the message says why."""


class TooFewMarkersError(ReconstructionError):
    """Too few markers overall, or next to one of the frame regions."""


class SubstrateNotVisibleError(ReconstructionError):
    """The setup's camera does not see the substrate (or the markers' rays miss it)."""


class InconsistentError(ReconstructionError):
    """The converged surface violates the frame condition that was not searched on (wrong indexing or setup)."""


class NotConvergedError(ReconstructionError):
    """The outer start-height loop did not converge; ``history`` holds what was done, ``surface`` its last surface."""

    def __init__(
        self, message: str, history: list[dict[str, Any]], history_path: Path | None, surface: Any = None
    ) -> None:
        super().__init__(message)
        self.history = history
        self.history_path = history_path
        self.surface = surface


@dataclass(frozen=True)
class Substrate2D:
    """The substrate's footprint on its base plane (seed §1.4, §1.10): extent, ROI length, frame position."""

    size_x: float
    size_y: float
    roi_length: float
    frame: Frame = field(default_factory=Frame.identity)
    frame_z: float = 0.0

    @classmethod
    def from_setup(cls, setup: Setup, frame_z: float = 0.0) -> Substrate2D:
        if setup.scene != "deflectometry" or setup.substrate is None:
            raise ReconstructionError(f"setup {setup.name} is a {setup.scene!r} scene, not a deflectometry setup")
        sx, sy = setup.substrate.size
        return cls(float(sx), float(sy), float(setup.substrate.roi_length), Frame.identity(), frame_z)

    @property
    def x_range(self) -> tuple[float, float]:
        return (-0.5 * self.size_x, 0.5 * self.size_x)

    @property
    def y_range(self) -> tuple[float, float]:
        return (-0.5 * self.size_y, 0.5 * self.size_y)

    def roi_grid(self, step: float) -> tuple[Array, Array]:
        """Points of a regular grid over the ROI (flattened x, y)."""
        nx = max(2, int(round(self.size_x / step)) + 1)
        ny = max(2, int(round(self.roi_length / step)) + 1)
        xx, yy = np.meshgrid(np.linspace(*self.x_range, nx), np.linspace(-0.5, 0.5, ny) * self.roi_length)
        return xx.ravel(), yy.ravel()

    def frame_grid(self, region: int, step: float) -> tuple[Array, Array]:
        """Points of a regular grid over frame region 1 (y < 0) or 2 (y > 0), edges included."""
        depth = 0.5 * (self.size_y - self.roi_length)
        nx = max(2, int(round(self.size_x / step)) + 1)
        ny = max(2, int(round(depth / step)) + 1)
        ys = 0.5 * self.roi_length + np.linspace(0.0, depth, ny)
        xx, yy = np.meshgrid(np.linspace(*self.x_range, nx), ys if region == 2 else -ys)
        return xx.ravel(), yy.ravel()


@dataclass(frozen=True)
class ReconstructionConfig:
    """Parameters of the reconstruction (basis of §1.8, thresholds and criterion of §1.4).

    Attributes
    ----------
    basis : {"gauss", "imq"}
        Basis function (§1.8).
    counts : (int, int) or None
        Centre grid (n_x, n_y) spanning the substrate (the seed's layout); None: a
        ``covering`` grid of spacing ``spacing*sigma`` overhanging by ``margin*sigma``.
    sigma : (float, float)
        Scales sigma_x, sigma_y, mm (a covering grid uses sigma_x).
    sigma_candidates : tuple of float or None
        Covering grids only: choose sigma among these from the data (:func:`select_sigma`: the scale
        whose fit best extrapolates the gradients of a held-out band of ``holdout_band`` mm at each
        end of the data, the situation of the frame regions) among those that fit the data; None: use ``sigma``.
    fit_ratio : float
        A candidate scale fits the data when its gradient residual on all markers is at most this many times the
        smallest candidate residual (:func:`select_sigma`; the finest candidate fits the noise too, so a basis
        that follows the surface lies within ~2-3 times of it: 2.7-5.2 against 1.4 µrad on the seed's surfaces,
        while a 12 mm basis on a 3 mm correlated glass leaves 240 times).
    tilt : bool
        Add the unpenalised plane terms x, y.
    regularization : float
        Relative ridge weight (see :func:`scopetwin.recon.shifted_basis.fit_gradients`).
    inner_tol_um, inner_max : float, int
        Inner loop stops when the RMS height change over the ROI is below ``inner_tol_um``.
    outer_tol_um, outer_max : float, int
        Outer loop stops when ``|criterion|`` <= ``outer_tol_um``.
    criterion : {"level", "delta"}
        Frame-region criterion (module docstring).
    search : {"secant", "thesis"}
        Start-height update (module docstring).
    warm_start : bool
        Start each inner loop from the previous surface moved to the new H (the seed starts from a plane).
    grid_step, frame_step : float
        Spacing of the evaluation grids over the ROI and over the frame regions, mm.
    min_markers : int
        Minimum number of usable markers overall.
    edge_band, min_edge_markers : float, int
        Each frame region needs at least ``min_edge_markers`` markers within ``edge_band`` mm of it.
    method : {"lstsq", "normal"}
        Linear solver of the fit.
    posterior : {"correct", "report", "off"}
        After convergence, read the fit as a Gaussian process (:mod:`scopetwin.recon.posterior`: smooth + broadband
        prior,
        scales and amplitudes by evidence) and give every reconstruction its uncertainty (absolute height, shape,
        per node); ``"correct"`` also replaces the extrapolated frame maxima of the fitted surface by their
        posterior mean (a Newton step on the start height, criterion ``level`` only); ``"off"``: neither.
    evidence_points : int
        Gradient observations (an even subsample) entering the evidence maximisation.
    posterior_iterations : int
        Most Newton steps on the start height with the posterior frame criterion (``posterior = "correct"``).
    posterior_points : int
        Most gradient observations entering the posterior (:func:`_posterior_subset`: all of the outermost
        along y, an even subsample of the rest).
    outlier_factor : float
        After convergence, markers whose gradient residual exceeds this many times the median residual are
        rejected one at a time (worst first, refitting in between, at most 5 % of them) and the surface is found
        again without them (:meth:`Reconstructor._index_outliers`): a wrongly indexed marker is ~3 mrad off, a
        good one within ~5 times the median (2-20 µrad); 0 turns the check off.
    consistency_um : float
        After convergence the criterion not searched on must hold too: ``|Delta h_max|`` (criterion
        ``level``) or ``|mean frame maximum - frame position|`` (criterion ``delta``) above this is an
        :class:`InconsistentError` (a mis-indexed image or a wrong setup gives a smooth but tilted
        surface that only one of the two frame conditions can hide).
    """

    basis: BasisKind = "gauss"
    counts: tuple[int, int] | None = None
    sigma: tuple[float, float] = (12.0, 12.0)
    sigma_candidates: tuple[float, ...] | None = (2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 12.0, 15.0, 18.0, 24.0)
    holdout_band: float = 4.0
    fit_ratio: float = 5.0
    spacing: float = 0.7
    margin: float = 1.0
    tilt: bool = True
    regularization: float = 1e-9
    inner_tol_um: float = 1e-4
    inner_max: int = 12
    outer_tol_um: float = 1e-4
    outer_max: int = 30
    criterion: FrameCriterion = "level"
    search: Literal["secant", "thesis"] = "secant"
    warm_start: bool = True
    grid_step: float = 0.5
    frame_step: float = 0.2
    min_markers: int = 20
    edge_band: float = 6.0
    min_edge_markers: int = 5
    method: Literal["lstsq", "normal"] = "lstsq"
    consistency_um: float = 10.0
    posterior: Literal["correct", "report", "off"] = "correct"
    evidence_points: int = 250
    posterior_points: int = 800
    posterior_iterations: int = 4
    outlier_factor: float = 10.0

    @classmethod
    def thesis(cls, literal_axes: bool = True, **changes: Any) -> ReconstructionConfig:
        """The seed's §1.10 reconstruction: 9x5 inverse multiquadrics, sigma_x = 4, sigma_y = 3, Delta h_max, eq. 1.4.

        ``literal_axes``: 9 centres and sigma 4 along x (the 25.2 mm side) as printed; False swaps
        them onto the long side (9 centres and sigma 4 along y), which fits the substrate's aspect.
        """
        counts, sigma = ((9, 5), (4.0, 3.0)) if literal_axes else ((5, 9), (3.0, 4.0))
        base = cls(
            basis="imq",
            counts=counts,
            sigma=sigma,
            sigma_candidates=None,
            tilt=False,
            regularization=0.0,
            inner_tol_um=1e-2,
            inner_max=3,
            outer_tol_um=0.01,
            outer_max=60,
            criterion="delta",
            search="thesis",
            warm_start=False,
            consistency_um=float("inf"),
            posterior="report",
        )
        return replace(base, **changes)

    @classmethod
    def realtime(cls, sigma: float = 12.0, **changes: Any) -> ReconstructionConfig:
        """A fixed-scale configuration for one frame period: coarser centre grid, normal equations, 2 nm tolerances."""
        base = cls(
            sigma=(sigma, sigma),
            sigma_candidates=None,
            spacing=1.0,
            method="normal",
            inner_tol_um=1e-3,
            outer_tol_um=2e-3,
            grid_step=1.0,
            frame_step=0.3,
            posterior="off",
        )
        return replace(base, **changes)

    def make_basis(self, sub: Substrate2D, sigma: float | None = None) -> ShiftedBasis:
        """The shifted basis of this configuration over a substrate (``sigma`` overrides a covering grid's scale)."""
        if self.counts is not None:
            return ShiftedBasis.grid(self.counts, sub.x_range, sub.y_range, self.sigma, self.basis, self.tilt)
        return ShiftedBasis.covering(
            sub.x_range,
            sub.y_range,
            sigma if sigma is not None else self.sigma[0],
            self.spacing,
            self.margin,
            self.basis,
            self.tilt,
        )


@dataclass(frozen=True)
class MarkerObservations:
    """Indexed markers of one image: pattern index (i, j) and image position (col, row) in continuous px."""

    ij: NDArray[np.int64]
    px: Array

    def __post_init__(self) -> None:
        ij = np.asarray(self.ij).reshape(-1, 2).astype(np.int64)
        px = np.asarray(self.px, dtype=np.float64).reshape(-1, 2)
        if len(ij) != len(px):
            raise ReconstructionError(f"{len(ij)} marker indices but {len(px)} image positions")
        ok = np.all(np.isfinite(px), axis=1)
        object.__setattr__(self, "ij", ij[ok])
        object.__setattr__(self, "px", px[ok])

    @classmethod
    def from_records(cls, records: list[dict[str, Any]]) -> MarkerObservations:
        """From the contract's ``markers`` records ({i, j, col, row})."""
        ij = np.array([[r["i"], r["j"]] for r in records], dtype=np.int64).reshape(-1, 2)
        px = np.array([[r["col"], r["row"]] for r in records], dtype=np.float64).reshape(-1, 2)
        return cls(ij, px)


@dataclass
class OuterStep:
    """One run of the inner loop for one start height (the iteration history of Fig. 1.4)."""

    start_height_um: float
    max_region1_um: float
    max_region2_um: float
    delta_h_max_um: float
    criterion_um: float
    inner_iterations: int
    inner_rms_change_um: list[float]
    gradient_residual_rms_urad: float
    markers_used: int
    sigma_mm: float


@dataclass(frozen=True)
class Uncertainty:
    """Standard uncertainties of a reconstruction (from :func:`scopetwin.recon.posterior.frame_posterior`).

    Attributes
    ----------
    absolute_um : float
        Of the absolute height (the ROI mean), µm: the posterior spread of the frame criterion's shape functional,
        plus the offset of the fitted surface's value from the posterior mean when no correction was applied,
        divided by the criterion's slope in the start height.
    shape_um : float
        Of the shape (RMS over the ROI after removing the mean), µm: sqrt of the mean, over the ROI, of the
        posterior variance of the height contrasts, the squared difference between the fitted and the
        posterior-mean contrasts, and the start height's uncertainty carried into the contrasts (a wrong start
        height tilts the traced gradients: :meth:`Reconstructor._start_height_sensitivity`).
    node_std : HeightMap
        Standard uncertainty of the height at the nodes of a coarse grid over the whole substrate, mm
        (absolute and shape parts together).
    correction_um : float
        Start-height correction applied from the posterior (0 when ``posterior`` is ``"report"``), µm.
    slope : float
        d criterion / d start height of the outer loop (from its last two runs; 1 when unknown).
    hyper : dict
        The prior chosen by evidence (:meth:`scopetwin.recon.posterior.Hyper.as_dict`).
    """

    absolute_um: float
    shape_um: float
    node_std: HeightMap
    correction_um: float
    slope: float
    hyper: dict[str, float]

    def summary(self) -> dict[str, Any]:
        """JSON-ready (the contract's ``uncertainty`` object plus details)."""
        return {
            "absolute_um": self.absolute_um,
            "shape_um": self.shape_um,
            "correction_um": self.correction_um,
            "criterion_slope": self.slope,
            "prior": self.hyper,
        }


@dataclass
class ReconstructionResult:
    """The reconstructed surface with its iteration history and (``config.posterior`` on) its uncertainty."""

    surface: SBFSurface
    substrate: Substrate2D
    history: list[OuterStep]
    converged: bool
    seconds: float
    config: ReconstructionConfig
    uncertainty: Uncertainty | None = None
    rejected: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))

    @property
    def outer_iterations(self) -> int:
        return len(self.history)

    @property
    def inner_iterations(self) -> int:
        """Total inner iterations over all outer runs."""
        return int(sum(s.inner_iterations for s in self.history))

    @property
    def delta_h_max_um(self) -> float:
        return self.history[-1].delta_h_max_um

    def heightmap(self, nx: int = 128, ny: int = 288) -> HeightMap:
        """The surface on a node grid covering the whole substrate (docs/contract.md, "Height maps")."""
        return self.surface.heightmap(self.substrate.x_range, self.substrate.y_range, nx, ny)

    def std_heightmap(self, nx: int = 128, ny: int = 288) -> HeightMap | None:
        """The per-node standard uncertainty on the same node grid as :meth:`heightmap` (bicubic), mm; or None."""
        if self.uncertainty is None:
            return None
        xs = np.linspace(*self.substrate.x_range, nx)
        ys = np.linspace(*self.substrate.y_range, ny)
        xx, yy = np.meshgrid(xs, ys)
        z = np.clip(self.uncertainty.node_std.height(xx, yy), 0.0, None)
        return HeightMap(z, xs[0], xs[-1], ys[0], ys[-1])

    def history_dicts(self) -> list[dict[str, Any]]:
        return [asdict(s) for s in self.history]

    def summary(self) -> dict[str, Any]:
        """JSON-ready summary (the `reconstruct` contract's keys plus the history)."""
        return {
            "outer_iterations": self.outer_iterations,
            "inner_iterations": self.inner_iterations,
            "delta_h_max_um": self.delta_h_max_um,
            "seconds": self.seconds,
            "converged": self.converged,
            "start_height_um": self.history[-1].start_height_um,
            "sigma_mm": list(self.surface.basis.sigma),
            "basis_functions": self.surface.basis.n_basis,
            **({"rejected_markers": self.rejected.tolist()} if len(self.rejected) else {}),
            **({"uncertainty": self.uncertainty.summary()} if self.uncertainty is not None else {}),
            "history": self.history_dicts(),
        }


def single_thread_blas() -> contextlib.AbstractContextManager:
    """Limit BLAS to one thread while the reconstruction runs (threadpoolctl, when installed).

    The matrices here are small (~1000 x 100): multithreaded BLAS gains nothing on them and, on a
    loaded machine, its spinning threads cost 5-20x (measured: the scopetwin run pipeline took 44 s
    instead of 2.5 s for detection + two reconstructions on a shared 2-core machine).
    """
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover - optional
        return contextlib.nullcontext()
    return threadpool_limits(limits=1, user_api="blas")


# -- geometry helpers ---------------------------------------------------------------------
def intersect_surface(
    surface: SBFSurface, origins: Array, dirs: Array, frame: Frame | None = None, tol: float = 1e-10, max_iter: int = 30
) -> tuple[Array, NDArray[np.bool_]]:
    """Ray parameters where rays meet a fitted surface z = f(x, y) (secant iteration of seed §1.6.4, eq. 1.6).

    :func:`scopetwin.scenes.surface.secant_intersection`, started at the rays' intersections with the plane
    z = offset and with the plane z = f there, which is close to the root for a nearly flat substrate.

    Parameters
    ----------
    surface : SBFSurface
        The current surface estimate (§1.8), in the coordinates of ``frame``.
    origins, dirs : ndarray, (n, 3)
        Camera rays, global coordinates.
    frame : Frame, optional
        The substrate's base plane (None: the rays are given in it).
    tol, max_iter : float, int
        Convergence threshold on ``|f|``, mm, and largest number of secant steps.

    Returns
    -------
    lam : ndarray, (n,)
        Ray parameters (meaningful where ``ok``).
    ok : ndarray of bool, (n,)
        Converged, and in front of the ray origin (lam > 0).
    """
    o = frame.to_local(origins) if frame is not None else np.asarray(origins, dtype=np.float64)
    d = frame.vectors_to_local(dirs) if frame is not None else np.asarray(dirs, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam0 = (surface.offset - o[:, 2]) / d[:, 2]
    lam, converged = secant_intersection(surface, o, d, lam0, tol=tol, max_iter=max_iter)
    return lam, converged & (lam > 0)


def check_substrate_visible(camera: Camera, sub: Substrate2D) -> None:
    """Raise :class:`SubstrateNotVisibleError` if no point of the ROI projects into the image."""
    xs, ys = sub.roi_grid(max(sub.size_x, sub.roi_length) / 12.0)
    pts = sub.frame.to_global(np.stack([xs, ys, np.full_like(xs, sub.frame_z)], axis=-1))
    px = camera.project(pts)
    inside = np.all(np.isfinite(px), axis=1) & camera.in_image(np.nan_to_num(px, nan=-1.0))
    if not inside.any():
        raise SubstrateNotVisibleError(
            "the setup's camera cannot see the substrate: no point of the region of interest projects into the "
            f"{camera.nx} x {camera.ny} image (check the camera pose in the setup)"
        )


def select_sigma(
    sub: Substrate2D, x: Array, y: Array, hx: Array, hy: Array, config: ReconstructionConfig
) -> tuple[float, dict[float, float], dict[float, float]]:
    """Basis scale from the data: among the scales that fit the data, the one that best extrapolates.

    A scale fits when its residual on all the gradients is at most ``config.fit_ratio`` times the smallest
    residual of the candidates (a basis too coarse for the surface — a 12 mm Gaussian on a 3 mm correlated
    glass — leaves hundreds of µrad and would otherwise win by extrapolating smoothly). Among those, for each end
    of the data along y the markers within ``config.holdout_band`` mm of the data's edge are held out, the basis
    is fitted to the rest, and the RMS gradient error on the held-out band is measured: the same extrapolation the
    frame criterion relies on (seed §1.4). The scale with the smallest RMS over both ends wins. Returns
    (sigma, {sigma: held-out score in µrad}, {sigma: residual of the fit to all gradients in µrad}).
    """
    scores: dict[float, float] = {}
    fits: dict[float, float] = {}
    ends = [y >= y.max() - config.holdout_band, y <= y.min() + config.holdout_band]
    for sigma in config.sigma_candidates or ():
        basis = config.make_basis(sub, sigma)
        coef, _ = fit_gradients(basis, x, y, hx, hy, config.regularization, method=config.method)
        gx, gy = SBFSurface(basis, coef).gradient(x, y)
        fits[float(sigma)] = float(np.sqrt(np.mean((gx - hx) ** 2 + (gy - hy) ** 2)) * 1e6)
        errs = []
        for test in ends:
            if test.all() or (~test).sum() * 2 < basis.n_terms // 4:
                continue
            coef, _ = fit_gradients(
                basis, x[~test], y[~test], hx[~test], hy[~test], config.regularization, method=config.method
            )
            gx, gy = SBFSurface(basis, coef).gradient(x[test], y[test])
            errs.append(np.mean((gx - hx[test]) ** 2 + (gy - hy[test]) ** 2))
        if errs:
            scores[float(sigma)] = float(np.sqrt(np.mean(errs)) * 1e6)
    if not scores:
        return float(config.sigma[0]), scores, fits
    floor = min(fits.values())
    fitting = [s for s in scores if fits[s] <= config.fit_ratio * floor] or list(scores)
    return min(fitting, key=scores.__getitem__), scores, fits


# -- the nested iteration ---------------------------------------------------------------
class Reconstructor:
    """The nested iteration of seed §1.4 for one setup, basis and set of marker observations.

    Parameters
    ----------
    camera : Camera
        Calibrated camera (rays from continuous pixel coordinates).
    pattern : MarkerPattern
        Calibrated pattern (global marker centres).
    substrate : Substrate2D
        Substrate extent, ROI and frame position.
    config : ReconstructionConfig
        Basis, thresholds, criterion, search.
    bias : BiasStep, optional
        Centroid-bias correction applied in every inner iteration (None: use the positions as measured).
    """

    def __init__(
        self,
        camera: Camera,
        pattern: MarkerPattern,
        substrate: Substrate2D,
        config: ReconstructionConfig | None = None,
        bias: BiasStep | None = None,
    ) -> None:
        self.camera = camera
        self.pattern = pattern
        self.sub = substrate
        self.config = config or ReconstructionConfig()
        self.bias = bias
        check_substrate_visible(camera, substrate)
        self.sigma_scores: dict[float, float] = {}
        self._last: SBFSurface | None = None
        self._post_delta: tuple[float, float] | None = None
        self._use_basis(self.config.make_basis(substrate))

    def _use_basis(self, basis: ShiftedBasis) -> None:
        """Set the basis and precompute its values on the ROI and frame-region evaluation grids."""
        self.basis = basis
        gx, gy = self.sub.roi_grid(self.config.grid_step)
        self._roi_values = basis.values(gx, gy)
        self._frame_values = [basis.values(*self.sub.frame_grid(r, self.config.frame_step)) for r in (1, 2)]

    @classmethod
    def from_setup(
        cls,
        setup: Setup,
        config: ReconstructionConfig | None = None,
        bias: BiasStep | None = None,
        frame_z: float = 0.0,
    ) -> Reconstructor:
        return cls(setup.camera_model, setup.marker_pattern, Substrate2D.from_setup(setup, frame_z), config, bias)

    # -- pieces --------------------------------------------------------------------------
    def _roi_mean(self, coef: Array) -> float:
        return float(np.mean(self._roi_values @ coef))

    def frame_maxima(self, surface: SBFSurface) -> tuple[float, float]:
        """max over frame region 1 and region 2 of the surface, mm (eq. 1.3)."""
        return (
            float(np.max(self._frame_values[0] @ surface.coef)) + surface.offset,
            float(np.max(self._frame_values[1] @ surface.coef)) + surface.offset,
        )

    def _prepare(self, markers: MarkerObservations) -> tuple[NDArray[np.int64], Array, Array]:
        cfg = self.config
        if len(markers.ij) < cfg.min_markers:
            raise TooFewMarkersError(
                f"only {len(markers.ij)} markers found; the reconstruction needs at least {cfg.min_markers}"
            )
        idx = self.pattern.indices()
        lo, hi = idx.min(axis=0), idx.max(axis=0)
        ok = np.all((markers.ij >= lo) & (markers.ij <= hi), axis=1)
        if not ok.all():
            raise ReconstructionError(
                f"{int((~ok).sum())} marker indices lie outside the {self.pattern.n_x} x {self.pattern.n_y} pattern"
            )
        return markers.ij, markers.px, self.pattern.centers(markers.ij)

    def _rays(self, px: Array) -> tuple[Array, Array]:
        """Camera rays of marker image positions, cached for the last positions seen (unchanged without bias step)."""
        cached = getattr(self, "_ray_cache", None)
        if cached is not None and cached[0] is px:
            return cached[1]
        rays = self.camera.rays(px)
        self._ray_cache = (px, rays)
        return rays

    def _trace(self, surface: SBFSurface, px: Array, targets: Array) -> tuple[Array, Array, Array, NDArray]:
        o, d = self._rays(px)
        lam, ok = intersect_surface(surface, o, d, self.sub.frame)
        hit = o + np.where(ok, lam, 0.0)[:, None] * d
        local = self.sub.frame.to_local(hit)
        ok &= (np.abs(local[:, 0]) <= 0.5 * self.sub.size_x) & (np.abs(local[:, 1]) < 0.5 * self.sub.roi_length)
        xy, hx, hy = marker_gradients(hit[ok], d[ok], targets[ok], self.sub.frame)
        return xy, hx, hy, ok

    def _check_coverage(self, xy: Array, n_total: int) -> None:
        cfg = self.config
        if len(xy) < max(cfg.min_markers, 0.5 * n_total):
            raise SubstrateNotVisibleError(
                f"only {len(xy)} of {n_total} marker rays meet the substrate's region of interest: the camera "
                "does not see the substrate as the setup describes it (wrong setup for this image?)"
            )
        half = 0.5 * self.sub.roi_length
        for region, near in ((1, xy[:, 1] <= -half + cfg.edge_band), (2, xy[:, 1] >= half - cfg.edge_band)):
            n = int(near.sum())
            if n < cfg.min_edge_markers:
                side = "y < 0" if region == 1 else "y > 0"
                raise TooFewMarkersError(
                    f"only {n} markers within {cfg.edge_band} mm of frame region {region} ({side}); at least "
                    f"{cfg.min_edge_markers} are needed to extrapolate the surface onto the holding frame (seed §1.4)"
                )

    def inner_loop(
        self, start_height: float, markers: MarkerObservations, initial: SBFSurface | None = None
    ) -> tuple[SBFSurface, list[float], float, int]:
        """Self-consistent surface for one start height (seed §1.4, eq. 1.5).

        Returns the surface, the RMS height changes (µm) per iteration, the final gradient
        residual RMS (rad) and the number of markers used.
        """
        cfg = self.config
        ij, px_meas, targets = self._prepare(markers)
        if initial is not None:
            surface = initial.shifted(start_height - self._roi_mean(initial.coef))
        else:
            surface = SBFSurface.plane(self.basis, start_height)
        rms_changes: list[float] = []
        resid = float("nan")
        used = 0
        prev_roi = self._roi_values @ surface.coef + surface.offset
        for _ in range(cfg.inner_max):
            px = self.bias(surface, ij, px_meas) if self.bias is not None else px_meas
            xy, hx, hy, ok = self._trace(surface, px, targets)
            self._check_coverage(xy, len(ij))
            used = int(ok.sum())
            coef, resid = fit_gradients(self.basis, xy[:, 0], xy[:, 1], hx, hy, cfg.regularization, method=cfg.method)
            roi = self._roi_values @ coef
            offset = start_height - float(np.mean(roi))
            surface = SBFSurface(self.basis, coef, offset)
            roi += offset
            change = float(np.sqrt(np.mean((roi - prev_roi) ** 2)))
            rms_changes.append(change * 1e3)
            prev_roi = roi
            if change * 1e3 < cfg.inner_tol_um:
                break
        return surface, rms_changes, resid, used

    def _outer(
        self,
        markers: MarkerObservations,
        h_start: float,
        history: list[OuterStep],
        surfaces: list[SBFSurface],
        runs: int | None = None,
    ) -> bool:
        """The start-height loop from ``h_start``; appends to ``history`` and ``surfaces``; True when converged.

        At most ``runs`` inner loops (default: what ``outer_max`` leaves after ``history``).
        """
        cfg = self.config
        values: list[tuple[float, float]] = []  # (H, F)
        tol = cfg.outer_tol_um * 1e-3
        h = h_start
        for _ in range(runs if runs is not None else cfg.outer_max - len(history)):
            init = _predict_surface(surfaces, values, h) if cfg.warm_start else None
            surf, changes, resid, used = self.inner_loop(h, markers, init)
            m1, m2 = self.frame_maxima(surf)
            crit = frame_criterion(m1, m2, self.sub.frame_z, cfg.criterion)
            history.append(
                OuterStep(
                    h * 1e3,
                    m1 * 1e3,
                    m2 * 1e3,
                    (m1 - m2) * 1e3,
                    crit * 1e3,
                    len(changes),
                    changes,
                    resid * 1e6,
                    used,
                    self.basis.sigma[0],
                )
            )
            surfaces.append(surf)
            values.append((h, crit))
            if abs(crit) <= tol:
                self._last = surf
                return True
            d_min = frame_distance(m1, m2, self.sub.frame_z)
            thesis_step = h - d_min if d_min != 0 else h - crit
            h_new = thesis_step if cfg.search == "thesis" else _secant_step(values, thesis_step)
            if not np.isfinite(h_new):
                break
            h = float(h_new)
        self._last = surfaces[-1] if surfaces else None
        return False

    def run(self, markers: MarkerObservations, history_path: str | Path | None = None) -> ReconstructionResult:
        """The nested iteration (seed §1.4, Fig. 1.4), with BLAS limited to one thread (see :func:`single_thread_blas`).

        Raises
        ------
        TooFewMarkersError, SubstrateNotVisibleError
            Input that cannot give a height map.
        NotConvergedError
            The outer loop reached ``outer_max`` runs; the partial history is attached and, when
            ``history_path`` is given, written there as JSON.
        """
        with single_thread_blas():
            return self._run(markers, history_path)

    def _index_outliers(self, markers: MarkerObservations, surface: SBFSurface) -> NDArray[np.bool_]:
        """Markers whose gradients no smooth surface explains: wrongly indexed ones (True = reject).

        A marker given its neighbour's index points at a pattern position a pitch away: its traced gradient is
        ~3 mrad off, while good markers scatter about the fit by a few µrad (at most ~5 times the median residual
        on the seed's surfaces, PSD glass with broadband content and 3 mm / 60 µm surfaces). The gradients are
        traced through the converged ``surface``; the worst marker above ``outlier_factor`` times the median
        residual is removed and the basis refitted, until none is left above it or 5 % are gone.
        """
        cfg = self.config
        ij, px, targets = self._prepare(markers)
        px = self.bias(surface, ij, px) if self.bias is not None else px
        xy, hx, hy, ok = self._trace(surface, px, targets)
        keep = np.ones(len(xy), dtype=bool)
        basis = surface.basis
        for _ in range(int(0.05 * len(xy))):
            coef, _ = fit_gradients(
                basis, xy[keep, 0], xy[keep, 1], hx[keep], hy[keep], cfg.regularization, method=cfg.method
            )
            gx, gy = SBFSurface(basis, coef).gradient(xy[:, 0], xy[:, 1])
            r = np.hypot(gx - hx, gy - hy)
            worst = np.flatnonzero(keep)[int(np.argmax(r[keep]))]
            if r[worst] <= cfg.outlier_factor * float(np.median(r[keep])):
                break
            keep[worst] = False
        drop = np.zeros(len(ij), dtype=bool)
        drop[np.flatnonzero(ok)[~keep]] = True
        return drop

    def coarse_surface(self, markers: MarkerObservations, iterations: int = 3) -> SBFSurface:
        """A coarse fit of the markers: the inner loop at the frame height, without the bias step or the height search.

        Where the nested iteration fails on a strongly bent substrate (3 mm / 60 µm: the bias model singular at a
        marker near a caustic, or start heights that throw the rays off the substrate), the markers still tell the
        surface's shape: their gradients, traced through the flat start at the frame height and through the fits
        that follow, fitted with a basis scale chosen on them (:meth:`_scale_from_flat_start`). The traced slopes are
        off by ~10 µrad per µm of height error, far inside the inverse fit's basin (a pitch on the pattern is ~8
        mrad); the start for :mod:`scopetwin.recon.inverse` (:func:`scopetwin.recon.inverse.inverse_start`), whose mean
        height — the
        frame height, nobody measured it — the inverse fit keeps. An iteration whose rays miss the substrate for more
        than 5 % of the markers is not taken.
        """
        cfg = self.config
        h = self.sub.frame_z
        ij, px, targets = self._prepare(markers)
        self._scale_from_flat_start(markers, bias=False)
        surface = SBFSurface.plane(self.basis, h)
        for _ in range(iterations):
            xy, hx, hy, _ = self._trace(surface, px, targets)
            if len(xy) < 0.95 * len(ij):
                break
            coef, _ = fit_gradients(self.basis, xy[:, 0], xy[:, 1], hx, hy, cfg.regularization, method=cfg.method)
            surface = SBFSurface(self.basis, coef, h - self._roi_mean(coef))
        return surface

    def _scale_from_flat_start(self, markers: MarkerObservations, bias: bool = True) -> bool:
        """Choose the basis scale on the gradients traced through the flat start; True if the scale changed.

        :func:`select_sigma` on the markers' gradients traced through the plane at the frame height (with the bias
        step where ``bias`` and the reconstructor has one).
        A default scale far too coarse for the surface (the 12 mm basis on a 3 mm / 60 µm one, whose markers the
        topological indexing of :func:`scopetwin.recon.markers.index_lattice` numbers) cannot fit the gradients, and
        its fits
        swing so far that the rays miss the substrate (or its ends) — in the first inner loop, before a surface
        exists for :func:`select_sigma` to be run on, or after many start heights that did not settle (3 mm / 60 µm
        seeds 2 and 1). The flat start at the frame height traces every marker; the scale is chosen on those
        gradients instead, and :meth:`_run` begins the start-height loop again (with a fresh budget of start
        heights); :meth:`coarse_surface` fits with it.
        """
        cfg = self.config
        plane = SBFSurface.plane(self.basis, self.sub.frame_z)
        ij, px, targets = self._prepare(markers)
        px = self.bias(plane, ij, px) if bias and self.bias is not None else px
        xy, hx, hy, _ = self._trace(plane, px, targets)
        self._check_coverage(xy, len(ij))  # a flat start that misses the substrate too: that error, not this one
        if not cfg.sigma_candidates or cfg.counts is not None:
            return False
        best, self.sigma_scores, _ = select_sigma(self.sub, xy[:, 0], xy[:, 1], hx, hy, cfg)
        if best == float(self.basis.sigma[0]):
            return False
        self._use_basis(cfg.make_basis(self.sub, best))
        return True

    def _run(self, markers: MarkerObservations, history_path: str | Path | None) -> ReconstructionResult:
        cfg = self.config
        t0 = time.perf_counter()
        history: list[OuterStep] = []
        surfaces: list[SBFSurface] = []
        try:
            converged = self._outer(markers, self.sub.frame_z, history, surfaces)
        except (SubstrateNotVisibleError, TooFewMarkersError):
            if not self._scale_from_flat_start(markers):
                raise
            surfaces = []  # the first scale's surfaces: no warm start for another basis
            converged = self._outer(markers, self.sub.frame_z, history, surfaces, cfg.outer_max)
        if surfaces and cfg.sigma_candidates and cfg.counts is None:
            # phase 2: choose the basis scale on data traced through the converged surface, then
            # search the start height again with it (from the height just found); also when the default
            # scale did not converge (too coarse for the surface: the bias step on a surface hundreds of
            # µrad off keeps the start-height loop from settling)
            ij, px, targets = self._prepare(markers)
            px = self.bias(surfaces[-1], ij, px) if self.bias is not None else px
            xy, hx, hy, _ = self._trace(surfaces[-1], px, targets)
            best, self.sigma_scores, fits = select_sigma(self.sub, xy[:, 0], xy[:, 1], hx, hy, cfg)
            current = float(self.basis.sigma[0])
            too_coarse = current in fits and fits[current] > cfg.fit_ratio * min(fits.values())
            if best != current and (converged or too_coarse):
                first = (self.basis, len(history), converged, self._last)
                self._use_basis(cfg.make_basis(self.sub, best))
                h_found = history[-1].start_height_um * 1e-3
                runs = None if converged else cfg.outer_max  # the scale that could not fit leaves no budget
                try:
                    converged = self._outer(markers, h_found, history, [], runs)
                except (SubstrateNotVisibleError, TooFewMarkersError):
                    # the finer scale's extrapolation into the frame regions threw the start height so far that
                    # the rays missed the substrate: keep the first scale's result
                    if not first[2]:
                        raise
                    self._use_basis(first[0])
                    del history[first[1] :]
                    converged, self._last = first[2], first[3]
        rejected = np.zeros((0, 2), dtype=np.int64)
        if converged and cfg.outlier_factor > 0 and self._last is not None:
            drop = self._index_outliers(markers, self._last)
            if drop.any():
                rejected = markers.ij[drop]
                markers = MarkerObservations(markers.ij[~drop], markers.px[~drop])
                h_found = history[-1].start_height_um * 1e-3
                converged = self._outer(markers, h_found, history, [], cfg.outer_max)
        seconds = time.perf_counter() - t0
        if self._last is None:
            raise ReconstructionError(f"the start-height loop ran no inner loop (outer_max = {cfg.outer_max})")
        result = ReconstructionResult(self._last, self.sub, history, converged, seconds, cfg, rejected=rejected)
        last = history[-1]
        other = (
            abs(last.delta_h_max_um)
            if cfg.criterion == "level"
            else abs(0.5 * (last.max_region1_um + last.max_region2_um) - self.sub.frame_z * 1e3)
        )
        if converged and other <= cfg.consistency_um:
            if cfg.posterior != "off":
                self._posterior(markers, result)
            return result
        if converged and cfg.posterior != "off" and cfg.criterion == "level":
            # the fitted surface's extrapolated Delta h_max can be microns off on surfaces with medium-scale
            # content; the posterior's Delta h_max (frame maxima from the data, with its spread) decides instead
            self._post_delta = None
            self._posterior(markers, result)
            if self._post_delta is not None:
                d_mean, d_std = self._post_delta
                other = abs(d_mean) * 1e3
                if other <= cfg.consistency_um + 3.0 * d_std * 1e3:
                    return result
        path = Path(history_path) if history_path is not None else None
        if path is not None:
            from scopetwin.scenes.io import write_json_atomic

            write_json_atomic(path, {"converged": converged, "config": asdict(cfg), **result.summary()})
        where = f"; partial history saved to {path}" if path is not None else ""
        if not converged:
            raise NotConvergedError(
                f"the start-height loop did not converge in {len(history)} runs (last criterion "
                f"{last.criterion_um:+.4g} µm, tolerance {cfg.outer_tol_um} µm){where}",
                result.history_dicts(),
                path,
                self._last,
            )
        what = "Delta h_max" if cfg.criterion == "level" else "the mean frame maximum's distance from the frame"
        raise InconsistentError(
            f"the reconstructed surface cannot lie on the holding frame: {what} is {other:.3g} µm "
            f"(> {cfg.consistency_um} µm) — are the markers indexed correctly and is the setup right?{where}"
        )

    def _start_height_sensitivity(
        self, surf: SBFSurface, markers: MarkerObservations, xx: Array, yy: Array, dh_mm: float = 2e-4
    ) -> Array:
        """d(height contrast)/d(start height) at (xx, yy): how a start-height error bends the shape (dimensionless).

        The gradients are traced through a surface at the start height, so a wrong start height tilts and bends
        them (seed §1.4: the start height is found by the frame criterion, not by the data); one more inner loop
        at H + ``dh_mm`` from the converged surface gives the derivative by a finite difference.
        """
        h = self._roi_mean(surf.coef) + surf.offset
        try:
            other = self.inner_loop(h + dh_mm, markers, surf)[0]
        except ScopetwinError:
            return np.zeros_like(np.asarray(xx, dtype=np.float64))
        h2 = self._roi_mean(other.coef) + other.offset
        return (_contrast(other, h2, xx, yy) - _contrast(surf, h, xx, yy)) / (h2 - h)

    def _posterior(self, markers: MarkerObservations, result: ReconstructionResult) -> None:
        """Uncertainty of the converged surface and (``posterior = "correct"``) the posterior start height.

        The gradient data are traced through the converged surface; the prior is chosen by evidence
        (:func:`scopetwin.recon.posterior.fit_hyper`) and the posterior of the frame criterion's shape functional D
        (frame
        maxima relative to the ROI mean) compared with the fitted surface's D. The start height solves
        H + D(H) = z_frame; with the posterior D in place of the extrapolated one this is solved by Newton steps
        H <- H + (D_fit - D_post) / slope (slope = dF/dH of the outer loop), each followed by the inner loop at the
        new H, so the traced gradients — which depend on H (a wrong H tilts them) — follow the start height.
        """
        from scopetwin.recon.posterior import GradientGP, PosteriorError, fit_hyper, frame_posterior

        cfg = self.config
        sub = self.sub
        rx, ry = sub.roi_grid(cfg.grid_step)
        axes = (np.unique(rx), np.unique(ry))
        same = [s for s in result.history if s.sigma_mm == result.history[-1].sigma_mm]
        slope = 1.0
        if len(same) >= 2 and same[-1].start_height_um != same[-2].start_height_um:
            slope = (same[-1].criterion_um - same[-2].criterion_um) / (
                same[-1].start_height_um - same[-2].start_height_um
            )
        if not 0.2 < abs(slope) < 5.0:
            slope = 1.0
        correcting = cfg.posterior == "correct" and cfg.criterion == "level"
        surf = result.surface
        h0 = self._roi_mean(surf.coef) + surf.offset
        ij, px_meas, targets = self._prepare(markers)
        hyper = None
        tried: list[tuple[float, float, SBFSurface]] = []  # (H, F_post(H), surface) of each step
        for it in range(cfg.posterior_iterations if correcting else 1):
            px = self.bias(surf, ij, px_meas) if self.bias is not None else px_meas
            xy, hx, hy, _ = self._trace(surf, px, targets)
            try:
                hyper = hyper or fit_hyper(xy, hx, hy, max_points=cfg.evidence_points)
                gp = GradientGP(*_posterior_subset(xy, hx, hy, cfg.posterior_points), hyper)
                post = frame_posterior(gp, sub.x_range, sub.y_range, sub.roi_length, axes)
            except PosteriorError:
                return
            # the fitted surface's frame maxima on the posterior's own frame points (same discretisation)
            m1 = float(np.max(surf.height(post.frame1[:, 0], post.frame1[:, 1])))
            m2 = float(np.max(surf.height(post.frame2[:, 0], post.frame2[:, 1])))
            h = self._roi_mean(surf.coef) + surf.offset
            self._post_delta = (post.delta_mean, post.delta_std)
            if cfg.criterion == "level":
                err, spread = (0.5 * (m1 + m2) - h) - post.d_mean, post.d_std
            else:
                err, spread = (m1 - m2) - post.delta_mean, post.delta_std
            if not correcting:
                break
            # F_post(H) = H + D_post(H) - z_frame; the fitted surface satisfies H + D_fit(H) ~ z_frame
            f_post = h + post.d_mean - sub.frame_z
            tried.append((h, f_post, surf))
            if len(tried) >= 2 and tried[-1][0] != tried[-2][0]:
                (ha, fa, _), (hb, fb, _) = tried[-2], tried[-1]
                s_post = (fb - fa) / (hb - ha)
                s_post = s_post if 0.2 < abs(s_post) < 5.0 else slope
            else:
                s_post = slope
            step = -f_post / s_post
            if abs(step) * 1e3 <= cfg.outer_tol_um or it == cfg.posterior_iterations - 1:
                surf = surf.shifted(surf.offset + step)  # the last, small step without another inner loop
                break
            surf = self.inner_loop(h + step, markers, surf)[0]
        if correcting:
            u_abs = spread / abs(slope)
        else:
            u_abs = float(np.hypot(err, spread)) / abs(slope)
        h_final = self._roi_mean(surf.coef) + surf.offset
        nxx, nyy = np.meshgrid(post.node_x, post.node_y)
        fit_c = surf.height(nxx, nyy) - h_final
        dev2 = (fit_c - post.contrast_mean) ** 2
        # the traced gradients depend on the start height: an error dH of it bends the shape by sens * dH
        sens = self._start_height_sensitivity(surf, markers, nxx, nyy)
        shape_var = post.contrast_std**2 + dev2 + (sens * u_abs) ** 2
        u_shape = float(np.sqrt(np.mean(shape_var[post.roi])))
        node = np.sqrt((u_abs * (1.0 + sens)) ** 2 + post.contrast_std**2 + dev2)
        std_map = HeightMap(node, post.node_x[0], post.node_x[-1], post.node_y[0], post.node_y[-1])
        result.surface = surf
        result.uncertainty = Uncertainty(
            u_abs * 1e3, u_shape * 1e3, std_map, (h_final - h0) * 1e3, slope, hyper.as_dict() if hyper else {}
        )


def _contrast(surf: SBFSurface, h: float, xx: Array, yy: Array) -> Array:
    """Heights relative to the ROI mean ``h``, mm."""
    return np.asarray(surf.height(xx, yy)) - h


def _posterior_subset(xy: Array, hx: Array, hy: Array, budget: int) -> tuple[Array, Array, Array]:
    """At most ``budget`` observations for the posterior: the outer half of the budget nearest the frame regions
    (largest |y|) in full, an even subsample of the interior for the rest; the extrapolation rests on the former."""
    if len(xy) <= budget:
        return xy, hx, hy
    order = np.argsort(-np.abs(xy[:, 1]))
    outer = order[: budget // 2]
    inner = order[budget // 2 :]
    inner = inner[np.linspace(0, len(inner) - 1, budget - len(outer)).round().astype(int)]
    keep = np.sort(np.concatenate([outer, inner]))
    return xy[keep], hx[keep], hy[keep]


def _predict_surface(surfaces: list[SBFSurface], values: list[tuple[float, float]], h: float) -> SBFSurface | None:
    """Warm start for start height ``h``: the last surface, or the linear extrapolation of the last two in H.

    The self-consistent surface depends almost linearly on the start height, so extrapolating the
    coefficients of the last two outer runs leaves the inner loop little to do.
    """
    if not surfaces:
        return None
    if len(surfaces) < 2 or len(values) < 2 or values[-1][0] == values[-2][0]:
        return surfaces[-1]
    (ha, _), (hb, _) = values[-2], values[-1]
    a, b = surfaces[-2], surfaces[-1]
    if a.basis is not b.basis:
        return b
    w = (h - hb) / (hb - ha)
    return SBFSurface(b.basis, b.coef + w * (b.coef - a.coef), b.offset + w * (b.offset - a.offset))


def _secant_step(values: list[tuple[float, float]], fallback: float) -> float:
    """Next start height of the root search on the criterion F(H).

    Secant through the last two evaluations; once a sign change is known, the step is kept
    inside the tightest bracket (bisection when the secant leaves it). ``fallback`` (the
    thesis step of eq. 1.4) is used with a single evaluation.
    """
    if len(values) < 2:
        return fallback
    (ha, fa), (hb, fb) = values[-2], values[-1]
    h_new = hb - fb * (hb - ha) / (fb - fa) if fb != fa else fallback
    pos = [h for h, f in values if f > 0]
    neg = [h for h, f in values if f < 0]
    if pos and neg:
        # tightest bracket around the root from all evaluations so far
        hp = min(pos, key=lambda h: abs(h - hb))
        hn = min(neg, key=lambda h: abs(h - hb))
        lo, hi = min(hp, hn), max(hp, hn)
        if not lo < h_new < hi:
            h_new = 0.5 * (lo + hi)
    return h_new


def reconstruct(
    setup: Setup,
    markers: MarkerObservations | ArrayLike,
    px: ArrayLike | None = None,
    config: ReconstructionConfig | None = None,
    bias: BiasStep | None = None,
    history_path: str | Path | None = None,
    frame_z: float = 0.0,
) -> ReconstructionResult:
    """Reconstruct the substrate's heights from indexed markers (seed §1.4, §1.7, §1.8).

    Parameters
    ----------
    setup : Setup
        A (calibrated) deflectometry setup.
    markers : MarkerObservations or array_like (n, 2)
        Observations, or the marker indices (i, j) with ``px`` their image positions.
    px : array_like, (n, 2), optional
        Continuous pixel coordinates (col, row) when ``markers`` are indices.
    config : ReconstructionConfig, optional
        Default: the improved reconstruction (Gaussian basis with ridge, ``level`` criterion, secant search).
    bias : BiasStep, optional
        Centroid-bias correction inside the inner loop.
    history_path : path, optional
        Where a partial history is written if the outer loop does not converge.
    frame_z : float
        z of the holding frame in the substrate's base frame, mm.
    """
    if isinstance(markers, MarkerObservations):
        obs = markers
    elif px is None:
        raise ReconstructionError("marker indices need their image positions px")
    else:
        obs = MarkerObservations(np.asarray(markers), np.asarray(px, dtype=np.float64))
    return Reconstructor.from_setup(setup, config, bias, frame_z).run(obs, history_path)


def centroid_bias_step(setup: Setup, recompute_um: float = 0.2, grid: tuple[int, int] = (48, 112)) -> BiasStep:
    """A bias step for the inner loop built on :mod:`scopetwin.recon.bias` (markers issue), or an error if absent.

    The bias of each marker's centroid (the spot is distorted by the curved mirror) is predicted
    from the current surface estimate and added to the measured centroid. The prediction is
    redone only when the surface's shape (mean removed) has changed by more than ``recompute_um``
    RMS since the last one: the bias follows the curvature, which settles after the first
    iterations, and hardly depends on the start height, which moves the surface as an offset.
    """
    try:
        from scopetwin.recon.bias import correct_centroids, model_for_setup
    except ImportError as exc:  # pragma: no cover - recon.bias is part of the package
        raise ReconstructionError(f"centroid-bias correction is unavailable: {exc}") from None
    sub = Substrate2D.from_setup(setup)
    xs = np.linspace(*sub.x_range, grid[0])
    ys = np.linspace(*sub.y_range, grid[1])
    xx, yy = np.meshgrid(xs, ys)
    cache: dict[str, Any] = {}

    def step(surface: SBFSurface, ij: NDArray[np.int64], px: Array) -> Array:
        z = surface.height(xx, yy)
        last = cache.get("z")
        if last is None or cache.get("n") != len(px) or np.std(z - last) * 1e3 > recompute_um:
            hm = HeightMap(z, sub.x_range[0], sub.x_range[1], sub.y_range[0], sub.y_range[1])
            corrected, _ = correct_centroids(px, ij, model_for_setup(setup, hm))
            cache.update(z=z, n=len(px), correction=corrected - px)
        return px + cache["correction"]

    return step


def reconstruct_image(
    image: NDArray[Any],
    setup: Setup,
    config: ReconstructionConfig | None = None,
    bias: BiasStep | None = None,
    history_path: str | Path | None = None,
) -> tuple[Any, ReconstructionResult, Reconstructor]:
    """Markers of a deflectometry image (:func:`scopetwin.recon.markers.find_markers_for`) and the surface they give
    (§1.4).

    Where the spots are distorted so much that two or more are about as large as the reference marker should be
    (:class:`scopetwin.recon.markers.ReferenceTieError`; 3 mm / 60 µm surfaces), each candidate is taken as the
    reference in
    turn: with a wrong one every index is a few pitches off, the traced slopes are milliradians off and the
    start-height loop cannot lay such a surface on the holding frame (its rays miss the substrate or one of its
    ends, or it does not converge). The one candidate whose markers reconstruct is kept; if none or several do,
    the tie is reported. Measured on 3 mm / 60 µm surface seed 7 (four candidates): the true one reconstructs
    (0.14 µm shape), the three others fail in 4-6 s each.

    Returns (markers, result, reconstructor).
    """
    from scopetwin.recon.markers import ReferenceTieError, find_markers_for

    def attempt(reference: int | None, path: str | Path | None) -> tuple[Any, ReconstructionResult, Reconstructor]:
        found = find_markers_for(image, setup, reference=reference)
        rec = Reconstructor.from_setup(setup, config, bias)
        return found, rec.run(MarkerObservations(found.ij, found.centroids), history_path=path), rec

    try:
        return attempt(None, history_path)
    except ReferenceTieError as tie:
        good = []
        for cand in tie.candidates:  # a candidate that fails leaves no partial history behind
            with contextlib.suppress(ScopetwinError):
                good.append(attempt(int(cand), None))
        if len(good) == 1:
            return good[0]
        raise ReferenceTieError(
            tie.candidates,
            f"{tie}; taken as the reference in turn, {len(good)} of the {len(tie.candidates)} candidates "
            "reconstruct a surface on the holding frame",
        ) from None
