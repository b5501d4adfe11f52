"""The basis scale chosen from the data (beyond the seed's fixed §1.8 scales): among the scales that fit, the one
that best extrapolates towards the holding frame (§1.4)."""

from __future__ import annotations

import numpy as np

from scopetwin.recon.config import ReconstructionConfig
from scopetwin.recon.shifted_basis import SBFSurface, fit_gradients
from scopetwin.recon.substrate import Substrate2D
from scopetwin.scenes.geometry import Array


def select_sigma(
    sub: Substrate2D, x: Array, y: Array, hx: Array, hy: Array, config: ReconstructionConfig
) -> tuple[float, dict[float, float], dict[float, float]]:
    """Basis scale from the data: among the scales that fit the data, the one that best extrapolates.

    A scale fits when its residual on all the gradients is at most ``config.fit_ratio`` times the smallest
    residual of the candidates (a basis too coarse for the surface — a 12 mm Gaussian on a 3 mm correlated
    glass — leaves hundreds of µrad and would otherwise win by extrapolating smoothly). Among those, for each end
    of the data along y the markers within ``config.holdout_band`` mm of the data's edge are held out, the basis
    is fitted to the rest, and the RMS gradient error on the held-out band is measured: the same extrapolation the
    frame criterion relies on (seed §1.4). The scale with the smallest RMS over both ends wins. Returns
    (sigma, {sigma: held-out score in µrad}, {sigma: residual of the fit to all gradients in µrad}).
    """
    scores: dict[float, float] = {}
    fits: dict[float, float] = {}
    ends = [y >= y.max() - config.holdout_band, y <= y.min() + config.holdout_band]
    for sigma in config.sigma_candidates or ():
        basis = config.make_basis(sub, sigma)
        coef, _ = fit_gradients(basis, x, y, hx, hy, config.regularization, method=config.method)
        gx, gy = SBFSurface(basis, coef).gradient(x, y)
        fits[float(sigma)] = float(np.sqrt(np.mean((gx - hx) ** 2 + (gy - hy) ** 2)) * 1e6)
        errs = []
        for test in ends:
            if test.all() or (~test).sum() * 2 < basis.n_terms // 4:
                continue
            coef, _ = fit_gradients(
                basis, x[~test], y[~test], hx[~test], hy[~test], config.regularization, method=config.method
            )
            gx, gy = SBFSurface(basis, coef).gradient(x[test], y[test])
            errs.append(np.mean((gx - hx[test]) ** 2 + (gy - hy[test]) ** 2))
        if errs:
            scores[float(sigma)] = float(np.sqrt(np.mean(errs)) * 1e6)
    if not scores:
        return float(config.sigma[0]), scores, fits
    floor = min(fits.values())
    fitting = [s for s in scores if fits[s] <= config.fit_ratio * floor] or list(scores)
    return min(fitting, key=scores.__getitem__), scores, fits
