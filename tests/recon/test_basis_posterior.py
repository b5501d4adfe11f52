"""The finite-basis posterior (:mod:`scopetwin.recon.basis_posterior`): the shifted basis as a Bayesian linear model.

Truth from elsewhere: the evidence and the posterior against the Gaussian linear model written out densely in the
observations' space (K = A Sigma_p A^T + B, solved densely); the prior's scale and noise recovered
from surfaces drawn from that very model with known parameters; the posterior's intervals covering draws of that
model; a rough surface handed to the Gaussian process; the §1.10 setup's own surface reconstructed from the exact
images of its marker centres plus centroid noise, its heights within the reported uncertainty.
"""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.recon.basis_posterior import (
    _Design,
    _evidence_and_gradient,
    basis_frame_model,
    basis_residual_correction,
    covering,
    fit_basis_prior,
)
from scopetwin.recon.posterior import BasisPrior, PosteriorError, prior_from_dict, recorded_prior

X_RANGE, Y_RANGE = (-12.6, 12.6), (-25.0, 25.0)  # the §1.10 substrate's extent, mm
ROI = 30.0  # its ROI length, mm


def _positions(step: float = 1.5, half_y: float = 23.0) -> np.ndarray:
    """A marker-like grid over the substrate (mm), slightly jittered."""
    xs = np.arange(-12.0, 12.01, step)
    ys = np.arange(-half_y, half_y + 0.01, step)
    xx, yy = np.meshgrid(xs, ys)
    xy = np.stack([xx.ravel(), yy.ravel()], axis=-1)
    return xy + 0.1 * np.random.default_rng(3).standard_normal(xy.shape)


