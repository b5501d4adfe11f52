"""Non-stereoscopic deflectometric height reconstruction: the nested start-height iteration (thesis §1.4).

Inner loop (self-consistent surface for a start height H, §1.4 and Fig. 1.4): start
with the plane z = H (or the previous outer run's surface moved to H); trace every
marker's camera ray to the current surface (secant iteration, §1.6.4,
:func:`scopetwin.scenes.secant.secant_intersection`), form the
normal from the camera ray and the ray to the marker centre (§1.7.1), turn it into a
gradient (§1.7.3), fit the shifted basis functions (§1.8) and set the bias so that the
surface's mean height over the region of interest is H (eq. 1.5). Stop when the RMS
height change over the ROI falls below a threshold. An optional centroid-bias step
(any callable) replaces the measured marker positions by bias-corrected ones in every
inner iteration.

Outer loop (start height, eq. 1.3-1.4): evaluate the maxima of the reconstructed
surface over the two holding-frame regions, where there are no data and the surface
is extrapolated. Criteria (:func:`scopetwin.recon.frame_criterion.frame_criterion`):

* ``"delta"`` — the thesis's Delta h_max = max_region1 - max_region2 = 0 (eq. 1.3);
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
image or a wrong setup is reported instead of giving a smooth, tilted, wrong map.

This module holds the iteration's pieces — the inner loop, the start-height loop, the coarse fit, the scale chosen
on the flat start, the outlier test — each returning what happened as a value (:class:`InnerRun`,
:class:`LoopOutcome`). What is done when one of them fails, and in which order, is decided in one place:
:func:`scopetwin.recon.strategy.solve` under a :class:`scopetwin.recon.policy.ReconstructionPolicy`; the
uncertainty is :mod:`scopetwin.recon.uncertainty`.

Nothing here imports Mitsuba or sim: input is a setup (camera, pattern, substrate
geometry) and marker observations (index + image position).
"""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

from scopetwin.recon.config import ReconstructionConfig
from scopetwin.recon.errors import ReconstructionError, SubstrateNotVisibleError, TooFewMarkersError
from scopetwin.recon.frame_criterion import frame_criterion, frame_distance, next_start_height
from scopetwin.recon.gradients import marker_gradients
from scopetwin.recon.policy import DEFAULT_POLICY
from scopetwin.recon.scale import select_sigma
from scopetwin.recon.shifted_basis import SBFSurface, ShiftedBasis, fit_gradients
from scopetwin.recon.substrate import Substrate2D, check_substrate_visible, intersect_surface
from scopetwin.recon.uncertainty import HeldPrior, Uncertainty
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.geometry import Array
from scopetwin.scenes.pattern import MarkerPattern
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap

if TYPE_CHECKING:
    from scopetwin.recon.posterior import Prior

#: A centroid-bias step: (current surface, marker indices (n, 2), measured image positions (n, 2) px)
#: -> corrected image positions of the marker centres (n, 2) px.
BiasStep = Callable[[SBFSurface, NDArray[np.int64], Array], Array]


@dataclass(frozen=True)
class Failure:
    """A step that could not be done, as a value: the error a user would see if nothing else worked."""

    kind: type[ReconstructionError]
    message: str

    def error(self, extra: str = "") -> ReconstructionError:
        """The user-facing error (``extra`` appended to the message)."""
        return self.kind(self.message + extra)


@dataclass
class InnerRun:
    """One inner loop (§1.4, eq. 1.5): its surface, RMS height changes (µm), gradient residual (rad), markers used;
    ``lost`` when the rays lost the substrate's ROI or a frame region's markers (the surface is the last one fitted).
    """

    surface: SBFSurface
    rms_changes_um: list[float]
    residual_rad: float
    used: int
    lost: Failure | None = None


