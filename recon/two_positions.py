"""Two pattern positions: the absolute height from a second image with the pattern moved along its normal (thesis §1.3).

One image leaves the height-normal ambiguity of thesis §1.3: for any start height the nested iteration of §1.4 finds a
self-consistent surface, and the thesis picks one with the holding frame (§1.4, eqs. 1.3-1.4), extrapolating the
surface 1-4.5 mm under the frame. A second image with the pattern moved by a known distance along its normal N_z
(:mod:`scopetwin.scenes.pattern_stage`) measures the height directly: a wrong start height biases the traced
gradients of a marker by an amount that depends on the pattern's distance — ~ -9 µrad per µm of height in y at the
§1.10 pattern position, ~ -11.6 µrad/µm with the pattern 20 mm closer — so only at the true height do the gradients
of both images belong to one surface. Stereo deflectometry (two cameras, which thesis §1.3 names) uses the same
principle with a second viewpoint; here one camera and a stage do.

The method (beyond the thesis; its steps and fallbacks are :func:`scopetwin.recon.strategy.solve_pair`'s, this module
holds the measurement's pieces):

1. image 1 alone through :func:`scopetwin.recon.strategy.solve` — the frame-criterion height ``h_frame`` with its
   posterior uncertainty, the basis scale, the rejected markers;
2. for a start height H, the **joint surface**: the inner loop of §1.4 with the gradients of both images' markers,
   each traced to its own pattern position (bias-corrected once through image 1's surface, with its own setup),
   fitted by one shifted-basis surface (§1.8) whose ROI mean is H (eq. 1.5); the residual vector r(H) of all marker
   gradients against it; the basis scale the one that gives the height the smallest uncertainty (no extrapolation
   into the frame regions is needed, so finer than image 1's where the surface has few-mm waviness);
3. the height ``h_pair`` minimising |r(H)|^2: Gauss-Newton in H with the derivative dr/dH of the refitted residual
   (two joint surfaces a micrometre apart; r is linear in H to far below the noise), its standard uncertainty
   sigma_r / |dr/dH| with sigma_r^2 = |r|^2 / (m - p), and a spatial block jackknife of the same estimator (the
   residuals of neighbouring markers are correlated where the surface has structure the basis cannot follow:
   glass's micro-waviness);
4. the pair checked: one surface fitted to both images' markers may add at most ``max_excess_urad`` of RMS gradient
   residual to what each image leaves alone (:func:`pair_excess`), else the second image does not belong to the
   first (another substrate, a shift other than the one given) and the pair is refused;
5. combined with the frame criterion by inverse-variance weighting, the uncertainty scaled by the Birge ratio where
   the two disagree beyond their uncertainties; where they disagree by more than ``disagree_sigmas`` the frame
   criterion's a-priori assumption (the substrate lies on the holding frame at the calibrated height) failed and the
   two positions are taken alone. The final surface is the joint surface at that height.

What limits it: the part of the surface the basis does not follow, sampled at different points in the two images
(a marker's two surface points lie 0.3-1.7 mm apart at a 40 mm shift). Measured with ``scopetwin study
second-measurement`` (§1.10 setup, 16 spp, EMVA 1288 sensor noise, the pattern 40 mm closer): on glass-like surfaces
without micro-waviness the two positions give the absolute height to a median 0.017 µm (max 0.15 µm, u median
0.03 µm, all within 2 u), where the frame criterion misses it by a median 0.86 µm (max 2.9 µm); with 20-100 nm of
micro-waviness at 1-8 mm every centroid carries 40-100 µrad of gradient that no smooth surface fits, and the two
positions give a median 0.2 µm (max 1.3 µm, u median 0.84 µm). Denser coding of the pattern (phase-shifted fringes:
the two pattern points of one camera pixel) or more pattern positions would move that.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.recon.config import ReconstructionConfig
from scopetwin.recon.errors import MismatchedPairError, ReconstructionError, TooFewMarkersError
from scopetwin.recon.reconstruct import (
    MarkerObservations,
    ReconstructionResult,
    Reconstructor,
    centroid_bias_step,
)
from scopetwin.recon.shifted_basis import SBFSurface, ShiftedBasis, fit_gradients
from scopetwin.recon.substrate import Substrate2D
from scopetwin.scenes.geometry import Array
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap


@dataclass(frozen=True)
class TwoPositionConfig:
    """Parameters of the two-position height (module docstring).

    Attributes
    ----------
    step_um : float
        Start-height step of the derivative dr/dH, µm.
    max_steps : int
        Most Gauss-Newton steps on the start height.
    tol_um : float
        A step below this ends the search, µm.
    blocks : (int, int)
        Spatial blocks (x, y) of the jackknife over the substrate.
    combine : bool
        Combine with the frame criterion's height (inverse-variance weights); False: the two positions alone.
    disagree_sigmas : float
        Where the two heights differ by more than this many combined standard uncertainties, the frame criterion is
        not combined: its a-priori assumption (the substrate lies on the holding frame at the calibrated height)
        is what failed, not the measurement (a bow that does not touch the frame, dirt under it, a wrong frame
        height). The result notes it.
    min_markers : int
        Fewest markers of the second image whose rays meet the ROI.
    sigmas : tuple of float
        Basis scales of the joint surface, mm, tried from the coarsest (beside image 1's own): the height is taken
        with the scale that gives it the smallest standard uncertainty; the search stops at the first finer scale
        that gives none smaller (or fails). Image 1's scale is chosen for the extrapolation into the frame regions
        (coarse); the two positions need none, and a finer basis that follows glass's few-mm waviness leaves far
        smaller residuals (measured on a glass-like render: 12 mm, u 3.8 µm; 4 mm, u 0.6 µm, error 0.02 µm).
    settle_um : float
        The joint surface at the height found must settle: its last RMS height change over the ROI at most this, µm
        (else no surface explains both images — a wrong shift, or centroids the bias step cannot model — and the
        height is refused rather than reported).
    max_excess_urad : float
        Both images must be of one surface (:func:`pair_excess`): one surface fitted to both images' markers may
        leave at most this much RMS gradient residual beyond what each image's markers leave fitted alone, µrad;
        more is one :class:`~scopetwin.recon.errors.MismatchedPairError` (a second image of another substrate, or a
        pattern shift other than the one given). The joint residual alone does not tell them apart: glass's
        micro-waviness leaves up to 126 µrad on true pairs, a mismatch of smooth surfaces of the thesis's kind 303.
        Measured with ``benchmarks/two_position_pairs.py`` (§1.10 setup, Mitsuba 16 spp, EMVA 1288 sensor noise,
        the pattern 40 mm closer; seeds 9100-9102 of each family): true pairs leave an excess of 0.39-0.67 µrad on
        the thesis's kind and 0.00 on glass-like, cut, steep and local-feature surfaces; a second image of the next
        seed's surface 308-430 µrad (thesis's kind), 595-633 (glass-like), 309-4333 (cut, steep, features; one cut
        pair gave no height at any basis scale, itself an error); the right images with a 30 mm shift given for
        40 mm 1614-1899. 30 µrad lies 45 times above the largest true pair and a tenth of the smallest mismatch.
    """

    step_um: float = 1.0
    max_steps: int = 6
    tol_um: float = 1e-4
    blocks: tuple[int, int] = (3, 8)
    combine: bool = True
    disagree_sigmas: float = 3.0
    min_markers: int = 20
    sigmas: tuple[float, ...] = (12.0, 8.0, 6.0, 4.0, 3.0)
    settle_um: float = 0.01
    max_excess_urad: float = 30.0


#: The two-position parameters every entry point uses unless given others.
DEFAULT_TWO_POSITIONS = TwoPositionConfig()


@dataclass(frozen=True)
class PatternView:
    """One image of the pattern at one position: the iteration's pieces for that position's setup (its pattern,
    its bias step) and the image's indexed markers."""

    reconstructor: Reconstructor
    markers: MarkerObservations