def _draw(prior: BasisPrior, xy: np.ndarray, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coefficients drawn from ``prior`` and the noisy gradients they give at ``xy``."""
    rng = np.random.default_rng(seed)
    basis = covering(X_RANGE, Y_RANGE, prior.sigma)
    coef = rng.standard_normal(basis.n_terms) * prior.tau
    coef[basis.n_basis :] = rng.standard_normal(2) * 1e-3  # a tilt
    px, py = basis.derivatives(xy[:, 0], xy[:, 1])
    gx = px @ coef + prior.noise * rng.standard_normal(len(xy))
    gy = py @ coef + prior.noise_y * rng.standard_normal(len(xy))
    return coef, gx, gy


def _dense(prior: BasisPrior, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The model in the observations' space: the design A = [A_x; A_y], the prior deviations and K."""
    basis = covering(X_RANGE, Y_RANGE, prior.sigma)
    px, py = basis.derivatives(xy[:, 0], xy[:, 1])
    a = np.concatenate([px, py])
    s = np.full(basis.n_terms, prior.tau)
    s[basis.n_basis :] = 1e-2
    noise = np.concatenate([np.full(len(xy), prior.noise**2), np.full(len(xy), prior.noise_y**2)])
    return a, s, (a * s**2) @ a.T + np.diag(noise)


def test_the_evidence_and_its_gradient_are_the_gaussian_models() -> None:
    """The negative log evidence equals the Gaussian density of the gradients under K = A Sigma_p A^T + B (in the
    observations' space), and its closed-form gradient the finite differences of it."""
    xy = _positions(3.0)
    prior = BasisPrior(10.0, 4e-3, 3e-6, 1.5e-6)
    _, gx, gy = _draw(prior, xy, 1)
    a, s, k = _dense(prior, xy)
    design = _Design.of(covering(X_RANGE, Y_RANGE, prior.sigma), xy, gx, gy)
    theta = np.log([prior.tau, prior.noise**2, prior.noise_y**2])
    nll, grad = _evidence_and_gradient(theta, design)
    g = np.concatenate([gx, gy])
    _, logdet = np.linalg.slogdet(k)
    dense = 0.5 * g @ np.linalg.solve(k, g) + 0.5 * logdet + 0.5 * len(g) * np.log(2 * np.pi)
    assert nll == pytest.approx(dense, rel=1e-9)
    for j in range(3):
        step = np.zeros(3)
        step[j] = 1e-4
        fd = (_evidence_and_gradient(theta + step, design)[0] - _evidence_and_gradient(theta - step, design)[0]) / 2e-4
        assert grad[j] == pytest.approx(fd, rel=1e-4, abs=1e-2)


def test_the_frame_model_reads_the_gaussian_posterior_of_its_linear_model() -> None:
    """Contrast means and standard deviations on the node grid, and g^T K^-1 g, equal the dense Gaussian posterior
    of the same linear model (K^-1 by a dense solve)."""
    xy = _positions(2.5)
    prior = BasisPrior(8.0, 3e-3, 2e-6, 1e-6)
    _, gx, gy = _draw(prior, xy, 2)
    axes = (np.linspace(-12.6, 12.6, 11), np.linspace(-14.0, 14.0, 13))
    model = basis_frame_model(prior, xy, X_RANGE, Y_RANGE, ROI, axes, node_step=2.0)
    post = model.read(gx, gy)
    a, s, k = _dense(prior, xy)
    g = np.concatenate([gx, gy])
    basis = covering(X_RANGE, Y_RANGE, prior.sigma)
    nxx, nyy = np.meshgrid(post.node_x, post.node_y)
    gxx, gyy = np.meshgrid(*axes)
    e = basis.values(nxx.ravel(), nyy.ravel()) - basis.values(gxx.ravel(), gyy.ravel()).mean(axis=0)
    cross = (e * s**2) @ a.T  # cov(contrasts, g)
    mean = cross @ np.linalg.solve(k, g)
    var = np.einsum("ij,j,ij->i", e, s**2, e) - np.einsum("ij,ji->i", cross, np.linalg.solve(k, cross.T))
    scale = float(np.max(np.abs(mean)))
    assert np.max(np.abs(post.contrast_mean.ravel() - mean)) < 1e-8 * scale
    assert np.allclose(post.contrast_std.ravel(), np.sqrt(np.clip(var, 0, None)), rtol=1e-6, atol=1e-9 * scale)
    assert post.chi2 is not None
    assert post.chi2[0] == pytest.approx(float(g @ np.linalg.solve(k, g)), rel=1e-6)
    assert post.chi2[1] == len(g)


@pytest.mark.parametrize(("sigma", "seed"), [(12.0, 5), (18.0, 6), (10.0, 7)])
def test_the_evidence_recovers_the_scale_and_noise_a_surface_was_drawn_with(sigma: float, seed: int) -> None:
    """Surfaces drawn from the model at a known scale, tau and noise (x and y different): the evidence chooses that
    scale, tau within 35 % and the noise within 10 % (n = 527-like grid; seeds fixed beforehand)."""
    xy = _positions()
    truth = BasisPrior(sigma, 2e-3 * sigma / 12.0, 2e-6, 0.8e-6)
    _, gx, gy = _draw(truth, xy, seed)
    found = fit_basis_prior(xy, gx, gy, X_RANGE, Y_RANGE)
    assert found is not None
    prior, log_evidence = found
    assert prior.sigma == sigma
    assert prior.tau == pytest.approx(truth.tau, rel=0.35)
    assert prior.noise == pytest.approx(truth.noise, rel=0.1)
    assert prior.noise_y == pytest.approx(truth.noise_y, rel=0.1)
    assert np.isfinite(log_evidence)
    # the fixed-point iteration's optimum is a zero of the closed-form gradient
    design = _Design.of(covering(X_RANGE, Y_RANGE, sigma), xy, gx, gy)
    nll, grad = _evidence_and_gradient(np.log([prior.tau, prior.noise**2, prior.noise_y**2]), design)
    assert nll == pytest.approx(-log_evidence, rel=1e-12)
    assert np.max(np.abs(grad)) < 0.2, grad  # nats per unit of log parameter; measured 0.0003-0.048
    # warm: the same prior from an earlier frame's, in fewer scales
    again = fit_basis_prior(xy, gx, gy, X_RANGE, Y_RANGE, start=prior)
    assert again is not None and again[0].sigma == sigma


def test_a_surface_rougher_than_the_basis_is_left_to_the_gaussian_process() -> None:
    """Drawn at 3 mm (its evidence still rises at the finest scale, 8 mm): no finite-basis prior."""
    xy = _positions()
    basis = covering(X_RANGE, Y_RANGE, 3.0)
    rng = np.random.default_rng(9)
    px, py = basis.derivatives(xy[:, 0], xy[:, 1])
    coef = 2e-4 * rng.standard_normal(basis.n_terms)
    gx = px @ coef + 1e-6 * rng.standard_normal(len(xy))
    gy = py @ coef + 1e-6 * rng.standard_normal(len(xy))
    assert fit_basis_prior(xy, gx, gy, X_RANGE, Y_RANGE) is None


def test_the_intervals_cover_draws_of_the_model() -> None:
    """300 surfaces drawn from the prior: each node's contrast within 2 posterior standard deviations in 93-97 % of
    them (pooled over the nodes), and the frame criterion's D within 2 of its spread in 90-99 %."""
    xy = _positions(2.0)
    prior = BasisPrior(10.0, 3e-3, 2e-6, 1e-6)
    axes = (np.linspace(-12.6, 12.6, 26), np.linspace(-14.5, 14.5, 30))
    model = basis_frame_model(prior, xy, X_RANGE, Y_RANGE, ROI, axes, node_step=2.0)
    basis = model.design.basis
    nxx, nyy = np.meshgrid(model.node_x, model.node_y)
    nodes = basis.values(nxx.ravel(), nyy.ravel())
    f1, f2 = basis.values(*model.frame1.T), basis.values(*model.frame2.T)
    inside, d_inside = [], []
    for seed in range(300):
        coef, gx, gy = _draw(prior, xy, 1000 + seed)
        post = model.read(gx, gy)
        truth = nodes @ coef - model.roi_row @ coef
        inside.append(np.abs(truth - post.contrast_mean.ravel()) <= 2 * post.contrast_std.ravel())
        d_true = 0.5 * (np.max(f1 @ coef) + np.max(f2 @ coef)) - model.roi_row @ coef
        d_inside.append(abs(d_true - post.d_mean) <= 2 * post.d_std)
    assert 0.93 <= np.mean(inside) <= 0.97
    assert 0.90 <= np.mean(d_inside) <= 0.99


def test_the_residual_correction_is_the_posterior_mean_of_the_residuals() -> None:
    """The correction's heights are the posterior mean of the residual gradients' surface, zero on the ROI mean."""
    xy = _positions(2.5)
    prior = BasisPrior(8.0, 3e-3, 2e-6, 1e-6)
    _, ex, ey = _draw(prior, xy, 4)
    axes = (np.linspace(-12.6, 12.6, 11), np.linspace(-14.0, 14.0, 13))
    model = basis_frame_model(prior, xy, X_RANGE, Y_RANGE, ROI, axes, node_step=2.0)
    corr = basis_residual_correction(model, ex, ey)
    post = model.read(ex, ey)
    nxx, nyy = np.meshgrid(post.node_x, post.node_y)
    assert np.allclose(corr.height(nxx, nyy), post.contrast_mean, atol=1e-9 * float(np.max(np.abs(post.contrast_mean))))
    gxx, gyy = np.meshgrid(*axes)
    assert abs(float(np.mean(corr.height(gxx, gyy)))) < 1e-12
    with pytest.raises(PosteriorError, match="residual gradients"):
        basis_residual_correction(model, ex[:-1], ey[:-1])


def test_a_recorded_basis_prior_round_trips_and_is_checked() -> None:
    prior = BasisPrior(12.0, 3.8e-3, 2.05e-6, 1.01e-6)
    record = {"uncertainty": {"prior": prior.as_dict()}}
    assert recorded_prior(record, "a.json") == prior_from_dict(prior.as_dict())
    back = recorded_prior(record, "a.json")
    assert isinstance(back, BasisPrior)
    assert np.allclose([back.sigma, back.tau, back.noise, back.noise_y], [12.0, 3.8e-3, 2.05e-6, 1.01e-6], rtol=1e-12)
    bad = {"uncertainty": {"prior": {**prior.as_dict(), "coef_std_um": -1}}}
    with pytest.raises(PosteriorError, match=r"uncertainty\.prior\.coef_std_um must be a positive number"):
        recorded_prior(bad, "a.json")
    with pytest.raises(PosteriorError, match="kind must be 'process' or 'basis'"):
        recorded_prior({"uncertainty": {"prior": {**prior.as_dict(), "kind": "kronecker"}}}, "a.json")
