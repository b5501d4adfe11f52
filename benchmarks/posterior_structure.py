"""What structure a finite-basis or low-rank posterior could use: the evidence-chosen prior's gradient covariance on
the marker data, split into its parts, one surface per family.

Run: ``.venv/bin/python benchmarks/posterior_structure.py [--families gauss,glass] [--seed 9100]`` (about a minute).

For each family of :mod:`scopetwin.sim.families` (the seed fixed before any tuning) the §1.10 setup's exact marker
images plus 0.005 px of centroid noise are reconstructed with the defaults (the ``coverage`` study's inputs), and the
prior its posterior step chose (:attr:`scopetwin.recon.uncertainty.Uncertainty.hyper`) is read back. On the gradients
traced through the result (n markers, 2n observations) it prints:

* ``rank>noise``: how many eigenvalues of the smooth part's 2n x 2n gradient covariance (with the local features'
  part where chosen) exceed the gradient noise variance — the directions the data resolve, the rank a low-rank
  (Nystroem, inducing-point) smooth part needs — and ``rank>1e-3``, above a thousandth of it;
* ``broad corr``: the broadband part's largest correlation between two different observations, and ``broad off``:
  the Frobenius norm of its off-diagonal part over its diagonal's (0: it acts on the data as independent noise);
* ``HS m``, ``box c``, ``HS nats``: the fewest Laplacian eigenfunctions of a Hilbert-space finite basis (Riutort-Mayol
  et al., Statistics and Computing 33, 2023) whose smooth part gives the evidence of the traced gradients within
  :data:`HS_NATS` of the exact kernel's (the broadband part, the noise and the tilt exact in both): boxes of c times
  the substrate's half extents (:data:`BOXES`), once and twice the paper's rule of thumb (1.75 c L / l per axis, l
  the smooth part's shortest length), and the evidence's difference there;
* ``dense GF``: the flops of a dense Cholesky factor, (2n)^3 / 3.

and, timed on one BLAS thread (minimum of :data:`REPEATS`), what one evidence evaluation's factorisations cost each way:

* ``dense ms``: the Cholesky factor and the inverse (LAPACK potrf + potri, what the evidence's gradient reads) of the
  whole 2n x 2n gradient covariance, as :func:`scopetwin.recon.posterior.fit_hyper` does now;
* ``struct ms``: the least a structured evaluation needs: the sparse LU factor (SuperLU) of the broadband part plus
  the noise, entries below :data:`SPARSE_CUT` of the diagonal dropped, its solve against the ``HS m`` basis columns
  and the Cholesky factor of the m x m matrix that leaves. It leaves out what the gradient would add (the broadband
  part's selected inverse, which SciPy does not offer), so it is a floor.

It measures how far a structured posterior could cut the work, for the choice between one.
Measured at seed 9100 (441-529 markers, 882-1058 observations; this machine, 2 cores): the smooth part resolves 21-125
directions above the noise (glass 456: its rational-quadratic part reaches 2.4 mm). Its lengths (6-29 mm) are near the
substrate's own size, so the paper's box (c = 1.2) and count are far from enough: the evidence was 290 (glass) to 9
million nats off (steep); within a nat (1.1 on gauss+broadband) it took c = 2.5-4 and twice the count, 98-336 functions
on five families, 798 on cut and 4784 on glass. The broadband part is short (0.25-0.45 mm; neighbouring markers
correlated by at most 0.35) on five families, 0.79 mm on gauss (0.47) and 2.1 mm on cut, where it is a second smooth
part (0.90). The factorisations of one evaluation: dense 20-32 ms; the structured floor 2.2 ms (features), 8-17 ms
(steep, gauss+broadband, gauss), 24 ms (power+broadband), 0.22 s (cut) and 1.8 s (glass, 4784 columns). So a finite-
basis structured posterior would gain 1.3-14x on five families and lose 9x on cut and 60x on glass, and it is an
approximation (within a nat) where the dense one is exact.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import time  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

FAMILIES = ("gauss", "gauss+broadband", "power+broadband", "glass", "cut", "steep", "features")
#: Hilbert-space boxes tried, as multiples c of the substrate's half extents (Riutort-Mayol et al. 2023 use c >= 1.2;
#: a smooth length near the substrate's own size needs more).
BOXES = (1.2, 2.5, 4.0)
#: The evidence of a Hilbert-space smooth part must lie within this many nats of the exact kernel's.
HS_NATS = 1.0
#: Most Hilbert-space functions tried (memory: 2n x m doubles).
HS_MAX = 6000
#: Entries of the broadband part below this fraction of the geometric mean of their two variances are dropped for the
#: sparse factor (a tolerance far below the noise: the part's correlations that matter are 1e-2 and up).
SPARSE_CUT = 1e-6
#: Timed repeats of each factorisation; the minimum is printed.
REPEATS = 20


def _kernel(xy: np.ndarray, comps: list[tuple[float, float]]) -> np.ndarray:
    """The gradient covariance [f_x; f_y] of squared-exponential components (amplitude mm, length mm), without the
    tilt or the noise: :mod:`scopetwin.recon.posterior`'s own pieces, its tilt taken off again."""
    from scopetwin.recon.posterior import TILT_STD, _assemble, _Pairs, _se_pieces

    pairs = _Pairs.of(xy)
    k = _assemble(_se_pieces(pairs, [c for c in comps if c[0] > 0])[0], pairs, 0.0, 0.0)
    n = len(xy)
    k[:n, :n] -= TILT_STD**2
    k[n:, n:] -= TILT_STD**2
    return k