@dataclass
class JointRun:
    """The joint surface for one start height: the surface, the gradient residuals (n_markers, 2) of every view's
    markers stacked (NaN where a ray missed the ROI), the markers' substrate positions (NaN likewise), iterations and
    the last RMS height change over the ROI (µm)."""

    height: float
    surface: SBFSurface
    residual: Array
    xy: Array
    iterations: int
    change_um: float


@dataclass(frozen=True)
class HeightEstimate:
    """The absolute height (ROI mean) from the frame criterion, from the two positions, and combined; µm.

    ``frame_um`` is None where image 1 alone could not be reconstructed (the two positions then start from a coarse
    fit of its markers). ``pair_std_um`` is the larger of the Gauss-Newton and the block-jackknife standard
    uncertainty; ``agreement`` is (pair - frame) / sqrt(u_pair^2 + u_frame^2); ``std_um`` includes the Birge-ratio
    scaling where 1 < |agreement| <= ``disagree_sigmas``. ``residual_urad`` is the joint fit's RMS gradient residual,
    ``separate_urad`` the residual standard deviation of each image's markers fitted alone and ``excess_urad`` what
    the joint fit adds to it (:func:`pair_excess`; µrad).
    """

    frame_um: float | None
    frame_std_um: float | None
    pair_um: float
    pair_std_um: float
    gauss_newton_std_um: float
    jackknife_std_um: float
    height_um: float
    std_um: float
    agreement: float | None
    residual_urad: float
    markers: tuple[int, int]
    steps: int
    sigma_mm: float
    separate_urad: float = float("nan")
    excess_urad: float = float("nan")

    def summary(self) -> dict[str, Any]:
        """JSON-ready."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


@dataclass
class TwoPositionResult:
    """The surface from two images of the pattern at two positions, with the image-1 reconstruction it started from.

    ``surface`` is the joint surface at the height found; ``single`` is image 1 reconstructed alone (None where that
    failed: ``strategy`` says why). ``shape_std_um`` is the single image's (its start height's part was the frame
    criterion's, so it is an upper bound; None without it).
    """

    surface: SBFSurface
    substrate: Substrate2D
    single: ReconstructionResult | None
    estimate: HeightEstimate
    shift_mm: float
    seconds: float
    strategy: list[str] = field(default_factory=list)

    @property
    def absolute_std_um(self) -> float:
        return self.estimate.std_um

    @property
    def shape_std_um(self) -> float | None:
        u = None if self.single is None else self.single.uncertainty
        return None if u is None else u.shape_um

    def height_at(self, x_mm: Any, y_mm: Any) -> NDArray[np.float64]:
        """Heights at substrate coordinates (x, y), mm (vectorised)."""
        return np.asarray(self.surface.height(np.asarray(x_mm, float), np.asarray(y_mm, float)), dtype=np.float64)

    def heightmap(self, nx: int = 128, ny: int = 288) -> HeightMap:
        """The surface on a node grid over the whole substrate (docs/contract.md, "Height maps")."""
        return self.surface.heightmap(self.substrate.x_range, self.substrate.y_range, nx, ny)

    def measured_mask(self, nx: int = 128, ny: int = 288) -> NDArray[np.bool_] | None:
        """The nodes image 1's markers measure (:meth:`ReconstructionResult.measured_mask`; None without it)."""
        return None if self.single is None else self.single.measured_mask(nx, ny)

    def std_heightmap(self, nx: int = 128, ny: int = 288) -> HeightMap | None:
        """Per-node standard uncertainty, mm: the single image's with its absolute part replaced by the two
        positions' (None without the single image's)."""
        u = None if self.single is None else self.single.uncertainty
        single = None if self.single is None else self.single.std_heightmap(nx, ny)
        if single is None or u is None:
            return None
        shape2 = np.clip(single.z**2 - (u.absolute_um * 1e-3) ** 2, 0.0, None)
        z = np.sqrt(shape2 + (self.estimate.std_um * 1e-3) ** 2)
        return HeightMap(z, single.x_min, single.x_max, single.y_min, single.y_max)

    def summary(self) -> dict[str, Any]:
        """JSON-ready: the single image's summary (where it was reconstructed), the start height replaced, and the
        two positions' estimate."""
        if self.single is not None:
            out = self.single.summary()
        else:
            out = {"outer_iterations": 0, "inner_iterations": 0, "delta_h_max_um": None, "converged": False}
        out.update(
            start_height_um=self.estimate.height_um,
            seconds=self.seconds,
            sigma_mm=list(self.surface.basis.sigma),
            basis_functions=self.surface.basis.n_basis,
            strategy=list(self.strategy),
            two_positions={"shift_mm": self.shift_mm, **self.estimate.summary()},
        )
        return out


