"""The uniform cubic B-spline (de Boor): its four weights around a point and their first and second derivatives.

Pure arithmetic on any array type (numpy, Dr.Jit), so the inverse fit's surface and the renderer that traces it use
one definition.
"""

from __future__ import annotations

from typing import Any


def cubic_bspline_weights(t: Any) -> tuple[Any, Any, Any, Any, Any, Any, Any, Any]:
    """Uniform cubic B-spline weights of the 4 coefficients around a point, and their derivatives in t.

    For u = (x - x_0)/dx with i = floor(u), t = u - i in [0, 1), the coefficients k = i-1 .. i+2 carry
    w_0 = (1-t)^3/6, w_1 = (3t^3 - 6t^2 + 4)/6, w_2 = (-3t^3 + 3t^2 + 3t + 1)/6, w_3 = t^3/6 (de Boor).
    Arithmetic only: runs on numpy arrays and on Dr.Jit arrays alike — the one definition of the inverse fit's
    surface (:mod:`scopetwin.recon.spline`) and of the differentiable render that traces it
    (:mod:`scopetwin.scenes.mitsuba.deflectometry_ad`).

    Returns
    -------
    w0, w1, w2, w3, d0, d1, d2, d3
        The weights and their derivatives dw/dt.
    """
    t2 = t * t
    t3 = t2 * t
    s = 1.0 - t
    w0 = s * s * s / 6.0
    w1 = (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0
    w2 = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0
    w3 = t3 / 6.0
    d0 = -0.5 * s * s
    d1 = 1.5 * t2 - 2.0 * t
    d2 = -1.5 * t2 + t + 0.5
    d3 = 0.5 * t2
    return w0, w1, w2, w3, d0, d1, d2, d3


def cubic_bspline_second(t: Any) -> tuple[Any, Any, Any, Any]:
    """Second derivatives d^2 w_k / dt^2 of :func:`cubic_bspline_weights`: 1 - t, 3t - 2, 1 - 3t, t (linear in t)."""
    return 1.0 - t, 3.0 * t - 2.0, 1.0 - 3.0 * t, t
