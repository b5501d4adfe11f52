"""The inverse reconstruction's entry: :class:`InverseReconstructor` runs the fit coarse to fine and searches the
start height by the frame criterion (thesis §1.4, eqs. 1.3-1.4); :func:`reconstruct_inverse` is the one call.

Coarse to fine from a plane start: first on binned images (b x b pixels each, rendered as one super-pixel), then on
the full-resolution image; from the centroid method's surface (already inside the basin) the full-resolution image
directly, the coefficients held to the span of its shifted basis where ``surface="start-basis"``. The absolute
height: from a centroid start the centroid method's mean ROI height H; with ``absolute="frame"`` or from a plane H is
searched (secant, :func:`scopetwin.recon.frame_criterion.next_start_height`) until the fitted surface's maxima over
the two frame regions lie on the holding frame.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.recon.frame_criterion import frame_criterion, frame_distance, next_start_height
from scopetwin.recon.inverse.config import InverseConfig
from scopetwin.recon.inverse.pose import _pose_update
from scopetwin.recon.inverse.render import _Level
from scopetwin.recon.inverse.result import InverseResult
from scopetwin.recon.inverse.uncertainty import _ShapeUncertainty
from scopetwin.recon.shifted_basis import ShiftedBasis
from scopetwin.recon.spline import SplineSurface
from scopetwin.scenes.setup import Setup

#: Most times the fit is checked against the pixels traced and fitted again with those its surface adds
#: (:meth:`scopetwin.recon.inverse.render._Level.widen`): only the pixels near the markers' images through the start
#: are traced (:attr:`InverseConfig.near_margin`), and a fit that moved an image further than the margin would
#: otherwise have fitted it without some of the pixels it lights. Each round adds pixels, so a few suffice; the
#: result says how many were added (``extras["pixels_added"]``).
WIDEN_ROUNDS = 3


@dataclass
class _HeightSearch:
    """The start-height search's end: the start height, criterion, frame maxima, heights tried, converged."""

    h: float
    crit: float
    m1: float
    m2: float
    tried: int
    converged: bool


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


class InverseReconstructor(_ShapeUncertainty):
    """Fits the substrate's surface to one deflectometry image through the differentiable render (package doc).

    The fit's pieces are its bases: the measurement and its window (:mod:`scopetwin.recon.inverse.measurement`),
    the Gauss-Newton steps of one level (:meth:`fit_level`) and the shape uncertainty (:meth:`shape_std_um`,
    :meth:`start_height_term_um`, :meth:`shape_bayes_bound_um`); here the run over levels and start heights.

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

    def frame_maxima(self, surf: SplineSurface) -> tuple[float, float]:
        """Maxima of the surface over frame region 1 and 2, mm (thesis eq. 1.3)."""
        (ax, ay), (bx, by) = self._frame_pts
        return float(np.max(surf.height(ax, ay))), float(np.max(surf.height(bx, by)))

    def run(self, initial: Any = None, absolute_std_um: float | None = None) -> InverseResult:
        """Coarse-to-fine fit with the start-height search (package docstring).

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
        search = initial is None or cfg.absolute == "frame"
        # the markers' images stay where they are (InverseConfig.near_margin): only the pixels near them traced
        near = (surf, cfg.near_margin) if cfg.near_margin > 0 and not (search or cfg.refine_setup) else None
        levels = [self._level(b, s, near) for b, s in schedule]
        surf = self._coarse_to_fine(levels, surf, h)
        fine = levels[-1]
        surf, found = self._height_search(fine, surf, h, len(levels) - 1, search)
        added = 0
        for _ in range(WIDEN_ROUNDS):  # the pixels the fit's surface sees near the markers: all traced?
            more = fine.widen(surf)
            if not more:
                break
            added += more
            surf = self.fit_level(fine, surf, found.h, cfg.iterations[-1], len(levels) - 1)
            surf, found = self._height_search(fine, surf, found.h, len(levels) - 1, search)
        return self._result(surf, found, fine, schedule[-1][1], search, absolute_std_um, t0, added)

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
        added: int = 0,
    ) -> InverseResult:
        """The result of :meth:`run`: the refined setup and the shape uncertainty (start-height term included);
        ``added``: the pixels the fit's surface added to those traced (:data:`WIDEN_ROUNDS`)."""
        cam, pat = (
            _pose_update(self.camera, self.pattern, self.pose)
            if self.config.refine_setup
            else (self.camera, self.pattern)
        )
        held_std_um = None if search else absolute_std_um  # a searched start height is not held
        shape_std, height_term = self._fit_uncertainty(surf, fine, sub_rays, found.h, held_std_um)
        return InverseResult(
            surf,
            self.sub,
            found.h * 1e3,
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
                "span_terms": None if self._span is None else int(self._span.shape[1]),
                "start_height_term_um": height_term,
                "pixels_added": added,
            },
        )


def reconstruct_inverse(
    setup: Setup,
    image: NDArray[Any],
    initial: Any = None,
    config: InverseConfig | None = None,
    variant: str | None = None,
    absolute_std_um: float | None = None,
) -> InverseResult:
    """Fit the substrate's surface to a deflectometry image through the differentiable render (package docstring).

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
