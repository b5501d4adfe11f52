"""Marker indexing: (i, j) of every marker by a flood from the reference marker (thesis §1.5.4, and §2.6.1).

:func:`index_grid` floods the grid from the reference marker (0, 0) through the eight neighbours of each marker,
with the neighbour steps re-estimated locally as it proceeds. Indices (i, j) count pitches along the pattern's own
T_x, T_y (docs/contract.md, "Marker indices").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from scopetwin.recon.markers.centroid_search import Array

#: Neighbour offsets of the flood (§1.5.4): the four axial neighbours first, then the diagonals.
NEIGHBOURS = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [-1, 1], [1, -1], [-1, -1]], dtype=np.int64)


#: Axial neighbour offsets of :func:`_local_basis`: +T_x, -T_x, +T_y, -T_y.
_AXIAL = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]], dtype=np.int64)
_AXIAL_SIGN = np.array([1.0, -1.0, 1.0, -1.0])
#: The same offsets as tuples of ints (index arithmetic of :func:`index_lattice`, one marker at a time).
_AXIAL_STEPS: tuple[tuple[int, int], ...] = tuple((int(di), int(dj)) for di, dj in _AXIAL)


def _in_basis(basis: Array, dv: Array) -> tuple[Array, Array]:
    """Coefficients (u, v) of the steps ``dv`` (..., 2) in the basis ``basis`` (..., 2, 2; rows a_x, a_y)."""
    det = basis[..., 0, 0] * basis[..., 1, 1] - basis[..., 0, 1] * basis[..., 1, 0]
    u = (dv[..., 0] * basis[..., 1, 1] - dv[..., 1] * basis[..., 1, 0]) / det
    v = (basis[..., 0, 0] * dv[..., 1] - basis[..., 0, 1] * dv[..., 0]) / det
    return u, v


def _local_basis(pts: Array, table: NDArray, off: int, ij: NDArray, fallback: Array) -> Array:
    """Local steps of the markers at indices ``ij`` from their indexed axial neighbours.

    a_x is the mean of p[i+1, j] - p[i, j] and p[i, j] - p[i-1, j] where those exist (a_y likewise);
    where neither exists the fallback step is kept. ``table`` must extend at least one index beyond
    every ``ij`` (:func:`index_grid` keeps it so).
    """
    p = pts[table[ij[:, 0] + off, ij[:, 1] + off]]
    nb = ij[:, None, :] + _AXIAL + off  # (m, 4, 2)
    sid = table[nb[..., 0], nb[..., 1]]
    has = sid >= 0
    steps = (pts[sid] - p[:, None, :]) * (_AXIAL_SIGN[:, None] * has[..., None])  # zero where missing
    acc = steps[:, 0::2] + steps[:, 1::2]  # (m, 2 axes, 2)
    cnt = has[:, 0::2].astype(np.float64) + has[:, 1::2]
    got = cnt > 0
    return np.where(got[..., None], acc / np.where(got, cnt, 1.0)[..., None], fallback)


def _grow_table(table: NDArray, off: int) -> tuple[NDArray, int]:
    """The index table with its offset doubled (same entries, more room around them)."""
    new_off = 2 * off
    size = 2 * new_off + 1
    out = np.full((size, size), -1, dtype=table.dtype)
    out[off : off + table.shape[0], off : off + table.shape[1]] = table
    return out, new_off


#: Neighbour offsets as floats (the steps' coefficients on a_x, a_y).
_OFFS = NEIGHBOURS.astype(np.float64)

#: Index of spots not (or not consistently) indexed.
_UNREACHED = np.iinfo(np.int32).min


@dataclass
class _Flood:
    """State of the :func:`index_grid` flood: indices, index table (offset ``off``), local steps, assigned spots."""

    pts: Array
    ij: NDArray[np.int64]
    table: NDArray[np.int64]
    off: int
    basis: Array
    assigned: NDArray[np.bool_]


def _start_flood(pts: Array, ref: int, axes: Array, ij: NDArray[np.int64]) -> _Flood:
    """The flood's state with only the reference marker indexed, as (0, 0), with the steps ``axes``."""
    n = len(pts)
    # table of spot rows by index (i + off, j + off); it grows as the flood spreads, always keeping
    # two indices of room beyond every assigned marker (neighbour look-ups go one step further)
    off = 16
    table = np.full((2 * off + 1, 2 * off + 1), -1, dtype=np.int64)
    basis = np.zeros((n, 2, 2))
    assigned = np.zeros(n, dtype=bool)
    ij[ref] = 0
    table[off, off] = ref
    basis[ref] = axes
    assigned[ref] = True
    return _Flood(pts, ij, table, off, basis, assigned)


