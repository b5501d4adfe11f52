"""The basis scale's choice from the data (:func:`scopetwin.recon.scale.select_sigma`): its scores against fits made
independently by least squares, and the same choice on any number of threads."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.recon.config import ReconstructionConfig
from scopetwin.recon.reconstruct import Reconstructor
from scopetwin.recon.scale import select_sigma
from scopetwin.recon.shifted_basis import fit_gradients
from scopetwin.scenes.setup import load_setup

SETUP = load_setup("thesis-1.10-deflectometry")


def _data() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Gradients of a known surface, a bow with 7 mm waviness (mm), at a jittered 1.5 mm grid over the ROI and a
    little beyond, with 1 µrad of noise (seeded)."""
    rng = np.random.default_rng(3)
    gx, gy = np.meshgrid(np.arange(-16.5, 16.6, 1.5), np.arange(-18.0, 18.1, 1.5))
    x = gx.ravel() + rng.uniform(-0.2, 0.2, gx.size)
    y = gy.ravel() + rng.uniform(-0.2, 0.2, gy.size)
    k = 2 * np.pi / 7.0
    hx = -2 * 2e-5 * x + 3e-4 * k * np.cos(k * x) * np.cos(0.6 * k * y) + rng.normal(0, 1e-6, x.size)
    hy = -2 * 1e-5 * y - 3e-4 * 0.6 * k * np.sin(k * x) * np.sin(0.6 * k * y) + rng.normal(0, 1e-6, x.size)
    return x, y, hx, hy


def test_scores_are_the_held_out_errors_of_least_squares_fits() -> None:
    rec = Reconstructor.from_setup(SETUP, ReconstructionConfig(sigma_candidates=(2.0, 4.0, 8.0, 15.0)))
    cfg = rec.config
    x, y, hx, hy = _data()
    best, scores, fits = select_sigma(rec.sub, x, y, hx, hy, cfg)
    ends = [y >= y.max() - cfg.holdout_band, y <= y.min() + cfg.holdout_band]
    for sigma in scores:
        basis = cfg.make_basis(rec.sub, sigma)
        _, rms = fit_gradients(basis, x, y, hx, hy, cfg.regularization)
        assert fits[sigma] == pytest.approx(np.sqrt(2.0) * rms * 1e6, rel=1e-4)
        errs = []
        for test in ends:
            coef, _ = fit_gradients(basis, x[~test], y[~test], hx[~test], hy[~test], cfg.regularization)
            px, py = basis.derivatives(x[test], y[test])
            errs.append(np.mean((px @ coef - hx[test]) ** 2 + (py @ coef - hy[test]) ** 2))
        assert scores[sigma] == pytest.approx(np.sqrt(np.mean(errs)) * 1e6, rel=1e-4)
    assert best == 4.0  # the waviness's scale: 2 mm extrapolates worse, 8 and 15 mm do not fit it
    assert fits[15.0] > cfg.fit_ratio * min(fits.values())


def test_the_choice_does_not_depend_on_the_threads() -> None:
    rec = Reconstructor.from_setup(SETUP, ReconstructionConfig())
    x, y, hx, hy = _data()
    one = select_sigma(rec.sub, x, y, hx, hy, rec.config, max_threads=1)
    two = select_sigma(rec.sub, x, y, hx, hy, rec.config, max_threads=2)
    assert one == two  # the same arrays, to the last bit
