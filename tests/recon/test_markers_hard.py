"""Marker identification where it used to fail: low exposures, strongly bent substrates.

Indices are checked against :mod:`scopetwin.sim.truth`: a marker is wrongly indexed when the true image nearest to its
centroid belongs to another marker (centroid bias on a strongly bent substrate reaches ~2 px, a pitch is ~20 px).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from scopetwin.recon.markers import MarkerError, find_markers_for
from scopetwin.scenes.setup import load_setup
from scopetwin.sim.measurement import apply_sensor
from scopetwin.sim.surfaces import surface_for
from scopetwin.sim.truth import marker_truth


def _wrong_indices(markers, truth) -> int:
    ok = truth.converged
    _, nearest = cKDTree(truth.center_px[ok]).query(markers.centroids)
    return int(np.any(truth.ij[ok][nearest] != markers.ij, axis=1).sum())


@pytest.mark.mitsuba
def test_low_exposure_calibration_view_finds_every_marker():
    """2 % and 5 % of the full well at the peak (``study noise`` lost both: 'no reference marker')."""
    from scopetwin.scenes.mitsuba.render import render_setup

    setup = load_setup("thesis-2.8.3-substrate")
    truth = marker_truth(setup)
    clean = render_setup(setup, None, spp=8, seed=2)
    for fill, seed in ((0.02, 5), (0.05, 6)):
        noisy = load_setup("thesis-2.8.3-substrate", {"sensor": {"fill_fraction": fill}})
        markers = find_markers_for(apply_sensor(noisy, clean, seed), setup)
        assert len(markers) == 99, fill
        assert _wrong_indices(markers, truth) == 0
        # noise fragments no longer eat into the marker windows: centroids stay within 0.25 px of the truth
        key = {tuple(k): n for n, k in enumerate(truth.ij.tolist())}
        err = markers.centroids - truth.center_px[[key[tuple(k)] for k in markers.ij.tolist()]]
        assert np.abs(err).max() < 0.25, fill


@pytest.mark.mitsuba
@pytest.mark.slow
@pytest.mark.parametrize("seed, indexing", [(2, "lattice"), (3, "flood"), (4, "flood")])
def test_strongly_bent_substrate_indexed_without_wrong_indices(seed, indexing):
    """3 mm correlation, 60 µm: spots 3-5x magnified in places ('two equally large reference candidates').

    Seed 4 has a row squeezed to no spot at all between compressed rows; the flood stepped across it (6 wrong
    indices) until steps were checked per axis against the local basis (``index_grid``'s ``axis_tol``). On seed 2
    the grid's image step changes from 20 to 47 px across the reference marker: the flood reached 12 markers (1
    with sensor noise), the topological indexing (``index_lattice``) that takes over reaches ~450.
    """
    from scopetwin.scenes.mitsuba.render import render_setup

    over = {"substrate": {"surface": {"correlation_length": 3.0, "range_um": 60.0, "seed": seed}}}
    setup = load_setup("thesis-1.10-deflectometry", over)
    heights = surface_for(setup)
    truth = marker_truth(setup, heights)
    markers = find_markers_for(render_setup(setup, heights, spp=4, seed=1), setup)
    assert markers.indexing == indexing
    assert _wrong_indices(markers, truth) == 0
    assert len(markers) >= 0.8 * truth.visible.sum()


def test_tied_reference_candidates_say_what_to_change():
    """Two equally large candidates near the nominal reference image: one error line that says what to do."""
    from scopetwin.recon.markers.filtering import find_reference

    pts = np.array([[100.0, 100.0], [110.0, 100.0], [300.0, 300.0]])
    ratio = np.array([2.0, 1.9, 5.0])
    with pytest.raises(MarkerError, match="nominal image.*place the reference marker"):
        find_reference(ratio, np.ones(3, dtype=bool), pts, expected=np.array([105.0, 100.0]), radius=30.0)
    # the far, larger spot does not win against a lone candidate at the nominal position
    assert (
        find_reference(ratio[1:], np.ones(2, dtype=bool), pts[1:], expected=np.array([105.0, 100.0]), radius=30.0) == 0
    )


@pytest.mark.mitsuba
@pytest.mark.slow
def test_tied_reference_marker_decided_by_the_lattice_offset() -> None:
    """3 mm / 60 µm surface seed 7: four spots about as large as the reference marker should be near its nominal
    image. Taken as the reference in turn, only the true one numbers the markers on the lattice's predicted image,
    and it is decided before any reconstruction runs."""
    from scopetwin.recon.markers import ReferenceTieError
    from scopetwin.recon.strategy import reconstruct_image
    from scopetwin.recon.substrate import Substrate2D
    from scopetwin.scenes.mitsuba.render import render_setup
    from scopetwin.sim.pipeline import roi_errors

    over = {"substrate": {"surface": {"correlation_length": 3.0, "range_um": 60.0, "seed": 7}}}
    setup = load_setup("thesis-1.10-deflectometry", over)
    heights = surface_for(setup)
    truth = marker_truth(setup, heights)
    image = render_setup(setup, heights, spp=4, seed=1)
    with pytest.raises(ReferenceTieError) as tie:
        find_markers_for(image, setup)
    assert len(tie.value.candidates) >= 2
    markers, result, _ = reconstruct_image(image, setup)  # the default policy: bias step, tie resolved
    assert result.strategy[0].startswith("reference marker tied between"), result.strategy
    assert "lattice's predicted image taken" in result.strategy[0]
    true_ref = truth.center_px[np.flatnonzero(np.all(truth.ij == 0, axis=1))[0]]
    assert np.hypot(*(markers.centroids[np.all(markers.ij == 0, axis=1)][0] - true_ref)) < 3.0
    assert _wrong_indices(markers, truth) <= 0.01 * len(markers)
    assert roi_errors(result.surface.height, heights, Substrate2D.from_setup(setup))["roi_shape_um"] < 0.3