def _flood_candidates(
    fl: _Flood, frontier: NDArray, tree: cKDTree, tol: float
) -> tuple[Array, NDArray[np.bool_], Array, NDArray[np.intp], NDArray[np.int64]]:
    """Local steps of the frontier, and per neighbour (m, 8): acceptable, distance and nearest spot, its index."""
    b = fl.basis[frontier]  # (m, 2, 2) rows a_x, a_y
    pred = fl.pts[frontier][:, None, :] + (
        _OFFS[None, :, 0, None] * b[:, None, 0] + _OFFS[None, :, 1, None] * b[:, None, 1]
    )
    tij = fl.ij[frontier][:, None, :] + NEIGHBOURS[None]
    free = fl.table[tij[..., 0] + fl.off, tij[..., 1] + fl.off] < 0
    step = np.minimum(np.linalg.norm(b[:, 0], axis=1), np.linalg.norm(b[:, 1], axis=1))
    # only predictions of indices still free need a search
    dist = np.full(free.shape, np.inf)
    sid = np.zeros(free.shape, dtype=np.intp)
    dist[free], sid[free] = tree.query(pred[free])
    ok = free & (dist < tol * step[:, None]) & ~fl.assigned[sid]
    return b, ok, dist, sid, tij


def _refuse_off_axis(
    ok: NDArray[np.bool_], b: Array, pts: Array, sid: NDArray[np.intp], frontier: NDArray, axis_tol: float
) -> None:
    """Clear ``ok`` where the step, in the parent's local basis, misses its neighbour offset on an axis."""
    # the step in the local basis: each coefficient must match the neighbour offset on its own axis
    pp, kk = np.nonzero(ok)
    u, v = _in_basis(b[pp], pts[sid[pp, kk]] - pts[frontier[pp]])
    off_axis = np.maximum(np.abs(u - NEIGHBOURS[kk, 0]), np.abs(v - NEIGHBOURS[kk, 1])) > axis_tol
    ok[pp[off_axis], kk[off_axis]] = False


def _refuse_blocked(
    ok: NDArray[np.bool_], pts: Array, sid: NDArray[np.intp], frontier: NDArray, btree: cKDTree, gap: float
) -> None:
    """Clear ``ok`` where a blocker lies within ``gap`` step lengths of the step's midpoint."""
    pp, kk = np.nonzero(ok)
    a, c = pts[frontier[pp]], pts[sid[pp, kk]]
    over = btree.query_ball_point(0.5 * (a + c), gap * np.linalg.norm(c - a, axis=1), return_length=True) > 0
    ok[pp[over], kk[over]] = False


def _first_claims(s: NDArray[np.intp], t: NDArray[np.int64], off: int) -> NDArray[np.bool_]:
    """Of claims ``s`` -> ``t`` ordered by distance, those first on their spot and then first on their index."""
    _, first_s = np.unique(s, return_index=True)
    keep = np.zeros(len(s), dtype=bool)
    keep[first_s] = True
    key = (t[:, 0] + off) * (2 * off + 1) + (t[:, 1] + off)  # >= 0: never equal to the sentinels below
    _, first_t = np.unique(np.where(keep, key, -1 - np.arange(len(key))), return_index=True)
    keep2 = np.zeros(len(s), dtype=bool)
    keep2[first_t] = True
    keep &= keep2
    return keep


def _assign_claims(fl: _Flood, parent: NDArray, k: NDArray[np.intp], s: NDArray[np.intp], t: NDArray[np.int64]) -> None:
    """Index spots ``s`` as ``t`` (reached from ``parent`` along neighbour ``k``) and estimate their local steps."""
    while np.abs(t).max() > fl.off - 2:
        fl.table, fl.off = _grow_table(fl.table, fl.off)
    fl.ij[s] = t
    fl.table[t[:, 0] + fl.off, t[:, 1] + fl.off] = s
    fl.assigned[s] = True
    fb = fl.basis[parent].copy()
    # keep the parent's steps, corrected by what the step to this marker showed
    resid = fl.pts[s] - fl.pts[parent] - (_OFFS[k, 0, None] * fb[:, 0] + _OFFS[k, 1, None] * fb[:, 1])
    nz = NEIGHBOURS[k] != 0
    share = nz / np.maximum(nz.sum(axis=1, keepdims=True), 1)
    fb += (share * np.sign(NEIGHBOURS[k]))[:, :, None] * resid[:, None, :]
    fl.basis[s] = _local_basis(fl.pts, fl.table, fl.off, t, fb)


