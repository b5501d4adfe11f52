"""The frame criterion of the outer loop (thesis §1.4, eqs. 1.3-1.4), public in recon and used by the reconstructor."""

from __future__ import annotations

import pytest

from scopetwin.recon.frame_criterion import frame_criterion, frame_distance


def test_delta_is_the_difference_of_the_frame_maxima() -> None:
    # eq. 1.3: Delta h_max = max_region1 - max_region2, whatever the frame position
    assert frame_criterion(0.012, 0.004, frame_z=0.5, criterion="delta") == pytest.approx(0.008)
    assert frame_criterion(0.004, 0.012, frame_z=-3.0, criterion="delta") == pytest.approx(-0.008)


def test_level_is_the_mean_frame_maximum_above_the_frame() -> None:
    assert frame_criterion(0.012, 0.004, frame_z=0.0) == pytest.approx(0.008)
    assert frame_criterion(0.012, 0.004, frame_z=0.008, criterion="level") == pytest.approx(0.0)
    # a surface resting on the frame with no tilt satisfies both criteria
    assert frame_criterion(0.25, 0.25, 0.25, "level") == 0.0
    assert frame_criterion(0.25, 0.25, 0.25, "delta") == 0.0


def test_a_tilted_surface_on_the_frame_fails_delta_but_a_raised_one_fails_level() -> None:
    tilted = (0.010, -0.010)  # mean on the frame, one end up, one down
    raised = (0.010, 0.010)  # level but 10 µm above the frame
    assert frame_criterion(*tilted, 0.0, "level") == pytest.approx(0.0)
    assert frame_criterion(*tilted, 0.0, "delta") == pytest.approx(0.020)
    assert frame_criterion(*raised, 0.0, "delta") == 0.0
    assert frame_criterion(*raised, 0.0, "level") == pytest.approx(0.010)


def test_d_min_is_the_signed_distance_of_the_closer_maximum() -> None:
    assert frame_distance(0.003, -0.010, 0.0) == pytest.approx(0.003)
    assert frame_distance(0.030, -0.010, 0.0) == pytest.approx(-0.010)
    assert frame_distance(1.004, 1.002, 1.0) == pytest.approx(0.002)


def test_unknown_criterion_is_rejected() -> None:
    with pytest.raises(ValueError, match="level"):
        frame_criterion(0.0, 0.0, 0.0, "median")  # type: ignore[arg-type]


def test_the_reconstructor_records_the_frame_criterion() -> None:
    from scopetwin.recon.config import ReconstructionConfig
    from scopetwin.recon.reconstruct import MarkerObservations
    from scopetwin.recon.strategy import reconstruct_markers as reconstruct
    from scopetwin.scenes.setup import load_setup
    from scopetwin.sim.surfaces import make_surface
    from scopetwin.sim.truth import marker_truth

    setup = load_setup("thesis-1.10-deflectometry")
    spec = setup.substrate.surface.model_copy(update={"kind": "cylinder", "range_um": 40.0})
    heights = make_surface(spec, setup.substrate)
    t = marker_truth(setup, heights)
    res = reconstruct(
        setup, MarkerObservations(t.ij[t.visible], t.center_px[t.visible]), config=ReconstructionConfig.realtime()
    )
    for step in res.history:
        m1, m2 = step.max_region1_um * 1e-3, step.max_region2_um * 1e-3
        assert step.criterion_um == pytest.approx(frame_criterion(m1, m2, 0.0, "level") * 1e3, abs=1e-9)
    assert abs(res.history[-1].criterion_um) <= ReconstructionConfig.realtime().outer_tol_um
