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
* ``HS basis``: the Laplacian eigenfunctions a Hilbert-space finite basis needs on the substrate (extent L per axis,
  boundary factor c = 1.2) for the smooth part's shortest component and for the broadband part,
  ``(1.75 c L / l)`` per axis (Riutort-Mayol et al., Statistics and Computing 33, 2023, eq. 14);
* the flops of one evidence evaluation on all the data: dense Cholesky (2n)^3 / 3, against low rank plus diagonal
  (Woodbury) 2n r^2 with r = ``rank>noise``.

and, timed on one BLAS thread (minimum of :data:`REPEATS`), what one evidence evaluation's factorisations cost each way:

* ``dense ms``: the Cholesky factor and the inverse (LAPACK potrf + potri, what the evidence's gradient reads) of the
  whole 2n x 2n gradient covariance, as :func:`scopetwin.recon.posterior.fit_hyper` does now;
* ``struct ms``: the least a structured evaluation needs: the sparse LU factor (SuperLU) of the broadband part plus
  the noise, entries below :data:`SPARSE_CUT` of the diagonal dropped, its solve against the Hilbert-space smooth
  basis (``HS smooth`` columns) and the Cholesky factor of the small m x m matrix that leaves. It leaves out what the
  gradient would add (the broadband part's selected inverse, which SciPy does not offer), so it is a floor.

It measures how far a structured posterior could cut the work, for the choice between one.
Measured at seed 9100 (441-529 markers, 882-1058 observations; this machine, 2 cores): the smooth part resolves
21-125 directions above the noise (glass 456: its rational-quadratic part reaches 2.4 mm), and a Hilbert-space basis
for it needs 6-78 functions (glass 420). The broadband part is short (0.25-0.45 mm; neighbouring markers correlated
by at most 0.35) on five families, 0.79 mm on gauss (0.47), and 2.1 mm on cut, where it is a second smooth part
(0.90). The factorisations of one evaluation: dense 22-34 ms; the structured floor 0.4-0.6 ms (steep, features),
4-8 ms (gauss, gauss+broadband, power+broadband), 22 ms (glass) and 46 ms (cut, whose long broadband part fills the
sparse factor). So a structured posterior would pay on the short-broadband families and not on cut, where the
broadband part belongs in the low-rank part.
"""

from __future__ import annotations

import argparse
import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import time  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

FAMILIES = ("gauss", "gauss+broadband", "power+broadband", "glass", "cut", "steep", "features")
BOUNDARY = 1.2  # c: the Hilbert-space box is c times the substrate's half extent
#: Entries of the broadband part below this fraction of the geometric mean of their two variances are dropped for the
#: sparse factor (a tolerance far below the noise: the part's correlations that matter are 1e-2 and up).
SPARSE_CUT = 1e-6
#: Timed repeats of each factorisation; the minimum is printed.
REPEATS = 20


def _kernel(xy: np.ndarray, comps: list[tuple[float, float]]) -> np.ndarray:
    """The gradient covariance [f_x; f_y] of squared-exponential components (amplitude mm, length mm), no tilt or
    noise (the formulas of :mod:`scopetwin.recon.posterior`)."""
    n = len(xy)
    k = np.zeros((2 * n, 2 * n))
    dx = xy[:, None, 0] - xy[None, :, 0]
    dy = xy[:, None, 1] - xy[None, :, 1]
    for amp, length in comps:
        if amp <= 0:
            continue
        e = amp**2 * np.exp(-(dx * dx + dy * dy) / (2.0 * length**2))
        il2, il4 = 1.0 / length**2, 1.0 / length**4
        k[:n, :n] += e * (il2 - dx * dx * il4)
        k[n:, n:] += e * (il2 - dy * dy * il4)
        k[:n, n:] += -e * dx * dy * il4
        k[n:, :n] += -e * dx * dy * il4
    return k


def one(family: str, seed: int) -> dict[str, float]:
    from scopetwin.recon.posterior import Hyper, _smooth_components
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
    rec = Reconstructor.from_setup(setup)
    obs = MarkerObservations(truth.ij[vis], px)
    with single_thread_blas():
        res = solve(rec, obs)
    assert res.uncertainty is not None
    hyper = Hyper.from_dict(res.uncertainty.hyper)
    xy, _, _, _ = rec.traced_gradients(res.surface, obs)
    smooth = _smooth_components(hyper) + ([(hyper.feature_amp, hyper.feature_len)] if hyper.feature_amp > 0 else [])
    noise2 = float(np.mean(np.square(hyper.noise_pair)))
    ev = np.linalg.eigvalsh(_kernel(xy, smooth))
    kb = _kernel(xy, [(hyper.broad_amp, hyper.broad_len)])
    d = np.sqrt(np.diag(kb))
    corr = kb / np.outer(d, d)
    np.fill_diagonal(corr, 0.0)
    off = kb - np.diag(np.diag(kb))
    half = [0.5 * (b - a) for a, b in (rec.sub.x_range, rec.sub.y_range)]

    def hs(length: float) -> float:
        return float(np.prod([np.ceil(1.75 * BOUNDARY * BOUNDARY * h / length) for h in half]))

    n2 = 2 * len(xy)
    rank = int(np.sum(ev > noise2))
    noise = np.repeat(np.square(hyper.noise_pair), len(xy))
    dense_ms = _dense_ms(_kernel(xy, smooth) + kb + np.diag(noise))
    struct_ms = _structured_ms(kb, noise, min(int(hs(min(length for _, length in smooth))), n2))
    return {
        "n": len(xy),
        "rank_noise": rank,
        "rank_milli": int(np.sum(ev > 1e-3 * noise2)),
        "broad_corr": float(np.abs(corr).max()),
        "broad_off": float(np.linalg.norm(off) / np.linalg.norm(np.diag(kb))),
        "broad_len": hyper.broad_len,
        "smooth_len": min(length for _, length in smooth),
        "hs_smooth": hs(min(length for _, length in smooth)),
        "hs_broad": hs(hyper.broad_len),
        "dense_gflop": n2**3 / 3 * 1e-9,
        "lowrank_gflop": n2 * rank**2 * 1e-9,
        "dense_ms": dense_ms,
        "struct_ms": struct_ms,
    }


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


def _structured_ms(kb: np.ndarray, noise: np.ndarray, m: int) -> float:
    """The structured evaluation's floor: sparse LU of the broadband part ``kb`` plus the ``noise`` variances, its solve
    against m basis columns, and the Cholesky factor of the m x m capacitance matrix."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spl

    d = np.sqrt(np.diag(kb) + noise)
    b = np.where(np.abs(kb) >= SPARSE_CUT * np.outer(d, d), kb, 0.0) + np.diag(noise)
    phi = np.random.default_rng(0).standard_normal((len(b), m))  # stands in for the basis: the cost is its shape's
    a = sp.csc_matrix(b)

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
        f"{'l_broad':>7} {'l_smooth':>8} {'HS smooth':>9} {'HS broad':>8} {'dense GF':>8} {'low-rank GF':>11} "
        f"{'dense ms':>8} {'struct ms':>9}"
    )
    for fam in args.families.split(","):
        r = one(fam, args.seed)
        print(
            f"{fam:18} {r['n']:4d} {r['rank_noise']:10d} {r['rank_milli']:9d} {r['broad_corr']:10.3f} "
            f"{r['broad_off']:9.3f} {r['broad_len']:7.2f} {r['smooth_len']:8.2f} {r['hs_smooth']:9.0f} "
            f"{r['hs_broad']:8.0f} {r['dense_gflop']:8.3f} {r['lowrank_gflop']:11.4f} {r['dense_ms']:8.2f} "
            f"{r['struct_ms']:9.2f}"
        )


if __name__ == "__main__":
    main()