def _flood_step(
    fl: _Flood,
    frontier: NDArray,
    tree: cKDTree,
    btree: cKDTree | None,
    tol: float,
    gap: float,
    axis_tol: float | None,
) -> NDArray:
    """Index the neighbours of the whole frontier at once; returns the next frontier (empty: the flood ends)."""
    b, ok, dist, sid, tij = _flood_candidates(fl, frontier, tree, tol)
    if axis_tol is not None and ok.any():
        _refuse_off_axis(ok, b, fl.pts, sid, frontier, axis_tol)
    if btree is not None and ok.any():
        _refuse_blocked(ok, fl.pts, sid, frontier, btree, gap)
    par, k = np.nonzero(ok)
    if par.size == 0:
        return par
    d, s, t = dist[par, k], sid[par, k], tij[par, k]
    order = np.argsort(d, kind="stable")
    par, k, s, t = par[order], k[order], s[order], t[order]
    keep = _first_claims(s, t, fl.off)
    par, k, s, t = par[keep], k[keep], s[keep], t[keep]
    _assign_claims(fl, frontier[par], k, s, t)
    return s


def _inconsistent(fl: _Flood, check: float) -> tuple[NDArray[np.intp], NDArray[np.bool_]]:
    """Assigned spots, and which depart from the mean of two opposite neighbours by > ``check`` local steps."""
    pts, table, off = fl.pts, fl.table, fl.off
    idx = np.flatnonzero(fl.assigned)
    tt = fl.ij[idx]
    bad = np.zeros(len(idx), dtype=bool)
    size = table.shape[0]
    for axis in (0, 1):
        lo, hi = tt.copy(), tt.copy()
        lo[:, axis] -= 1
        hi[:, axis] += 1
        inside = np.all((lo + off >= 0) & (hi + off < size), axis=1)
        a = np.full(len(idx), -1)
        c = np.full(len(idx), -1)
        a[inside] = table[lo[inside, 0] + off, lo[inside, 1] + off]
        c[inside] = table[hi[inside, 0] + off, hi[inside, 1] + off]
        both = (a >= 0) & (c >= 0)
        mid = 0.5 * (pts[a[both]] + pts[c[both]])
        dev = np.linalg.norm(pts[idx[both]] - mid, axis=1)
        loc = 0.5 * np.linalg.norm(pts[c[both]] - pts[a[both]], axis=1)
        bad[np.flatnonzero(both)[dev > check * loc]] = True
    return idx, bad


