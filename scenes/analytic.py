"""The analytic reference renderer of thesis §1.6: numpy, float64, supersampled.

It traces camera rays (§1.6.2) to the substrate (secant iteration, §1.6.4), a
flat mirror or a target plane, reflects them (§1.6.5), intersects the pattern
plane (§1.6.3) and reads the marker grey value there. Pixels integrate their
area with a box filter (stratified jittered samples), as a sensor does. It is
the independent cross-check of the Mitsuba renders (scenes/mitsuba/), and
slow by design: float64 everywhere, no acceleration structures.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.camera import Camera, concentric_disk
from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.geometry import Array, Frame, intersect_plane, reflect
from scopetwin.scenes.pattern import MarkerPattern
from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap, Substrate

Window = tuple[int, int, int, int]  # row0, row1, col0, col1 (half-open)


def _pattern_hit(pattern: MarkerPattern, origins: Array, dirs: Array) -> tuple[Array, NDArray[np.bool_]]:
    """Local (x, y) where rays meet the pattern plane; True where they reach its emitting side."""
    lam = intersect_plane(origins, dirs, pattern.frame)
    ok = ((dirs @ pattern.frame.nz) < 0) & np.isfinite(lam) & (lam > 0)
    local = pattern.frame.to_local(origins + np.where(ok, lam, 0.0)[:, None] * dirs)
    return local[:, :2], ok


class AnalyticScene:
    """A setup ready for tracing: camera, pattern and the reflecting element."""

    def __init__(self, setup: Setup, heights: HeightMap | None = None) -> None:
        self.setup = setup
        self.camera: Camera = setup.camera_model
        self.pattern: MarkerPattern = setup.marker_pattern
        self.radiance = setup.pattern.radiance
        self.substrate: Substrate | None = None
        if setup.scene == "deflectometry":
            if heights is None:
                raise SetupError("a deflectometry render needs the substrate's height map (heights=...)")
            sub = setup.substrate
            assert sub is not None
            self.substrate = Substrate(heights, sub.size[0], sub.size[1], sub.roi_length)

    def pattern_hits(self, origins: Array, dirs: Array) -> tuple[Array, NDArray[np.bool_]]:
        """Where camera rays end on the pattern (local x, y, mm) and whether they get there.

        The mask is False for rays that miss the reflecting element (outside the ROI, off
        the substrate or mirror) or reach the pattern plane from behind.
        """
        scene = self.setup.scene
        if scene == "target":
            return _pattern_hit(self.pattern, origins, dirs)
        if scene == "mirror":
            assert self.setup.mirror is not None
            lam = intersect_plane(origins, dirs, Frame.identity())
            ok = np.isfinite(lam) & (lam > 0) & (dirs[:, 2] < 0)
            p = origins + np.where(ok, lam, 0.0)[:, None] * dirs
            sx, sy = self.setup.mirror.size
            ok &= (np.abs(p[:, 0]) <= 0.5 * sx) & (np.abs(p[:, 1]) <= 0.5 * sy)
            xy, hit = _pattern_hit(self.pattern, p, reflect(dirs, np.array([0.0, 0.0, 1.0])))
            return xy, ok & hit
        assert self.substrate is not None
        p, normals, ok = self.substrate.points_and_normals(origins, dirs)
        xy, hit = _pattern_hit(self.pattern, p, reflect(dirs, normals))
        return xy, ok & hit

    def trace(self, origins: Array, dirs: Array) -> Array:
        """Radiance along camera rays (one value per ray)."""
        xy, ok = self.pattern_hits(origins, dirs)
        return np.where(ok, self.radiance * self.pattern.grey_local(xy), 0.0)

    def camera_rays(self, px: Array, rng: np.random.Generator) -> tuple[Array, Array]:
        if self.camera.lens is None:
            return self.camera.rays(px)
        return self.camera.lens_rays(px, concentric_disk(rng.random((len(px), 2))))


def render(
    setup: Setup,
    heights: HeightMap | None = None,
    spp: int | None = None,
    seed: int | None = None,
    window: Window | None = None,
    chunk: int = 1 << 18,
) -> NDArray[np.float32]:
    """Render a setup with the float64 analytic ray model.

    Parameters
    ----------
    setup : Setup
        The scene ("deflectometry" needs ``heights``).
    heights : HeightMap, optional
        Substrate height map (base-plane coordinates, mm).
    spp : int, optional
        Samples per pixel (default: ``setup.render.spp``).
    seed : int, optional
        Seed of the sample positions (default: ``setup.render.seed``).
    window : (row0, row1, col0, col1), optional
        Render only these pixels (half-open ranges); default the whole image.

    Returns
    -------
    ndarray, float32, (rows, cols)
        Mean radiance per pixel (box filter).
    """
    cam = setup.camera_model
    r0, r1, c0, c1 = window if window is not None else (0, cam.ny, 0, cam.nx)
    if not (0 <= r0 < r1 <= cam.ny and 0 <= c0 < c1 <= cam.nx):
        raise SetupError(f"render window {window} lies outside the {cam.ny} x {cam.nx} image")
    cc, rr = np.meshgrid(np.arange(c0, c1), np.arange(r0, r1))
    values = render_pixels(setup, rr.ravel(), cc.ravel(), heights, spp, seed, chunk)
    return values.reshape(r1 - r0, c1 - c0)


def render_pixels(
    setup: Setup,
    rows: NDArray,
    cols: NDArray,
    heights: HeightMap | None = None,
    spp: int | None = None,
    seed: int | None = None,
    chunk: int = 1 << 18,
) -> NDArray[np.float32]:
    """Render an arbitrary list of pixels (row, col); one float32 value per pixel (see :func:`render`)."""
    spp = spp or setup.render.spp
    seed = setup.render.seed if seed is None else seed
    scene = AnalyticScene(setup, heights)
    rng = np.random.default_rng(seed)
    rows = np.asarray(rows)
    cols = np.asarray(cols)
    out = np.empty(len(rows), dtype=np.float64)
    step = max(1, chunk // spp)
    for start in range(0, len(rows), step):
        stop = min(len(rows), start + step)
        samples = _chunk_samples(rows[start:stop], cols[start:stop], spp, rng)
        o, d = scene.camera_rays(samples, rng)
        out[start:stop] = scene.trace(o, d).reshape(-1, spp).mean(axis=1)
    return out.astype(np.float32)


def _chunk_samples(rows: NDArray, cols: NDArray, spp: int, rng: np.random.Generator) -> Array:
    """Stratified samples for an arbitrary list of pixels (row, col)."""
    s = int(round(np.sqrt(spp)))
    n = len(rows)
    base = np.stack([cols, rows], axis=-1).astype(np.float64)
    if s * s == spp:
        k = np.arange(spp)
        strata = np.stack([k % s, k // s], axis=-1).astype(np.float64)
        offs = (strata[None] + rng.random((n, spp, 2))) / s
    else:
        offs = rng.random((n, spp, 2))
    return (base[:, None, :] + offs).reshape(-1, 2)
