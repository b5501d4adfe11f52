"""Phase-shift decoding (recon/fringes/phase.py) against known phases and the §1.10 setup's per-pixel truth.

Acceptance: the N-step phase noise equals sqrt(2/N) sigma_I / B within 10 %; the decoded display points of the
thesis setup agree with the truth map ``pattern_xy`` to 2 µm RMS with normalised errors of unit spread; pixels that
see no fringes, or whose periods disagree, are flagged; bad input is one clear error.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))
from fringe_cases import PERIODS, capture, seen, thesis_setup, truth  # noqa: E402

from scopetwin.recon.fringes.phase import (  # noqa: E402
    FringeDecodingError,
    NoiseModel,
    PhaseMap,
    decode_display,
    fit_noise_model,
    phase_shift,
    phase_shifts,
    unwrap_temporal,
)


@pytest.mark.parametrize("steps", [4, 8])
def test_phase_noise_follows_sqrt_2_over_n(steps):
    rng = np.random.default_rng(4)
    n = 200_000
    phi = rng.uniform(-np.pi, np.pi, n)
    a, b, sigma = 1000.0, 600.0, 20.0
    frames = a + b * np.cos(phi[None, :] + phase_shifts(steps)[:, None]) + rng.normal(0, sigma, (steps, n))
    pm = phase_shift(frames, sigma)
    err = np.angle(np.exp(1j * (pm.phase - phi)))
    expected = np.sqrt(2.0 / steps) * sigma / b
    assert abs(np.median(pm.phase_std) / expected - 1) < 0.01  # (B estimated per pixel: its noise spreads it)
    assert abs(err.std() / expected - 1) < 0.1
    assert abs(np.mean(pm.background) - a) < 0.5 and abs(np.mean(pm.modulation) - b) < 0.5
    model = fit_noise_model([frames])
    assert abs(np.sqrt(model.read + model.shot * a) / sigma - 1) < 0.05


def test_decoded_display_points_match_the_truth_map():
    setup = thesis_setup()
    _, maps = truth(setup)
    frames = capture(setup, maps, seed=11)
    coords = decode_display(frames.x, frames.y, PERIODS, tuple(setup.pattern.size))
    ok = seen(maps)
    assert np.array_equal(coords.valid, ok)  # every seen pixel decoded, nothing else
    err = np.stack([coords.u, coords.v], axis=-1)[ok] - maps["pattern_xy"][ok]
    std = np.stack([coords.u_std, coords.v_std], axis=-1)[ok]
    assert np.sqrt(np.mean(err**2)) < 2e-3  # mm: 2 µm RMS at 4 steps, 1 mm finest period
    z = err / std
    assert np.all(np.abs(z.std(axis=0) - 1.0) < 0.1) and np.abs(z).max() < 6.0
    assert coords.low_modulation[~ok].all()


def test_unwrapping_flags_a_wrong_fringe_order():
    p = np.array([64.0, 8.0, 1.0])
    u = np.array([3.3, -7.9, 12.45])
    zero = np.zeros(3)
    maps = [PhaseMap(np.angle(np.exp(2j * np.pi * u / pk)), zero + 1, zero + 1, zero + 1e-3, zero) for pk in p]
    out = unwrap_temporal(maps, p)
    assert np.allclose(out.coordinate, u) and out.consistent.all()
    # the middle period's phase off by half a period at one pixel: the finest order cannot be trusted there
    bad = [
        maps[0],
        PhaseMap(maps[1].phase + np.array([0, np.pi, 0]), *(zero + 1, zero + 1, zero + 1e-3, zero)),
        maps[2],
    ]
    assert unwrap_temporal(bad, p).consistent.tolist() == [True, False, True]


def test_bad_input_is_one_clear_error():
    frames = np.zeros((3, 4, 4))
    with pytest.raises(FringeDecodingError, match="at least 4 steps"):
        phase_shift(frames, 1.0)
    good = [np.ones((4, 4, 4))]
    with pytest.raises(FringeDecodingError, match="coarsest period"):
        decode_display(good, good, [40.0], (50.0, 50.0), noise=NoiseModel(1.0, 0.0))
    with pytest.raises(FringeDecodingError, match="strictly decreasing"):
        unwrap_temporal([phase_shift(good[0], 1.0)] * 2, [8.0, 64.0])
