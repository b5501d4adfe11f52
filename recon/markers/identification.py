"""Marker identification, all four steps (thesis §1.5 for the deflectometry grid, §2.6 for the calibration grid).

:func:`find_markers` runs centroid search (:mod:`scopetwin.recon.markers.centroid_search`, §1.5.1), filtering
(:mod:`scopetwin.recon.markers.filtering`, §1.5.2), grid identification
(:mod:`scopetwin.recon.markers.grid_identification`,
§1.5.3 / §2.6.1) and indexing (:mod:`scopetwin.recon.markers.indexing`, §1.5.4) and returns the :class:`Markers`.
:func:`find_markers_for` takes layout, axis hint, view, region, index range and the reference marker's nominal image
from a setup: the nominal geometry
(a flat substrate or mirror in z = 0) tells where the axes and the reflecting region lie in the image
(:func:`expected_axes`, :func:`region_for_setup`, :func:`index_range`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.recon.markers.centroid_search import Array, MarkerError, Spots, centroids
from scopetwin.recon.markers.filtering import Region, filter_spots
from scopetwin.recon.markers.grid_identification import fourier_axes, nearest_spacing, orient_axes, reference_axes
from scopetwin.recon.markers.indexing import index_grid, index_lattice
from scopetwin.recon.policy import DEFAULT_POLICY

if TYPE_CHECKING:  # annotations only: the height map's spline (scipy.interpolate) is not needed to find markers
    from scopetwin.scenes.setup import Setup
    from scopetwin.scenes.surface import HeightMap


@dataclass(frozen=True)
class Markers:
    """Identified markers of one image.

    Attributes
    ----------
    ij : ndarray, (n, 2), int
        Marker indices on the pattern (docs/contract.md, "Marker indices"), reference (0, 0).
    centroids : ndarray, (n, 2)
        Raw grey-weighted centroids (col, row), continuous pixel coordinates.
    areas : ndarray, (n,)
        Pixel counts above the threshold.
    peak : ndarray, (n,)
        Peak grey values.
    saturated : ndarray of bool, (n,)
        Peak at the saturation level (the centroid may be biased).
    axes : ndarray, (2, 2)
        Image steps of +T_x, +T_y at the reference marker.
    rejected : int
        Candidate spots not reported (filtered out or not reached by the indexing).
    reasons : dict
        Number of rejected candidates per reason.
    spots : Spots
        All candidates of the centroid search.
    indexing : {"flood", "lattice"}
        Which indexing numbered them: the thesis's flood (:func:`index_grid`) or, where it reached too few of the
        kept spots, the topological one (:func:`index_lattice`).
    """

    ij: NDArray[np.int64]
    centroids: Array
    areas: NDArray[np.int64]
    peak: Array
    saturated: NDArray[np.bool_]
    axes: Array
    rejected: int
    reasons: dict[str, int]
    spots: Spots
    indexing: str = "flood"

    def __len__(self) -> int:
        return len(self.ij)

    def as_json(self) -> dict:
        """The ``markers`` JSON of docs/contract.md: ``{"markers": [{i, j, col, row, area}], "rejected": n}``."""
        recs = [
            {"i": int(i), "j": int(j), "col": float(c), "row": float(r), "area": int(a), "saturated": bool(s)}
            for (i, j), (c, r), a, s in zip(self.ij, self.centroids, self.areas, self.saturated, strict=True)
        ]
        return {
            "markers": recs,
            "rejected": int(self.rejected),
            "saturated": int(self.saturated.sum()),
            "reasons": dict(self.reasons),
            "indexing": self.indexing,
        }


def find_markers(
    image: NDArray,
    layout: str = "deflectometry",
    *,
    hint: Array | None = None,
    mirrored: bool | None = None,
    region: Region | None = None,
    index_range: tuple[tuple[int, int], tuple[int, int]] | None = None,
    threshold: float | None = None,
    saturation: float | None = None,
    area_range: tuple[float, float] = (0.7, 1.4),
    region_margin: float = 0.5,
    reference_hint: Array | None = None,
    reference: int | None = None,
    lattice_below: float = DEFAULT_POLICY.lattice_below,
) -> Markers:
    """Find, filter and index the markers of an image (thesis §1.5 and §2.6).

    Parameters
    ----------
    image : ndarray, (rows, cols)
        Camera image (float of any scale, or integer of any bit depth).
    layout : {"deflectometry", "calibration"}
        Deflectometry grid (reference in the centre, axes from the Fourier transform, §1.5.3) or
        calibration target (reference at the -x/-y corner, axes from its neighbours, §2.6.1).
    hint : ndarray, (2, 2), optional
        Approximate image directions of the pattern's +T_x and +T_y (rows), e.g. from
        :func:`expected_axes`. Default (thesis §1.5.3): T_x along +col, T_y along -row in a direct view
        and along +row in a mirror view.
    mirrored : bool, optional
        The pattern is seen in a mirror (deflectometry); default: ``layout == "deflectometry"``.
        Decides the calibration grid's x/y assignment by right-handedness.
    region : Region, optional
        Image of the region where markers are reflected whole (:func:`region_for_setup`); spots whose
        rim leaves it by more than ``region_margin`` px are rejected as partially reflected.
    index_range : ((i_min, i_max), (j_min, j_max)), optional
        Indices that exist on the pattern; markers indexed outside are rejected.
    threshold, saturation : float, optional
        See :func:`centroids`.
    area_range : (float, float)
        Accepted area relative to the neighbours' median (§1.5.2).
    reference_hint : ndarray, (2,), optional
        Nominal image of the reference marker (px, e.g. from :func:`expected_reference`): the reference is
        looked for near it first (:func:`scopetwin.recon.markers.filtering.find_reference`).
    reference : int, optional
        Take this spot of the centroid search as the reference marker (one of the ``candidates`` of a
        :class:`scopetwin.recon.markers.filtering.ReferenceTieError`, which the search raises where two spots are about
        equally large).
    lattice_below : float
        Where the flood indexing numbers fewer than this fraction of the kept spots, the grid's topology
        (:func:`index_lattice`) numbers them too and the indexing that reached more is kept
        (:attr:`scopetwin.recon.policy.ReconstructionPolicy.lattice_below`).

    Raises
    ------
    MarkerError
        Bad or blank image, no reference marker, two equally large reference candidates, no grid.
    """
    if layout not in ("deflectometry", "calibration"):
        raise MarkerError(f"layout must be 'deflectometry' or 'calibration', got {layout!r}")
    mirrored = (layout == "deflectometry") if mirrored is None else bool(mirrored)
    spots = centroids(image, threshold=threshold, saturation=saturation)
    filt = filter_spots(
        spots,
        np.shape(image),
        region=region,
        area_range=area_range,
        region_margin=region_margin,
        reference_hint=reference_hint,
        reference=reference,
    )
    keep = np.flatnonzero(filt.keep)
    if len(keep) < 3:
        raise MarkerError(f"too few markers left after filtering ({len(keep)})")
    pts = spots.centroids[keep]
    ref = int(np.flatnonzero(keep == filt.reference)[0])
    axes = _grid_axes(image, pts, ref, layout, mirrored, hint)
    ij, found, indexing = _index(spots.centroids, keep, int(filt.reference), ref, axes, lattice_below)
    return _markers(spots, keep, ij, found, axes, filt.reasons, index_range, indexing)


def _seen_points(setup: Setup, points: Array) -> Array:
    """Pixel coordinates of pattern points seen directly (target) or in the plane mirror z = 0."""
    cam = setup.camera_model
    if setup.scene == "target":
        return cam.project(points)
    return cam.project(points * np.array([1.0, 1.0, -1.0]))


def expected_axes(setup: Setup) -> Array:
    """Image steps of the pattern's +T_x and +T_y at the reference marker, from the nominal setup.

    The reflecting element is taken as the flat plane z = 0 (the substrate's base plane, §1.10), so
    this is the thesis's coarse axis estimate made exact for an unbent substrate.
    """
    pat = setup.marker_pattern
    px = _seen_points(setup, pat.centers(np.array([[0, 0], [1, 0], [0, 1]])))
    return np.stack([px[1] - px[0], px[2] - px[0]])


def expected_reference(setup: Setup) -> Array:
    """Image (px) of the reference marker (0, 0) that the nominal setup predicts (flat reflector in z = 0)."""
    return _seen_points(setup, setup.marker_pattern.centers(np.array([[0, 0]])))[0]


def region_for_setup(setup: Setup, heights: HeightMap | None = None, per_side: int = 8) -> Region | None:
    """Image of the region where markers are reflected whole.

    Deflectometry: the substrate's region of interest (``|x| <= size_x/2``, ``|y| < roi_length/2``, §1.6.4);
    mirror: the mirror; calibration target: None (the markers lie on the target itself). The outline
    lies on the surface: points (x, y, h(x, y)) with ``heights`` (a current surface estimate or the
    truth), else on the flat base plane z = 0, where the thesis's 40 µm bow moves the outline's image by
    up to ~0.7 px. Each side is sampled with ``per_side`` points so lens distortion bends it correctly.
    """
    if setup.scene == "target":
        return None
    if setup.scene == "deflectometry":
        assert setup.substrate is not None
        hx, hy = 0.5 * setup.substrate.size[0], 0.5 * setup.substrate.roi_length
    else:
        assert setup.mirror is not None
        hx, hy = 0.5 * setup.mirror.size[0], 0.5 * setup.mirror.size[1]
    t = np.linspace(0.0, 1.0, per_side, endpoint=False)
    corners = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    sides = [corners[k] + t[:, None] * (corners[(k + 1) % 4] - corners[k]) for k in range(4)]
    outline = np.concatenate(sides)
    z = (
        np.zeros(len(outline))
        if heights is None or setup.scene != "deflectometry"
        else heights.height(outline[:, 0], outline[:, 1])
    )
    pts = np.concatenate([outline, z[:, None]], axis=1)
    px = setup.camera_model.project(pts)
    if not np.all(np.isfinite(px)):
        raise MarkerError("the reflecting region is not in front of the camera")
    return Region(px)


def index_range(setup: Setup) -> tuple[tuple[int, int], tuple[int, int]]:
    """Smallest and largest marker index along T_x and T_y of a setup's pattern."""
    ij = setup.marker_pattern.indices()
    return (int(ij[:, 0].min()), int(ij[:, 0].max())), (int(ij[:, 1].min()), int(ij[:, 1].max()))


def _markers(
    spots: Spots,
    keep: NDArray[np.int64],
    ij: NDArray[np.int64],
    found: NDArray[np.bool_],
    axes: Array,
    filtered: dict[str, int],
    index_range: tuple[tuple[int, int], tuple[int, int]] | None,
    indexing: str,
) -> Markers:
    """The indexed markers inside ``index_range``, with the count of rejected spots per reason."""
    reasons = dict(filtered)
    reasons["not_indexed"] = int((~found).sum())
    if index_range is not None:
        (i0, i1), (j0, j1) = index_range
        inside = (ij[:, 0] >= i0) & (ij[:, 0] <= i1) & (ij[:, 1] >= j0) & (ij[:, 1] <= j1)
        reasons["index_range"] = int((found & ~inside).sum())
        found &= inside
    sel = keep[found]
    return Markers(
        ij=ij[found],
        centroids=spots.centroids[sel],
        areas=spots.areas[sel],
        peak=spots.peak[sel],
        saturated=spots.saturated[sel],
        axes=axes,
        rejected=len(spots) - len(sel),
        reasons=reasons,
        spots=spots,
        indexing=indexing,
    )


def _grid_axes(image: NDArray, pts: Array, ref: int, layout: str, mirrored: bool, hint: Array | None) -> Array:
    """Image steps of +T_x, +T_y at the reference marker: from its neighbours on a calibration target (§2.6.1), from
    the Fourier transform of the image, oriented by ``hint``, on the deflectometry grid (§1.5.3)."""
    if layout == "calibration":
        return reference_axes(pts, ref, mirrored)
    h = hint if hint is not None else np.array([[1.0, 0.0], [0.0, 1.0 if mirrored else -1.0]])
    steps = fourier_axes(image, pts[ref], nearest_spacing(pts))
    return orient_axes(steps, np.asarray(h, dtype=np.float64))


def _index(
    centroids: Array, keep: NDArray[np.int64], reference: int, ref: int, axes: Array, lattice_below: float
) -> tuple[NDArray[np.int64], NDArray[np.bool_], str]:
    """Indices of the kept spots (§1.5.4): the thesis's flood (:func:`index_grid`), or where it numbers fewer than
    ``lattice_below`` of them the grid's topology (:func:`index_lattice`) if that numbers more. Returns the indices,
    which were numbered, and which indexing won."""
    pts = centroids[keep]
    ij = index_grid(pts, ref, axes, blockers=centroids)
    found = ij[:, 0] != np.iinfo(np.int32).min
    if found.sum() < lattice_below * len(keep):
        # the flood stopped early (a strongly bent substrate): number the grid by its topology instead, over every
        # spot of the image (a rejected spot still holds its place in the grid), and keep whichever reached more
        ij_lat = index_lattice(centroids, reference, axes)[keep]
        found_lat = ij_lat[:, 0] != np.iinfo(np.int32).min
        if found_lat.sum() > found.sum():
            return ij_lat, found_lat, "lattice"
    return ij, found, "flood"


def find_markers_for(image: NDArray, setup: Setup, heights: HeightMap | None = None, **kwargs) -> Markers:
    """:func:`find_markers` with layout, axis hint, view, region and index range from a setup.

    ``heights`` (a surface estimate) places the region's outline on the bent surface
    (:func:`region_for_setup`); keyword arguments override any option.
    """
    opts: dict[str, Any] = dict(
        layout=setup.marker_pattern.layout,
        hint=expected_axes(setup),
        mirrored=setup.scene != "target",
        region=region_for_setup(setup, heights),
        index_range=index_range(setup),
        reference_hint=expected_reference(setup),
    )
    opts.update(kwargs)
    return find_markers(image, **opts)