def _traced(family: str, seed: int) -> tuple[np.ndarray, np.ndarray, Any, list[float]]:
    """The family's surface reconstructed with the defaults: the traced gradients' positions relative to the
    substrate's centre (n, 2), the gradients [f_x; f_y] (2n,), the prior the posterior chose and the half extents."""
    from scopetwin.recon.config import ReconstructionConfig
    from scopetwin.recon.posterior import Hyper
    from scopetwin.recon.reconstruct import MarkerObservations, Reconstructor, single_thread_blas
    from scopetwin.recon.strategy import solve
    from scopetwin.scenes.setup import load_setup
    from scopetwin.sim.families import family_spec
    from scopetwin.sim.surfaces import surface_for
    from scopetwin.sim.truth import marker_truth

    setup = load_setup("thesis-1.10-deflectometry", {"substrate": {"surface": family_spec(family, seed)}})
    heights = surface_for(setup)
    assert heights is not None
    truth = marker_truth(setup, heights)
    vis = truth.visible
    px = truth.center_px[vis] + 0.005 * np.random.default_rng([seed, 7]).standard_normal((int(vis.sum()), 2))
    rec = Reconstructor.from_setup(setup, ReconstructionConfig(prior="process"))  # the process's parts
    obs = MarkerObservations(truth.ij[vis], px)
    with single_thread_blas():
        res = solve(rec, obs)
    assert res.uncertainty is not None
    xy, hx, hy, _ = rec.traced_gradients(res.surface, obs)
    ranges = (rec.sub.x_range, rec.sub.y_range)
    centre = np.array([0.5 * (a + b) for a, b in ranges])
    return (
        xy - centre,
        np.concatenate([hx, hy]),
        Hyper.from_dict(res.uncertainty.hyper),
        [0.5 * (b - a) for a, b in ranges],
    )


def one(family: str, seed: int) -> dict[str, float]:
    from scopetwin.recon.posterior import _smooth_components, gradient_kernel

    xy, g, hyper, half = _traced(family, seed)
    smooth = _smooth_components(hyper) + ([(hyper.feature_amp, hyper.feature_len)] if hyper.feature_amp > 0 else [])
    noise2 = float(np.mean(np.square(hyper.noise_pair)))
    ks = _kernel(xy, smooth)
    ev = np.linalg.eigvalsh(ks)
    kb = _kernel(xy, [(hyper.broad_amp, hyper.broad_len)])
    d = np.sqrt(np.diag(kb))
    corr = kb / np.outer(d, d)
    np.fill_diagonal(corr, 0.0)
    off = kb - np.diag(np.diag(kb))
    n, n2 = len(xy), 2 * len(xy)
    noise = np.repeat(np.square(hyper.noise_pair), n)
    exact = gradient_kernel(xy, hyper)  # the posterior's own covariance of the data
    rest = exact - ks  # the broadband part, the noise and the (unpenalised) tilt
    m, box, nats, phi = _hs_accurate(xy, g, smooth, exact, rest, half)
    return {
        "n": n,
        "rank_noise": int(np.sum(ev > noise2)),
        "rank_milli": int(np.sum(ev > 1e-3 * noise2)),
        "broad_corr": float(np.abs(corr).max()),
        "broad_off": float(np.linalg.norm(off) / np.linalg.norm(np.diag(kb))),
        "broad_len": hyper.broad_len,
        "smooth_len": min(length for _, length in smooth),
        "hs_m": m,
        "hs_box": box,
        "hs_nats": nats,
        "dense_gflop": n2**3 / 3 * 1e-9,
        "dense_ms": _dense_ms(exact),
        "struct_ms": _structured_ms(kb, noise, phi),
    }