@dataclass(frozen=True)
class LoopOutcome:
    """How a start-height loop ended: ``"converged"``, ``"not-converged"`` (the budget of runs spent) or ``"lost"``
    (an inner loop's rays lost the substrate: ``failure`` says how)."""

    status: Literal["converged", "not-converged", "lost"]
    failure: Failure | None = None

    @property
    def converged(self) -> bool:
        return self.status == "converged"


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


#: A point of the ROI farther than this from every marker is not covered by the measurement, mm (two marker spacings
#: of the §1.10 setup; :meth:`ReconstructionResult.roi_coverage`).
ROI_COVERAGE_GAP_MM = 3.0


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
    strategy: list[str] = field(default_factory=list)
    marker_xy: Array | None = None

    def height_at(self, x_mm: Any, y_mm: Any) -> NDArray[np.float64]:
        """Heights of the reconstructed surface at substrate coordinates (x, y), mm (vectorised, broadcast)."""
        return np.asarray(self.surface.height(np.asarray(x_mm, float), np.asarray(y_mm, float)), dtype=np.float64)

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

    def measured_mask(self, nx: int = 128, ny: int = 288) -> NDArray[np.bool_] | None:
        """Which nodes of :meth:`heightmap`'s grid the markers measure (None: unknown, no marker points).

        :func:`measured_nodes` on the node grid over the whole substrate: a ROI node farther than
        :data:`ROI_COVERAGE_GAP_MM` from every marker is False; the frame regions are True (their heights are the
        frame criterion's extrapolation by design, with its uncertainty in :meth:`std_heightmap`).
        """
        if self.marker_xy is None or len(self.marker_xy) == 0:
            return None
        xx, yy = np.meshgrid(np.linspace(*self.substrate.x_range, nx), np.linspace(*self.substrate.y_range, ny))
        return measured_nodes(self.substrate, self.marker_xy, xx, yy)

    def roi_coverage(self, max_gap_mm: float = ROI_COVERAGE_GAP_MM, step_mm: float = 0.5) -> float | None:
        """Share of the region of interest within ``max_gap_mm`` of a marker the surface rests on (None: unknown).

        The markers sample the slopes about 1.5 mm apart (§1.10); a point farther than two such spacings from every
        marker is the basis's interpolation or extrapolation, not a measurement. Evaluated on a ``step_mm`` grid
        over the ROI against the markers' points on the substrate (:attr:`marker_xy`).
        """
        if self.marker_xy is None or len(self.marker_xy) == 0:
            return None
        gx, gy = self.substrate.roi_grid(step_mm)
        return float(np.mean(measured_nodes(self.substrate, self.marker_xy, gx, gy, max_gap_mm)))

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
            **({"roi_coverage": self.roi_coverage()} if self.marker_xy is not None else {}),
            **({"rejected_markers": self.rejected.tolist()} if len(self.rejected) else {}),
            **({"strategy": list(self.strategy)} if self.strategy else {}),
            **({"uncertainty": self.uncertainty.summary()} if self.uncertainty is not None else {}),
            "history": self.history_dicts(),
        }


def measured_nodes(
    sub: Substrate2D, marker_xy: Array, xx: Array, yy: Array, max_gap_mm: float = ROI_COVERAGE_GAP_MM
) -> NDArray[np.bool_]:
    """Points (xx, yy) the markers measure: outside the ROI, or within ``max_gap_mm`` of a marker's point.

    The markers sample the slopes about 1.5 mm apart (§1.10); a ROI point farther than two such spacings from every
    marker holds only the basis's interpolation or extrapolation. A height map written from a reconstruction leaves
    those points NaN (:func:`scopetwin.scenes.io.write_heightmap`'s ``measured``).
    """
    from scipy.spatial import cKDTree

    xx, yy = np.broadcast_arrays(np.asarray(xx, dtype=np.float64), np.asarray(yy, dtype=np.float64))
    pts = np.stack([xx.ravel(), yy.ravel()], axis=-1)
    dist, _ = cKDTree(np.asarray(marker_xy, dtype=np.float64).reshape(-1, 2)).query(pts)
    outside = np.abs(pts[:, 1]) > 0.5 * sub.roi_length
    return np.asarray((dist <= max_gap_mm) | outside).reshape(xx.shape)