def index_grid(
    points: Array,
    ref: int,
    axes: Array,
    tol: float = 0.3,
    check: float = 0.25,
    blockers: Array | None = None,
    gap: float = 0.3,
    axis_tol: float | None = 0.18,
) -> NDArray[np.int64]:
    """Index spots relative to the reference marker by a flood over the eight neighbours (thesis §1.5.4).

    From each indexed marker the positions of its eight neighbours are predicted with the *local*
    grid steps (a_x, a_y), re-estimated at every marker from its already indexed axial neighbours, so
    the flood follows a grid distorted by a bowed substrate or by perspective. The thesis's search
    within r_s = sqrt((1.5 p_x)^2 + (1.5 p_y)^2) and its eight angle classes "with the tilt" become
    the eight predicted positions; as in the thesis, the closest candidate of each class is kept, and
    only if it lies within ``tol`` times the shorter local step of the prediction. Claims on one spot
    from several markers go to the closest prediction. The whole frontier is processed at once.

    A step is also refused where, in the parent's local basis, it differs from its neighbour offset by
    more than ``axis_tol`` on either axis (a row or column with no visible spot skipped).

    A final check drops a marker whose position departs from the mean of its two opposite
    neighbours (along either axis) by more than ``check`` times the local step: a spurious blob that
    slipped in where a marker is missing.

    Parameters
    ----------
    points : ndarray, (n, 2)
        Spot centroids (col, row).
    ref : int
        Row of the reference marker in ``points``; it gets index (0, 0).
    axes : ndarray, (2, 2)
        Rows: image steps of +T_x and +T_y at the reference.
    blockers : ndarray, (k, 2), optional
        Every spot of the image, rejected ones included. A step whose midpoint lies within ``gap`` times its
        length of one of them passes over a marker and is refused (where a strongly bent
        substrate squeezes rows of markers into small or merged spots that filtering rejects, the flood
        otherwise steps across them and numbers everything beyond wrongly).
    axis_tol : float or None
        A step must also match its neighbour offset on each axis separately: written in the parent's local
        basis (a_x, a_y), each coefficient may differ from the offset by at most ``axis_tol`` (None: no such
        test). Where a row or column that shows no spot at all is squeezed between strongly compressed rows,
        the step across it is only 1.2-1.3 times the parent's step along that axis, within
        ``tol`` of the prediction but outside this test; the flood then reaches the markers beyond by other
        paths or not at all. 0.18 measured on 3 mm / 60 µm surfaces (seeds 1-8): 0 wrong on seeds 1 and 4
        (49 and 6 before), wrong counts unchanged on the rest (seeds 5 and 8 keep 5 and 10); 0.22 no longer
        catches them, 0.15 and below lose most markers on some surfaces.

    Returns
    -------
    ndarray, (n, 2), int
        (i, j) of each spot; unreached spots get the sentinel ``-2**31``.
    """
    n = len(points)
    none = _UNREACHED
    ij = np.full((n, 2), none, dtype=np.int64)
    if n == 0:
        return ij
    pts = np.asarray(points, dtype=np.float64)
    tree = cKDTree(pts)
    btree = cKDTree(np.asarray(blockers, dtype=np.float64)) if blockers is not None and len(blockers) else None
    fl = _start_flood(pts, ref, axes, ij)
    frontier = np.array([ref])
    while frontier.size:
        frontier = _flood_step(fl, frontier, tree, btree, tol, gap, axis_tol)
    # consistency check against opposite neighbours
    idx, bad = _inconsistent(fl, check)
    bad &= idx != ref
    ij[idx[bad]] = none
    return ij


def _axial_neighbour(
    pts: Array, tree: cKDTree, a: int, basis: Array, k: int, on: tuple[float, float], off_tol: float
) -> int:
    """The nearest spot along axial direction ``k`` (row of ``_AXIAL``) of spot ``a`` in its local basis, or -1.

    A candidate's step written in the basis (rows a_x, a_y) must lie between ``on`` times the step along the axis
    and ``off_tol`` times that (at least one step) off it: the axial neighbour however much the grid is stretched
    or squeezed along the axis, never a diagonal one.
    """
    # called thousands of times on a few candidates each: the arithmetic of _in_basis and np.linalg.norm written out
    # on floats, the same operations in the same order
    (b00, b01), (b10, b11) = basis.tolist()
    det = b00 * b11 - b01 * b10
    if abs(det) < 1e-12:
        return -1
    axis = 0 if k < 2 else 1  # rows 0, 1 of _AXIAL step along T_x, rows 2, 3 along T_y
    row = basis[axis]
    length = float(np.sqrt(row.dot(row)))
    cand = np.asarray(tree.query_ball_point(pts[a], on[1] * length + 1e-9), dtype=np.intp)
    cand = cand[cand != a]
    if cand.size == 0:
        return -1
    dv = pts[cand] - pts[a]
    dx, dy = dv[:, 0], dv[:, 1]
    u = (dx * b11 - dy * b10) / det
    v = (b00 * dy - b01 * dx) / det
    along, across = (u, v) if axis == 0 else (v, u)
    if k % 2:  # the negative direction (_AXIAL_SIGN)
        along = -along
    ok = (along > on[0]) & (along < on[1]) & (np.abs(across) < off_tol * np.maximum(along, 1.0))
    if not ok.any():
        return -1
    c = cand[ok]
    return int(c[np.argmin(np.einsum("ij,ij->i", dv[ok], dv[ok]))])