# -- the joint surface -----------------------------------------------------------------------------------------------
def joint_surface(
    views: list[PatternView], basis: ShiftedBasis, height: float, initial: SBFSurface, cfg: ReconstructionConfig
) -> JointRun:
    """The inner loop of thesis §1.4 on the markers of every view at once, for start height ``height`` (mm).

    Each view's markers are traced through the current surface to their own pattern position; one shifted-basis fit
    (§1.8) of all their gradients; the offset so that the ROI mean is ``height`` (eq. 1.5); until the RMS height
    change over the ROI is below ``cfg.inner_tol_um``.
    """
    sub = views[0].reconstructor.sub
    roi = basis.values(*sub.roi_grid(cfg.grid_step))
    surface = SBFSurface(basis, initial.coef, height - float(np.mean(roi @ initial.coef)))
    prev = roi @ surface.coef + surface.offset
    iterations, change_um = 0, float("inf")
    for iterations in range(1, cfg.inner_max + 1):  # noqa: B007 - the count is returned
        traced = [v.reconstructor.traced_gradients(surface, v.markers) for v in views]
        if sum(int(t[3].sum()) for t in traced) < cfg.min_markers:
            raise TooFewMarkersError(
                f"the joint surface at {height * 1e3:+.4g} µm lost the substrate: fewer than {cfg.min_markers} marker "
                "rays meet its region of interest"
            )
        xy = np.concatenate([t[0] for t in traced])
        hx = np.concatenate([t[1] for t in traced])
        hy = np.concatenate([t[2] for t in traced])
        coef, _ = fit_gradients(basis, xy[:, 0], xy[:, 1], hx, hy, cfg.regularization, method=cfg.method)
        surface = SBFSurface(basis, coef, height - float(np.mean(roi @ coef)))
        now = roi @ coef + surface.offset
        change_um = float(np.sqrt(np.mean((now - prev) ** 2))) * 1e3
        prev = now
        if change_um < cfg.inner_tol_um:
            break
    residual, points = _residuals(views, traced, surface)
    return JointRun(height, surface, residual, points, iterations, change_um)


