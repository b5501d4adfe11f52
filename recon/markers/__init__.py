"""Marker identification in camera images (thesis §1.5 for the deflectometry grid, §2.6 for the calibration grid).

Four steps, as in the thesis, each a module named after its section:

1. :mod:`scopetwin.recon.markers.centroid_search` — centroid search (§1.5.1): background level and noise from the image,
   threshold, connected components (OpenCV), grey-value-weighted centre of mass (:func:`centroids`, :class:`Spots`).
2. :mod:`scopetwin.recon.markers.filtering` — marker filtering (§1.5.2): area against the median area of the
   neighbouring
   spots, spots touching the image border or leaving the reflecting :class:`Region` (partially reflected markers),
   spots with a clipped edge; the reference marker (:func:`find_reference`, :func:`filter_spots`).
3. :mod:`scopetwin.recon.markers.grid_identification` — grid identification: :func:`fourier_axes` (deflectometry,
   §1.5.3)
   and :func:`reference_axes` (calibration, §2.6.1), the image vectors of one pitch step along T_x and T_y.
4. :mod:`scopetwin.recon.markers.indexing` — marker indexing (§1.5.4): :func:`index_grid`, a flood from the reference
   marker [0, 0] through the eight neighbours of each marker, the steps re-estimated locally as it proceeds; and
   :func:`index_lattice`, a flood over mutual axial neighbours (the grid's topology), where a strongly bent substrate
   stretches and squeezes the reflected grid too much for the flood's predictions.

:mod:`scopetwin.recon.markers.identification` runs all four (:func:`find_markers`) and takes their options from a setup
(:func:`find_markers_for`, :func:`region_for_setup`); :mod:`scopetwin.recon.markers.worker` runs that search one frame
at a time in a worker process (:class:`MarkerWorker`, the live loop's, :mod:`scopetwin.recon.stream`). This package's
namespace is that public API.

Coordinates are continuous pixel coordinates (col, row): pixel (r, c) covers [c, c+1) x [r, r+1)
(docs/contract.md, "Camera"). Indices (i, j) count pitches along the pattern's own T_x, T_y
(docs/contract.md, "Marker indices").
"""

from scopetwin.recon.markers.centroid_search import MarkerError, Spots, background_level, centroids, check_image
from scopetwin.recon.markers.filtering import (
    Filtered,
    ReferenceTieError,
    Region,
    filter_spots,
    find_reference,
    local_area_ratio,
    rim_clearance,
)
from scopetwin.recon.markers.grid_identification import fourier_axes, nearest_spacing, orient_axes, reference_axes
from scopetwin.recon.markers.identification import (
    Markers,
    expected_axes,
    expected_reference,
    find_markers,
    find_markers_for,
    index_range,
    region_for_setup,
)
from scopetwin.recon.markers.indexing import index_grid, index_lattice
from scopetwin.recon.markers.worker import MarkerWorker

__all__ = [
    "Filtered",
    "MarkerError",
    "MarkerWorker",
    "Markers",
    "ReferenceTieError",
    "Region",
    "Spots",
    "background_level",
    "centroids",
    "check_image",
    "expected_axes",
    "expected_reference",
    "filter_spots",
    "find_markers",
    "find_markers_for",
    "find_reference",
    "fourier_axes",
    "index_grid",
    "index_lattice",
    "index_range",
    "local_area_ratio",
    "nearest_spacing",
    "orient_axes",
    "reference_axes",
    "region_for_setup",
    "rim_clearance",
]