def _hs_gradients(xy: np.ndarray, half: list[float], m_axes: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """The gradients [d/dx; d/dy] of the first ``m_axes`` Laplacian eigenfunctions per axis on the box of half
    extents ``half`` (Dirichlet), at ``xy`` (2n, m), and their eigenvalues |omega|^2 (m,)."""
    w = [np.pi * np.arange(1, k + 1) / (2.0 * h) for k, h in zip(m_axes, half, strict=True)]
    arg = [w[a][None, :] * (xy[:, a : a + 1] + half[a]) for a in (0, 1)]
    s, c = [np.sin(t) for t in arg], [np.cos(t) * w[a][None, :] for a, t in enumerate(arg)]
    norm = 1.0 / np.sqrt(half[0] * half[1])
    gx = (c[0][:, :, None] * s[1][:, None, :]).reshape(len(xy), -1) * norm
    gy = (s[0][:, :, None] * c[1][:, None, :]).reshape(len(xy), -1) * norm
    return np.concatenate([gx, gy]), (w[0][:, None] ** 2 + w[1][None, :] ** 2).ravel()


def _nll(k: np.ndarray, g: np.ndarray) -> float:
    """The negative log evidence of gradients ``g`` under covariance ``k`` (without the constant)."""
    low = np.linalg.cholesky(k)
    a = np.linalg.solve(low, g)
    return float(0.5 * a @ a + np.sum(np.log(np.diag(low))))


def _hs_accurate(
    xy: np.ndarray,
    g: np.ndarray,
    smooth: list[tuple[float, float]],
    exact_k: np.ndarray,
    rest: np.ndarray,
    half: list[float],
) -> tuple[int, float, float, np.ndarray]:
    """The fewest Hilbert-space functions (of the boxes :data:`BOXES` times the half extents, 1 or 2 times the
    rule of thumb 1.75 c L / l per axis) whose smooth part gives the evidence within :data:`HS_NATS` of the exact
    covariance ``exact_k``'s (the broadband part, the noise and the tilt ``rest`` exact in both); where none does, the
    last tried. Returns (functions, box factor c, evidence difference in nats, the basis' gradients (2n, m))."""
    exact = _nll(exact_k, g)
    lmin = min(length for _, length in smooth)
    tried: tuple[int, float, float, np.ndarray] = (0, 0.0, float("inf"), np.zeros((len(g), 0)))
    for c in BOXES:
        for mult in (1.0, 2.0):
            m_axes = [int(np.ceil(mult * 1.75 * c * h / lmin)) for h in half]
            if int(np.prod(m_axes)) > HS_MAX:
                continue
            phi, w2 = _hs_gradients(xy, [c * h for h in half], m_axes)
            spec = sum(a * a * 2.0 * np.pi * ln * ln * np.exp(-0.5 * ln * ln * w2) for a, ln in smooth)
            nats = _nll((phi * spec[None, :]) @ phi.T + rest, g) - exact
            tried = (int(np.prod(m_axes)), c, nats, phi)
            if abs(nats) <= HS_NATS:
                return tried
    return tried


def _best_ms(fn: Any) -> float:
    """The least of :data:`REPEATS` runs of ``fn``, ms."""
    times = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * min(times)


def _dense_ms(k: np.ndarray) -> float:
    """The dense evaluation's factorisations: Cholesky and inverse of the 2n x 2n covariance ``k``."""
    from scopetwin.recon.lapack import cholesky_lower, lower_inverse

    return _best_ms(lambda: lower_inverse(cholesky_lower(k.copy())))


def _structured_ms(kb: np.ndarray, noise: np.ndarray, phi: np.ndarray) -> float:
    """The structured evaluation's floor: sparse LU of the broadband part ``kb`` plus the ``noise`` variances, its solve
    against the basis' gradients ``phi`` (2n, m), and the Cholesky factor of the m x m capacitance matrix."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spl

    d = np.sqrt(np.diag(kb) + noise)
    b = np.where(np.abs(kb) >= SPARSE_CUT * np.outer(d, d), kb, 0.0) + np.diag(noise)
    a = sp.csc_matrix(b)
    m = phi.shape[1]

    def once() -> None:
        w = spl.splu(a, permc_spec="MMD_AT_PLUS_A").solve(phi)
        cap = phi.T @ w
        cap[np.diag_indices(m)] += 1.0
        np.linalg.cholesky(cap)

    return _best_ms(once)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--seed", type=int, default=9100)
    args = ap.parse_args()
    print(
        f"{'family':18} {'n':>4} {'rank>noise':>10} {'rank>1e-3':>9} {'broad corr':>10} {'broad off':>9} "
        f"{'l_broad':>7} {'l_smooth':>8} {'HS m':>6} {'box c':>5} {'HS nats':>7} {'dense GF':>8} {'dense ms':>8} "
        f"{'struct ms':>9}"
    )
    for fam in args.families.split(","):
        r = one(fam, args.seed)
        print(
            f"{fam:18} {r['n']:4d} {r['rank_noise']:10d} {r['rank_milli']:9d} {r['broad_corr']:10.3f} "
            f"{r['broad_off']:9.3f} {r['broad_len']:7.2f} {r['smooth_len']:8.2f} {r['hs_m']:6d} {r['hs_box']:5.1f} "
            f"{r['hs_nats']:+7.2f} {r['dense_gflop']:8.3f} {r['dense_ms']:8.2f} {r['struct_ms']:9.2f}"
        )


if __name__ == "__main__":
    main()