def _residuals(views: list[PatternView], traced: list[Any], surface: SBFSurface) -> tuple[Array, Array]:
    """Model minus traced gradient of every marker of every view, (n, 2), and its substrate position; NaN where the
    marker's ray missed the ROI."""
    res, pts = [], []
    for view, (xy, hx, hy, ok) in zip(views, traced, strict=True):
        r = np.full((len(view.markers.ij), 2), np.nan)
        p = np.full((len(view.markers.ij), 2), np.nan)
        gx, gy = surface.gradient(xy[:, 0], xy[:, 1])
        r[ok] = np.stack([gx - hx, gy - hy], axis=1)
        p[ok] = xy
        res.append(r)
        pts.append(p)
    return np.concatenate(res), np.concatenate(pts)


# -- the start height -----------------------------------------------------------------------------------------------
def pair_height(
    views: list[PatternView], basis: ShiftedBasis, start: SBFSurface, h0: float, tp: TwoPositionConfig
) -> tuple[JointRun, Array, int]:
    """The start height whose joint surface explains every view best (Gauss-Newton on |r(H)|^2, from ``h0``).

    Returns the joint run at that height, the derivative dr/dH (per residual component, 1/mm; NaN where a marker
    was lost at either height) and the number of steps.
    """
    cfg = views[0].reconstructor.config
    d = tp.step_um * 1e-3
    run = joint_surface(views, basis, h0, start, cfg)
    steps = 0
    while True:  # the derivative taken again where the steps moved the height beyond the step it was taken over
        at = run.height
        ahead = joint_surface(views, basis, at + d, run.surface, cfg)
        jac = (ahead.residual - run.residual) / d
        for _ in range(tp.max_steps):
            ok = np.isfinite(jac) & np.isfinite(run.residual)
            jj = float(np.sum(jac[ok] ** 2))
            if jj <= 0:
                raise ReconstructionError("the two pattern positions do not constrain the height (dr/dH = 0)")
            step = -float(np.sum(jac[ok] * run.residual[ok])) / jj
            run = joint_surface(views, basis, run.height + step, run.surface, cfg)
            steps += 1
            if abs(step) * 1e3 < tp.tol_um:
                break
        if abs(run.height - at) <= d or steps >= 3 * tp.max_steps:
            break
    if not run.change_um <= tp.settle_um:
        raise ReconstructionError(
            f"the joint surface of both images did not settle at the height found (last change {run.change_um:.3g} "
            f"µm > {tp.settle_um:g} µm after {run.iterations} iterations): no smooth surface explains the markers of "
            "both pattern positions (is the shift right? are the centroids biased beyond the bias step's model?)"
        )
    return run, jac, steps


