"""The frame criterion of the outer loop: is the reconstructed surface lying on the holding frame? (thesis §1.4).

The substrate's ends lie on a holding frame (thesis Fig. 1.3). A surface reconstructed with a wrong start height
shows a characteristic tilt, visible in the maxima of the surface over the two frame regions, where there are no
data and the surface is extrapolated. The outer loop of the nested iteration (:mod:`scopetwin.recon.reconstruct`)
searches the start height at which this criterion vanishes:

* ``"delta"`` — the thesis's Delta h_max = max_region1 - max_region2 (eq. 1.3);
* ``"level"`` — both maxima at the frame position: (max_1 + max_2)/2 - z_frame. The start height moves the ROI
  almost as a pure offset but Delta h_max only at about half that rate, so an extrapolation error in the frame
  regions costs roughly twice as much absolute height with ``"delta"`` as with ``"level"``.

:func:`frame_distance` is the thesis's d_min of eq. 1.4: the frame maximum closest to the frame position, with its
sign; the thesis's start-height update is H_{i+1} = H_i - d_min. :func:`next_start_height` is the one root search
on the criterion both reconstruction methods use (a secant kept inside the bracket once the root is bracketed).
"""

from __future__ import annotations

from typing import Literal

FrameCriterion = Literal["level", "delta"]


def frame_criterion(max_1: float, max_2: float, frame_z: float, criterion: FrameCriterion = "level") -> float:
    """The frame criterion of a reconstructed surface (thesis §1.4, eq. 1.3); zero on the correct surface.

    Parameters
    ----------
    max_1, max_2 : float
        Maxima of the surface over frame region 1 (y < 0) and region 2 (y > 0), mm.
    frame_z : float
        z-position of the holding frame, mm (from the calibration of the setup, thesis §2.7).
    criterion : {"level", "delta"}
        ``"delta"``: Delta h_max = max_1 - max_2 (eq. 1.3); ``"level"``: (max_1 + max_2)/2 - frame_z
        (module docstring).

    Returns
    -------
    float
        The criterion, mm.

    Raises
    ------
    ValueError
        An unknown criterion.
    """
    if criterion == "delta":
        return max_1 - max_2
    if criterion == "level":
        return 0.5 * (max_1 + max_2) - frame_z
    raise ValueError(f"frame criterion must be 'level' or 'delta', got {criterion!r}")


def frame_distance(max_1: float, max_2: float, frame_z: float) -> float:
    """d_min of thesis eq. 1.4: the distance of the frame maximum closest to the frame position, with its sign, mm.

    Parameters
    ----------
    max_1, max_2 : float
        Maxima of the surface over the two frame regions, mm.
    frame_z : float
        z-position of the holding frame, mm.

    Returns
    -------
    float
        max_k - frame_z of the region k where it is smaller in magnitude (region 1 on a tie).
    """
    d1, d2 = max_1 - frame_z, max_2 - frame_z
    return d1 if abs(d1) <= abs(d2) else d2


def next_start_height(values: list[tuple[float, float]], fallback: float) -> float:
    """Next start height of the root search on the criterion F(H) (thesis §1.4, beyond eq. 1.4).

    Secant through the last two evaluations; once a sign change is known, the step is kept inside the tightest
    bracket (bisection when the secant leaves it). ``fallback`` (the thesis step of eq. 1.4, H - d_min, or H - F)
    is used with a single evaluation and where the last two criteria are equal.

    Parameters
    ----------
    values : list of (float, float)
        The (start height, criterion) pairs evaluated so far, mm, in order.
    fallback : float
        The step to take without a secant, mm.

    Returns
    -------
    float
        The next start height, mm.
    """
    if len(values) < 2:
        return fallback
    (ha, fa), (hb, fb) = values[-2], values[-1]
    h_new = hb - fb * (hb - ha) / (fb - fa) if fb != fa else fallback
    pos = [h for h, f in values if f > 0]
    neg = [h for h, f in values if f < 0]
    if pos and neg:
        # tightest bracket around the root from all evaluations so far
        hp = min(pos, key=lambda h: abs(h - hb))
        hn = min(neg, key=lambda h: abs(h - hb))
        lo, hi = min(hp, hn), max(hp, hn)
        if not lo < h_new < hi:
            h_new = 0.5 * (lo + hi)
    return h_new
