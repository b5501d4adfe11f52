"""Phase-measuring deflectometry reconstruction: the nested start-height iteration on dense slopes (thesis §1.4).

The marker method's iteration (:mod:`scopetwin.recon.reconstruct`) with every decoded pixel as an observation:

* inner loop for a start height H: the pixels' rays meet the current surface (first the plane z = H), their slopes
  follow from the display points they see (:func:`scopetwin.recon.fringes.slopes.dense_slopes`), the slopes are
  integrated into a B-spline surface whose mean over the ROI is H (eq. 1.5,
  :class:`scopetwin.recon.fringes.integration.SlopeIntegrator`); repeated until the ROI heights change by less
  than ``inner_tol_um``;
* outer loop: the frame criterion (:func:`scopetwin.recon.frame_criterion.frame_criterion`, eq. 1.3) on the
  surface's maxima over the two frame regions, the next H by :func:`scopetwin.recon.frame_criterion.
  next_start_height`, until the criterion is below ``outer_tol_um``.

With a second display position (``second``, ``shift_mm``) the absolute height comes from the per-pixel
triangulation of :mod:`scopetwin.recon.fringes.two_positions` instead: H is the weighted mean, over the pixels, of
the triangulated height minus the integrated shape there, iterated with the inner loop.

The frame criterion's extrapolation: the spline's fixed curvature prior extrapolates the surface 1-6 mm beyond the
last decoded pixel into the frame regions, and on steep sheets (80-200 µm of waviness, a bow) it misses the frame
maxima by microns. With ``frame_posterior`` (default) the criterion's shape functional D (frame maxima relative to
the ROI mean) is read instead from the Gaussian-process posterior of the marker path (:mod:`scopetwin.recon.
posterior`: prior chosen by evidence, :func:`~scopetwin.recon.posterior.fit_hyper`; the slopes traced through the
converged surface, a few hundred of them by :func:`scopetwin.recon.uncertainty.posterior_subset_indices`), and the start
height solves H + D_post(H) = z_frame by Newton steps, each but the last followed by the inner loop at the new H (as
:func:`scopetwin.recon.uncertainty.posterior` does for the markers; ``level`` criterion only).

Uncertainty: posterior samples of the integration (the display points' noise carried through the slopes, and the
curvature prior) give the shape's standard deviation relative to the ROI mean; the start height's comes from the
posterior spread of D divided by the criterion's slope in H, but not less than the spread of the frame criterion
over the integration's samples (frame criterion with ``frame_posterior``; without it that spread and the distance
left to the criterion's root), or from the triangulated heights' noise and the
samples' shape at the pixels (two positions). The start height's uncertainty
tilts the slopes; its effect on the shape (the surface's change per unit H, ROI mean removed) is added in quadrature.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from scopetwin.recon.errors import ReconstructionError
from scopetwin.recon.frame_criterion import FrameCriterion, frame_criterion, frame_distance, next_start_height
from scopetwin.recon.fringes.blocks import block_average, block_size
from scopetwin.recon.fringes.integration import Integrated, SlopeIntegrator
from scopetwin.recon.fringes.phase import DisplayCoordinates
from scopetwin.recon.fringes.slopes import PixelRays, SlopeObservations, dense_slopes
from scopetwin.recon.fringes.two_positions import DirectPoints, two_position_points
from scopetwin.recon.parallel import Background
from scopetwin.recon.policy import DEFAULT_POLICY
from scopetwin.recon.posterior import Hyper, PosteriorError, fit_hyper
from scopetwin.recon.reconstruct import measured_nodes, single_thread_blas
from scopetwin.recon.spline import SplineSurface
from scopetwin.recon.substrate import Substrate2D
from scopetwin.recon.uncertainty import FrameReading, read_frame
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array, Frame
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap

#: Two display positions: a pixel whose triangulated height is farther from the surface than this many robust
#: standard deviations (1.4826 x the median absolute deviation of the whitened residuals) is left out of H.
OUTLIER_ROBUST_SIGMAS = 4.0


def distance_left(change: float, last_change: float) -> float:
    """The RMS distance of the ROI heights to the inner loop's fixed point (mm), extrapolated from the last two
    RMS changes (mm) of a contracting iteration: with the ratio q = change / last_change < 1 the steps still to come
    sum to change q / (1 - q) (geometric series); infinite where the changes do not shrink or there is no last
    change (``last_change`` infinite)."""
    if not (np.isfinite(last_change) and 0.0 <= change < last_change):
        return float("inf")
    q = change / last_change
    return change * q / (1.0 - q)


#: The frame loop hands its slopes to the posterior's evidence search once its criterion lies within this of its
#: root, µm: the search runs in a second thread beside the loop's remaining start heights instead of after them, on
#: slopes traced at a start height about this far from the final one at most (the prior describes the surface's kind
#: and the slopes' noise, which a start height that close barely changes). The same slopes on one CPU (searched when
#: the posterior asks for the prior). Measured on the ``thesis-1.10-fringes`` preset's render, the prior searched on
#: the slopes traced through the final surface shifted by 10, 20, 50 and 100 µm moves the posterior's D by 0.002,
#: 0.06, 0.13 and 0.14 of its spread (0.020 µm; the fringe result's u(absolute) is 0.31 µm): the first start height,
#: 10.6 µm from the root, starts the search beside the second's inner loop.
EVIDENCE_EARLY_UM = 20.0
#: Newton steps of the posterior start height up to this size (µm) move the surface to first order instead of running
#: the inner loop again: shifted by the step and bent by the frame loop's change per unit start height (the tilt)
#: times the step, the slopes traced through it anew. Measured on the ``thesis-1.10-fringes`` preset's render (a
#: 0.125 µm step): the first-order surface lies 0.0002 µm RMS (ROI, mean removed) from the inner loop's, whose
#: change it predicts (0.016 µm RMS). Larger steps (steep sheets: several µm) run the inner loop.
LINEAR_STEP_UM = 1.0


#: With the frame posterior, the frame loop hands over to the posterior's Newton steps once its criterion lies within
#: this of its root, µm (and it has two start heights, for the criterion's slope): the posterior moves the start height
#: by its own correction anyway (0.1-0.2 µm on the thesis's kind), and steps up to :data:`LINEAR_STEP_UM` move the
#: surface to first order, so a last inner loop to the fitted criterion's root buys nothing the result keeps. Where
#: the posterior cannot be formed, the loop goes on to that root. Measured on the ``thesis-1.10-fringes`` preset's
#: render: the loop hands over at 0.047 µm after two start heights instead of converging after three, and the result's
#: start height moves by 0.0009 µm, D by 0.0008 µm (0.04 of its spread), u(absolute) by 1e-5 µm.
POSTERIOR_HANDOFF_UM = 0.5


class _EarlyEvidence:
    """The posterior's prior, searched from the frame loop's slopes as soon as the loop is near its root
    (:data:`EVIDENCE_EARLY_UM`), beside the loop (:class:`scopetwin.recon.parallel.Background`)."""

    def __init__(self, fit: Callable[[SlopeObservations], Hyper], wanted: bool) -> None:
        self._fit, self._wanted = fit, wanted
        self._job: Background[Hyper] | None = None

    def offer(self, criterion_mm: float, obs: SlopeObservations) -> None:
        """Start the search on ``obs`` if none has started and the criterion is near its root."""
        if self._wanted and self._job is None and abs(criterion_mm) * 1e3 <= EVIDENCE_EARLY_UM:
            self._job = Background(lambda: self._fit(obs))

    def result(self) -> Hyper | None:
        """The prior (None where no search started).

        Raises
        ------
        scopetwin.recon.posterior.PosteriorError
            The search failed (too few slopes).
        """
        return None if self._job is None else self._job.result()

    def close(self) -> None:
        if self._job is not None:
            self._job.close()


@dataclass(frozen=True)
class FringeConfig:
    """Parameters of the fringe reconstruction.

    Attributes
    ----------
    knot_spacing_mm : float
        Knot spacing of the B-spline surface, mm.
    curvature_std_per_mm : float
        kappa of the curvature prior (a knot cell's curvature components N(0, kappa^2)), 1/mm.
    samples : int
        Posterior samples for the uncertainty.
    seed : int
        Seed of the posterior samples.
    start_height_mm : float
        First start height H, mm.
    inner_tol_um, inner_max : float, int
        RMS change of the ROI heights, or RMS distance left to the self-consistent surface that the last two
        changes extrapolate to (:func:`distance_left`), that ends the inner loop, µm; most inner iterations.
    outer_tol_um, outer_max : float, int
        |frame criterion| (or |start-height change| with two positions) that ends the outer loop, µm; most steps.
    criterion : {"level", "delta"}
        The frame criterion (:func:`scopetwin.recon.frame_criterion.frame_criterion`).
    frame_step_mm, roi_step_mm : float
        Steps of the evaluation grids over the frame regions and the ROI, mm.
    measured_gap_mm : float
        A ROI node farther than this from every observation is not measured, mm.
    block_px : int
        Edge of the pixel blocks the display points are averaged over before the iteration
        (:mod:`scopetwin.recon.fringes.blocks`), pixels; 0: chosen from the knot spacing
        (:func:`scopetwin.recon.fringes.blocks.block_size`), 1: every pixel its own observation.
    frame_posterior : bool
        The frame criterion's D from the Gaussian-process posterior of the slopes (prior by evidence) and the start
        height from H + D_post = z_frame (module docstring); False: D of the spline's extrapolation. ``level``
        criterion only.
    evidence_points, evidence_coarse_points : int
        Slopes (an even subsample) the evidence is maximised on, and the coarse subsample its starts run on
        (:func:`scopetwin.recon.posterior.fit_hyper`).
    posterior_points : int
        Slopes the posterior is conditioned on (:func:`scopetwin.recon.uncertainty.posterior_subset_indices`: the half
        nearest the frame regions in full, an even subsample of the rest).
    posterior_iterations : int
        Most Newton steps on H + D_post(H) = z_frame.
    """

    knot_spacing_mm: float = 0.4
    curvature_std_per_mm: float = 1e-3
    samples: int = 24
    seed: int = 0
    start_height_mm: float = 0.0
    inner_tol_um: float = 0.002
    inner_max: int = 8
    outer_tol_um: float = 0.002
    outer_max: int = 12
    criterion: FrameCriterion = "level"
    frame_step_mm: float = 0.25
    roi_step_mm: float = 0.5
    measured_gap_mm: float = 0.5
    block_px: int = 0
    frame_posterior: bool = True
    evidence_points: int = 250
    evidence_coarse_points: int = 100
    posterior_points: int = 600
    posterior_iterations: int = 3

    def __post_init__(self) -> None:
        for name in ("knot_spacing_mm", "curvature_std_per_mm", "inner_tol_um", "outer_tol_um"):
            if not getattr(self, name) > 0:
                raise ReconstructionError(f"fringe reconstruction: {name} must be > 0, got {getattr(self, name)}")
        if self.block_px < 0:
            raise ReconstructionError(
                f"fringe reconstruction: block_px must be >= 0 (0: automatic), got {self.block_px}"
            )
        if self.evidence_points < 10 or self.posterior_points < 10 or self.posterior_iterations < 1:
            raise ReconstructionError(
                "fringe reconstruction: evidence_points >= 10, posterior_points >= 10 and posterior_iterations >= 1 "
                f"needed, got {self.evidence_points}, {self.posterior_points}, {self.posterior_iterations}"
            )
        if self.samples < 2 or self.inner_max < 1 or self.outer_max < 1:
            raise ReconstructionError("fringe reconstruction: samples >= 2, inner_max >= 1 and outer_max >= 1 needed")


@dataclass(frozen=True)
class FringeStep:
    """One outer step: start height, frame maxima, criterion (µm), inner iterations, observations, chi^2."""

    start_height_um: float
    max_1_um: float
    max_2_um: float
    criterion_um: float
    inner_iterations: int
    observations: int
    chi2_per_dof: float


@dataclass
class FringeResult:
    """The reconstructed surface with its uncertainty (the fringe counterpart of
    :class:`scopetwin.recon.reconstruct.ReconstructionResult`).

    Attributes
    ----------
    surface : SplineSurface
        The surface, base-plane coordinates, mm.
    substrate : Substrate2D
    method : {"frame-criterion", "two-positions"}
        Where the absolute height comes from.
    start_height_mm : float
        The ROI mean height H, mm.
    absolute_um : float
        Standard uncertainty of H, µm.
    shape_um : float
        RMS over the ROI of the standard uncertainty of the height relative to the ROI mean, µm.
    samples : ndarray, (k, n_coef)
        Posterior coefficient deviations (ROI mean removed), start-height part excluded.
    tilt_per_mm : ndarray, (n_coef,)
        The surface's change per unit start height, ROI mean removed (coefficients per mm).
    observation_xy : ndarray, (n, 2)
        Where the slopes were observed, mm.
    block_px : int
        Edge of the pixel blocks the display points were averaged over (one observation each), pixels.
    history : list of FringeStep
    converged : bool
    seconds : float
    frame_posterior : dict or None
        The frame criterion read from the Gaussian-process posterior (``FringeConfig.frame_posterior``): D's
        posterior mean and spread and the spline's D (µm), the start-height correction it made (µm), the Newton
        steps, the prior chosen by evidence, and the two parts of ``absolute_um`` (the larger is reported): D's
        posterior spread and the criterion's spread over the spline's samples (µm); None where not used.
    """

    surface: SplineSurface
    substrate: Substrate2D
    method: Literal["frame-criterion", "two-positions"]
    start_height_mm: float
    absolute_um: float
    shape_um: float
    samples: Array
    tilt_per_mm: Array
    observation_xy: Array
    history: list[FringeStep] = field(default_factory=list)
    block_px: int = 1
    converged: bool = True
    seconds: float = 0.0
    frame_posterior: dict[str, Any] | None = None

    def height_at(self, x_mm: Any, y_mm: Any) -> NDArray[np.float64]:
        """Heights at substrate coordinates (x, y), mm (vectorised)."""
        return np.asarray(self.surface.height(np.asarray(x_mm, float), np.asarray(y_mm, float)), dtype=np.float64)

    def shape_std_at(self, x_mm: Any, y_mm: Any) -> NDArray[np.float64]:
        """Standard uncertainty of the height relative to the ROI mean at (x, y), mm (posterior samples and the
        start height's tilt)."""
        x = np.asarray(x_mm, dtype=np.float64)
        design = self.surface.design(x.ravel(), np.broadcast_to(np.asarray(y_mm, float), x.shape).ravel())
        var = np.var(np.asarray(design @ self.samples.T), axis=1, ddof=1)
        var += (np.asarray(design @ self.tilt_per_mm) * self.absolute_um * 1e-3) ** 2
        return np.sqrt(var).reshape(x.shape)

    def heightmap(self, nx: int = 128, ny: int = 288) -> HeightMap:
        """The surface on the contract's node grid over the substrate (docs/contract.md, "Height maps")."""
        return self.surface.heightmap(self.substrate, nx, ny)

    def std_heightmap(self, nx: int = 128, ny: int = 288) -> HeightMap:
        """Per-node standard uncertainty of the absolute height (shape and start height together), mm."""
        xs, ys = np.linspace(*self.substrate.x_range, nx), np.linspace(*self.substrate.y_range, ny)
        xx, yy = np.meshgrid(xs, ys)
        z = np.hypot(self.shape_std_at(xx, yy), self.absolute_um * 1e-3)
        return HeightMap(z, xs[0], xs[-1], ys[0], ys[-1])

    def measured_mask(self, nx: int = 128, ny: int = 288, max_gap_mm: float = 0.5) -> NDArray[np.bool_]:
        """Nodes of :meth:`heightmap`'s grid the pixels measure (frame regions True: the criterion's extrapolation)."""
        xx, yy = np.meshgrid(np.linspace(*self.substrate.x_range, nx), np.linspace(*self.substrate.y_range, ny))
        return measured_nodes(self.substrate, self.observation_xy, xx, yy, max_gap_mm)

    def roi_coverage(self, max_gap_mm: float = 0.5, step_mm: float = 0.5) -> float:
        """Share of the region of interest within ``max_gap_mm`` of a decoded pixel's point on the substrate (the
        marker method's :meth:`scopetwin.recon.reconstruct.ReconstructionResult.roi_coverage`, with the pixels'
        spacing of a few tens of µm in place of the markers' 1.5 mm), on a ``step_mm`` grid over the ROI."""
        if len(self.observation_xy) == 0:
            return 0.0
        gx, gy = self.substrate.roi_grid(step_mm)
        return float(np.mean(measured_nodes(self.substrate, self.observation_xy, gx, gy, max_gap_mm)))

    def summary(self) -> dict[str, Any]:
        """JSON-ready summary (the ``reconstruct`` contract's keys where they apply)."""
        return {
            "method": f"fringes/{self.method}",
            "outer_iterations": len(self.history),
            "inner_iterations": int(sum(s.inner_iterations for s in self.history)),
            "start_height_um": self.start_height_mm * 1e3,
            "observations": int(len(self.observation_xy)),
            "block_px": self.block_px,
            "converged": self.converged,
            "seconds": self.seconds,
            "uncertainty": {"absolute_um": self.absolute_um, "shape_um": self.shape_um},
            "history": [s.__dict__ for s in self.history],
            "frame_posterior": self.frame_posterior,
        }


@dataclass
class _Inner:
    surface: SplineSurface
    obs: SlopeObservations
    integrated: Integrated
    iterations: int


@dataclass
class _Loop:
    """The frame loop's start heights so far: (H, criterion) and (H, inner run) of each, its steps, whether it
    converged, and whether it stopped short of the root to hand over to the posterior (:data:`POSTERIOR_HANDOFF_UM`)."""

    values: list[tuple[float, float]]
    runs: list[tuple[float, _Inner]]
    history: list[FringeStep]
    converged: bool
    handed_over: bool = False


@dataclass(frozen=True)
class _Root:
    """The frame loop's run nearest the fitted criterion's root: its start height (mm), inner run and criterion
    (mm), the criterion's slope in the start height, and the surface's change per unit start height (ROI mean
    removed)."""

    h: float
    inner: _Inner
    criterion: float
    slope: float
    tilt: Array


class FringeReconstructor:
    """The pieces of the nested iteration on dense slopes for one camera, display and substrate (module docstring)."""

    def __init__(
        self, camera: Camera, display: Frame, substrate: Substrate2D, config: FringeConfig | None = None
    ) -> None:
        self.camera = camera
        self.display = display
        self.sub = substrate
        self.config = config or FringeConfig()
        cfg = self.config
        self.integrator = SlopeIntegrator(substrate, cfg.knot_spacing_mm, cfg.curvature_std_per_mm, cfg.roi_step_mm)
        spline = self.integrator.spline
        gx, gy = substrate.roi_grid(cfg.roi_step_mm)
        self._roi = spline.design(gx, gy)
        self._frames = [spline.design(*substrate.frame_grid(r, cfg.frame_step_mm)) for r in (1, 2)]
        #: The latest integration: its factorisation preconditions the next one's (SlopeIntegrator.solve, warm).
        self._warm: Integrated | None = None

    def plane(self, height: float) -> SplineSurface:
        """The plane z = ``height`` as a spline."""
        return self.integrator.spline.with_coef(np.full(self.integrator.n_coef, float(height)))

    def frame_maxima(self, coef: Array) -> tuple[Array, Array]:
        """Maxima of surfaces (coefficients on the last axis) over frame regions 1 and 2, mm."""
        c = np.atleast_2d(coef).T
        return np.asarray(self._frames[0] @ c).max(axis=0), np.asarray(self._frames[1] @ c).max(axis=0)

    def inner_loop(
        self, height: float, coords: DisplayCoordinates, rays: PixelRays, initial: SplineSurface | None = None
    ) -> _Inner:
        """Self-consistent surface at ROI-mean height ``height`` (thesis §1.4, eq. 1.5)."""
        cfg = self.config
        if initial is None:
            surface = self.plane(height)
        else:
            c = initial.coef.ravel()
            surface = initial.with_coef(c + height - float(self.integrator.roi_mean(c)))
        prev = self._roi @ surface.coef.ravel()
        iterations, last_change = 0, float("inf")
        while iterations < cfg.inner_max:
            iterations += 1
            obs = dense_slopes(self.camera, self.display, coords, surface, self.sub, rays)
            integ = self.integrator.solve(obs, height, warm=self._warm)
            self._warm = integ
            surface = integ.surface
            roi = self._roi @ surface.coef.ravel()
            change = float(np.sqrt(np.mean((roi - prev) ** 2)))
            prev = roi
            if min(change, distance_left(change, last_change)) * 1e3 < cfg.inner_tol_um:
                break
            last_change = change
        return _Inner(surface, obs, integ, iterations)

    def _step(self, h: float, inner: _Inner, crit: float, m1: float, m2: float) -> FringeStep:
        return FringeStep(
            h * 1e3,
            m1 * 1e3,
            m2 * 1e3,
            crit * 1e3,
            inner.iterations,
            len(inner.obs),
            inner.integrated.chi2_per_dof,
        )

    def frame_loop(self, coords: DisplayCoordinates) -> FringeResult:
        """The start-height loop on the frame criterion (§1.4, eqs. 1.3-1.4), with the start height's uncertainty."""
        cfg = self.config
        t0 = time.perf_counter()
        rays = PixelRays.of(self.camera, coords.valid, coords.block)
        early = _EarlyEvidence(self.evidence, cfg.frame_posterior and cfg.criterion == "level")
        try:
            return self._frame_loop(coords, rays, early, t0)
        finally:
            early.close()

    def _start_heights(
        self,
        coords: DisplayCoordinates,
        rays: PixelRays,
        early: _EarlyEvidence,
        handoff: bool = False,
        earlier: _Loop | None = None,
    ) -> _Loop:
        """The outer loop's start heights: (H, criterion) and (H, inner run) of each, its steps, whether it
        converged; at least two start heights (the criterion's slope needs them). ``handoff``: stop within
        :data:`POSTERIOR_HANDOFF_UM` of the root (the posterior's Newton steps go on from there); ``earlier``: a loop
        that handed over, continued to the root."""
        cfg = self.config
        loop = earlier or _Loop([], [], [], False)
        values, runs, history = loop.values, loop.runs, loop.history
        h, converged = cfg.start_height_mm, False
        initial = runs[-1][1].surface if runs else None
        if earlier is not None:
            m1, m2 = (float(v[0]) for v in self.frame_maxima(runs[-1][1].surface.coef.ravel()))
            h = float(next_start_height(values, self._thesis_step(values[-1][0], m1, m2, values[-1][1])))
        for _ in range(cfg.outer_max - len(values)):
            inner = self.inner_loop(h, coords, rays, initial)
            m1, m2 = (float(v[0]) for v in self.frame_maxima(inner.surface.coef.ravel()))
            crit = frame_criterion(m1, m2, self.sub.frame_z, cfg.criterion)
            history.append(self._step(h, inner, crit, m1, m2))
            values.append((h, crit))
            runs.append((h, inner))
            initial = inner.surface
            early.offer(crit, inner.obs)
            if abs(crit) * 1e3 <= cfg.outer_tol_um:
                converged = True
                break
            if handoff and len(runs) >= 2 and abs(crit) * 1e3 <= POSTERIOR_HANDOFF_UM:
                return _Loop(values, runs, history, True, handed_over=True)
            h = float(next_start_height(values, self._thesis_step(h, m1, m2, crit)))
        if len(runs) < 2:  # the criterion's slope needs a second start height
            probe = h + 1e-3
            runs.append((probe, self.inner_loop(probe, coords, rays, initial)))
            m1, m2 = (float(v[0]) for v in self.frame_maxima(runs[-1][1].surface.coef.ravel()))
            values.append((probe, frame_criterion(m1, m2, self.sub.frame_z, cfg.criterion)))
        return _Loop(values, runs, history, converged)

    def _thesis_step(self, h: float, m1: float, m2: float, crit: float) -> float:
        """The thesis's next start height after a run at ``h`` with frame maxima ``m1``, ``m2`` and criterion
        ``crit`` (§1.4, eqs. 1.3-1.4), mm."""
        return h - (frame_distance(m1, m2, self.sub.frame_z) if self.config.criterion == "delta" else crit)

    def _frame_loop(
        self, coords: DisplayCoordinates, rays: PixelRays, early: _EarlyEvidence, t0: float
    ) -> FringeResult:
        cfg = self.config
        posterior = cfg.frame_posterior and cfg.criterion == "level"
        loop = self._start_heights(coords, rays, early, handoff=posterior)
        fit = self._fitted_root(loop)
        solved, info = None, None
        # the spline's posterior draws depend on the run's observation rows, not on its start height: drawn beside
        # the posterior's Newton steps, kept where those moved the surface without another inner loop
        best_run = fit.inner.integrated
        with Background(lambda: self.integrator.with_samples(best_run, cfg.samples, cfg.seed)) as draws:
            if posterior:
                solved = self.posterior_start_height(fit.h, fit.inner, fit.slope, coords, rays, early, fit.tilt)
            if solved is None and loop.handed_over:  # no posterior after all: the loop goes on to the fitted root
                loop = self._start_heights(coords, rays, early, earlier=loop)
                fit = self._fitted_root(loop)
                integ = self.integrator.with_samples(fit.inner.integrated, cfg.samples, cfg.seed)
            elif solved is None:
                integ = draws.result()
            elif solved[1].integrated.rows is best_run.rows:
                integ = self._at_height(draws.result(), solved[1].surface, solved[0])
        h_best, inner = fit.h, fit.inner
        if solved is None:
            # the criterion's spread over the posterior, and the distance left to its root, in start height
            sigma_h = float(np.hypot(self._criterion_spread(integ), fit.criterion) / abs(fit.slope))
        else:
            h_best, moved, sigma_post, info = solved
            if moved.integrated.rows is not best_run.rows:  # an inner loop ran: its own draws
                integ = self.integrator.with_samples(moved.integrated, cfg.samples, cfg.seed, h_best)
            inner = moved
            # not below the criterion's spread over the spline's own posterior samples: the Gaussian process sees a
            # subset of the slopes with the white noise of its evidence, and on rendered steep sheets and the
            # dimple its spread alone is short by 2-5 (docs/markers-vs-fringes.md)
            sigma_spline = self._criterion_spread(integ) / abs(fit.slope)
            sigma_h = max(sigma_post, sigma_spline)
            info |= {"u_posterior_um": sigma_post * 1e3, "u_spline_um": sigma_spline * 1e3}
        elapsed = time.perf_counter() - t0
        result = self._result(
            integ, inner.obs, "frame-criterion", h_best, sigma_h, fit.tilt, loop.history, loop.converged, elapsed
        )
        result.frame_posterior = info
        return result

    def _fitted_root(self, loop: _Loop) -> _Root:
        """The run nearest the fitted criterion's root, the criterion's slope and the surface's tilt between it and
        the run farthest from it."""
        values, runs = loop.values, loop.runs
        best = min(range(len(values)), key=lambda i: abs(values[i][1]))
        h_best, inner = runs[best]
        other = max((i for i in range(len(values)) if i != best), key=lambda i: abs(values[i][0] - h_best))
        dh = values[other][0] - h_best
        tilt = (runs[other][1].surface.coef.ravel() - inner.surface.coef.ravel()) / dh
        tilt -= float(self.integrator.roi_mean(tilt))
        return _Root(h_best, inner, values[best][1], (values[other][1] - values[best][1]) / dh, tilt)

    def _at_height(self, drawn: Integrated, surface: SplineSurface, height: float) -> Integrated:
        """``drawn`` (with its posterior draws) carrying ``surface`` moved to ROI-mean height ``height`` (mm)."""
        c = surface.coef.ravel()
        return replace(drawn, surface=surface.with_coef(c + (height - float(self.integrator.roi_mean(c)))))

    def _criterion_spread(self, integ: Integrated) -> float:
        """The frame criterion's standard deviation over the spline's posterior samples ``integ.samples``, mm."""
        c = integ.surface.coef.ravel()
        m1s, m2s = self.frame_maxima(c[None, :] + integ.samples)
        pairs = zip(m1s, m2s, strict=True)
        return float(np.std([frame_criterion(a, b, self.sub.frame_z, self.config.criterion) for a, b in pairs], ddof=1))

    def _moved(self, inner: _Inner, step: float, tilt: Array, coords: DisplayCoordinates, rays: PixelRays) -> _Inner:
        """``inner`` at a start height ``step`` (mm) away, to first order: shifted by the step and bent by ``tilt``
        times it, the slopes traced through that surface (no integration; the factorisation kept)."""
        surface = inner.surface.with_coef(inner.surface.coef.ravel() + step + tilt * step)
        obs = dense_slopes(self.camera, self.display, coords, surface, self.sub, rays)
        return _Inner(surface, obs, replace(inner.integrated, surface=surface), 0)

    def evidence(self, obs: SlopeObservations) -> Hyper:
        """The posterior's prior by evidence on the slopes ``obs`` (:func:`scopetwin.recon.posterior.fit_hyper`)."""
        cfg = self.config
        return fit_hyper(obs.xy, obs.hx, obs.hy, cfg.evidence_points, coarse_points=cfg.evidence_coarse_points)

    def read_frame_posterior(
        self, obs: SlopeObservations, earlier: FrameReading | None = None, hyper: Hyper | None = None
    ) -> FrameReading:
        """The Gaussian-process posterior of the frame criterion's shape functional D from the slopes ``obs``, on
        the ROI grid of the integrator's ROI mean: under ``earlier``'s prior (and its model where the slopes have
        not moved: :func:`scopetwin.recon.uncertainty.read_frame`), else ``hyper``, else the prior by evidence on
        ``obs``.

        Raises
        ------
        scopetwin.recon.posterior.PosteriorError
            Too few slopes, or the posterior cannot be formed.
        """
        cfg, sub = self.config, self.sub
        prior = earlier.post.hyper if earlier is not None else hyper or self.evidence(obs)
        rx, ry = sub.roi_grid(cfg.roi_step_mm)
        axes = (np.unique(rx), np.unique(ry))
        # D alone: the fringe shape's uncertainty comes from the spline's own samples, not the contrast map
        return read_frame(sub, axes, (obs.xy, obs.hx, obs.hy), prior, cfg.posterior_points, earlier, contrasts=False)

    def posterior_start_height(
        self,
        h: float,
        inner: _Inner,
        slope: float,
        coords: DisplayCoordinates,
        rays: PixelRays,
        early: _EarlyEvidence | None = None,
        tilt: Array | None = None,
    ) -> tuple[float, _Inner, float, dict[str, Any]] | None:
        """The start height from the posterior frame criterion: H + D_post(H) = z_frame (thesis §1.4, eq. 1.4 with
        the posterior D) by Newton steps from the fitted root ``h``, each but the last followed by the inner loop at
        the new H (the traced slopes follow the start height), the marker path's
        :func:`scopetwin.recon.uncertainty.posterior` on the fringe slopes.

        Returns the start height (mm), the last inner run, the start height's standard uncertainty (D's posterior
        spread over the criterion's slope, mm) and a summary; None where the posterior cannot be formed (the
        spline's extrapolation is kept). ``early``: the prior searched while the frame loop ran (on its slopes near
        the root), else by evidence on ``inner``'s. ``tilt``: the surface's change per unit start height (ROI mean
        removed), with which steps up to :data:`LINEAR_STEP_UM` move the surface to first order (:meth:`_moved`).
        """
        cfg = self.config
        slope = DEFAULT_POLICY.trusted_slope(slope)
        h0 = h
        m1, m2 = (float(v[0]) for v in self.frame_maxima(inner.surface.coef.ravel()))
        d_fit = 0.5 * (m1 + m2) - h
        reading: FrameReading | None = None
        tried: list[tuple[float, float]] = []  # (H, F_post(H))
        for k in range(cfg.posterior_iterations):
            try:
                prior = early.result() if early is not None and reading is None else None
                reading = self.read_frame_posterior(inner.obs, reading, prior)
            except PosteriorError:
                return None
            post = reading.post
            f_post = h + post.d_mean - self.sub.frame_z
            tried.append((h, f_post))
            step = -f_post / DEFAULT_POLICY.newton_slope(tried, slope)
            sigma = post.d_std / abs(slope)
            h += step
            if abs(step) <= sigma or abs(step) * 1e3 <= cfg.outer_tol_um or k == cfg.posterior_iterations - 1:
                break  # the last, small step without another inner loop
            if tilt is not None and abs(step) * 1e3 <= LINEAR_STEP_UM:
                inner = self._moved(inner, step, tilt, coords, rays)
            else:
                inner = self.inner_loop(h, coords, rays, inner.surface)
        info = {
            "d_um": post.d_mean * 1e3,
            "d_std_um": post.d_std * 1e3,
            "d_spline_um": d_fit * 1e3,
            "correction_um": (h - h0) * 1e3,
            "steps": len(tried),
            "prior": post.hyper.as_dict(),
        }
        return h, inner, sigma, info

    def two_position_loop(self, coords: DisplayCoordinates, direct: DirectPoints) -> FringeResult:
        """The start height from per-pixel triangulated heights (two display positions), iterated with the inner loop.

        Raises
        ------
        ReconstructionError
            Fewer than 10 triangulated pixels on the ROI.
        """
        cfg = self.config
        t0 = time.perf_counter()
        on = (np.abs(direct.xy[:, 0]) <= 0.5 * self.sub.size_x) & (np.abs(direct.xy[:, 1]) < 0.5 * self.sub.roi_length)
        on &= np.isfinite(direct.z) & (direct.z_std > 0)
        if on.sum() < 10:
            raise ReconstructionError(f"only {int(on.sum())} pixels triangulated on the ROI from the two positions")
        xy, z, w = direct.xy[on], direct.z[on], 1.0 / direct.z_std[on] ** 2
        rays = PixelRays.of(self.camera, coords.valid, coords.block)
        design = self.integrator.spline.design(xy[:, 0], xy[:, 1])
        h, initial, history, converged = cfg.start_height_mm, None, [], False
        keep = np.ones(len(z), dtype=bool)
        runs: list[tuple[float, _Inner]] = []
        for _ in range(cfg.outer_max):
            inner = self.inner_loop(h, coords, rays, initial)
            runs.append((h, inner))
            resid = z - np.asarray(design @ inner.surface.coef.ravel())
            # H moves the surface by a constant: the weighted mean residual is the correction, the pixels beyond
            # OUTLIER_ROBUST_SIGMAS of the whitened residuals' robust scale (1.4826 MAD: the cut does not depend on
            # how well the stated sigmas are scaled) left out
            for _ in range(3):
                shift = float(np.sum(w[keep] * resid[keep]) / np.sum(w[keep]))
                t = (resid - shift) * np.sqrt(w)
                scale = 1.4826 * float(np.median(np.abs(t - np.median(t))))
                keep = np.abs(t) < OUTLIER_ROBUST_SIGMAS * scale
            history.append(self._step(h, inner, -shift, float("nan"), float("nan")))
            initial = inner.surface
            h += shift
            if abs(shift) * 1e3 <= cfg.outer_tol_um:
                converged = True
                break
        h_last, inner = runs[-1]
        resid = z - np.asarray(design @ inner.surface.coef.ravel())
        chi2 = float(np.sum(w[keep] * (resid[keep] - shift) ** 2) / max(int(keep.sum()) - 1, 1))
        integ = self.integrator.with_samples(inner.integrated, cfg.samples, cfg.seed, h)
        # the samples' shape at the pixels, weighted as H is, relative to the ROI mean
        wk = np.where(keep, w, 0.0)
        at_pixels = np.asarray(design @ integ.samples.T).T @ wk / wk.sum()
        sigma_h = float(np.sqrt(max(chi2, 1.0) / wk.sum() + np.var(at_pixels, ddof=1)))
        if len(runs) >= 2 and runs[0][0] != h_last:
            tilt = (runs[0][1].surface.coef.ravel() - inner.surface.coef.ravel()) / (runs[0][0] - h_last)
            tilt -= float(self.integrator.roi_mean(tilt))
        else:
            tilt = np.zeros(self.integrator.n_coef)
        return self._result(
            integ, inner.obs, "two-positions", h, sigma_h, tilt, history, converged, time.perf_counter() - t0
        )

    def _result(
        self,
        integ: Integrated,
        obs: SlopeObservations,
        method: Literal["frame-criterion", "two-positions"],
        h: float,
        sigma_h: float,
        tilt: Array,
        history: list[FringeStep],
        converged: bool,
        seconds: float,
    ) -> FringeResult:
        result = FringeResult(
            integ.surface, self.sub, method, h, sigma_h * 1e3, 0.0, integ.samples, tilt, obs.xy, history, converged
        )
        gx, gy = self.sub.roi_grid(self.config.roi_step_mm)
        std = result.shape_std_at(gx, gy)
        result.shape_um = float(np.sqrt(np.mean(std**2)) * 1e3)
        result.seconds = seconds
        return result


def reconstruct_fringes(
    setup: Setup,
    coords: DisplayCoordinates,
    config: FringeConfig | None = None,
    second: DisplayCoordinates | None = None,
    shift_mm: float | None = None,
    frame_z: float = 0.0,
) -> FringeResult:
    """Height map of the substrate from decoded fringe images (module docstring).

    Parameters
    ----------
    setup : Setup
        A deflectometry setup: its camera, its pattern frame (the display: origin at the centre, T_x / T_y along
        the display coordinates u / v) and its substrate.
    coords : DisplayCoordinates
        The decoded display point of every pixel (:func:`scopetwin.recon.fringes.phase.decode_display`).
    config : FringeConfig, optional
    second : DisplayCoordinates, optional
        The display points with the display moved by ``shift_mm`` along its normal: the absolute height then comes
        from the two positions (no frame criterion).
    shift_mm : float, optional
        The second position's distance along N_z, mm (required with ``second``).
    frame_z : float
        The holding frame's height, mm (frame criterion).

    Raises
    ------
    ReconstructionError
        Not a deflectometry setup, decoded maps of another shape than the camera's image, ``second`` without
        ``shift_mm``, or no decoded pixel on the substrate.
    """
    sub = Substrate2D.from_setup(setup, frame_z)
    camera = setup.camera_model
    if coords.shape != (camera.ny, camera.nx):
        raise ReconstructionError(
            f"decoded maps of shape {coords.shape} for the setup's {camera.ny} x {camera.nx} (rows x cols) camera"
        )
    if second is not None and shift_mm is None:
        raise ReconstructionError("a second display position needs its shift along the display normal (shift_mm)")
    if not coords.valid.any():
        raise ReconstructionError("no pixel was decoded: nothing to reconstruct")
    config = config or FringeConfig()
    block = config.block_px or block_size(camera, sub, config.knot_spacing_mm)
    coords, _ = block_average(coords, block)
    if second is not None:
        second, _ = block_average(second, block)
    if not coords.valid.any():
        raise ReconstructionError(f"no full {block} x {block} pixel block was decoded: nothing to reconstruct")
    with single_thread_blas():  # the banded factorisation: threaded BLAS gains nothing on 2 cores and can cost 10x
        rec = FringeReconstructor(camera, setup.marker_pattern.frame, sub, config)
        if second is None:
            result = rec.frame_loop(coords)
        else:
            assert shift_mm is not None
            direct = two_position_points(camera, setup.marker_pattern.frame, shift_mm, coords, second, sub.frame)
            result = rec.two_position_loop(coords, direct)
    result.block_px = block
    return result