class _Lattice:
    """State of the :func:`index_lattice` flood: indices, index -> spot map, local steps, spots in conflict."""

    def __init__(self, pts: Array, on: tuple[float, float], off_tol: float) -> None:
        n = len(pts)
        self.pts = pts
        self.tree = cKDTree(pts)
        self.on, self.off_tol = on, off_tol
        self.ij = np.full((n, 2), _UNREACHED, dtype=np.int64)
        self.basis = np.zeros((n, 2, 2))
        self.where: dict[tuple[int, int], int] = {}
        self.index: dict[int, tuple[int, int]] = {}  # the inverse of ``where``: ``ij`` of the indexed spots
        self.xy: list[list[float]] = pts.tolist()  # the centroids as floats, for the steps of one marker
        self.bad = np.zeros(n, dtype=bool)

    def near(self, a: int, b: NDArray, k: int) -> int:
        """The axial neighbour of spot ``a`` along direction ``k`` in the basis ``b`` (:func:`_axial_neighbour`)."""
        return _axial_neighbour(self.pts, self.tree, a, b, k, self.on, self.off_tol)

    def local(self, a: int) -> NDArray:
        """The local steps of indexed spot ``a`` from its indexed axial neighbours (else the inherited ones).

        Along each axis the mean of p[i+1] - p[i] and p[i] - p[i-1] where both are indexed, else the one that is
        (floats: the same operations as on arrays, one marker is too few for numpy to pay).
        """
        b = self.basis[a].copy()
        i, j = self.index[a]
        xa, ya = self.xy[a]
        for axis, (up, down) in enumerate((((i + 1, j), (i - 1, j)), ((i, j + 1), (i, j - 1)))):
            hi, lo = self.where.get(up), self.where.get(down)
            if hi is not None and lo is not None:
                (xh, yh), (xl, yl) = self.xy[hi], self.xy[lo]
                b[axis] = (((xh - xa) - (xl - xa)) / 2.0, ((yh - ya) - (yl - ya)) / 2.0)
            elif hi is not None:
                xh, yh = self.xy[hi]
                b[axis] = (xh - xa, yh - ya)
            elif lo is not None:
                xl, yl = self.xy[lo]
                b[axis] = (-(xl - xa), -(yl - ya))
        return b

    def stepped(self, b: NDArray, a: int, c: int, k: int) -> NDArray:
        """Basis ``b`` of ``a`` with the axis of direction ``k`` replaced by the step a -> c."""
        out = b.copy()
        axis = 0 if _AXIAL[k, 0] else 1
        out[axis] = _AXIAL_SIGN[k] * (self.pts[c] - self.pts[a])
        return out

    def assign(self, c: int, t: tuple[int, int], b: NDArray) -> None:
        """Index spot ``c`` as ``t`` with the local steps ``b``."""
        self.ij[c] = t
        self.where[t] = c
        self.index[c] = t
        self.basis[c] = b


def _first_quad(lat: _Lattice, ref: int, axes: Array) -> tuple[int, int, int, int, int, NDArray, NDArray] | None:
    """The first closed quadrilateral at the reference: (kx, ky, cx, cy, d, bx, by), or None."""
    for kx in (0, 1):
        for ky in (2, 3):
            cx, cy = lat.near(ref, axes, kx), lat.near(ref, axes, ky)
            if cx < 0 or cy < 0:
                continue
            bx, by = lat.stepped(axes, ref, cx, kx), lat.stepped(axes, ref, cy, ky)
            if lat.near(cx, bx, kx ^ 1) != ref or lat.near(cy, by, ky ^ 1) != ref:
                continue
            d = lat.near(cx, bx, ky)
            if d >= 0 and d == lat.near(cy, by, kx) and d not in (ref, cx, cy):
                return kx, ky, cx, cy, d, bx, by
    return None


def _closes_quad(lat: _Lattice, ia: tuple[int, int], c: int, bc: NDArray, k: int) -> bool:
    """Whether the step a -> c along ``k`` closes a quadrilateral with an indexed perpendicular neighbour of a.

    a -> c, a -> p (indexed perpendicular neighbour), p -> q along k, c -> q across; ``ia`` is the index of a.
    """
    for kp in (2, 3) if k < 2 else (0, 1):
        dp = _AXIAL_STEPS[kp]
        p = lat.where.get((ia[0] + dp[0], ia[1] + dp[1]))
        if p is None or lat.bad[p]:
            continue
        q = lat.near(p, lat.local(p), k)
        if q >= 0 and q == lat.near(c, bc, kp):
            return True
    return False


