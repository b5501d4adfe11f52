"""Sequential float64 ray tracer of the microscope unit (numpy): perfect thin lenses, bowed plates, stops.

This is the analytic reference of the unit (the thesis's Zemax model of §5.1.2: perfect lenses, the measured
splitter surfaces in reflection and transmission). Rays are arrays (N, 3); every element acts on the whole batch.

Perfect lens (Zemax's "paraxial surface"): a ray meeting the lens plane at local (x, y) with slopes
s = d_perp / |d_z| leaves with s' = s - (x, y)/f. All rays of one slope meet in one point of the focal plane
and all rays from one point of the front focal plane leave parallel: an aberration-free lens at any field.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from scopetwin.scenes.geometry import Array, Frame, intersect_plane, normalize, reflect, refract
from scopetwin.scenes.surface import HeightMap


def axis_frame(origin: Array, axis: Array) -> Frame:
    """A frame with N_z = ``axis`` and T_x the projection of global x (or y when axis is near x)."""
    nz = normalize(np.asarray(axis, dtype=np.float64))
    ref = np.array([1.0, 0.0, 0.0]) if abs(nz[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    tx = normalize(ref - (ref @ nz) * nz)
    return Frame(np.asarray(origin, dtype=np.float64), tx, np.cross(nz, tx), nz)


@dataclass
class Rays:
    """A batch of rays: origins o, unit directions d, current index n, optical path length, alive mask."""

    o: Array
    d: Array
    n: Array
    opl: Array
    alive: np.ndarray

    @classmethod
    def start(cls, o: Array, d: Array, n: float = 1.0) -> Rays:
        o = np.atleast_2d(np.asarray(o, dtype=np.float64))
        d = normalize(np.atleast_2d(np.asarray(d, dtype=np.float64)))
        o, d = np.broadcast_arrays(o, d)
        m = len(o)
        return cls(o.copy(), d.copy(), np.full(m, n), np.zeros(m), np.ones(m, dtype=bool))

    def advance(self, lam: Array) -> None:
        ok = np.isfinite(lam) & (lam > -1e-9)
        self.alive &= ok
        lam = np.where(ok, lam, 0.0)
        self.o = self.o + lam[:, None] * self.d
        self.opl = self.opl + self.n * lam


@dataclass(frozen=True)
class PerfectLens:
    """Perfect lens of focal length ``f`` in the plane of ``frame`` (axis N_z), clear radius ``radius``."""

    frame: Frame
    f: float
    radius: float = np.inf

    def apply(self, r: Rays) -> None:
        r.advance(intersect_plane(r.o, r.d, self.frame))
        loc = self.frame.to_local(r.o)
        dl = self.frame.vectors_to_local(r.d)
        r.alive &= loc[:, 0] ** 2 + loc[:, 1] ** 2 <= self.radius**2
        sign = np.where(dl[:, 2] >= 0, 1.0, -1.0)
        az = np.maximum(np.abs(dl[:, 2]), 1e-300)
        sx = dl[:, 0] / az - loc[:, 0] / self.f
        sy = dl[:, 1] / az - loc[:, 1] / self.f
        r.d = normalize(self.frame.vectors_to_global(np.stack([sx, sy, sign], axis=-1)))


@dataclass(frozen=True)
class Stop:
    """Circular aperture of ``radius`` centred on the frame origin, in the frame's plane."""

    frame: Frame
    radius: float

    def apply(self, r: Rays) -> None:
        r.advance(intersect_plane(r.o, r.d, self.frame))
        loc = self.frame.to_local(r.o)
        r.alive &= loc[:, 0] ** 2 + loc[:, 1] ** 2 <= self.radius**2


@dataclass(frozen=True)
class Surface:
    """One face of a plate: z_local = h(x, y) + ``offset`` in ``frame`` (h = 0 when ``heights`` is None).

    ``mode`` "R" reflects, "T" refracts from the current index into ``n_after``. Rays outside the
    ``half_width`` x ``half_height`` rectangle are lost.
    """

    frame: Frame
    heights: HeightMap | None
    mode: str
    n_after: float = 1.0
    offset: float = 0.0
    half_width: float = np.inf
    half_height: float = np.inf
    iterations: int = 8

    def _hit(self, o: Array, d: Array) -> Array:
        lam = (self.offset - o[:, 2]) / np.where(d[:, 2] != 0, d[:, 2], 1e-300)
        if self.heights is None:
            return lam
        for _ in range(self.iterations):  # Newton on f = h(x, y) + offset - z
            p = o + lam[:, None] * d
            h = self.heights.height(p[:, 0], p[:, 1])
            hx, hy = self.heights.gradient(p[:, 0], p[:, 1])
            f = h + self.offset - p[:, 2]
            df = hx * d[:, 0] + hy * d[:, 1] - d[:, 2]
            lam = lam - f / np.where(np.abs(df) > 1e-12, df, 1e-12)
        return lam

    def apply(self, r: Rays) -> None:
        o = self.frame.to_local(r.o)
        d = self.frame.vectors_to_local(r.d)
        lam = self._hit(o, d)
        r.advance(lam)
        p = o + np.where(np.isfinite(lam), lam, 0.0)[:, None] * d
        r.alive &= (np.abs(p[:, 0]) <= self.half_width) & (np.abs(p[:, 1]) <= self.half_height)
        nrm = (
            np.broadcast_to([0.0, 0.0, 1.0], p.shape)
            if self.heights is None
            else self.heights.normals(p[:, 0], p[:, 1])
        )
        if self.mode == "R":
            dn = reflect(d, nrm)
        else:
            dn, tir = refract(d, nrm, r.n, self.n_after)
            r.alive &= ~tir
            r.n = np.full_like(r.n, self.n_after)
        r.d = normalize(self.frame.vectors_to_global(dn))


@dataclass
class System:
    """A sequence of elements traced in order."""

    elements: list = field(default_factory=list)

    def trace(self, r: Rays) -> Rays:
        for e in self.elements:
            e.apply(r)
        return r