#: One basis scale's two-position height: the joint run there, dr/dH, steps, Gauss-Newton and jackknife standard
#: uncertainties (mm), residual RMS (rad), and the basis.
PairFit = tuple[JointRun, Array, int, float, float, float, ShiftedBasis]


def pair_fit(
    views: list[PatternView], basis: ShiftedBasis, start: SBFSurface, h0: float, tp: TwoPositionConfig
) -> PairFit:
    """The two-position height in one basis (:func:`pair_height` from ``h0``) with its uncertainties
    (:func:`pair_uncertainty`). Which basis scales are tried is the strategy's
    (:func:`scopetwin.recon.strategy.solve_pair`)."""
    for view in views:
        view.reconstructor.use_basis(basis)
    run, jac, steps = pair_height(views, basis, start, h0, tp)
    sub = views[0].reconstructor.sub
    return (run, jac, steps, *pair_uncertainty(run, jac, basis.n_terms, tp.blocks, sub), basis)


def rebase(surface: SBFSurface, basis: ShiftedBasis, sub: Substrate2D, cfg: ReconstructionConfig) -> SBFSurface:
    """``surface`` in another basis: its gradients on a 1 mm grid over the ROI fitted (§1.8), the same ROI mean."""
    x, y = sub.roi_grid(1.0)
    gx, gy = surface.gradient(x, y)
    coef, _ = fit_gradients(basis, x, y, gx, gy, cfg.regularization, method=cfg.method)
    roi = sub.roi_grid(cfg.grid_step)
    mean = float(np.mean(surface.height(*roi)))
    return SBFSurface(basis, coef, mean - float(np.mean(basis.values(*roi) @ coef)))


def pair_uncertainty(
    run: JointRun, jac: Array, n_terms: int, blocks: tuple[int, int], sub: Substrate2D
) -> tuple[float, float, float]:
    """Standard uncertainties of the two-position height, mm: Gauss-Newton, block jackknife; and the residual RMS.

    Gauss-Newton: sigma_r / |dr/dH| with sigma_r^2 = |r|^2 / (m - p) (m residual components, p basis terms). The
    jackknife leaves out one spatial block of markers at a time ((nx, ny) blocks over the substrate) and takes the
    linearised estimate's spread, (B - 1)/B sum (dH_b - mean)^2: residuals correlated within a block count as one.
    """
    ok = np.isfinite(jac) & np.isfinite(run.residual)
    r, j = run.residual[ok], jac[ok]
    m = r.size
    jj = float(np.sum(j**2))
    sigma_r2 = float(np.sum(r**2)) / max(m - n_terms, 1)
    gauss_newton = float(np.sqrt(sigma_r2 / jj))
    nx, ny = blocks
    x = np.broadcast_to(run.xy[:, :1], run.residual.shape)[ok]
    y = np.broadcast_to(run.xy[:, 1:], run.residual.shape)[ok]
    bx = np.clip(((x - sub.x_range[0]) / sub.size_x * nx).astype(int), 0, nx - 1)
    by = np.clip(((y - sub.y_range[0]) / sub.size_y * ny).astype(int), 0, ny - 1)
    label = bx * ny + by
    moves = []
    for b in np.unique(label):
        inside = label == b
        rest = float(np.sum(j[~inside] ** 2))
        if rest > 0:
            moves.append(float(np.sum(j[inside] * r[inside])) / rest)
    k = len(moves)
    jackknife = float(np.sqrt((k - 1) / k * np.sum((np.array(moves) - np.mean(moves)) ** 2))) if k > 1 else np.inf
    return gauss_newton, jackknife, float(np.sqrt(np.mean(r**2)))