def _extend_lattice(lat: _Lattice, a: int, queue: list[int]) -> None:
    """Index the mutual axial neighbours of spot ``a`` that close a quadrilateral; queue them and their neighbours."""
    b = lat.local(a)
    lat.basis[a] = b
    ia = lat.index[a]
    for k, (di, dj) in enumerate(_AXIAL_STEPS):
        t = (ia[0] + di, ia[1] + dj)
        if t in lat.where:
            continue
        c = lat.near(a, b, k)
        if c < 0:
            continue
        bc = lat.stepped(b, a, c, k)
        if lat.near(c, bc, k ^ 1) != a:  # mutual
            continue
        if not _closes_quad(lat, ia, c, bc, k):
            continue
        if lat.ij[c, 0] != _UNREACHED:
            lat.bad[c] = True  # reached before with another index
            continue
        lat.assign(c, t, bc)
        queue.append(c)
        # the indexed neighbours of c may close quadrilaterals now
        queue.extend(
            o for di, dj in _AXIAL_STEPS if (o := lat.where.get((t[0] + di, t[1] + dj))) is not None and o != a
        )


def index_lattice(
    points: Array,
    ref: int,
    axes: Array,
    on: tuple[float, float] = (0.35, 2.9),
    off_tol: float = 0.4,
) -> NDArray[np.int64]:
    """Index spots by the grid's topology: a flood over closed quadrilaterals of axial neighbours (thesis §1.5.4).

    :func:`index_grid` predicts each neighbour's position from the local grid steps; where a strongly bent
    substrate stretches the reflected grid on one side of a marker and squeezes it on the other (3 mm correlation,
    60 µm: image steps of 20 and 47 px on either side of one marker), the prediction misses and the flood stops
    (12 of ~500 markers on such a surface). Here the step is not predicted: the axial neighbour of a marker along
    +T_x (say) is the *nearest* spot whose offset, written in the marker's local basis (a_x, a_y), lies between
    ``on[0]`` and ``on[1]`` steps along the axis and within ``off_tol`` of that off it, and whose own nearest
    neighbour in the opposite direction is the marker (mutual). A step is taken only where it closes a
    quadrilateral with an indexed perpendicular neighbour (a -> c along T_x, b = a + T_y indexed, and b's neighbour
    along T_x is c's neighbour along T_y): where a marker is missing, the nearest spot along the axis is the one two
    pitches away, and no such quadrilateral closes, so the gap is left instead of numbering everything beyond it
    wrongly. Pass every spot of the image as ``points``, rejected ones included. The local basis is re-estimated at
    each marker from its indexed axial neighbours; a spot claimed with two indices, or an index claimed by two spots,
    is dropped.

    Parameters
    ----------
    points : ndarray, (n, 2)
        Spot centroids (col, row): every spot of the image.
    ref : int
        Row of the reference marker (index (0, 0)).
    axes : ndarray, (2, 2)
        Rows: approximate image steps of +T_x and +T_y at the reference (directions matter, lengths within a
        factor of ~2.5).
    on, off_tol : see above.

    Returns
    -------
    ndarray, (n, 2), int
        (i, j) of each spot; unreached or conflicting spots get the sentinel ``-2**31``.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) == 0:
        return np.full((0, 2), _UNREACHED, dtype=np.int64)
    lat = _Lattice(pts, on, off_tol)
    # the first quadrilateral, at the reference
    axes_ref = np.asarray(axes, dtype=np.float64)
    start = _first_quad(lat, ref, axes_ref)
    lat.assign(ref, (0, 0), axes_ref)
    if start is None:
        return lat.ij
    kx, ky, cx, cy, d, bx, by = start
    lat.assign(cx, (int(_AXIAL[kx, 0]), 0), bx)
    lat.assign(cy, (0, int(_AXIAL[ky, 1])), by)
    lat.assign(d, (int(_AXIAL[kx, 0]), int(_AXIAL[ky, 1])), by)
    queue = [ref, cx, cy, d]
    head = 0
    while head < len(queue):
        a = queue[head]
        head += 1
        if not lat.bad[a]:
            _extend_lattice(lat, a, queue)
    lat.bad[ref] = False
    lat.ij[lat.bad] = _UNREACHED
    return lat.ij
