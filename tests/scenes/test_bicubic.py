"""scenes.bicubic: the height map's own spline as per-cell polynomials, and the substrate's ray intersection on it,
against scipy's fitpack evaluation of the same spline (``RectBivariateSpline.ev``) and the secant fed by it."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.scenes.geometry import Frame, intersect_plane
from scopetwin.scenes.secant import secant_intersection
from scopetwin.scenes.surface import HeightMap, Substrate


@pytest.fixture
def wavy():
    """A rough map with heights of ~0.1 mm on a non-square node grid (the bias step's 48 x 112 kind)."""
    rng = np.random.default_rng(5)
    z = np.cumsum(rng.normal(0, 1e-3, (112, 48)), axis=0) + 0.02 * np.sin(np.linspace(0, 9, 48))[None]
    return HeightMap(z, -12.6, 12.6, -28.5, 28.5)


def _rays(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Rays from one camera point 300 mm above, aimed over and beyond the map (some miss it, some graze)."""
    o = np.tile([3.0, -40.0, 300.0], (n, 1))
    target = np.column_stack([rng.uniform(-16, 16, n), rng.uniform(-34, 34, n), np.zeros(n)])
    d = target - o
    return o, d / np.linalg.norm(d, axis=1, keepdims=True)


def test_the_cells_are_the_height_maps_own_spline(wavy):
    """Heights and gradients to rounding, outside the extents included (constant continuation, zero gradient)."""
    rng = np.random.default_rng(6)
    x = np.concatenate([rng.uniform(-14, 14, 5000), [-12.6, 12.6, 0.0, 0.0, 13.0]])
    y = np.concatenate([rng.uniform(-30, 30, 5000), [0.0, 0.0, -28.5, 28.5, 29.0]])
    h, hx, hy = wavy.cells().height_and_gradient(x, y)
    gx, gy = wavy.gradient(x, y)
    scale = np.abs(wavy.z).max()
    assert np.abs(h - wavy.spline.ev(np.clip(y, -28.5, 28.5), np.clip(x, -12.6, 12.6))).max() < 1e-12 * scale
    assert np.abs(h - wavy.height(x, y)).max() < 1e-12 * scale
    assert np.abs(hx - gx).max() < 1e-10 * scale and np.abs(hy - gy).max() < 1e-10 * scale
    assert wavy.cells() is wavy.cells()  # built once per map


def test_the_substrates_hits_and_normals_are_the_fitpack_iterations(wavy):
    """Substrate.points_and_normals (on the cells) against the secant iteration on fitpack from the same starts (the
    camera and the base plane) and HeightMap.normals there: the same rays converge, to the same points."""
    rng = np.random.default_rng(7)
    o, d = _rays(rng, 4000)
    sub = Substrate(wavy, 25.2, 57.0, 48.0)
    p, n, mask = sub.points_and_normals(o, d)
    lam_ref, ok_ref = secant_intersection(wavy, o, d, np.zeros(len(o)), intersect_plane(o, d, Frame.identity()))
    lam, ok = sub.intersect(o, d)
    assert (ok == ok_ref).all() and ok.mean() > 0.9
    assert np.abs(lam[ok] - lam_ref[ok]).max() < 1e-9  # mm; |f| < 1e-10 mm at both
    p_ref = o + lam_ref[:, None] * d
    assert np.abs(p[ok] - p_ref[ok]).max() < 1e-9
    n_ref = wavy.normals(p_ref[ok, 0], p_ref[ok, 1])
    assert np.abs(n[ok] - n_ref).max() < 1e-12
    assert (mask == (ok & sub.in_roi(p[:, 0], p[:, 1]))).all()


def test_the_cells_secant_from_the_base_plane_meets_the_surface(wavy):
    """The default start (the base plane and one flat Newton step) lands on the surface: |h - z| < tol."""
    rng = np.random.default_rng(8)
    o, d = _rays(rng, 2000)
    lam, ok, h, _, _ = wavy.cells().intersect(o, d)
    q = o[ok] + lam[ok, None] * d[ok]
    assert ok.mean() > 0.9
    assert np.abs(wavy.height(q[:, 0], q[:, 1]) - q[:, 2]).max() < 1e-10
    assert np.abs(h[ok] - q[:, 2]).max() < 1e-10


def _compiled_or_skip() -> None:
    from scopetwin.scenes.mitsuba import secant as compiled_secant

    if not compiled_secant.available():
        pytest.skip("Dr.Jit's LLVM backend is not available")


def _same(a: tuple, b: tuple, tol: float) -> None:
    """lam, converged, h, hx, hy of two intersections: the same rays converged, the values within ``tol`` mm."""
    assert (a[1] == b[1]).all()
    for x, y in zip(a, b, strict=True):
        assert (np.isnan(x) == np.isnan(y)).all()
        assert np.nanmax(np.abs(np.asarray(x, dtype=float) - np.asarray(y, dtype=float)), initial=0.0) <= tol


@pytest.mark.mitsuba
def test_the_compiled_iteration_gives_the_numpy_iterations_hits(wavy):
    """The Dr.Jit kernel against the numpy iteration on the same rays and starts: every default start (rays that miss,
    graze and run parallel to the base plane included), given starts, and an iteration cut short (max_iter 1)."""
    _compiled_or_skip()
    rng = np.random.default_rng(9)
    o, d = _rays(rng, 3000)
    d[:5] = [1.0, 0.0, 0.0]  # parallel to the base plane: not traced
    cells = wavy.cells()
    _same(cells.intersect(o, d, compiled=True), cells.intersect(o, d), 1e-12)
    assert cells.intersect(o, d)[1][5:].mean() > 0.9
    lam0, lam1 = np.zeros(len(o)), intersect_plane(o, d, Frame.identity())  # the substrate's starts
    _same(cells.intersect(o, d, lam0, lam1, compiled=True), cells.intersect(o, d, lam0, lam1), 1e-12)
    short = cells.intersect(o, d, max_iter=1, compiled=True)
    _same(short, cells.intersect(o, d, max_iter=1), 1e-12)
    assert 0 < short[1].sum() < cells.intersect(o, d)[1].sum()  # some rays need more than one step


@pytest.mark.mitsuba
def test_the_compiled_iteration_is_compiled_once(wavy):
    """Later calls, on other rays in other memory and on another surface of the same node grid (other heights and
    extents), run the first call's kernel: none is built again (Dr.Jit compiles for the alignment of the memory it
    reads, which the aligned copies fix, and the surface's scalars are opaque)."""
    _compiled_or_skip()
    import drjit as dr

    rng = np.random.default_rng(10)
    other = HeightMap(wavy.z[::-1] * 0.5, -10.0, 11.0, -20.0, 24.0)
    wavy.cells().intersect(*_rays(rng, 1000), compiled=True)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # cleared
        for n, surface in [(999, wavy), (1500, other), (700, wavy)]:
            o, d = _rays(rng, n)
            got = surface.cells().intersect(o[1:], d[1:], compiled=True)  # a view at another offset
            _same(got, surface.cells().intersect(o[1:], d[1:]), 1e-12)
        kernels = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert len(kernels) == 3 and all(k["cache_hit"] for k in kernels)


def test_without_dr_jit_the_numpy_iteration_serves(wavy, monkeypatch):
    from scopetwin.scenes.mitsuba import secant as compiled_secant

    monkeypatch.setattr(compiled_secant, "available", lambda: False)
    monkeypatch.setattr(compiled_secant, "intersect", None)  # never reached
    o, d = _rays(np.random.default_rng(11), 500)
    _same(wavy.cells().intersect(o, d, compiled=True), wavy.cells().intersect(o, d), 0.0)
