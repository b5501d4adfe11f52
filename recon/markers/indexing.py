"""Marker indexing: (i, j) of every marker by a flood from the reference marker (seed §1.5.4, and §2.6.1).

:func:`index_grid` floods the grid from the reference marker (0, 0) through the eight neighbours of each marker,
with the neighbour steps re-estimated locally as it proceeds. Indices (i, j) count pitches along the pattern's own
T_x, T_y (DESIGN.md, "Marker indices").
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from recon.markers.centroid_search import Array

#: Neighbour offsets of the flood (§1.5.4): the four axial neighbours first, then the diagonals.
NEIGHBOURS = np.array([[1, 0], [-1, 0], [0, 1], [0, -1], [1, 1], [-1, 1], [1, -1], [-1, -1]], dtype=np.int64)


#: Axial neighbour offsets of :func:`_local_basis`: +T_x, -T_x, +T_y, -T_y.
_AXIAL = np.array([[1, 0], [-1, 0], [0, 1], [0, -1]], dtype=np.int64)
_AXIAL_SIGN = np.array([1.0, -1.0, 1.0, -1.0])


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
    """Index spots relative to the reference marker by a flood over the eight neighbours (seed §1.5.4).

    From each indexed marker the positions of its eight neighbours are predicted with the *local*
    grid steps (a_x, a_y), re-estimated at every marker from its already indexed axial neighbours, so
    the flood follows a grid distorted by a bowed substrate or by perspective. The seed's search
    within r_s = sqrt((1.5 p_x)^2 + (1.5 p_y)^2) and its eight angle classes "with the tilt" become
    the eight predicted positions; as in the seed, the closest candidate of each class is kept, and
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
        length of one of them passes over a marker and is refused (issue 14 item 5: where a strongly bent
        substrate squeezes rows of markers into small or merged spots that filtering rejects, the flood
        otherwise steps across them and numbers everything beyond wrongly).
    axis_tol : float or None
        A step must also match its neighbour offset on each axis separately: written in the parent's local
        basis (a_x, a_y), each coefficient may differ from the offset by at most ``axis_tol`` (None: no such
        test). Where a row or column that shows no spot at all is squeezed between strongly compressed rows
        (issue 14 item 5), the step across it is only 1.2-1.3 times the parent's step along that axis, within
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
    none = np.iinfo(np.int32).min
    ij = np.full((n, 2), none, dtype=np.int64)
    if n == 0:
        return ij
    pts = np.asarray(points, dtype=np.float64)
    tree = cKDTree(pts)
    btree = cKDTree(np.asarray(blockers, dtype=np.float64)) if blockers is not None and len(blockers) else None
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
    frontier = np.array([ref])
    offs = NEIGHBOURS.astype(np.float64)
    while frontier.size:
        b = basis[frontier]  # (m, 2, 2) rows a_x, a_y
        pred = pts[frontier][:, None, :] + (
            offs[None, :, 0, None] * b[:, None, 0] + offs[None, :, 1, None] * b[:, None, 1]
        )
        tij = ij[frontier][:, None, :] + NEIGHBOURS[None]
        free = table[tij[..., 0] + off, tij[..., 1] + off] < 0
        step = np.minimum(np.linalg.norm(b[:, 0], axis=1), np.linalg.norm(b[:, 1], axis=1))
        # only predictions of indices still free need a search
        dist = np.full(free.shape, np.inf)
        sid = np.zeros(free.shape, dtype=np.intp)
        dist[free], sid[free] = tree.query(pred[free])
        ok = free & (dist < tol * step[:, None]) & ~assigned[sid]
        if axis_tol is not None and ok.any():
            # the step in the local basis: each coefficient must match the neighbour offset on its own axis
            pp, kk = np.nonzero(ok)
            bb = b[pp]  # (q, 2, 2) rows a_x, a_y
            det = bb[:, 0, 0] * bb[:, 1, 1] - bb[:, 0, 1] * bb[:, 1, 0]
            dv = pts[sid[pp, kk]] - pts[frontier[pp]]
            u = (dv[:, 0] * bb[:, 1, 1] - dv[:, 1] * bb[:, 1, 0]) / det
            v = (bb[:, 0, 0] * dv[:, 1] - bb[:, 0, 1] * dv[:, 0]) / det
            off_axis = np.maximum(np.abs(u - NEIGHBOURS[kk, 0]), np.abs(v - NEIGHBOURS[kk, 1])) > axis_tol
            ok[pp[off_axis], kk[off_axis]] = False
        if btree is not None and ok.any():
            pp, kk = np.nonzero(ok)
            a, c = pts[frontier[pp]], pts[sid[pp, kk]]
            over = btree.query_ball_point(0.5 * (a + c), gap * np.linalg.norm(c - a, axis=1), return_length=True) > 0
            ok[pp[over], kk[over]] = False
        par, k = np.nonzero(ok)
        if par.size == 0:
            break
        d, s, t = dist[par, k], sid[par, k], tij[par, k]
        order = np.argsort(d, kind="stable")
        par, k, s, t = par[order], k[order], s[order], t[order]
        _, first_s = np.unique(s, return_index=True)
        keep = np.zeros(len(s), dtype=bool)
        keep[first_s] = True
        key = (t[:, 0] + off) * (2 * off + 1) + (t[:, 1] + off)  # >= 0: never equal to the sentinels below
        _, first_t = np.unique(np.where(keep, key, -1 - np.arange(len(key))), return_index=True)
        keep2 = np.zeros(len(s), dtype=bool)
        keep2[first_t] = True
        keep &= keep2
        par, k, s, t = par[keep], k[keep], s[keep], t[keep]
        while np.abs(t).max() > off - 2:
            table, off = _grow_table(table, off)
        ij[s] = t
        table[t[:, 0] + off, t[:, 1] + off] = s
        assigned[s] = True
        parent = frontier[par]
        fb = basis[parent].copy()
        # keep the parent's steps, corrected by what the step to this marker showed
        resid = pts[s] - pts[parent] - (offs[k, 0, None] * fb[:, 0] + offs[k, 1, None] * fb[:, 1])
        nz = NEIGHBOURS[k] != 0
        share = nz / np.maximum(nz.sum(axis=1, keepdims=True), 1)
        fb += (share * np.sign(NEIGHBOURS[k]))[:, :, None] * resid[:, None, :]
        basis[s] = _local_basis(pts, table, off, t, fb)
        frontier = s
    # consistency check against opposite neighbours
    idx = np.flatnonzero(assigned)
    tt = ij[idx]
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
    bad &= idx != ref
    ij[idx[bad]] = none
    return ij
