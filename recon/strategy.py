"""The one reconstruction strategy: what is tried, in which order, when a step fails.

Every entry point — ``scopetwin reconstruct`` and ``run``, the studies, the datasets, the focus map and
:func:`scopetwin.reconstruct` — goes through :func:`reconstruct` (an image) or :func:`solve` (indexed markers), so
one image and setup give the same heights everywhere. The thresholds are the fields of
:class:`scopetwin.recon.policy.ReconstructionPolicy`; the pieces are those of the nested iteration of thesis §1.4
(:class:`scopetwin.recon.reconstruct.Reconstructor`), the uncertainty step (:mod:`scopetwin.recon.uncertainty`) and
the inverse fit (:mod:`scopetwin.recon.inverse`).

The order, for one image:

1. markers: the thesis's flood indexing, the grid's topology where the flood numbers too few
   (:attr:`~scopetwin.recon.policy.ReconstructionPolicy.lattice_below`); a tied reference marker decided by which
   candidate's indices lie on the lattice's predicted image
   (:attr:`~scopetwin.recon.policy.ReconstructionPolicy.resolve_tied_reference`);
2. the start-height search with the default basis scale; where its rays lose the substrate or it does not converge,
   the scale chosen on the flat start and the search again (``rescale_from_flat_start``);
3. the scale chosen on the data traced through that surface and the search again (``rechoose_scale``), keeping the
   first scale's result where the finer one loses the substrate or does not converge (``keep_first_scale``);
4. wrongly indexed markers rejected and the search again (``outlier_factor``);
5. the posterior: uncertainty and start height; the frame condition not searched on checked, by the posterior where
   the extrapolation disagrees (``posterior_consistency_sigmas``);
6. ``method="inverse"``: the inverse fit from the best start left (``inverse_starts``);
7. a second image with the pattern moved (thesis §1.3, :func:`reconstruct_pair`): image 1 by steps 1-5, else the
   first start of ``pair_starts``; the second image's markers sought through that surface, wrongly indexed ones
   rejected; the height in each basis scale of the two-position configuration, the one of smallest uncertainty
   kept; both images checked to be of one surface; combined with the frame criterion (:func:`solve_pair`; the
   measurement's pieces are :mod:`scopetwin.recon.two_positions`'s).

A phase-shifted fringe measurement (``method="fringes"``, :func:`reconstruct_fringe_images`; the setup's
``[fringes]`` table says what each of its K images shows): the stack checked against the sequence, every pixel's
display point decoded (:mod:`scopetwin.recon.fringes.phase`), the nested start-height iteration on the dense slopes
with the frame criterion, or the absolute height of two display positions (:mod:`scopetwin.recon.fringes`).

Inside, a failed step is a value (:class:`scopetwin.recon.reconstruct.LoopOutcome`,
:class:`scopetwin.recon.reconstruct.Failure`); the user sees one error, only when every path failed, and its message
names what each path tried. Each result lists the path it took (``strategy``).
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scopetwin.recon.config import ReconstructionConfig
from scopetwin.recon.errors import InconsistentError, MethodMismatchError, NotConvergedError, ReconstructionError
from scopetwin.recon.policy import DEFAULT_POLICY, ReconstructionPolicy
from scopetwin.recon.reconstruct import (
    BiasStep,
    Failure,
    LoopOutcome,
    MarkerObservations,
    ReconstructionResult,
    Reconstructor,
    centroid_bias_step,
    single_thread_blas,
)
from scopetwin.recon.scale import select_sigma
from scopetwin.recon.two_positions import (
    DEFAULT_TWO_POSITIONS,
    PairFit,
    PatternView,
    TwoPositionConfig,
    TwoPositionResult,
    check_pair,
    check_second,
    estimate_lines,
    height_estimate,
    held_bias,
    joint_surface,
    pair_excess,
    pair_fit,
    rebase,
    view_for,
    without,
    without_outliers,
)
from scopetwin.recon.uncertainty import HeldPrior, PriorAhead, posterior
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.pattern_stage import shift_pattern, stage_shift
from scopetwin.scenes.setup import Setup

if TYPE_CHECKING:
    from scopetwin.recon.fringes.reconstruct import FringeConfig, FringeResult
    from scopetwin.recon.inverse import InverseConfig, InverseResult
    from scopetwin.recon.markers import Markers
    from scopetwin.recon.posterior import Prior
    from scopetwin.recon.shifted_basis import SBFSurface

Method = Literal["centroid", "inverse", "fringes"]


# -- indexed markers -> surface (thesis §1.4) --------------------------------------------------------------------------
def solve(
    rec: Reconstructor,
    markers: MarkerObservations,
    policy: ReconstructionPolicy = DEFAULT_POLICY,
    history_path: str | Path | None = None,
) -> ReconstructionResult:
    """The nested iteration of thesis §1.4 on indexed markers, with every fallback of ``policy``.

    Parameters
    ----------
    rec : Reconstructor
        The iteration's pieces for one setup (camera, pattern, substrate, configuration, bias step).
    markers : MarkerObservations
        Indexed markers of one image.
    policy : ReconstructionPolicy
        The fallbacks and their thresholds.
    history_path : path, optional
        Where the history is written (atomically, JSON) when no surface is accepted.

    Returns
    -------
    ReconstructionResult
        With ``strategy``: the path taken, one line per step.

    Raises
    ------
    TooFewMarkersError, SubstrateNotVisibleError, NotConvergedError, InconsistentError
        Only when every path failed; the message names what each tried.
    """
    with single_thread_blas():
        return _solve(rec, markers, policy, history_path)


class _Search:
    """The state of one image's search: history of start heights, the current loop's surfaces, the path taken."""

    def __init__(self, rec: Reconstructor, markers: MarkerObservations, policy: ReconstructionPolicy) -> None:
        self.rec, self.markers, self.policy = rec, markers, policy
        self.history: list[Any] = []
        self.surfaces: list[SBFSurface] = []
        self.path: list[str] = []
        self.rejected: NDArray[np.int64] = np.zeros((0, 2), dtype=np.int64)
        self.ahead: PriorAhead | None = None  # the posterior step's evidence search, started early

    def loop(self, h: float, runs: int | None = None, fresh: bool = False) -> LoopOutcome:
        """One start-height loop from ``h`` (``fresh``: no warm start from an earlier loop's surfaces)."""
        if fresh:
            self.surfaces = []
        out = self.rec.start_height_loop(self.markers, h, self.history, self.surfaces, runs)
        what = {"converged": "converged", "not-converged": "did not converge", "lost": "lost the substrate"}
        self.path.append(
            f"start-height search, basis scale {self.rec.basis.sigma[0]:g} mm: {what[out.status]} "
            f"after {len(self.history)} runs" + (f" ({out.failure.message})" if out.failure is not None else "")
        )
        return out

    def fail(self, failure: Failure) -> ReconstructionError:
        """The user-facing error of ``failure``, naming the path tried."""
        return failure.error(self.tried())

    def tried(self) -> str:
        return " [tried: " + "; ".join(self.path) + "]" if self.path else ""


def _solve(
    rec: Reconstructor, markers: MarkerObservations, policy: ReconstructionPolicy, history_path: str | Path | None
) -> ReconstructionResult:
    t0 = time.perf_counter()
    search = _Search(rec, markers, policy)
    try:
        return _search_and_accept(search, history_path, t0)
    finally:
        if search.ahead is not None:
            search.ahead.close()


def _search_and_accept(search: _Search, history_path: str | Path | None, t0: float) -> ReconstructionResult:
    rec = search.rec
    out = _first_search(search)
    out = _rechoose_scale(search, out)
    out = _reject_outliers(search, out)
    if rec.last is None:
        raise ReconstructionError(f"the start-height loop ran no inner loop (outer_max = {rec.config.outer_max})")
    result = ReconstructionResult(
        rec.last,
        rec.sub,
        search.history,
        out.converged,
        time.perf_counter() - t0,
        rec.config,
        rejected=search.rejected,
        strategy=search.path,
        marker_xy=rec.last_xy,
    )
    return _accept(search, result, history_path)


def _first_search(search: _Search) -> LoopOutcome:
    """The start-height search from the frame height; where its rays lose the substrate or it does not converge,
    the scale chosen on the flat start and the search again with a fresh budget (``rescale_from_flat_start``)."""
    rec, policy = search.rec, search.policy
    budget = min(policy.scale_search_runs, rec.config.outer_max) if policy.rescale_from_flat_start else None
    out = search.loop(rec.sub.frame_z, budget)
    if out.converged:
        return out
    changed = rec.scale_from_flat_start(search.markers) if policy.rescale_from_flat_start else False
    if isinstance(changed, Failure):
        search.path.append("basis scale on the flat start: its rays lose the substrate too")
        raise search.fail(changed if out.failure is None else out.failure)
    if not changed:
        if out.failure is not None:
            raise search.fail(out.failure)
        if len(search.history) < rec.config.outer_max:  # the same scale: the rest of its budget
            out = search.loop(search.history[-1].start_height_um * 1e-3)
        return out  # not converged: the scale chosen on the data may still help
    search.path.append(f"basis scale chosen on the flat start: {rec.basis.sigma[0]:g} mm")
    out = search.loop(rec.sub.frame_z, rec.config.outer_max, fresh=True)
    if out.failure is not None:
        raise search.fail(out.failure)
    return out


def _rechoose_scale(search: _Search, out: LoopOutcome) -> LoopOutcome:
    """The basis scale chosen on the data traced through the search's surface, and the search again with it
    (``rechoose_scale``); the first scale's converged result kept where it fits the data and the finer one loses the
    substrate or does not converge (``keep_first_scale``). Where the first scale is too coarse for the data and the
    re-chosen one does not converge either, the scale chosen on the flat start is searched from the frame height.
    """
    rec, policy, cfg = search.rec, search.policy, search.rec.config
    if not (policy.rechoose_scale and search.surfaces and cfg.sigma_candidates and cfg.counts is None):
        return out
    xy, hx, hy, _ = rec.traced_gradients(search.surfaces[-1], search.markers)
    # the posterior's evidence search starts beside the choice on this surface: taken where nothing changes it
    # (results identical), else refined from on the gradients traced anew (PriorAhead)
    speculate = out.converged and cfg.posterior != "off"
    if speculate:
        search.ahead = PriorAhead(rec, search.surfaces[-1], search.markers, (xy, hx, hy))
    # the choice leaves a CPU to the search: the longer of the two, warm-started or not (measured on the §1.10 preset's
    # renders, medians of the whole solve, 12-16 runs alternated: beside a cold search 0.52 s on one CPU against
    # 0.58 s on both; beside one warm-started from the frame before, 0.49 against 0.50 s where the scale changes and
    # that search runs on the first scale's surface, 0.46 against 0.40 s where it does not)
    # on a smooth surface the scale its finite-basis prior's evidence chose (that search waited for), else held out
    chosen = _scale_by_evidence(search, out) if policy.scale_by_evidence else None
    how = "by the finite basis's evidence" if chosen is not None else "on the data"
    fits: dict[float, float] = {}
    if chosen is not None:
        best = chosen
    else:
        best, rec.sigma_scores, fits = select_sigma(
            rec.sub, xy[:, 0], xy[:, 1], hx, hy, cfg, max_threads=1 if speculate else None
        )
    current = float(rec.basis.sigma[0])
    too_coarse = current in fits and fits[current] > cfg.fit_ratio * min(fits.values())
    if best == current or not (out.converged or too_coarse):
        return out
    first = (rec.basis, len(search.history), out, rec.last, rec.last_xy)
    rec.use_basis(cfg.make_basis(rec.sub, best))
    search.path.append(f"basis scale chosen {how}: {current:g} -> {best:g} mm")
    # a converged search's start height is kept; an unconverged one's is no start: from the frame height again.
    # Where the first result can be kept, the finer scale gets a refinement's budget, not a whole search's
    h_start = search.history[-1].start_height_um * 1e-3 if out.converged else rec.sub.frame_z
    keep = out.converged and policy.keep_first_scale
    runs = min(policy.scale_search_runs, cfg.outer_max) if keep else (None if out.converged else cfg.outer_max)
    again = search.loop(h_start, runs, fresh=True)
    if not again.converged and too_coarse and policy.rescale_from_flat_start:
        # the gradients traced through a scale too coarse for them can choose a scale that does not settle either
        # (a 12 mm basis on a 3 mm / 60 µm surface: 3 mm chosen, its rays lose the substrate); the flat start's
        # choice is the other estimate, searched from the frame height
        # (only a finer one: the first scale was too coarse for the data, and a coarser one does not fit them either)
        flat = rec.scale_from_flat_start(search.markers)
        if flat is True and float(rec.basis.sigma[0]) != best and float(rec.basis.sigma[0]) < current:
            search.path.append(f"basis scale chosen on the flat start: {rec.basis.sigma[0]:g} mm")
            again = search.loop(rec.sub.frame_z, cfg.outer_max, fresh=True)
    if again.converged or not (first[2].converged and policy.keep_first_scale):
        if again.status != "lost":
            return again
        assert again.failure is not None
        raise search.fail(again.failure)
    rec.use_basis(first[0])
    del search.history[first[1] :]
    rec.last, rec.last_xy = first[3], first[4]  # the markers' points with it (the coverage, the height map's mask)
    search.path.append(f"kept the first basis scale, {first[0].sigma[0]:g} mm")
    return first[2]


def _scale_by_evidence(search: _Search, out: LoopOutcome) -> float | None:
    """The basis scale of the finite-basis prior the early evidence search chose on the converged surface's gradients,
    where it chose one among the configuration's candidates; None otherwise (a rough surface: the held-out choice)."""
    if search.ahead is None or not out.converged:
        return None
    prior = search.ahead.basis()
    cands = search.rec.config.sigma_candidates or ()
    return prior.sigma if prior is not None and prior.sigma in cands else None


def _reject_outliers(search: _Search, out: LoopOutcome) -> LoopOutcome:
    """Wrongly indexed markers rejected after convergence and the search again without them (``outlier_factor``)."""
    rec, policy = search.rec, search.policy
    if not (out.converged and policy.outlier_factor > 0 and rec.last is not None):
        return out
    drop = rec.index_outliers(search.markers, rec.last, policy.outlier_factor, policy.outlier_max_fraction)
    if not drop.any():
        return out
    search.rejected = search.markers.ij[drop]
    search.markers = MarkerObservations(search.markers.ij[~drop], search.markers.px[~drop])
    search.path.append(f"{int(drop.sum())} wrongly indexed marker(s) rejected")
    again = search.loop(search.history[-1].start_height_um * 1e-3, rec.config.outer_max, fresh=True)
    if again.failure is not None:
        raise search.fail(again.failure)
    return again


def _accept(search: _Search, result: ReconstructionResult, history_path: str | Path | None) -> ReconstructionResult:
    """The posterior step and the check of the frame condition not searched on; the user-facing error if neither
    the fitted surface nor the posterior lays the surface on the holding frame."""
    rec, policy, cfg = search.rec, search.policy, search.rec.config
    last = result.history[-1]
    other = (
        abs(last.delta_h_max_um)
        if cfg.criterion == "level"
        else abs(0.5 * (last.max_region1_um + last.max_region2_um) - rec.sub.frame_z * 1e3)
    )
    if result.converged and (other <= cfg.consistency_um or cfg.criterion == "level"):
        post = (
            posterior(rec, search.markers, result.surface, result.history, policy, search.ahead)
            if cfg.posterior != "off"
            else None
        )
        if post is not None:
            result.surface, result.uncertainty = post.surface, post.uncertainty
            search.path.append(
                f"posterior ({cfg.posterior}): start height moved {post.uncertainty.correction_um:+.3g} µm"
            )
            if post.prior_note:
                search.path.append(post.prior_note)
            if post.shape_note:
                search.path.append(post.shape_note)
        if other <= cfg.consistency_um:
            return result
        if post is not None:
            d_mean, d_std = post.delta
            other = abs(d_mean) * 1e3
            if other <= cfg.consistency_um + policy.posterior_consistency_sigmas * d_std * 1e3:
                search.path.append("frame condition checked on the posterior's Delta h_max")
                return result
    path = Path(history_path) if history_path is not None else None
    if path is not None:
        from scopetwin.scenes.io import write_json_atomic

        write_json_atomic(path, {"converged": result.converged, "config": asdict(cfg), **result.summary()})
    where = f"; partial history saved to {path}" if path is not None else ""
    if not result.converged:
        raise NotConvergedError(
            f"the start-height loop did not converge in {len(result.history)} runs (last criterion "
            f"{last.criterion_um:+.4g} µm, tolerance {cfg.outer_tol_um} µm){where}{search.tried()}",
            result.history_dicts(),
            path,
            rec.last,
        )
    what = "Delta h_max" if cfg.criterion == "level" else "the mean frame maximum's distance from the frame"
    raise InconsistentError(
        f"the reconstructed surface cannot lie on the holding frame: {what} is {other:.3g} µm "
        f"(> {cfg.consistency_um} µm) — are the markers indexed correctly and is the setup right?{where}"
        f"{search.tried()}"
    )


def reconstruct_markers(
    setup: Setup,
    markers: MarkerObservations | ArrayLike,
    px: ArrayLike | None = None,
    config: ReconstructionConfig | None = None,
    bias: BiasStep | None = None,
    history_path: str | Path | None = None,
    frame_z: float = 0.0,
    policy: ReconstructionPolicy = DEFAULT_POLICY,
) -> ReconstructionResult:
    """Reconstruct the substrate's heights from indexed markers (thesis §1.4, §1.7, §1.8): :func:`solve` for a setup.

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
        Centroid-bias correction inside the inner loop (exact marker images need none).
    history_path : path, optional
        Where a partial history is written if no surface is accepted.
    frame_z : float
        z of the holding frame in the substrate's base frame, mm.
    policy : ReconstructionPolicy
        The fallbacks and their thresholds.
    """
    if isinstance(markers, MarkerObservations):
        obs = markers
    elif px is None:
        raise ReconstructionError("marker indices need their image positions px")
    else:
        obs = MarkerObservations(np.asarray(markers), np.asarray(px, dtype=np.float64))
    return solve(Reconstructor.from_setup(setup, config, bias, frame_z), obs, policy, history_path)


# -- an image -> surface -------------------------------------------------------------------------------------------
class ImageReconstruction(NamedTuple):
    """The markers of an image, the surface they give, and the iteration that gave it."""

    markers: Markers
    result: ReconstructionResult
    reconstructor: Reconstructor


def reconstruct_image(
    image: NDArray[Any],
    setup: Setup,
    config: ReconstructionConfig | None = None,
    policy: ReconstructionPolicy = DEFAULT_POLICY,
    history_path: str | Path | None = None,
    evidence_start: Prior | None = None,
    held_prior: HeldPrior | None = None,
) -> ImageReconstruction:
    """Markers of a deflectometry image and the surface they give (thesis §1.4-§1.8), with every fallback of ``policy``.

    The bias step is on where ``policy.bias_step``. Where the spots are distorted so much that two or more are
    about as large as the reference marker should be (:class:`scopetwin.recon.markers.ReferenceTieError`; 3 mm /
    60 µm surfaces), each candidate numbers the markers in turn (``resolve_tied_reference``): with a wrong one every
    index is a pitch or more off the lattice the nominal setup predicts (:meth:`Reconstructor.lattice_offset`), with
    the right one a small fraction of a pitch. The one candidate within ``reference_offset_max`` is kept; if none or
    several are, the tie is reported with each offset. ``evidence_start``: the posterior's warm start
    (:attr:`Reconstructor.evidence_start`); ``held_prior``: a prior read as it is where plausible
    (:attr:`Reconstructor.held_prior`).
    """
    from scopetwin.recon.markers import ReferenceTieError, find_markers_for

    bias = centroid_bias_step(setup, policy.bias_recompute_um) if policy.bias_step else None

    try:
        found = find_markers_for(image, setup, lattice_below=policy.lattice_below)
        note = None
    except ReferenceTieError as tie:
        if not policy.resolve_tied_reference:
            raise
        found, note = _decide_tied_reference(image, setup, config, policy, tie)
    rec = Reconstructor.from_setup(setup, config, bias)
    rec.evidence_start = evidence_start
    rec.held_prior = held_prior
    result = solve(rec, MarkerObservations(found.ij, found.centroids), policy, history_path)
    if found.indexing == "lattice":
        result.strategy.insert(
            0,
            f"markers indexed by the grid's topology: the flood numbered fewer than {policy.lattice_below:g} of the "
            f"kept spots ({len(found.ij)} indexed)",
        )
    if note is not None:
        result.strategy.insert(0, note)
    return ImageReconstruction(found, result, rec)


def _decide_tied_reference(
    image: NDArray[Any],
    setup: Setup,
    config: ReconstructionConfig | None,
    policy: ReconstructionPolicy,
    tie: Exception,
) -> tuple[Markers, str]:
    """The tied reference candidate whose indexing agrees with the lattice's predicted image, and a note saying so.

    Each candidate numbers the markers; :meth:`Reconstructor.lattice_offset` says how many pitches those indices lie
    off the image the nominal setup predicts. The one candidate within ``policy.reference_offset_max`` pitches is
    taken; none or several: the tie is reported with each candidate's offset.
    """
    from scopetwin.recon.markers import MarkerError, ReferenceTieError, find_markers_for

    assert isinstance(tie, ReferenceTieError)
    rec = Reconstructor.from_setup(setup, config)
    good: list[Markers] = []
    notes: list[str] = []
    for cand in tie.candidates:
        try:
            found = find_markers_for(image, setup, reference=int(cand), lattice_below=policy.lattice_below)
            off = rec.lattice_offset(MarkerObservations(found.ij, found.centroids))
        except (MarkerError, ReconstructionError) as exc:
            notes.append(f"spot {int(cand)}: {type(exc).__name__}")
            continue
        notes.append(f"spot {int(cand)}: ({off[0]:+.2f}, {off[1]:+.2f})")
        if np.all(np.abs(off) <= policy.reference_offset_max):
            good.append(found)
    if len(good) == 1:
        return good[0], (
            f"reference marker tied between {len(tie.candidates)} spots: the one whose indices lie on the lattice's "
            f"predicted image taken (offsets in pitches: {'; '.join(notes)})"
        )
    raise ReferenceTieError(
        tie.candidates,
        f"{tie}; {len(good)} of the {len(tie.candidates)} candidates number the markers within "
        f"{policy.reference_offset_max:g} pitch of the lattice's predicted image (offsets: {'; '.join(notes)})",
    ) from None


# -- the inverse fit's start --------------------------------------------------------------------------------------
@dataclass
class InverseStart:
    """Where the inverse fit starts from (:func:`inverse_start`).

    Attributes
    ----------
    surface : object with ``height(x, y)`` or None
        The start surface (None: a plane at the frame height).
    kind : str
        One of :attr:`scopetwin.recon.policy.ReconstructionPolicy.inverse_starts`: "centroid" (the centroid method
        with its bias step), "centroid-unbiased" (without it), "centroid-unconverged" (the last surface of a
        start-height loop that did not converge), "coarse" (:meth:`scopetwin.recon.reconstruct.Reconstructor.
        coarse_surface`: the markers' gradients at the frame height) or "plane".
    note : str
        What failed on the way, one entry per attempt.
    absolute_std_um : float or None
        The centroid method's standard uncertainty of the absolute height, µm.
    markers : object or None
        The indexed markers used.
    strategy : list of str
        The centroid method's path where it gave the start.
    """

    surface: Any
    kind: str
    note: str = ""
    absolute_std_um: float | None = None
    markers: Any = None
    strategy: list[str] = field(default_factory=list)

    @property
    def holds_height(self) -> bool:
        """The fit keeps the start's mean height (``absolute="start"``) rather than searching it on its own surface.

        Every start but a plane: where the centroid method converged its frame criterion decided the height; where
        it did not (a coarse fit or an unconverged loop on a 3 mm / 60 µm surface) the frame criterion on the fitted
        B-spline, whose thin-plate continuation into the frame regions of so short-correlated a surface is no
        estimate of their maxima, ran away (the height -29 µm off from the unbiased centroid start of surface seed 4,
        which held +2.6 µm; -420 µm from the coarse start of seed 5, which holds the frame height, ~27 µm off).
        """
        return self.kind != "plane"

    @property
    def absolute(self) -> Literal["start", "frame"]:
        """The inverse fit's ``absolute`` setting for this start: hold its height, or search it from a plane."""
        return "start" if self.holds_height else "frame"


def inverse_start(
    image: NDArray[Any],
    setup: Setup,
    config: ReconstructionConfig | None = None,
    policy: ReconstructionPolicy = DEFAULT_POLICY,
) -> InverseStart:
    """The start of the inverse fit: the first of ``policy.inverse_starts`` that can be had.

    In the default order: the centroid method (thesis §1.4-§1.8) with its bias step; without it (the bias model cannot
    be evaluated near a caustic — "singular at a marker" — and the start-height loop swings with it on some 3 mm /
    60 µm surfaces that converge without it; the inverse fit needs no centroid model, only a start inside its basin);
    the last surface of a start-height loop that did not converge; a coarse fit of the indexed markers
    (:meth:`scopetwin.recon.reconstruct.Reconstructor.coarse_surface`); a plane at the frame height. A tied
    reference marker is decided on the way (:func:`reconstruct_image`). ``policy.bias_step`` False leaves out the
    biased start.
    """
    notes: list[str] = []
    unconverged: Any = None
    for kind in policy.inverse_starts:
        if kind in ("centroid", "centroid-unbiased"):
            biased = kind == "centroid" and policy.bias_step
            if kind == "centroid" and not policy.bias_step:
                continue
            name = kind if policy.bias_step else "centroid"
            try:
                done = reconstruct_image(image, setup, config, policy.with_changes(bias_step=biased))
            except NotConvergedError as exc:
                unconverged = unconverged if unconverged is not None else exc.surface
                notes.append(f"{name}: {type(exc).__name__}: {exc}")
                continue
            except ScopetwinError as exc:
                notes.append(f"{name}: {type(exc).__name__}: {exc}")
                continue
            u = done.result.uncertainty
            absolute = None if u is None else u.absolute_um
            return InverseStart(
                done.result.surface, name, "; ".join(notes), absolute, done.markers, done.result.strategy
            )
        if kind == "centroid-unconverged" and unconverged is not None:
            return InverseStart(unconverged, kind, "; ".join(notes))
        if kind == "coarse":
            with contextlib.suppress(ScopetwinError):
                return _coarse_start(image, setup, config, policy, notes)
        if kind == "plane":
            return InverseStart(None, "plane", "; ".join(notes))
    raise ReconstructionError("no start for the inverse fit: " + "; ".join(notes))


def _coarse_start(
    image: NDArray[Any],
    setup: Setup,
    config: ReconstructionConfig | None,
    policy: ReconstructionPolicy,
    notes: list[str],
) -> InverseStart:
    """A coarse fit of the indexed markers (its failure noted in ``notes`` and raised)."""
    from scopetwin.recon.markers import find_markers_for

    try:
        found = find_markers_for(image, setup, lattice_below=policy.lattice_below)
        rec = Reconstructor.from_setup(setup, config)
        obs = MarkerObservations(found.ij, found.centroids)
        surface = rec.coarse_surface(obs, policy.coarse_iterations, policy.coarse_min_hit)
    except ScopetwinError as exc:
        notes.append(f"coarse: {type(exc).__name__}: {exc}")
        raise
    return InverseStart(surface, "coarse", "; ".join(notes), markers=found)


# -- two pattern positions (thesis §1.3) -----------------------------------------------------------------------------
def solve_pair(
    first: PatternView,
    single: ReconstructionResult | None,
    second: PatternView,
    shift_mm: float,
    tp: TwoPositionConfig = DEFAULT_TWO_POSITIONS,
    start: SBFSurface | None = None,
    notes: tuple[str, ...] = (),
) -> TwoPositionResult:
    """The two-position height and surface from image 1's reconstruction and a second image's markers
    (:mod:`scopetwin.recon.two_positions`).

    The steps: each view's centroid bias corrected once through image 1's surface and held; the second image's
    markers checked to meet the ROI; the height in each basis scale of ``tp.sigmas`` (:func:`_pair_scale`); both
    images checked to be of one surface (``tp.max_excess_urad``); combined with the frame criterion's height; the
    joint surface at the height taken.

    Parameters
    ----------
    first : PatternView
        Image 1's iteration pieces and markers (rejected ones removed).
    single : ReconstructionResult or None
        Image 1 reconstructed alone (:func:`solve`): the frame criterion's height, the start surface and its basis.
        None: no frame criterion, the search starts from ``start``.
    second : PatternView
        The pieces for the setup with the pattern moved (:func:`scopetwin.scenes.pattern_stage.shift_pattern`) and
        the second image's markers.
    shift_mm : float
        The pattern's shift along N_z, mm (reported).
    tp : TwoPositionConfig
        Steps, tolerances, basis scales, jackknife blocks, whether to combine with the frame criterion.
    start : SBFSurface, optional
        The start surface where there is no ``single`` (a coarse fit of image 1's markers, a plane).
    notes : tuple of str
        Lines put before the path's own (what failed on the way).
    """
    t0 = time.perf_counter()
    rec = first.reconstructor
    begin = single.surface if single is not None else start
    if begin is None:
        raise ReconstructionError("the two-position search needs image 1's reconstruction or a start surface")
    for view in (first, second):
        if view.reconstructor.basis is not begin.basis:
            view.reconstructor.use_basis(begin.basis)
    with single_thread_blas():
        views = [held_bias(first, begin), held_bias(second, begin)]
        check_second(views[1], begin, tp)
        h_start = rec.roi_mean(begin.coef) + begin.offset
        best, tried = _pair_scale(views, begin, h_start, tp)
        run, basis = best[0], best[6]
        separate, excess = pair_excess(views, run, basis)
        check_pair(excess, separate, shift_mm, tp)
        u = None if single is None else single.uncertainty
        frame_std = None if u is None else u.absolute_um * 1e-3
        est, h = height_estimate(first, best, None if single is None else h_start, frame_std, tp, (separate, excess))
        final = joint_surface(views, basis, h, run.surface, rec.config) if h != run.height else run
    path = [*notes, *(single.strategy if single is not None else []), *tried, *estimate_lines(est, shift_mm, tp)]
    seconds = (single.seconds if single is not None else 0.0) + time.perf_counter() - t0
    return TwoPositionResult(final.surface, rec.sub, single, est, float(shift_mm), seconds, path)


def _pair_scale(
    views: list[PatternView], begin: SBFSurface, h0: float, tp: TwoPositionConfig
) -> tuple[PairFit, list[str]]:
    """The two-position height with the basis scale that gives it the smallest uncertainty (``tp.sigmas`` from the
    coarsest, beside ``begin``'s own; stopping at the first finer one that gives none smaller), and a line per scale
    tried. A scale whose joint surface loses the substrate or does not settle is passed over (a finer one may still
    follow the surface). Each scale starts from the best surface so far in its basis; the views are left on the
    chosen basis.
    """
    rec = views[0].reconstructor
    own = float(begin.basis.sigma[0])
    best: PairFit | None = None
    notes: list[str] = []
    h, surface = h0, begin
    for sigma in sorted({*tp.sigmas, own}, reverse=True):
        basis = begin.basis if sigma == own else rec.config.make_basis(rec.sub, sigma)
        start = begin if basis is begin.basis else rebase(surface, basis, rec.sub, rec.config)
        try:
            fit = pair_fit(views, basis, start, h, tp)
        except (ScopetwinError, np.linalg.LinAlgError) as exc:
            notes.append(f"two positions, basis scale {sigma:g} mm: {type(exc).__name__}: {exc}")
            continue
        if best is not None and max(fit[3], fit[4]) >= max(best[3], best[4]):
            notes.append(
                f"two positions, basis scale {sigma:g} mm: no smaller uncertainty; {best[6].sigma[0]:g} mm kept"
            )
            break
        best, h, surface = fit, fit[0].height, fit[0].surface
    if best is None:
        raise ReconstructionError(
            "the two pattern positions gave no height with any basis scale (a second image of another substrate, or "
            "a pattern shift other than the one given, ends here too): " + "; ".join(notes)
        )
    for view in views:
        view.reconstructor.use_basis(best[6])
    return best, notes


def reconstruct_markers_pair(
    setup: Setup,
    markers: MarkerObservations,
    second_markers: MarkerObservations,
    shift_mm: float | None = None,
    config: ReconstructionConfig | None = None,
    policy: ReconstructionPolicy = DEFAULT_POLICY,
    tp: TwoPositionConfig = DEFAULT_TWO_POSITIONS,
    bias: bool = False,
) -> TwoPositionResult:
    """The substrate from indexed markers of two images, the pattern at its setup position and moved by ``shift_mm``
    along N_z (default: the setup's ``[pattern_stage]``): :func:`solve` on image 1, then :func:`solve_pair`. Exact
    marker images need no bias step (``bias``)."""
    shift = stage_shift(setup, shift_mm)
    first = view_for(setup, markers, config, bias)
    single = solve(first.reconstructor, markers, policy)
    kept = without(markers, single.rejected)
    second = view_for(shift_pattern(setup, shift), second_markers, config, bias)
    return solve_pair(PatternView(first.reconstructor, kept), single, second, shift, tp)


def reconstruct_pair(
    image: NDArray[Any],
    second_image: NDArray[Any],
    setup: Setup,
    shift_mm: float | None = None,
    config: ReconstructionConfig | None = None,
    policy: ReconstructionPolicy = DEFAULT_POLICY,
    tp: TwoPositionConfig = DEFAULT_TWO_POSITIONS,
) -> Reconstruction:
    """The substrate from two deflectometry images, the pattern at its setup position and moved by ``shift_mm`` along
    its normal (default: the setup's ``[pattern_stage]``), thesis §1.3-§1.8.

    Image 1 goes through :func:`reconstruct_image` (every fallback of ``policy``); where it fails, the two positions
    start from the first of ``policy.pair_starts`` that can be had (a coarse fit of image 1's markers, a plane at
    the frame height: they need no frame criterion) and the path says what failed. The second image's markers are
    found with the moved setup and image 1's surface, wrongly indexed ones rejected as in image 1
    (``policy.outlier_factor``); then :func:`solve_pair`.

    Returns
    -------
    Reconstruction
        ``method = "centroid"``, ``result`` a :class:`~scopetwin.recon.two_positions.TwoPositionResult`, ``markers``
        image 1's, the uncertainty's absolute part the two positions' (combined with the frame criterion's).
    """
    from scopetwin.recon.markers import find_markers_for

    shift = stage_shift(setup, shift_mm)
    moved = shift_pattern(setup, shift)
    first, single, surface, markers, notes = _pair_first_image(image, setup, config, policy)
    sub = first.reconstructor.sub
    coarse_map = surface.heightmap(sub.x_range, sub.y_range, 64, 128)  # where the second image's markers are sought
    found2 = find_markers_for(second_image, moved, coarse_map, lattice_below=policy.lattice_below)
    bias = policy.bias_step and first.reconstructor.bias is not None  # both images alike
    second = view_for(moved, MarkerObservations(found2.ij, found2.centroids), config, bias)
    second = without_outliers(second, surface, policy.outlier_factor, policy.outlier_max_fraction)
    result = solve_pair(first, single, second, shift, tp, surface, notes)
    unc = StandardUncertainty(result.absolute_std_um, result.shape_std_um)
    return Reconstruction("centroid", result, markers, unc, result.strategy)


def _pair_first_image(
    image: NDArray[Any], setup: Setup, config: ReconstructionConfig | None, policy: ReconstructionPolicy
) -> tuple[PatternView, ReconstructionResult | None, SBFSurface, Any, tuple[str, ...]]:
    """Image 1 through :func:`reconstruct_image`: its view (rejected markers removed), result, surface, markers; where
    that fails, its view and the first of ``policy.pair_starts`` that can be had, and a note saying what failed."""
    from scopetwin.recon.markers import find_markers_for
    from scopetwin.recon.shifted_basis import SBFSurface

    try:
        done = reconstruct_image(image, setup, config, policy)
    except ScopetwinError as exc:
        if not policy.pair_starts:
            raise
        failed = f"image 1 alone: {type(exc).__name__}: {exc}"
        found = find_markers_for(image, setup, lattice_below=policy.lattice_below)
        rec = Reconstructor.from_setup(setup, config)
        obs = MarkerObservations(found.ij, found.centroids)
        notes: list[str] = []
        for kind in policy.pair_starts:
            if kind == "coarse":
                try:
                    start = rec.coarse_surface(obs, policy.coarse_iterations, policy.coarse_min_hit)
                except ScopetwinError as why:  # e.g. no markers near a frame region: the two positions need none
                    notes.append(f"coarse: {type(why).__name__}: {why}")
                    continue
                what = "a coarse fit of its markers"
            else:
                start, what = SBFSurface.plane(rec.basis, rec.sub.frame_z), "a plane at the frame height"
            tried = f" ({'; '.join(notes)})" if notes else ""
            note = f"{failed}; the two positions start from {what}{tried}, without the bias step"
            return PatternView(rec, obs), None, start, found, (note,)
        raise ReconstructionError(f"{failed}; no start for the two positions: {'; '.join(notes)}") from None
    obs = without(MarkerObservations(done.markers.ij, done.markers.centroids), done.result.rejected)
    return PatternView(done.reconstructor, obs), done.result, done.result.surface, done.markers, ()


# -- one entry point for both methods ---------------------------------------------------------------------------
@dataclass(frozen=True)
class StandardUncertainty:
    """One standard uncertainty of the absolute height (ROI mean) and of the shape (RMS about it), µm (None: not
    known, e.g. the inverse fit from a plane)."""

    absolute_um: float | None
    shape_um: float | None


@dataclass
class Reconstruction:
    """A reconstructed surface, whichever method gave it, with its uncertainty and the path the strategy took.

    Attributes
    ----------
    method : {"centroid", "inverse", "fringes"}
        The marker centroids (thesis §1.4-§1.8), the inverse fit of the whole image, or phase-shifted fringes (every
        pixel's display point decoded).
    result : ReconstructionResult, InverseResult, TwoPositionResult or FringeResult
        The method's own result (history, iterations, per-node uncertainty).
    markers : Markers or None
        The indexed markers the surface rests on (the inverse fit's start's; None for fringes).
    uncertainty : StandardUncertainty
        Absolute and shape, µm.
    strategy : list of str
        The path taken, one line per step (fallbacks included).
    start : str or None
        The inverse fit's start (``kind (what failed)``); None for the centroid method.
    """

    method: Method
    result: Any
    markers: Any
    uncertainty: StandardUncertainty
    strategy: list[str]
    start: str | None = None

    def height_at(self, x_mm: Any, y_mm: Any) -> NDArray[np.float64]:
        """Heights at substrate coordinates (x, y), mm (vectorised: arrays broadcast)."""
        return np.asarray(self.result.surface.height(np.asarray(x_mm, float), np.asarray(y_mm, float)), float)

    def heightmap(self, nx: int = 128, ny: int = 288) -> Any:
        """The surface on a node grid over the whole substrate (:class:`scopetwin.scenes.surface.HeightMap`, mm)."""
        return self.result.heightmap(nx, ny)

    def measured_mask(self, nx: int = 128, ny: int = 288) -> NDArray[np.bool_] | None:
        """Which nodes of :meth:`heightmap`'s grid the markers measure (the ROI within two marker spacings of a
        marker, and the frame regions; for fringes within half a millimetre of a decoded pixel's point); None where
        the method keeps no marker points."""
        mask = getattr(self.result, "measured_mask", None)
        return None if mask is None else mask(nx, ny)

    @property
    def scale(self) -> float | None:
        """The basis scale (mm) the centroid method's surface ended on (None for the other methods): where the next
        frame of the same setup starts its search (:meth:`ReconstructionConfig.starting_at`)."""
        from scopetwin.recon.shifted_basis import ShiftedBasis

        basis = getattr(getattr(self.result, "surface", None), "basis", None)
        return float(basis.sigma[0]) if self.method == "centroid" and isinstance(basis, ShiftedBasis) else None

    @property
    def prior(self) -> Prior | None:
        """The prior the centroid method's posterior chose by evidence (None without one): the warm start of the next
        frame of the same setup (``evidence_start``)."""
        from scopetwin.recon.posterior import prior_from_dict

        u = getattr(self.result, "uncertainty", None)
        return prior_from_dict(u.hyper) if self.method == "centroid" and u is not None else None

    @property
    def held_prior(self) -> HeldPrior | None:
        """:attr:`prior` with its plausibility on this frame's gradients: what a later frame of the same surface
        holds (``scopetwin.reconstruct(previous=, hold=True)``); None without a prior."""
        u = getattr(self.result, "uncertainty", None)
        prior = self.prior
        if prior is None or u is None or u.prior_z is None:
            return None
        return HeldPrior(prior, u.prior_z)

    def summary(self) -> dict[str, Any]:
        """JSON-ready: the method's own summary, the uncertainty and the strategy's path (for fringes ``method`` is
        ``"fringes"`` and ``absolute_from`` says where the absolute height came from)."""
        own = self.result.summary()
        if self.method == "fringes":
            own = {**own, "method": "fringes", "absolute_from": self.result.method}
        return {
            "method": self.method,
            **own,
            "uncertainty": {"absolute_um": self.uncertainty.absolute_um, "shape_um": self.uncertainty.shape_um},
            "strategy": list(self.strategy),
            **({"start": self.start} if self.start is not None else {}),
        }


def reconstruct(
    image: NDArray[Any],
    setup: Setup,
    method: Method | None = None,
    *,
    config: ReconstructionConfig | None = None,
    inverse_config: InverseConfig | None = None,
    policy: ReconstructionPolicy = DEFAULT_POLICY,
    history_path: str | Path | None = None,
    evidence_start: Prior | None = None,
    held_prior: HeldPrior | None = None,
    second: tuple[NDArray[Any], float | None] | None = None,
    two_positions: TwoPositionConfig = DEFAULT_TWO_POSITIONS,
    fringe_config: FringeConfig | None = None,
) -> Reconstruction:
    """The surface of one deflectometry measurement (or of two, the pattern moved between them) by any method, with
    every fallback of ``policy``: the one place that chooses the method.

    ``method=None`` (default): ``"fringes"`` where the setup has a ``[fringes]`` table and ``image`` is its (K, rows,
    cols) stack, else ``"centroid"``. ``method="centroid"``: :func:`reconstruct_image` (``evidence_start``: its
    posterior's warm start; ``held_prior``: a prior it reads as it is where plausible); with ``second`` = (image 2,
    its pattern shift along N_z in mm or None for the setup's ``[pattern_stage]``): :func:`reconstruct_pair`
    (``two_positions``: its parameters). ``method="inverse"``: the inverse fit
    (:func:`scopetwin.recon.inverse.reconstruct_inverse`) from :func:`inverse_start`, holding the start's height unless
    it starts from a plane (``inverse_config``'s other settings are kept); it uses one image. ``method="fringes"``:
    :func:`reconstruct_fringe_images` (``second``: the stack at the second display position and its shift;
    ``fringe_config``: its parameters).

    Raises
    ------
    MethodMismatchError
        A marker method asked of a fringe setup, fringes of a marker setup, or a stack of images for a marker setup
        (before any work).
    """
    method = _choose_method(image, setup, method)
    if method == "fringes":
        return reconstruct_fringe_images(image, setup, second=second, config=fringe_config)
    if second is not None:
        if method != "centroid":
            raise ReconstructionError("a second image takes the centroid method (the inverse fit uses one image)")
        return reconstruct_pair(image, second[0], setup, second[1], config, policy, two_positions)
    if method == "centroid":
        done = reconstruct_image(image, setup, config, policy, history_path, evidence_start, held_prior)
        u = done.result.uncertainty
        unc = StandardUncertainty(u.absolute_um, u.shape_um) if u is not None else StandardUncertainty(None, None)
        return Reconstruction("centroid", done.result, done.markers, unc, done.result.strategy)
    return _reconstruct_inverse(image, setup, config, inverse_config, policy)


def _choose_method(image: NDArray[Any], setup: Setup, method: Method | None) -> Method:
    """The method of :func:`reconstruct`: the one asked for where it fits the setup, else one clear error."""
    if method not in (None, "centroid", "inverse", "fringes"):
        raise ReconstructionError(f"method must be 'centroid', 'inverse' or 'fringes', got {method!r}")
    fringe_setup = setup.fringes is not None
    stack = np.ndim(image) == 3
    if method is None:
        method = "fringes" if fringe_setup else "centroid"
    if method == "fringes":
        if not fringe_setup:
            raise MethodMismatchError(
                f"setup {setup.name} has no [fringes] table: it is a marker setup, reconstruct its image with the "
                "centroid or the inverse method"
            )
        if not stack:
            raise MethodMismatchError(
                f"setup {setup.name} shows fringes: give the (K, rows, cols) stack of its "
                f"{len(setup.fringe_sequence or ())} frames, not an image of shape {np.shape(image)}"
            )
        return method
    if fringe_setup:
        raise MethodMismatchError(
            f"setup {setup.name} shows fringes, not markers: the {method} method does not apply; reconstruct its "
            "frames with method 'fringes'"
        )
    if stack:
        raise MethodMismatchError(
            f"a stack of shape {np.shape(image)} is a fringe measurement, but setup {setup.name} has no [fringes] "
            "table: give the marker setup's single image"
        )
    return method


def reconstruct_fringe_images(
    images: NDArray[Any],
    setup: Setup,
    *,
    second: tuple[NDArray[Any], float | None] | None = None,
    config: FringeConfig | None = None,
) -> Reconstruction:
    """The substrate from the camera images of a phase-shifted fringe sequence (phase-measuring deflectometry in the
    §1.10 setup, thesis §1.2-§1.4).

    The frames' meaning (direction, period, phase step) is the setup's ``[fringes]`` sequence. The stack is checked
    first (:func:`scopetwin.recon.fringes.frames.check_fringe_stack`: its K frames, the camera's size, finite
    values), then every pixel's display point is decoded (:func:`scopetwin.recon.fringes.phase.decode_display`, the
    image noise from the phase-step residuals) and the surface reconstructed from the dense slopes
    (:func:`scopetwin.recon.fringes.reconstruct.reconstruct_fringes`): the nested start-height iteration with the
    frame criterion (eqs. 1.3-1.4), or, with ``second``, the absolute height of two display positions (§1.3).

    Parameters
    ----------
    images : ndarray, (K, rows, cols)
        One camera image per frame, in the sequence's order (any linear scale, e.g. digital numbers).
    setup : Setup
        The (calibrated) deflectometry setup with a ``[fringes]`` table.
    second : (ndarray, float or None), optional
        The stack with the display moved along its normal N_z, and the shift in mm (None: the setup's
        ``[pattern_stage]`` shift).
    config : FringeConfig, optional
        The reconstruction's parameters (:class:`scopetwin.recon.fringes.reconstruct.FringeConfig`).

    Returns
    -------
    Reconstruction
        ``method = "fringes"``, ``result`` the :class:`~scopetwin.recon.fringes.reconstruct.FringeResult`,
        ``markers`` None, ``uncertainty`` its absolute (start height) and shape parts, ``strategy`` the path: the
        decode of each stack (pixels decoded, why the others were not), where the absolute height came from, the
        iterations.

    Raises
    ------
    MethodMismatchError
        A marker setup.
    FringeDecodingError
        A stack of another number of frames or size than the setup's sequence and camera, a non-finite value, or
        the second stack unlike the first (all before any work).
    ReconstructionError
        No pixel decoded, too few pixels triangulated on the region of interest (two positions).
    """
    from scopetwin.recon.fringes.frames import DecodeReport, check_fringe_stack, decode_stack
    from scopetwin.recon.fringes.phase import FringeDecodingError
    from scopetwin.recon.fringes.reconstruct import reconstruct_fringes

    t0 = time.perf_counter()
    label = "the fringe images" if second is None else "the fringe images at the first display position"
    stack = check_fringe_stack(images, setup, label)
    stack2, shift = None, None
    if second is not None:
        if not isinstance(second, tuple) or len(second) != 2:
            raise FringeDecodingError("second must be (the second display position's stack, its shift in mm or None)")
        shift = stage_shift(setup, second[1])
        stack2 = check_fringe_stack(second[0], setup, "the fringe images at the second display position")
    coords = decode_stack(stack, setup)
    path = [DecodeReport.of(coords).line("decode" if second is None else "decode, first display position")]
    coords2 = None
    if stack2 is not None:
        coords2 = decode_stack(stack2, setup)
        path.append(DecodeReport.of(coords2).line(f"decode, display moved {shift:+g} mm along its normal"))
    if not coords.valid.any():
        raise ReconstructionError(f"no pixel of the fringe images was decoded: nothing to reconstruct ({path[0]})")
    result: FringeResult = reconstruct_fringes(setup, coords, config, second=coords2, shift_mm=shift)
    path.append(_fringe_height_line(result, shift))
    result.seconds = time.perf_counter() - t0
    unc = StandardUncertainty(result.absolute_um, result.shape_um)
    return Reconstruction("fringes", result, None, unc, path)


def _fringe_height_line(result: FringeResult, shift: float | None) -> str:
    """The strategy's line for the fringe reconstruction's start-height loop."""
    steps = result.history
    inner = sum(s.inner_iterations for s in steps)
    done = "converged" if result.converged else "did not converge"
    last = steps[-1] if steps else None
    obs = f"{last.observations} slopes, chi^2/dof {last.chi2_per_dof:.3g}" if last is not None else "no slopes"
    if result.method == "two-positions":
        where = f"absolute height from two display positions ({shift:+g} mm): start-height correction"
    else:
        where = "absolute height by the frame criterion: criterion"
    crit = f" {last.criterion_um:+.3g} µm" if last is not None else ""
    return (
        f"{where}{crit} at the last step; {done} after {len(steps)} start heights, {inner} inner iterations ({obs}); "
        f"u(absolute) = {result.absolute_um:.3g} µm, u(shape) = {result.shape_um:.3g} µm"
    )


def _reconstruct_inverse(
    image: NDArray[Any],
    setup: Setup,
    config: ReconstructionConfig | None,
    inverse_config: InverseConfig | None,
    policy: ReconstructionPolicy,
) -> Reconstruction:
    """The inverse fit from the best start left (``policy.inverse_starts``)."""
    from dataclasses import replace

    from scopetwin.recon.inverse import InverseConfig, reconstruct_inverse

    begin = inverse_start(image, setup, config, policy)
    cfg = replace(inverse_config or InverseConfig(), absolute=begin.absolute)
    result: InverseResult = reconstruct_inverse(setup, image, begin.surface, cfg, absolute_std_um=begin.absolute_std_um)
    start = begin.kind + (f" ({begin.note})" if begin.note else "")
    path = [*begin.strategy, f"inverse fit from the {begin.kind} start ({cfg.absolute} height)"]
    unc = StandardUncertainty(begin.absolute_std_um, result.shape_std_um)
    return Reconstruction("inverse", result, begin.markers, unc, path, start)
