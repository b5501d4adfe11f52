"""The reconstruction's fallbacks and their thresholds: one policy object.

The nested start-height iteration of thesis §1.4 (:mod:`scopetwin.recon.reconstruct`) and the inverse fit
(:mod:`scopetwin.recon.inverse`) are algorithms; whether they succeed on a hard image depends on what is done when a
step fails — the markers numbered by another indexing, a tied reference marker retried, the basis scale chosen again,
wrongly indexed markers rejected, the start height taken from the posterior, the inverse fit started from the best
surface left. Every one of those decisions is a named field here, with the measurement that chose its value; the
strategy (:mod:`scopetwin.recon.strategy`) is the one place that reads them and acts.

Nothing here imports the rest of :mod:`scopetwin.recon`: the marker identification, the nested iteration and the
strategy all read their thresholds from :data:`DEFAULT_POLICY` or from a policy passed in.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any, Literal

#: The starts of the inverse fit, best first (:func:`scopetwin.recon.strategy.inverse_start`).
InverseStartKind = Literal["centroid", "centroid-unbiased", "centroid-unconverged", "coarse", "plane"]


@dataclass(frozen=True)
class ReconstructionPolicy:
    """What the reconstruction does when a step fails, and the thresholds that decide it.

    Attributes
    ----------
    lattice_below : float
        The topological indexing (:func:`scopetwin.recon.markers.index_lattice`) is tried when the thesis's flood
        indexing (§1.5.4) numbers fewer than this fraction of the kept spots; the indexing that numbers more is
        kept. Measured on 3 mm / 60 µm surfaces (seeds 1-8, Mitsuba 16 spp): the flood reached 12 and 308 of ~470
        spots on seeds 2 and 1, the lattice 454 and 458 (none nearer another marker's true image than its own); on
        the other six and on the thesis's surfaces (5-20 mm correlation) the flood reaches more than 0.8 and is kept.
    resolve_tied_reference : bool
        Where two or more spots are about as large as the reference marker
        (:class:`scopetwin.recon.markers.ReferenceTieError`), number the markers from each in turn and keep the one
        whose indices lie on the lattice's predicted image
        (:meth:`scopetwin.recon.reconstruct.Reconstructor.lattice_offset`). 3 mm / 60 µm surface seed 7 (four
        candidates): the true one lies 0.02 pitch off, the others 2.1, 2.3 and 2.2 pitches (3 ms each).
    reference_offset_max : float
        A tied candidate is the reference where its indices lie within this many pitches of the lattice's
        predicted image in both directions: a wrong candidate k markers away lies near k pitches off, a substrate
        on its frame tilts the image by a small fraction of a pitch.
    bias_step : bool
        Correct the marker centroids for the spot distortion of the curved mirror inside the inner loop
        (:func:`scopetwin.recon.reconstruct.centroid_bias_step`).
    bias_recompute_um : float
        The bias is predicted again only when the surface's shape (mean removed) moved by more than this RMS, µm:
        it follows the curvature, which settles after the first inner iterations.
    rescale_from_flat_start : bool
        Where the default basis scale's fits throw the rays off the substrate (or leave a frame region without
        markers) — a 12 mm basis on a 3 mm / 60 µm surface — choose the scale on the gradients traced through the
        plane at the frame height and search the start height again with a fresh budget
        (:meth:`scopetwin.recon.reconstruct.Reconstructor.scale_from_flat_start`; 3 mm / 60 µm seeds 1 and 2); also
        where the search does not converge (seed 7: 30 runs at 12 mm do not settle, the 4 mm scale chosen on the
        flat start converges).
    scale_search_runs : int
        Start-height runs a search gets where another path can follow it: the first search before the scale chosen
        on the flat start is tried (the same scale: the rest of ``outer_max``), and a re-chosen scale's search where
        the first scale's converged result can be kept. On the hard families a search that converges does so in
        3-10 runs; one that does not cycles through all 30 (glass-like seeds 9100 and 9104: 20 s each).
    rechoose_scale : bool
        After the first start-height search, choose the basis scale on data traced through its surface
        (:func:`scopetwin.recon.scale.select_sigma`) and search again with it; also when the first scale did not
        converge because it cannot fit the data (its residual above ``fit_ratio`` times the best).
    keep_first_scale : bool
        Where the re-chosen (finer) scale's extrapolation throws the start height so far that the rays miss the
        substrate, or its start-height search does not converge, keep the first scale's converged result instead of
        failing (on bent glass a finer scale's frame maxima can swing by tens to thousands of µm between runs).
    scale_by_evidence : bool
        Where the posterior's early evidence search (:class:`scopetwin.recon.uncertainty.PriorAhead`) read the first
        search's surface with the finite-basis prior (:mod:`scopetwin.recon.basis_posterior`: a smooth surface, its
        evidence peaking at one of the basis scales), the fit takes that prior's scale instead of the held-out choice
        of ``rechoose_scale``: one model for the fit and its uncertainty. Rough surfaces keep the held-out choice.
        Measured with ``scopetwin study coverage`` (112 surfaces, 41 of them read by the finite basis): the absolute
        coverage the same (90.2 %), the shape's 97.3 -> 96.4 % (gauss and gauss+broadband one surface fewer each,
        steep one more), the shape errors' medians within 6 %; the §1.10 preset's first frame 0.22 -> 0.11 s.
    outlier_factor : float
        After convergence, markers whose gradient residual exceeds this many times the median residual are suspects;
        those a neighbouring index explains are rejected and the surface is found again without them
        (:meth:`scopetwin.recon.reconstruct.Reconstructor.index_outliers`): a wrongly indexed marker is milliradians
        off, a good one within ~5 times the median (2-20 µrad), a marker on a local feature finer than the basis
        can be as far off but no neighbour's index explains it. 0 turns it off.
    outlier_max_fraction : float
        At most this fraction of the markers is rejected as wrongly indexed (a missed row skip of five markers on
        the §1.10 pattern of ~470 is 1 %).
    posterior_consistency_sigmas : float
        A converged surface whose extrapolated Delta h_max exceeds ``consistency_um`` is still accepted when the
        posterior's Delta h_max (frame maxima from the data, :mod:`scopetwin.recon.posterior`) lies within
        ``consistency_um`` plus this many of its standard deviations: on surfaces with medium-scale content the
        fitted surface's extrapolation is microns off while the data are consistent.
    posterior_shape_factor : float
        Where the fitted surface's height contrasts lie further from the posterior mean (RMS over the ROI) than this
        many times the posterior's own spread, the shape is taken from the posterior: the fit plus the posterior
        mean of the heights it missed (:class:`scopetwin.recon.posterior.ResidualCorrection`). Glass-like
        substrates (waviness at 5-80 mm, tens of nm at 1-8 mm) leave a Gaussian basis hundreds of µrad of residual
        gradients that the evidence's two-scale prior explains. 0 turns it off.
    slope_range : (float, float)
        The criterion's slope in the start height (dF/dH, ~1 for the ``level`` criterion, ~0.5 for ``delta``) is
        trusted only inside this range; outside it (two start heights too close, a noisy pair) 1 is used.
    inverse_starts : tuple of str
        The inverse fit's starts, tried in order (:func:`scopetwin.recon.strategy.inverse_start`): the centroid
        method with its bias step, without it (the bias model is singular near a caustic on some 3 mm / 60 µm
        surfaces that converge without it), the last surface of a start-height loop that did not converge, a coarse
        fit of the markers, a plane at the frame height.
    pair_starts : tuple of str
        Where the two-position search (thesis §1.3, :func:`scopetwin.recon.strategy.reconstruct_pair`) starts when
        image 1 alone cannot be reconstructed by this policy's own steps: a coarse fit of its markers, else a plane at
        the frame height (the two positions need no frame criterion). Empty: image 1's failure is the pair's.
    coarse_iterations : int
        Fits of the coarse start (the markers' gradients traced at the frame height, then through each fit).
    coarse_min_hit : float
        A coarse iteration whose rays meet the substrate for fewer than this fraction of the markers is not taken.
    """

    lattice_below: float = 0.8
    resolve_tied_reference: bool = True
    reference_offset_max: float = 0.5
    bias_step: bool = True
    bias_recompute_um: float = 0.2
    rescale_from_flat_start: bool = True
    scale_search_runs: int = 15
    rechoose_scale: bool = True
    keep_first_scale: bool = True
    scale_by_evidence: bool = True
    outlier_factor: float = 10.0
    outlier_max_fraction: float = 0.05
    posterior_consistency_sigmas: float = 3.0
    posterior_shape_factor: float = 2.0
    slope_range: tuple[float, float] = (0.2, 5.0)
    inverse_starts: tuple[InverseStartKind, ...] = (
        "centroid",
        "centroid-unbiased",
        "centroid-unconverged",
        "coarse",
        "plane",
    )
    pair_starts: tuple[Literal["coarse", "plane"], ...] = ("coarse", "plane")
    coarse_iterations: int = 3
    coarse_min_hit: float = 0.95

    def __post_init__(self) -> None:
        if not 0.0 <= self.lattice_below <= 1.0:
            raise ValueError(f"lattice_below must lie in [0, 1], got {self.lattice_below}")
        if self.scale_search_runs < 1:
            raise ValueError(f"scale_search_runs must be >= 1, got {self.scale_search_runs}")
        if not 0.0 < self.reference_offset_max < 1.0:
            raise ValueError(f"reference_offset_max must lie in (0, 1), got {self.reference_offset_max}")
        if self.outlier_factor < 0 or not 0.0 <= self.outlier_max_fraction < 1.0:
            raise ValueError("outlier_factor must be >= 0 and outlier_max_fraction in [0, 1)")
        lo, hi = self.slope_range
        if not 0.0 < lo < hi:
            raise ValueError(f"slope_range must be 0 < low < high, got {self.slope_range}")
        if not self.inverse_starts:
            raise ValueError("inverse_starts needs at least one start")

    def with_changes(self, **changes: Any) -> ReconstructionPolicy:
        """A copy with some fields changed (validated like a new one)."""
        return replace(self, **changes)

    def trusted_slope(self, slope: float) -> float:
        """``slope`` where it lies inside :attr:`slope_range`, else 1."""
        lo, hi = self.slope_range
        return slope if lo < abs(slope) < hi else 1.0

    def newton_slope(self, tried: list[tuple[float, float]], slope: float) -> float:
        """The slope of a Newton step on F(H) = 0 from its evaluations ``tried`` = [(H, F(H)), ...]: the secant
        through the last two where they differ in H and it lies inside :attr:`slope_range`, else ``slope``."""
        if len(tried) >= 2 and tried[-1][0] != tried[-2][0]:
            (ha, fa), (hb, fb) = tried[-2], tried[-1]
            secant = (fb - fa) / (hb - ha)
            lo, hi = self.slope_range
            if lo < abs(secant) < hi:
                return secant
        return slope


#: The policy every entry point uses unless given another.
DEFAULT_POLICY = ReconstructionPolicy()
