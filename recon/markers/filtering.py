"""Marker filtering and the reference marker (thesis §1.5.2; reference marker §1.5.4, §2.6.1).

:func:`filter_spots` keeps a candidate spot when its area agrees with its neighbours' (:func:`local_area_ratio`),
its rim ellipse stays inside the image and inside the :class:`Region` where markers are reflected whole
(:func:`rim_clearance`; partially reflected markers are dropped) and its edge fades out (no clipped edge); the
reference marker, much larger than its neighbours, is found by :func:`find_reference`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from scopetwin.recon.markers.centroid_search import Array, MarkerError, Spots


def local_area_ratio(points: Array, areas: NDArray, reference: NDArray[np.bool_] | None = None, k: int = 8) -> Array:
    """Area of each spot divided by the median area of its ``k`` nearest reference spots (§1.5.2, made local).

    A bowed substrate magnifies spots unevenly and perspective shrinks distant ones, so the thesis's
    comparison with the median area is made against the neighbourhood. ``reference`` selects the
    spots that may serve as neighbours (default all): fragments of partially reflected markers at
    the region's edge would otherwise make a whole marker beside them look large.
    """
    n = len(points)
    ref = np.ones(n, dtype=bool) if reference is None else np.asarray(reference, dtype=bool)
    m = int(ref.sum())
    if m < 2:
        return np.ones(n)
    kk = min(k, m - 1)
    rp = points[ref]
    _, nb = cKDTree(rp).query(points, k=kk + 1)
    nb = np.asarray(nb).reshape(n, -1)
    d = np.linalg.norm(rp[nb] - points[:, None, :], axis=-1)
    # drop the spot itself where it is one of the reference spots
    self_hit = d[:, 0] == 0
    nbs = np.where(self_hit[:, None], nb[:, 1:], nb[:, :-1])
    return areas / np.maximum(np.median(areas[ref][nbs], axis=1), 1e-300)


class ReferenceTieError(MarkerError):
    """Two or more spots about equally likely to be the reference marker; ``candidates``: their spot indices."""

    def __init__(self, candidates: NDArray[np.intp], message: str) -> None:
        super().__init__(message)
        self.candidates = np.asarray(candidates, dtype=np.intp)

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled with its candidates (a marker search in another process raises it in this one)."""
        return type(self), (self.candidates, *self.args), self.__dict__


@dataclass(frozen=True)
class Filtered:
    """Outcome of :func:`filter_spots`: which candidates are kept, and why the others are not."""

    keep: NDArray[np.bool_]
    reference: int
    ratio: Array
    reasons: dict[str, int]


def find_reference(
    ratio: Array,
    candidates: NDArray[np.bool_],
    points: Array,
    min_ratio: float = 1.45,
    tie: float = 0.8,
    expected: Array | None = None,
    radius: float = 0.0,
) -> int:
    """Index of the reference marker: the spot much larger than its neighbours (§1.5.4, §2.6.1).

    With ``expected`` (the image of the reference marker that the nominal setup predicts, px) the candidates
    within ``radius`` px of it are judged first: on a strongly bent substrate (3 mm
    correlation, 60 µm) whole regions magnify spots 3-5 times against their neighbours, far more than the
    reference's own 1.8-3.5, while the reference stays within a few spacings of its nominal image. Only when
    no candidate lies there does the largest ratio anywhere decide.

    Raises
    ------
    MarkerError
        No spot is ``min_ratio`` times larger than its neighbours, or two candidates are about equally
        large (the second within ``tie`` of the first).
    """
    cand = np.flatnonzero(candidates & (ratio >= min_ratio))
    if cand.size == 0:
        raise MarkerError(
            f"no reference marker: no spot is at least {min_ratio:g}x larger than its neighbours (check the "
            "exposure, the threshold and that the reference marker lies in the view)"
        )
    where = "anywhere in the image"
    if expected is not None and radius > 0:
        near = cand[np.linalg.norm(points[cand] - np.asarray(expected, dtype=np.float64), axis=1) <= radius]
        if near.size:
            cand = near
            where = f"within {radius:.0f} px of the reference's nominal image ({expected[0]:.1f}, {expected[1]:.1f})"
    order = cand[np.argsort(-ratio[cand])]
    if order.size > 1 and ratio[order[1]] >= tie * ratio[order[0]]:
        a, b = points[order[0]], points[order[1]]
        raise ReferenceTieError(
            order[ratio[order] >= tie * ratio[order[0]]],
            f"two equally large reference marker candidates {where} at "
            f"(col, row) = ({a[0]:.1f}, {a[1]:.1f}) and ({b[0]:.1f}, {b[1]:.1f}) "
            f"(area ratios {ratio[order[0]]:.2f} and {ratio[order[1]]:.2f}); the substrate distorts the spots "
            "too much to tell the reference marker: place the reference marker where the substrate is flatter, "
            "or give the setup the camera and pattern placement that puts its nominal image on it",
        )
    return int(order[0])


