"""Focus maps from height maps: known surfaces give known piezo positions; the depth of field formula."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.recon.focusmap import FocusMapError, Objective, focus_map


def test_depth_of_field_of_the_seed_objective() -> None:
    obj = Objective()  # 10x, NA 0.45, 520 nm, 6.45 µm pixels
    assert obj.depth_of_field_um == pytest.approx(0.52 / 0.45**2 + 6.45 / (10 * 0.45), rel=1e-12)
    assert obj.field_of_view_mm == pytest.approx((1392 * 6.45e-4, 1040 * 6.45e-4))


def test_focus_positions_follow_a_known_tilted_surface() -> None:
    a, b = 2e-4, -5e-4  # mm/mm

    def h(x, y):
        return a * x + b * y

    fm = focus_map(h, (-12.6, 12.6), (-24.0, 24.0), reference_um=200.0, stage_offset_mm=(10.0, 5.0))
    assert np.allclose(fm.focus_um, 200.0 + 1e3 * (a * fm.x_mm + b * fm.y_mm), atol=1e-9)
    assert np.all(np.abs(fm.x_mm) <= 12.6) and np.all(np.abs(fm.y_mm) <= 24.0)
    assert np.allclose(fm.stage_x_mm - fm.x_mm, 10.0) and np.allclose(fm.stage_y_mm - fm.y_mm, 5.0)
    fov = Objective().field_of_view_mm
    spread = 1e3 * (abs(a) * fov[0] + abs(b) * fov[1])
    assert np.allclose(fm.spread_um, spread)
    assert fm.in_focus.all() == (spread <= fm.depth_of_field_um)
    rows = fm.to_csv().splitlines()
    assert rows[0].startswith("index,stage_x_mm") and len(rows) == len(fm.x_mm) + 1
    # serpentine raster: consecutive fields are neighbours
    steps = np.hypot(np.diff(fm.x_mm), np.diff(fm.y_mm))
    assert steps.max() <= max(fov) + 1e-9


def test_focus_outside_the_drive_travel_is_an_error() -> None:
    with pytest.raises(FocusMapError, match="outside the drive"):
        focus_map(lambda x, y: 0.3 + 0 * x, (-5, 5), (-5, 5), reference_um=200.0)
    with pytest.raises(FocusMapError, match="holds no"):
        focus_map(lambda x, y: 0 * x, (0, 0.1), (0, 0.1))


def test_focus_map_carries_each_fields_uncertainty_and_flags_wide_intervals():
    from scopetwin.recon.focusmap import focus_map

    def height(x, y):
        return 1e-4 * x + 0.0 * y  # 0.1 µm/mm tilt

    def std(x, y):  # uncertain on the y > 0 half only
        return np.where(y > 0, 2e-3, 1e-5) + 0.0 * x

    fm = focus_map(height, (-5.0, 5.0), (-5.0, 5.0), height_std=std)
    assert fm.std_um is not None and fm.std_um.shape == fm.focus_um.shape
    right = fm.y_mm - 0.0 > 0.5
    assert np.allclose(fm.std_um[right], 2.0) and np.all(fm.std_um[fm.y_mm < -0.5] < 0.02)
    # 95 % interval: spread/2 + 1.96 u must stay inside DOF/2
    expect = 0.5 * fm.spread_um + 1.96 * fm.std_um <= 0.5 * fm.depth_of_field_um
    assert np.array_equal(fm.interval_in_dof, expect)
    assert (~fm.interval_in_dof[right]).all() and fm.interval_in_dof[fm.y_mm < -0.5].all()
    head = fm.to_csv().splitlines()[0].split(",")
    assert head[-2:] == ["std_um", "interval_in_dof"]
    assert fm.summary()["fields_interval_leaves_dof"] == int((~fm.interval_in_dof).sum())