def pair_excess(views: list[PatternView], run: JointRun, basis: ShiftedBasis) -> tuple[float, float]:
    """What fitting both images by one surface adds to the gradient residual, rad: each view's markers fitted alone
    (the inner loop at the joint run's height, in its basis), their pooled residual standard deviation
    sigma_s^2 = sum |r_v|^2 / (m_1 + m_2 - 2p), the joint fit's sigma_j^2 = |r|^2 / (m - p) (m residual components,
    p basis terms); returns sigma_s and the excess sqrt(max(sigma_j^2 - sigma_s^2, 0)).
    """
    cfg = views[0].reconstructor.config
    p = basis.n_terms
    ok = np.isfinite(run.residual)
    joint2 = float(np.sum(run.residual[ok] ** 2)) / max(int(ok.sum()) - p, 1)
    r2, m = 0.0, 0
    for view in views:
        alone = joint_surface([view], basis, run.height, run.surface, cfg)
        ok = np.isfinite(alone.residual)
        r2 += float(np.sum(alone.residual[ok] ** 2))
        m += int(ok.sum())
    separate2 = r2 / max(m - 2 * p, 1)
    return float(np.sqrt(separate2)), float(np.sqrt(max(joint2 - separate2, 0.0)))


def combine(
    frame: float,
    frame_std: float | None,
    pair: float,
    pair_std: float,
    use_frame: bool = True,
    disagree_sigmas: float = 3.0,
) -> tuple[float, float, float | None]:
    """The height from the frame criterion's and the two positions': their inverse-variance mean and its standard
    uncertainty (scaled by the Birge ratio |z| where they disagree beyond their uncertainties, 1 < |z|), and z =
    (pair - frame) / sqrt(u_frame^2 + u_pair^2). Where |z| > ``disagree_sigmas`` (or without a frame uncertainty, or
    ``use_frame`` False) the two positions alone: the frame criterion's assumption failed, the measurement did not.
    """
    if not use_frame or frame_std is None or not np.isfinite(frame_std) or frame_std <= 0:
        return pair, pair_std, None
    z = (pair - frame) / float(np.hypot(frame_std, pair_std))
    if abs(z) > disagree_sigmas:
        return pair, pair_std, z
    w_f, w_p = 1.0 / frame_std**2, 1.0 / pair_std**2
    mean = (w_f * frame + w_p * pair) / (w_f + w_p)
    return mean, float(1.0 / np.sqrt(w_f + w_p)) * max(1.0, abs(z)), z


# -- the pieces around the height: the views, the checks, the estimate ---------------------------------------------
def height_estimate(
    first: PatternView,
    fit: PairFit,
    frame: float | None,
    frame_std: float | None,
    tp: TwoPositionConfig,
    residuals: tuple[float, float],
) -> tuple[HeightEstimate, float]:
    """The :class:`HeightEstimate` of a two-position fit beside the frame criterion's height ``frame`` (mm; None
    without it) and its standard uncertainty (mm), with the (separate, excess) residuals of :func:`pair_excess`
    (rad); and the height taken (mm, :func:`combine`)."""
    run, _, steps, gn, jk, resid, basis = fit
    h, h_std, z = combine(
        run.height if frame is None else frame, frame_std, run.height, max(gn, jk), tp.combine, tp.disagree_sigmas
    )
    n1, n2 = (int(np.sum(np.isfinite(v))) for v in np.split(run.residual[:, 0], [len(first.markers.ij)]))
    est = HeightEstimate(
        None if frame is None else frame * 1e3,
        None if frame_std is None else frame_std * 1e3,
        run.height * 1e3,
        max(gn, jk) * 1e3,
        gn * 1e3,
        jk * 1e3,
        h * 1e3,
        h_std * 1e3,
        z,
        resid * 1e6,
        (n1, n2),
        steps,
        float(basis.sigma[0]),
        residuals[0] * 1e6,
        residuals[1] * 1e6,
    )
    return est, h


