"""Parameters of the nested start-height iteration: the §1.8 basis, the §1.4 tolerances and criterion.

What the reconstruction does when a step fails is not configured here but in
:class:`scopetwin.recon.policy.ReconstructionPolicy`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Literal

from scopetwin.recon.frame_criterion import FrameCriterion
from scopetwin.recon.shifted_basis import BasisKind, ShiftedBasis
from scopetwin.recon.substrate import Substrate2D


@dataclass(frozen=True)
class ReconstructionConfig:
    """Parameters of the reconstruction (basis of §1.8, thresholds and criterion of §1.4).

    Attributes
    ----------
    basis : {"gauss", "imq"}
        Basis function (§1.8).
    counts : (int, int) or None
        Centre grid (n_x, n_y) spanning the substrate (the thesis's layout); None: a
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
        that follows the surface lies within ~2-3 times of it: 2.7-5.2 against 1.4 µrad on the thesis's surfaces,
        while a 12 mm basis on a 3 mm correlated glass leaves 240 times).
    tilt : bool
        Add the unpenalised plane terms x, y.
    regularization : float
        Relative ridge weight (see :func:`scopetwin.recon.shifted_basis.fit_gradients`).
    intersection_start : {"surface", "offset"}
        Where the rays' secant search on the current surface starts
        (:func:`scopetwin.recon.substrate.intersect_surface`): the plane through the fit's height at the substrate's
        centre with far roots refused ("surface"), or the plane of the fit's offset term ("offset"). The offset
        plane loses the substrate on cut sheets with rolled-off edges, whose fits carry a large offset and tilt that
        the basis cancels over the substrate (5 of ``benchmarks/hard_families.py``'s 6 cut sheets failed with it,
        none with "surface" and the evidence-chosen prior), and on glass-like sheets whose first fit extrapolates
        far.
    inner_tol_um, inner_max : float, int
        Inner loop stops when the RMS height change over the ROI is below ``inner_tol_um``.
    outer_tol_um, outer_max : float, int
        Outer loop stops when ``|criterion|`` <= ``outer_tol_um``.
    criterion : {"level", "delta"}
        Frame-region criterion (module docstring).
    search : {"secant", "thesis"}
        Start-height update (module docstring).
    warm_start : bool
        Start each inner loop from the previous surface moved to the new H (the thesis starts from a plane).
    grid_step, frame_step : float
        Spacing of the evaluation grids over the ROI and over the frame regions, mm.
    min_markers : int
        Minimum number of usable markers overall.
    edge_band, min_edge_markers : float, int
        Each frame region needs at least ``min_edge_markers`` markers within ``edge_band`` mm of it.
    method : {"lstsq", "normal"}
        Linear solver of the fit.
    posterior : {"correct", "report", "off"}
        After convergence, read the fit as a Gaussian process (:mod:`scopetwin.recon.posterior`: smooth +
        broadband prior, scales and amplitudes by evidence) and give every reconstruction its uncertainty (absolute
        height, shape, per node); ``"correct"`` also replaces the extrapolated frame maxima of the fitted surface by
        their posterior mean (a Newton step on the start height, criterion ``level`` only); ``"off"``: neither.
    evidence_points : int
        Gradient observations (an even subsample) entering the evidence maximisation.
    evidence_coarse_points : int
        The evidence's starts run on an even subsample of this many of them, the best refined on all (coarse to
        fine, :func:`scopetwin.recon.posterior.fit_hyper`; 0: every start on all, three times the time).
    posterior_iterations : int
        Most Newton steps on the start height with the posterior frame criterion (``posterior = "correct"``).
    posterior_settle : float
        A Newton step smaller than this fraction of the absolute height's standard uncertainty is the last: it is
        taken without tracing the gradients and reading the posterior again. The posterior criterion is linear in
        the start height over such a step to a few parts in 10^4, so the step that would follow is that small
        (measured on a 16 spp §1.10 render with sensor noise: first step -0.0092 µm, the next -0.0000025 µm without
        and +0.0000085 µm with the bias step, against u = 0.015 µm).
    local_features : bool
        Let the posterior's prior have a local-features part (micrometres over 1-6 mm: dimples and bumps the basis
        fit smooths away) where the evidence asks for it (:func:`scopetwin.recon.posterior.fit_hyper`). It costs one
        more maximisation of the evidence on all its observations (about 20-50 evaluations, ~0.3-0.6 s a frame on
        2 cores); measured on a 16 spp §1.10 render with sensor noise, a 3 mm wide, 2 µm deep dimple comes back at
        88 % of its depth with it, -9 % without. Surfaces without such features keep the prior without it.
    prior : {"auto", "process"}
        The posterior's prior (:func:`scopetwin.recon.uncertainty.evidence_prior`): ``"auto"``, the shifted basis
        itself as a Bayesian linear model (:mod:`scopetwin.recon.basis_posterior`: one m x m factorisation) where the
        evidence peaks at one of its scales, the Gaussian process of :mod:`scopetwin.recon.posterior` where the surface
        is rougher than that (and wherever ``local_features`` is on); ``"process"``: always the Gaussian process.
    posterior_points : int
        Most gradient observations entering the posterior (:func:`scopetwin.recon.uncertainty.posterior_subset_indices`:
        all of the outermost along y, an even subsample of the rest).
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
    intersection_start: Literal["surface", "offset"] = "surface"
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
    evidence_coarse_points: int = 100
    local_features: bool = False
    posterior_points: int = 800
    posterior_iterations: int = 4
    posterior_settle: float = 1.0
    prior: Literal["auto", "process"] = "auto"

    @classmethod
    def thesis(cls, literal_axes: bool = True, **changes: Any) -> ReconstructionConfig:
        """The thesis's §1.10 reconstruction: 9x5 inverse multiquadrics, sigma_x = 4, sigma_y = 3, Delta h_max, eq. 1.4.

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

    def starting_at(self, sigma: float | None) -> ReconstructionConfig:
        """This configuration with the search starting on the basis scale ``sigma`` (mm: the scale an earlier frame
        of the same setup ended on, a rig's next frame) where the scale is chosen from the data: the scale choice then
        mostly keeps it, and the search on the default scale before it is saved. Unchanged for a fixed basis
        (``sigma_candidates`` None, the thesis's grid) or ``sigma`` None."""
        if sigma is None or self.sigma_candidates is None or self.counts is not None:
            return self
        if not 0.0 < sigma < float("inf"):
            raise ValueError(f"a basis scale must be a positive number of mm, got {sigma!r}")
        return replace(self, sigma=(float(sigma), float(sigma)))

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