def single_thread_blas() -> contextlib.AbstractContextManager:
    """Limit BLAS to one thread while the reconstruction runs (threadpoolctl, when installed).

    The matrices here are small (~1000 x 100): multithreaded BLAS gains nothing on them and, on a
    loaded machine, its spinning threads cost 5-20x (measured: the scopetwin run pipeline took 44 s
    instead of 2.5 s for detection + two reconstructions on a shared 2-core machine).

    The limiter comes from one controller of the process (:func:`_blas_controller`): a fresh
    ``threadpool_limits`` scans the loaded libraries each time (~1.3 ms, a realtime frame's budget is 33 ms).
    """
    controller = _blas_controller()
    return contextlib.nullcontext() if controller is None else controller.limit(limits=1, user_api="blas")


@functools.cache
def _blas_controller() -> Any:
    """The process's ``threadpoolctl.ThreadpoolController`` (None without threadpoolctl), created on first use.

    It knows the thread pools loaded when it was made: numpy's and SciPy's BLAS (scipy.linalg is imported first, so
    its library is among them); a library loaded later is not limited.
    """
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover - optional
        return None
    import scipy.linalg  # noqa: F401  (its BLAS loaded before the scan)

    return ThreadpoolController()


# -- the nested iteration ---------------------------------------------------------------
class Reconstructor:
    """The pieces of the nested iteration of thesis §1.4 for one setup and basis.

    :func:`scopetwin.recon.strategy.solve` runs them in order (start-height loop, scale chosen from the data, outlier
    test, posterior) and decides what to do where one fails.

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

    Attributes
    ----------
    evidence_start : Hyper or BasisPrior or None
        The one start of the posterior step's evidence maximisation (a warm start: the prior of an earlier frame of
        the same setup, :attr:`scopetwin.recon.uncertainty.Uncertainty.hyper` through
        :func:`scopetwin.recon.posterior.prior_from_dict`); None (default): cold starts. Set by the caller, never
        by a solve, so that a frame's result does not depend on the frames before it unless asked.
    held_prior : HeldPrior or None
        A prior the posterior step reads the gradients with as it is, without an evidence search, where they are as
        plausible a draw of it as the frame's it was chosen on (:class:`scopetwin.recon.uncertainty.HeldPrior`; else
        searched again from ``evidence_start``): an earlier frame's of the same setup and surface, on a rig. None
        (default): searched. Set by the caller, as ``evidence_start``.
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
        self.last: SBFSurface | None = None
        self.last_xy: Array | None = None  # the markers' points on the substrate in the last inner iteration, mm
        self.evidence_start: Prior | None = None
        self.held_prior: HeldPrior | None = None
        self.use_basis(self.config.make_basis(substrate))

    def use_basis(self, basis: ShiftedBasis) -> None:
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
        """The pieces for a deflectometry setup's camera, pattern and substrate."""
        return cls(setup.camera_model, setup.marker_pattern, Substrate2D.from_setup(setup, frame_z), config, bias)

    # -- pieces --------------------------------------------------------------------------
    def roi_mean(self, coef: Array) -> float:
        """Mean over the ROI's evaluation grid of the basis part with coefficients ``coef``, mm."""
        return float(np.mean(self._roi_values @ coef))

    def frame_maxima(self, surface: SBFSurface) -> tuple[float, float]:
        """max over frame region 1 and region 2 of the surface, mm (eq. 1.3)."""
        return (
            float(np.max(self._frame_values[0] @ surface.coef)) + surface.offset,
            float(np.max(self._frame_values[1] @ surface.coef)) + surface.offset,
        )

    def prepare(self, markers: MarkerObservations) -> tuple[NDArray[np.int64], Array, Array]:
        """Indices, image positions and pattern positions of the markers; bad input is an error here, before work."""
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

    def trace(self, surface: SBFSurface, px: Array, targets: Array) -> tuple[Array, Array, Array, NDArray]:
        """Marker rays through ``surface``: points (x, y) and gradients of those that meet the ROI, and the mask."""
        ((xy, hx, hy),), ok = self.trace_targets(surface, px, [targets])
        return xy, hx, hy, ok

    def trace_targets(
        self, surface: SBFSurface, px: Array, targets: list[Array]
    ) -> tuple[list[tuple[Array, Array, Array]], NDArray]:
        """:meth:`trace` of the same rays towards several sets of pattern points: the rays meet ``surface`` once
        (the secant iteration, the costly part), the gradients (§1.7) follow per set. Returns (xy, hx, hy) per set
        and the mask of the rays that meet the ROI."""
        o, d = self._rays(px)
        lam, ok = intersect_surface(surface, o, d, self.sub.frame, start=self.config.intersection_start)
        hit = o + np.where(ok, lam, 0.0)[:, None] * d
        local = self.sub.frame.to_local(hit)
        ok &= (np.abs(local[:, 0]) <= 0.5 * self.sub.size_x) & (np.abs(local[:, 1]) < 0.5 * self.sub.roi_length)
        hit_ok, d_ok = hit[ok], d[ok]
        return [marker_gradients(hit_ok, d_ok, t[ok], self.sub.frame) for t in targets], ok

    def corrected(self, surface: SBFSurface, ij: NDArray[np.int64], px: Array, bias: bool = True) -> Array:
        """The image positions the inner loop uses: bias-corrected through ``surface`` where there is a bias step."""
        return self.bias(surface, ij, px) if bias and self.bias is not None else px

    def coverage(self, xy: Array, n_total: int) -> Failure | None:
        """Whether the traced markers cover the ROI and both frame regions' neighbourhoods (None: they do)."""
        cfg = self.config
        if len(xy) < max(cfg.min_markers, 0.5 * n_total):
            return Failure(
                SubstrateNotVisibleError,
                f"only {len(xy)} of {n_total} marker rays meet the substrate's region of interest: the camera "
                "does not see the substrate as the setup describes it (wrong setup for this image?)",
            )
        half = 0.5 * self.sub.roi_length
        for region, near in ((1, xy[:, 1] <= -half + cfg.edge_band), (2, xy[:, 1] >= half - cfg.edge_band)):
            n = int(near.sum())
            if n < cfg.min_edge_markers:
                side = "y < 0" if region == 1 else "y > 0"
                return Failure(
                    TooFewMarkersError,
                    f"only {n} markers within {cfg.edge_band} mm of frame region {region} ({side}); at least "
                    f"{cfg.min_edge_markers} are needed to extrapolate the surface onto the holding frame "
                    "(thesis §1.4)",
                )
        return None

    def inner_loop(
        self, start_height: float, markers: MarkerObservations, initial: SBFSurface | None = None
    ) -> InnerRun:
        """Self-consistent surface for one start height (thesis §1.4, eq. 1.5)."""
        cfg = self.config
        ij, px_meas, targets = self.prepare(markers)
        if initial is not None:
            surface = initial.shifted(start_height - self.roi_mean(initial.coef))
        else:
            surface = SBFSurface.plane(self.basis, start_height)
        run = InnerRun(surface, [], float("nan"), 0)
        prev_roi = self._roi_values @ surface.coef + surface.offset
        for _ in range(cfg.inner_max):
            xy, hx, hy, ok = self.trace(surface, self.corrected(surface, ij, px_meas), targets)
            self.last_xy = xy
            run.lost = self.coverage(xy, len(ij))
            if run.lost is not None:
                return run
            run.used = int(ok.sum())
            coef, run.residual_rad = fit_gradients(
                self.basis, xy[:, 0], xy[:, 1], hx, hy, cfg.regularization, method=cfg.method
            )
            roi = self._roi_values @ coef
            offset = start_height - float(np.mean(roi))
            surface = run.surface = SBFSurface(self.basis, coef, offset)
            roi += offset
            change = float(np.sqrt(np.mean((roi - prev_roi) ** 2)))
            run.rms_changes_um.append(change * 1e3)
            prev_roi = roi
            if change * 1e3 < cfg.inner_tol_um:
                break
        return run

    def start_height_loop(
        self,
        markers: MarkerObservations,
        h_start: float,
        history: list[OuterStep],
        surfaces: list[SBFSurface],
        runs: int | None = None,
    ) -> LoopOutcome:
        """The start-height loop (§1.4, eqs. 1.3-1.4) from ``h_start``; appends to ``history`` and ``surfaces``.

        At most ``runs`` inner loops (default: what ``outer_max`` leaves after ``history``). The next start height
        is the thesis step (``search = "thesis"``) or :func:`scopetwin.recon.frame_criterion.next_start_height`.
        """
        cfg = self.config
        values: list[tuple[float, float]] = []  # (H, F)
        tol = cfg.outer_tol_um * 1e-3
        h = h_start
        for _ in range(runs if runs is not None else cfg.outer_max - len(history)):
            init = predict_surface(surfaces, values, h) if cfg.warm_start else None
            run = self.inner_loop(h, markers, init)
            if run.lost is not None:
                return LoopOutcome("lost", run.lost)
            m1, m2 = self.frame_maxima(run.surface)
            crit = frame_criterion(m1, m2, self.sub.frame_z, cfg.criterion)
            history.append(
                OuterStep(
                    h * 1e3,
                    m1 * 1e3,
                    m2 * 1e3,
                    (m1 - m2) * 1e3,
                    crit * 1e3,
                    len(run.rms_changes_um),
                    run.rms_changes_um,
                    run.residual_rad * 1e6,
                    run.used,
                    self.basis.sigma[0],
                )
            )
            surfaces.append(run.surface)
            values.append((h, crit))
            if abs(crit) <= tol:
                self.last = run.surface
                return LoopOutcome("converged")
            d_min = frame_distance(m1, m2, self.sub.frame_z)
            thesis_step = h - d_min if d_min != 0 else h - crit
            h_new = thesis_step if cfg.search == "thesis" else next_start_height(values, thesis_step)
            if not np.isfinite(h_new):
                break
            h = float(h_new)
        self.last = surfaces[-1] if surfaces else None
        return LoopOutcome("not-converged")

    def traced_gradients(self, surface: SBFSurface, markers: MarkerObservations) -> tuple[Array, Array, Array, NDArray]:
        """The markers' gradients traced through ``surface`` (bias-corrected through it where there is a bias step)."""
        ij, px, targets = self.prepare(markers)
        return self.trace(surface, self.corrected(surface, ij, px), targets)

    def index_outliers(
        self, markers: MarkerObservations, surface: SBFSurface, factor: float, max_fraction: float
    ) -> NDArray[np.bool_]:
        """Markers whose gradients no smooth surface explains but a neighbouring index does: wrongly indexed ones.

        A marker given its neighbour's index points at a pattern position a pitch away: its traced gradient is
        milliradians off, while good markers scatter about the fit by a few µrad. A local feature finer than the
        basis (a dimple of a few µm over 1-4 mm) leaves residuals as large on markers that are numbered right. The
        two are told apart by tracing each marker to its eight neighbouring pattern positions as well (the same ray
        through the converged ``surface``, another target): markers above ``factor`` times the median residual are
        suspects; on a fit without them, a wrongly indexed suspect's residual at its own index is the pitch's whole
        slope (~8 mrad) and at the right neighbour that of a good marker, a feature's is smaller at its own index
        than at any neighbour. Suspects whose best neighbour halves the residual are rejected (worst first, at most
        ``max_fraction`` of the markers); a second and third round find what a contaminated fit hid
        (:attr:`scopetwin.recon.policy.ReconstructionPolicy.outlier_factor`). Returns True = reject.

        Measured: a row of five markers given the next row's index is rejected exactly; on a local-feature surface
        (five bumps and dimples of 0.5-3 µm over 1-4 mm) the 26 markers the bumps deflect, all numbered right, are
        kept.
        """
        ij, px, targets = self.prepare(markers)
        px = self.corrected(surface, ij, px)
        xy, hx, hy, ok = self.trace(surface, px, targets)
        steps = [(di, dj) for di in (-1, 0, 1) for dj in (-1, 0, 1) if di or dj]
        # the gradients each marker would have with a neighbouring index: same rays (one intersection), other targets
        neighbours = [self.pattern.centers(ij[ok] + np.asarray(step)) for step in steps]
        shifted, _ = self.trace_targets(surface, px[ok], neighbours)
        alt = np.stack([np.stack([sx, sy], axis=-1) for _, sx, sy in shifted], axis=1)  # (n, 8, 2)
        keep = np.ones(len(xy), dtype=bool)
        budget = int(max_fraction * len(xy))
        for _ in range(3):  # a second round finds what the first round's contaminated fit hid
            r, _ = self._gradient_residuals(surface.basis, xy, hx, hy, alt, keep)
            suspect = keep & (r > factor * float(np.median(r[keep])))
            if not suspect.any() or suspect.sum() > 0.5 * keep.sum():
                break
            # judged on a fit that the suspects do not pull: the wrong index's residual is then the pitch's whole
            # slope (~8 mrad), its neighbour's that of a good marker
            r_clean, r_alt = self._gradient_residuals(surface.basis, xy, hx, hy, alt, keep & ~suspect)
            wrong = np.flatnonzero(suspect & (r_alt < 0.5 * r_clean))
            wrong = wrong[np.argsort(-r_clean[wrong])][: budget - int((~keep).sum())]
            if wrong.size == 0:
                break
            keep[wrong] = False
        drop = np.zeros(len(markers.ij), dtype=bool)
        drop[np.flatnonzero(ok)[~keep]] = True
        return drop

    def _gradient_residuals(
        self, basis: ShiftedBasis, xy: Array, hx: Array, hy: Array, alt: Array, use: NDArray[np.bool_]
    ) -> tuple[Array, Array]:
        """Residuals of every marker's traced gradient from a fit on the ``use`` markers, and the smallest residual
        of its gradients traced to the neighbouring pattern positions ``alt`` (n, k, 2)."""
        cfg = self.config
        coef, _ = fit_gradients(basis, xy[use, 0], xy[use, 1], hx[use], hy[use], cfg.regularization, method=cfg.method)
        gx, gy = SBFSurface(basis, coef).gradient(xy[:, 0], xy[:, 1])
        r_alt = np.min(np.hypot(gx[:, None] - alt[..., 0], gy[:, None] - alt[..., 1]), axis=1)
        return np.hypot(gx - hx, gy - hy), r_alt

    def lattice_offset(self, markers: MarkerObservations) -> Array:
        """How many pitches the markers' indices lie off the lattice's predicted image, (di, dj).

        Each marker's ray is reflected at the plane of the holding frame (the flat start, thesis §1.6.4) and the slope
        that would send it to its indexed pattern position is read (:func:`marker_gradients`); the median of those
        slopes, divided by the slope change one index step makes (traced the same way), is the indexing's offset
        from the lattice the nominal setup predicts. A substrate resting on its frame tilts by far less than a pitch
        sends (a pitch is ~8 mrad in the §1.10 setup, a 60 µm bow over the ROI ~1.5 mrad), so the right reference
        marker gives an offset well under half a pitch and a wrong one by k markers an offset near k pitches; the
        median keeps a few wrongly numbered markers or a caustic from moving it.

        Returns
        -------
        ndarray, (2,)
            The offset (di, dj), in index steps; NaN where fewer than ``config.min_markers`` rays meet the plane.
        """
        plane = SBFSurface.plane(self.basis, self.sub.frame_z)
        ij, px, _ = self.prepare(markers)
        whole = np.zeros(2, dtype=np.int64)
        for _ in range(3):  # the slope per index step varies across the pattern: linearise again where it is
            slopes = []
            for step in ((0, 0), (1, 0), (0, 1)):
                targets = self.pattern.centers(ij - whole + np.asarray(step, dtype=np.int64))
                _, hx, hy, ok = self.trace(plane, px, targets)
                if int(ok.sum()) < self.config.min_markers:
                    return np.full(2, np.nan)
                slopes.append(np.stack([hx, hy], axis=-1))
            g0, gi, gj = slopes
            per_index = np.stack([np.median(gi - g0, axis=0), np.median(gj - g0, axis=0)], axis=-1)
            rest = np.linalg.solve(per_index, np.median(g0, axis=0))
            if np.all(np.abs(rest) < 0.5):
                break
            whole += np.round(rest).astype(np.int64)
        return np.asarray(whole + rest, dtype=np.float64)

    def coarse_surface(self, markers: MarkerObservations, iterations: int = 3, min_hit: float = 0.95) -> SBFSurface:
        """A coarse fit of the markers: the inner loop at the frame height, without the bias step or the height search.

        Where the nested iteration fails on a strongly bent substrate (3 mm / 60 µm: the bias model singular at a
        marker near a caustic, or start heights that throw the rays off the substrate), the markers still tell the
        surface's shape: their gradients, traced through the flat start at the frame height and through the fits
        that follow, fitted with a basis scale chosen on them (:meth:`scale_from_flat_start`). The traced slopes are
        off by ~10 µrad per µm of height error, far inside the inverse fit's basin (a pitch on the pattern is ~8
        mrad); the start for :mod:`scopetwin.recon.inverse` (:func:`scopetwin.recon.strategy.inverse_start`), whose
        mean height — the frame height, nobody measured it — the inverse fit keeps. An iteration whose rays miss the
        substrate for more than ``1 - min_hit`` of the markers is not taken.
        """
        cfg = self.config
        h = self.sub.frame_z
        ij, px, targets = self.prepare(markers)
        lost = self.scale_from_flat_start(markers, bias=False)
        if isinstance(lost, Failure):
            raise lost.error()
        surface = SBFSurface.plane(self.basis, h)
        for _ in range(iterations):
            xy, hx, hy, _ = self.trace(surface, px, targets)
            if len(xy) < min_hit * len(ij):
                break
            coef, _ = fit_gradients(self.basis, xy[:, 0], xy[:, 1], hx, hy, cfg.regularization, method=cfg.method)
            surface = SBFSurface(self.basis, coef, h - self.roi_mean(coef))
        return surface

    def scale_from_flat_start(self, markers: MarkerObservations, bias: bool = True) -> bool | Failure:
        """Choose the basis scale on the gradients traced through the flat start; True if the scale changed.

        :func:`scopetwin.recon.scale.select_sigma` on the markers' gradients traced through the plane at the frame
        height (with the bias step where ``bias`` and the reconstructor has one). A default scale far too coarse for
        the surface (the 12 mm basis on a 3 mm / 60 µm one, whose markers the topological indexing of
        :func:`scopetwin.recon.markers.index_lattice` numbers) cannot fit the gradients, and its fits swing so far
        that the rays miss the substrate (or its ends) — in the first inner loop, before a surface exists for
        :func:`scopetwin.recon.scale.select_sigma` to be run on, or after many start heights that did not settle
        (3 mm / 60 µm seeds 2 and 1). The flat start at the frame height traces every marker; the scale is chosen on
        those gradients instead. A flat start that misses the substrate too is returned as that :class:`Failure`.
        """
        cfg = self.config
        plane = SBFSurface.plane(self.basis, self.sub.frame_z)
        ij, px, targets = self.prepare(markers)
        xy, hx, hy, _ = self.trace(plane, self.corrected(plane, ij, px, bias), targets)
        lost = self.coverage(xy, len(ij))
        if lost is not None:
            return lost
        if not cfg.sigma_candidates or cfg.counts is not None:
            return False
        best, self.sigma_scores, _ = select_sigma(self.sub, xy[:, 0], xy[:, 1], hx, hy, cfg)
        if best == float(self.basis.sigma[0]):
            return False
        self.use_basis(cfg.make_basis(self.sub, best))
        return True