def estimate_lines(est: HeightEstimate, shift_mm: float, tp: TwoPositionConfig) -> list[str]:
    """The strategy's lines of the two positions: the height found, and how the frame criterion entered."""
    where = (
        f"height {est.pair_um - est.frame_um:+.3g} µm from the frame criterion's"
        if est.frame_um is not None
        else f"height {est.pair_um:+.4g} µm"
    )
    path = [
        f"second pattern position ({shift_mm:+g} mm along N_z): {est.markers[1]} markers, basis scale "
        f"{est.sigma_mm:g} mm, {where}, u = {est.pair_std_um:.3g} µm"
    ]
    z = est.agreement
    if z is not None and abs(z) > tp.disagree_sigmas:
        path.append(
            f"the frame criterion disagrees by {z:+.3g} combined standard uncertainties (beyond "
            f"{tp.disagree_sigmas:g}): the substrate does not lie on the holding frame as the setup says; the two "
            "positions' height taken alone"
        )
    elif z is not None:
        path.append(f"combined with the frame criterion (z = {z:+.2f}): u = {est.std_um:.3g} µm")
    return path


def check_pair(excess: float, separate: float, shift_mm: float, tp: TwoPositionConfig) -> None:
    """Both images must be of one surface: the joint fit may add at most ``tp.max_excess_urad`` to the residual
    each image leaves alone (:func:`pair_excess`, rad)."""
    if not excess * 1e6 <= tp.max_excess_urad:
        raise MismatchedPairError(
            f"the second image does not belong to the first: one surface fitted to both images' markers leaves "
            f"{excess * 1e6:.3g} µrad RMS of gradient residual beyond the {separate * 1e6:.3g} µrad each image leaves "
            f"alone (two images of one surface: at most {tp.max_excess_urad:g} µrad); is it an image of the same "
            f"substrate, with the pattern moved {shift_mm:+g} mm along its normal?"
        )


def held_bias(view: PatternView, surface: SBFSurface) -> PatternView:
    """The view with its markers' centroid-bias correction made once, through ``surface`` (image 1's), and held.

    The bias follows the surface's curvature, which image 1's reconstruction already gives, and hardly its height;
    a bias step redone inside the joint iteration whenever the shape moves (a finer basis than image 1's) makes the
    joint surface jump between corrections instead of settling.
    """
    rec = view.reconstructor
    if rec.bias is None:
        return view
    ij, px, _ = rec.prepare(view.markers)
    held = MarkerObservations(ij, rec.corrected(surface, ij, px))
    rec.bias = None
    return PatternView(rec, held)


def check_second(second: PatternView, surface: SBFSurface, tp: TwoPositionConfig) -> None:
    """The second image's markers must meet the ROI through image 1's surface: enough of them."""
    _, _, _, ok = second.reconstructor.traced_gradients(surface, second.markers)
    if int(ok.sum()) < tp.min_markers:
        raise TooFewMarkersError(
            f"only {int(ok.sum())} markers of the second image meet the substrate's region of interest (at least "
            f"{tp.min_markers} are needed): is the pattern shift right, and was the image taken with it?"
        )


def view_for(
    setup: Setup, markers: MarkerObservations, config: ReconstructionConfig | None, bias: bool, frame_z: float = 0.0
) -> PatternView:
    """The iteration's pieces for one pattern position's setup (with its own centroid-bias step where ``bias``)."""
    step = centroid_bias_step(setup) if bias else None
    return PatternView(Reconstructor.from_setup(setup, config, step, frame_z), markers)


def without(markers: MarkerObservations, rejected: NDArray[np.int64]) -> MarkerObservations:
    """``markers`` without the indices in ``rejected``."""
    if len(rejected) == 0:
        return markers
    drop = (markers.ij[:, None, :] == rejected[None, :, :]).all(axis=2).any(axis=1)
    return MarkerObservations(markers.ij[~drop], markers.px[~drop])


def without_outliers(view: PatternView, surface: SBFSurface, factor: float, max_fraction: float) -> PatternView:
    """The view's markers without those whose gradients no smooth surface explains (wrongly indexed:
    :meth:`scopetwin.recon.reconstruct.Reconstructor.index_outliers`; ``factor`` 0 keeps all)."""
    rec = view.reconstructor
    if factor <= 0:
        return view
    if rec.basis is not surface.basis:
        rec.use_basis(surface.basis)
    drop = rec.index_outliers(view.markers, surface, factor, max_fraction)
    return PatternView(rec, MarkerObservations(view.markers.ij[~drop], view.markers.px[~drop]))