@dataclass(frozen=True)
class Region:
    """The image of the region where markers are reflected whole: a closed polygon in pixel coordinates.

    For the deflectometry setup it is the image of the substrate's region of interest (thesis §1.6.4,
    the gap between the holding-frame regions), for the mirror setup the mirror; a spot whose rim
    crosses its edge belongs to a partially reflected marker (§1.5.2). See :func:`region_for_setup`.
    """

    polygon: Array

    def signed_distance(self, points: Array) -> Array:
        """Distance (px) of points (..., 2) to the polygon's edge, positive inside."""
        p = np.asarray(points, dtype=np.float64)
        shape = p.shape[:-1]
        px = p[..., 0].reshape(-1, 1)
        py = p[..., 1].reshape(-1, 1)
        ax, ay = self.polygon[:, 0], self.polygon[:, 1]
        bx, by = np.roll(ax, -1), np.roll(ay, -1)
        abx, aby = bx - ax, by - ay
        # closest point of each edge (clamped projection), x and y kept apart: (points, edges) arrays
        dx, dy = px - ax, py - ay
        t = np.clip((dx * abx + dy * aby) / np.maximum(abx * abx + aby * aby, 1e-300), 0.0, 1.0)
        dx -= t * abx
        dy -= t * aby
        d = np.sqrt(np.min(dx * dx + dy * dy, axis=1))
        crosses = (ay > py) != (by > py)
        with np.errstate(divide="ignore", invalid="ignore"):
            xc = ax + (py - ay) * abx / aby
        inside = (np.count_nonzero(crosses & (px < xc), axis=1) % 2) == 1
        return np.where(inside, d, -d).reshape(shape)


def rim_clearance(
    spots: Spots, shape: tuple[int, int], region: Region | None = None, n_points: int = 24
) -> tuple[Array, Array]:
    """Smallest distance (px) of each spot's estimated rim ellipse to the image border and to the region's edge.

    Returns
    -------
    border, region : ndarray, (n,)
        Clearances; negative where the rim crosses the image border or the region's edge
        (+inf for the region when ``region`` is None).
    """
    rows, cols = shape
    reach = spots.major_radius() + 2.0
    c = spots.centroids
    border = np.minimum(np.minimum(c[:, 0], cols - c[:, 0]), np.minimum(c[:, 1], rows - c[:, 1])) - reach + 2.0
    near = np.flatnonzero(border < 2.0)
    if near.size:
        rim = spots.rim(n_points, near)
        b = np.minimum(np.minimum(rim[..., 0], cols - rim[..., 0]), np.minimum(rim[..., 1], rows - rim[..., 1]))
        border[near] = b.min(axis=1)
    inner = np.full(len(spots), np.inf)
    if region is None or len(spots) == 0:
        return border, inner
    centre = region.signed_distance(c)
    inner = centre - reach + 2.0
    near = np.flatnonzero(centre < reach)
    if near.size:
        inner[near] = region.signed_distance(spots.rim(n_points, near)).min(axis=1)
    return border, inner


def _cut_off(spots: Spots, edge_slack: float, edge_noise_sigmas: float) -> NDArray[np.bool_]:
    """Spots whose threshold boundary does not fade out: cut off by the edge of the reflecting region."""
    noise_rel = spots.noise / np.maximum(spots.peak - spots.background, 1e-300)
    return spots.edge > (
        spots.relative_threshold + edge_slack / np.maximum(spots.minor_radius(), 1.0) + edge_noise_sigmas * noise_rel
    )


def _hint_radius(spots: Spots, big: NDArray[np.bool_], reference_hint: Array | None, hint_spacings: float) -> float:
    """Radius (px) of the reference search around the hint: ``hint_spacings`` median spacings (0 without a hint)."""
    radius = 0.0
    if reference_hint is not None:
        pts = spots.centroids[big]
        d, _ = cKDTree(pts).query(pts, k=2)
        radius = hint_spacings * float(np.median(np.asarray(d)[:, 1]))
    return radius