def predict_surface(surfaces: list[SBFSurface], values: list[tuple[float, float]], h: float) -> SBFSurface | None:
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


#: Passes of :func:`scopetwin.recon.bias.predict_spots` in the bias step: its local maps fitted once, around the
#: measured centroids, which lie within the bias (hundredths of a pixel) of the centre images a second pass would
#: re-centre on. Measured on the §1.10 setup's markers through 50 and 200 µm bowed substrates (0.011 and 0.058 px
#: corrections): one pass and two differ by at most 2e-7 px with the start 0.3 px off the centre images, 6e-11 px
#: on them.
BIAS_PASSES = 1
#: Most shapes whose bias predictions the bias step keeps for reuse (a bound on its memory, about 50 kB a shape for the
#: §1.10 markers, not a tuned value: the solves measured predict 6-9 shapes). On the §1.10 preset's render (seed 1,
#: the basis scale re-chosen 12 -> 15 mm) the new scale's search from the flat start repeats the first's shape
#: exactly and its last lies 0.05 µm RMS from the first search's last: 6 predictions instead of 8.
BIAS_SHAPES_KEPT = 16


def centroid_bias_step(
    setup: Setup, recompute_um: float = DEFAULT_POLICY.bias_recompute_um, grid: tuple[int, int] = (48, 112)
) -> BiasStep:
    """A bias step for the inner loop built on :mod:`scopetwin.recon.bias`, or an error if absent.

    The bias of each marker's centroid (the spot is distorted by the curved mirror) is predicted
    from the current surface estimate and added to the measured centroid. The prediction is
    made only for a shape (mean removed) more than ``recompute_um`` RMS from each of the last
    :data:`BIAS_SHAPES_KEPT` predicted for the same markers; otherwise the nearest-in-time of those
    within it is reused: the bias follows the curvature, which settles after the first iterations,
    and hardly depends on the start height, which moves the surface as an offset.
    Each prediction fits the local maps once, around the measured centroids
    (:data:`BIAS_PASSES`).
    """
    try:
        from scopetwin.recon.bias import correct_centroids, model_for_setup
    except ImportError as exc:  # pragma: no cover - recon.bias is part of the package
        raise ReconstructionError(f"centroid-bias correction is unavailable: {exc}") from None
    sub = Substrate2D.from_setup(setup)
    xs = np.linspace(*sub.x_range, grid[0])
    ys = np.linspace(*sub.y_range, grid[1])
    xx, yy = np.meshgrid(xs, ys)
    # the shapes predicted for (latest first) and their corrections, for the markers of one solve: a search started
    # afresh (another basis scale: from the flat start again, then through shapes near the last search's) finds
    # its shapes' corrections there
    known: list[tuple[Array, Array]] = []
    markers: list[NDArray[np.int64]] = []

    def step(surface: SBFSurface, ij: NDArray[np.int64], px: Array) -> Array:
        z = surface.height(xx, yy)
        if not markers or markers[0] is not ij and not np.array_equal(markers[0], ij):
            known.clear()
            markers[:] = [ij]
        for shape, correction in known:
            if np.std(z - shape) * 1e3 <= recompute_um:
                return px + correction
        hm = HeightMap(z, sub.x_range[0], sub.x_range[1], sub.y_range[0], sub.y_range[1])
        corrected, _ = correct_centroids(px, ij, model_for_setup(setup, hm), passes=BIAS_PASSES)
        known.insert(0, (z, corrected - px))
        del known[BIAS_SHAPES_KEPT:]
        return corrected

    return step
