"""Marker patterns (thesis §1.6.3, §2.2): layouts, indices, grey values."""

import numpy as np
import pytest

from scopetwin.scenes.errors import GeometryError
from scopetwin.scenes.geometry import Frame
from scopetwin.scenes.pattern import MarkerPattern


def _p(n_x, n_y, layout, **kw):
    args = dict(pitch_x=1.5, pitch_y=1.5, radius=0.5, ref_radius=0.7)
    args.update(kw)
    return MarkerPattern(Frame.identity(), n_x, n_y, layout=layout, **args)


def test_odd_deflectometry_pattern_has_reference_at_centre():
    p = _p(33, 33, "deflectometry", size_x=50, size_y=50)
    ij = p.indices()
    assert ij.min() == -16 and ij.max() == 16 and len(ij) == 33 * 33
    np.testing.assert_allclose(p.centers_local([[0, 0], [3, -2]]), [[0, 0], [4.5, -3.0]])
    assert p.radii([[0, 0]])[0] == 0.7 and p.radii([[1, 0]])[0] == 0.5


def test_even_deflectometry_pattern_marker_zero_left_edge_at_centre():
    p = _p(4, 4, "deflectometry")
    np.testing.assert_allclose(p.centers_local([[0, 0], [-2, 1]]), [[0.75, 0.75], [-2.25, 2.25]])
    # the cell of marker 0 starts at the centre (thesis: IX = floor(x/ms_x))
    assert tuple(p.nearest_index(np.array([0.01, 0.01]))) == (0, 0)
    assert tuple(p.nearest_index(np.array([-0.01, 1.6]))) == (-1, 1)


def test_calibration_pattern_reference_in_minus_corner():
    p = _p(11, 9, "calibration", pitch_x=4.0, pitch_y=4.0, radius=1.0, ref_radius=1.4)
    c = p.centers_local()
    ref = c[(p.indices() == [0, 0]).all(axis=1)][0]
    np.testing.assert_allclose(ref, [-20.0, -16.0])
    np.testing.assert_allclose(c.mean(axis=0), [0, 0], atol=1e-12)


def test_grey_value_fades_linearly():
    p = _p(3, 3, "deflectometry")
    g = p.grey_local(np.array([[0, 0], [0.35, 0], [1.5 + 0.25, 0], [1.5 + 0.6, 0], [10, 10]]))
    np.testing.assert_allclose(g, [1.0, 0.5, 0.5, 0.0, 0.0])


@pytest.mark.parametrize(
    ("kw", "message"),
    [
        (dict(pitch_x=-1.5), "pitch_x must be > 0"),
        (dict(radius=0.7, ref_radius=0.9), "markers overlap"),
        (dict(ref_radius=0.3), "ref_radius"),
        (dict(size_x=2.0), "smaller than its marker grid"),
    ],
)
def test_bad_patterns_raise(kw, message):
    with pytest.raises(GeometryError, match=message):
        _p(5, 5, "deflectometry", **kw)