def _rejections(
    tiny: NDArray[np.bool_],
    big: NDArray[np.bool_],
    at_border: NDArray[np.bool_],
    outside: NDArray[np.bool_],
    whole: NDArray[np.bool_],
    in_range: NDArray[np.bool_],
    sharp: NDArray[np.bool_],
) -> dict[str, int]:
    """Number of spots rejected for each reason (the reference marker is not counted among the areas)."""
    return {
        "tiny": int(tiny.sum()),
        "image_border": int((big & at_border).sum()),
        "outside_region": int((big & outside).sum()),
        "area": int((big & whole & ~in_range).sum()) - 1,
        "clipped_edge": int((big & whole & in_range & sharp).sum()),
    }


def filter_spots(
    spots: Spots,
    shape: tuple[int, int],
    region: Region | None = None,
    area_range: tuple[float, float] = (0.7, 1.4),
    min_area: int = 4,
    edge_slack: float = 1.5,
    border_margin: float = 0.5,
    region_margin: float = 0.5,
    ref_ratio: float = 1.45,
    edge_noise_sigmas: float = 8.0,
    reference_hint: Array | None = None,
    hint_spacings: float = 3.0,
    reference: int | None = None,
) -> Filtered:
    """Marker filtering of thesis §1.5.2 and the reference marker.

    A candidate is kept when

    * its area lies within ``area_range`` times the median area of its neighbours (the reference
      marker, much larger, is found by :func:`find_reference` and kept);
    * its rim ellipse (estimated from the spot's second moments, :meth:`Spots.rim`) stays
      ``border_margin`` px inside the image and ``region_margin`` px inside the region where markers
      are reflected whole (``region``, see :func:`region_for_setup`);
    * its threshold boundary fades out: a cone spot of minor semi-axis R px reaches at most about
      ``t + 1/R`` of its peak on the boundary (t the relative threshold), so a boundary value above
      ``t + edge_slack/R`` marks a spot cut off by the edge of the reflecting region. The boundary value is the
      largest of many noisy pixels, so the limit grows by ``edge_noise_sigmas`` times the image noise relative
      to the spot's peak (at 2-10 % of the full well photon and read noise lifted whole spots,
      the reference marker first with its longer boundary, over the noise-free limit; the noise at the
      threshold level, photon noise included, reaches ~6 times the dark noise there).

    ``reference_hint`` (px), the nominal image of the reference marker, narrows the reference search to the
    candidates within ``hint_spacings`` marker spacings of it (:func:`find_reference`). ``reference``: the spot
    (index into ``spots``) to take as the reference marker instead of searching (one of the candidates of a
    :class:`ReferenceTieError`).

    Returns
    -------
    Filtered
        Mask of kept spots, the index of the reference spot, the local area ratios and the number of
        spots rejected for each reason.
    """
    n = len(spots)
    tiny = spots.areas < max(min_area, 0.15 * np.median(spots.areas))
    ratio = np.zeros(n)
    big = ~tiny
    if big.sum() < 3:
        raise MarkerError(f"too few spots to identify a marker grid ({int(big.sum())} found)")
    border, inner = rim_clearance(spots, shape, region)
    at_border = border < border_margin
    outside = ~at_border & (inner < region_margin)
    whole = ~at_border & ~outside
    neighbours = (whole & (spots.areas >= 0.5 * np.median(spots.areas[big])))[big]
    ratio[big] = local_area_ratio(spots.centroids[big], spots.areas[big], neighbours)
    sharp = _cut_off(spots, edge_slack, edge_noise_sigmas)
    radius = _hint_radius(spots, big, reference_hint, hint_spacings)
    if reference is not None:
        if not 0 <= int(reference) < n:
            raise MarkerError(f"reference spot {reference} is not one of the {n} spots")
        ref = int(reference)
    else:
        ref = find_reference(
            ratio, big & whole & ~sharp, spots.centroids, ref_ratio, expected=reference_hint, radius=radius
        )
    in_range = (ratio >= area_range[0]) & (ratio <= area_range[1])
    keep = big & whole & in_range & ~sharp
    keep[ref] = True
    return Filtered(keep, ref, ratio, _rejections(tiny, big, at_border, outside, whole, in_range, sharp))
