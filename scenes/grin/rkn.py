"""Vectorised numpy float64 reference ray tracer for GRIN objectives (thesis §7.5, §8.3).

Inside a radial GRIN rod the ray equation is integrated with the Sharma-Kumar-Ghatak
Runge-Kutta-Nystrom scheme (Sharma, Kumar & Ghatak, Appl. Opt. 21, 984 (1982)):

    d²R/dt² = D(R) = ½ ∇n²,   T = dR/dt = n dR/ds,   dt = ds / n,

with the optical path length dOPL/dt = n² integrated alongside (Simpson's rule on the
stage points). Because n does not depend on z, D_z = 0 and T_z is conserved; with
Δt = L / (N T_z) every ray lands exactly on the flat exit face after N steps, so only
(x, y, T_x, T_y) are integrated.

Outside the rods every interface is a plane z = const, where Snell's law in vector form
reduces to conservation of the transverse optical direction cosines (T_x, T_y) = n (d_x, d_y)
(:func:`scopetwin.scenes.geometry.refract` gives the same for a plane normal to z; this form keeps the
state exact in float64 and needs no normal vectors).

The RKN step itself (:func:`rkn_step`) is written once, over an array namespace (as the profiles are):
:func:`rkn_rod` runs it on numpy float64 arrays, and the ``dr.while_loop`` body of the Dr.Jit/Mitsuba tracer
(:func:`scopetwin.scenes.mitsuba.grin.rkn_rod_dr`) calls the same function on Dr.Jit arrays. This module is the
independent
cross-check of that tracer: same step, plain numpy, float64, everything else (the layer stack) traced separately.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.grin.profiles import NP, RadialProfile
from scopetwin.scenes.grin.setup import Layer, Stack

Array = NDArray[np.float64]


def rkn_step(
    x: Any, y: Any, tx: Any, ty: Any, opl: Any, n2: Any, k: Any, dt: Any, profile: RadialProfile, xp: Any = NP
) -> tuple[Any, Any, Any, Any, Any, Any, Any, Any]:
    """One Sharma-Kumar-Ghatak Runge-Kutta-Nystrom step of a ray in a radial GRIN medium (thesis §7.5.1 profiles).

    Integrates d²R/dt² = D(R) = ½∇n² with T = dR/dt over one step ``dt`` (Sharma, Kumar & Ghatak, Appl. Opt. 21,
    984 (1982)); D = 2 n dn/d(r²) (x, y) = k (x, y) comes from :meth:`RadialProfile.sharma`. The optical path
    dOPL/dt = n² is integrated by Simpson's rule on the stage points. Written once over the array namespace
    ``xp`` (only arithmetic and ``profile.sharma(r2, xp)``): numpy (:func:`rkn_rod`) and Dr.Jit (the
    ``dr.while_loop`` body of :func:`scopetwin.scenes.mitsuba.grin.rkn_rod_dr`) run this same function.

    Parameters
    ----------
    x, y : array
        Ray heights at the start of the step (mm).
    tx, ty : array
        Transverse optical direction cosines T = n dR/ds.
    opl : array
        Optical path so far (mm).
    n2, k : array
        n² and k = 2 n dn/d(r²) at (x, y), carried from the step before (``profile.sharma``).
    dt : array or float
        Step in the Sharma parameter t (dt = ds/n = Δz/T_z).
    profile : RadialProfile
        The monochromatic index profile.
    xp : namespace
        Array namespace of the profile formulas (``scenes.grin.profiles.NP`` or the Dr.Jit one).

    Returns
    -------
    x, y, tx, ty, opl, n2, k : array
        The state after the step (n² and k at the new point, for the next step).
    r2 : array
        x² + y² at the new point (for the wall test).
    """
    ax, ay = dt * k * x, dt * k * y
    x1 = x + dt * (0.5 * tx + 0.125 * ax)
    y1 = y + dt * (0.5 * ty + 0.125 * ay)
    n2_1, k1 = profile.sharma(x1 * x1 + y1 * y1, xp)
    bx, by = dt * k1 * x1, dt * k1 * y1
    x2 = x + dt * (tx + 0.5 * bx)
    y2 = y + dt * (ty + 0.5 * by)
    _, k2 = profile.sharma(x2 * x2 + y2 * y2, xp)
    cx, cy = dt * k2 * x2, dt * k2 * y2
    # (Dr.Jit turns a division by a Python number into a multiplication by its reciprocal, numpy divides)
    x = x + dt * (tx + (ax + 2.0 * bx) / 6.0)
    y = y + dt * (ty + (ay + 2.0 * by) / 6.0)
    tx = tx + (ax + 4.0 * bx + cx) / 6.0
    ty = ty + (ay + 4.0 * by + cy) / 6.0
    r2 = x * x + y * y
    n2_new, k = profile.sharma(r2, xp)
    opl = opl + dt / 6.0 * (n2 + 4.0 * n2_1 + n2_new)
    return x, y, tx, ty, opl, n2_new, k, r2


def rkn_rod(
    x: Array,
    y: Array,
    tx: Array,
    ty: Array,
    tz: Array,
    profile: RadialProfile,
    length: float,
    steps: int,
    radius: float = np.inf,
) -> tuple[Array, Array, Array, Array, Array, NDArray[np.bool_]]:
    """Sharma-Kumar-Ghatak RKN through a rod of ``length`` (thesis §7.5.1 profile), vectorised over rays.

    Parameters
    ----------
    x, y : ndarray
        Ray heights on the entry face (mm).
    tx, ty, tz : ndarray
        Optical direction cosines T = n dR/ds inside the rod at the entry face; ``tz`` > 0 is the
        component along the direction of travel (the rod is traversed in whichever z sense).
    profile : RadialProfile
        Monochromatic profile n(r²).
    length : float
        Rod length (mm).
    steps : int
        Number of RKN steps N (Δt = L / (N T_z)).
    radius : float
        Rod radius; rays whose step node leaves r <= radius are absorbed at the wall.

    Returns
    -------
    x, y, tx, ty : ndarray
        State on the exit face.
    opl : ndarray
        Optical path length through the rod (mm).
    alive : ndarray of bool
        False for rays absorbed at the wall.
    """
    x = np.array(x, dtype=np.float64)
    y = np.array(y, dtype=np.float64)
    tx = np.array(tx, dtype=np.float64)
    ty = np.array(ty, dtype=np.float64)
    dt = length / (steps * np.asarray(tz, dtype=np.float64))
    opl = np.zeros_like(x)
    r2 = x * x + y * y
    alive = r2 <= radius * radius
    n2, k = profile.sharma(r2, NP)
    for _ in range(steps):
        x, y, tx, ty, opl, n2, k, r2 = rkn_step(x, y, tx, ty, opl, n2, k, dt, profile, NP)
        alive &= r2 <= radius * radius
    return x, y, tx, ty, opl, alive


def rod_steps(length: float, step_mm: float) -> int:
    """Number of RKN steps for a rod (at least 4)."""
    return max(4, int(np.ceil(length / step_mm - 1e-9)))


@dataclass
class RayState:
    """Rays after the objective's last surface (z = ``z``), in air: position, T and OPL from the object."""

    x: Array
    y: Array
    tx: Array
    ty: Array
    opl: Array
    alive: NDArray[np.bool_]
    z: float
    n: float = 1.0
    max_r: dict[str, Array] = field(default_factory=dict)

    @property
    def tz(self) -> Array:
        return np.sqrt(np.maximum(self.n * self.n - self.tx**2 - self.ty**2, 0.0))

    def at(self, dz: float) -> tuple[Array, Array]:
        """Ray heights on the plane ``dz`` beyond ``z`` (homogeneous medium of index ``n``)."""
        tz = self.tz
        return self.x + dz * self.tx / tz, self.y + dz * self.ty / tz


def _through_homogeneous(
    layer: Layer, x: Array, y: Array, tx: Array, ty: Array, opl: Array, alive: NDArray[np.bool_]
) -> tuple[Array, Array, Array, NDArray[np.bool_]]:
    """Ray heights, OPL and survivors (``alive`` updated in place) after a homogeneous layer (T is conserved)."""
    t2 = tx * tx + ty * ty
    n = layer.index
    tz2 = n * n - t2
    alive &= tz2 > 0
    tz = np.sqrt(np.maximum(tz2, 1e-300))
    x = x + layer.thickness * tx / tz
    y = y + layer.thickness * ty / tz
    opl = opl + layer.thickness * n * n / tz
    return x, y, opl, alive


def _through_rod(
    layer: Layer,
    axis: tuple[float, float],
    x: Array,
    y: Array,
    tx: Array,
    ty: Array,
    opl: Array,
    alive: NDArray[np.bool_],
) -> tuple[Array, Array, Array, Array, Array, NDArray[np.bool_], Array]:
    """State after a GRIN rod layer (``alive`` updated in place), and each ray's radius on the rod's exit face."""
    rod, profile = layer.rod, layer.profile
    assert rod is not None and profile is not None  # a rod layer carries its profile (build_stack)
    ax, ay = axis
    t2 = tx * tx + ty * ty
    lx, ly = x - ax, y - ay
    r2 = lx * lx + ly * ly
    inside = r2 <= rod.radius**2
    n_rod = np.asarray(profile.index(np.minimum(r2, rod.radius**2))) * np.ones_like(x)
    n_in = np.where(inside, n_rod, 1.0)
    tz2 = n_in * n_in - t2
    alive &= inside & (tz2 > 0)
    tz = np.sqrt(np.maximum(tz2, 1e-300))
    lx, ly, tx, ty, dopl, ok = rkn_rod(
        lx, ly, tx, ty, tz, profile, rod.length, rod_steps(rod.length, rod.step_mm), rod.radius
    )
    alive &= ok
    return lx + ax, ly + ay, tx, ty, opl + dopl, alive, np.hypot(lx, ly)


def trace_stack(
    stack: Stack,
    x0: Array,
    y0: Array,
    tx0: Array,
    ty0: Array,
    *,
    axis: tuple[float, float] = (0.0, 0.0),
    stop_radius: float | None = None,
    until_layer: int | None = None,
) -> RayState:
    """Trace rays from the object plane (z = 0) through every layer but the image gap.

    Parameters
    ----------
    stack : Stack
        The objective (:func:`scopetwin.scenes.grin.setup.build_stack`).
    x0, y0 : ndarray
        Object points (mm), in the object plane.
    tx0, ty0 : ndarray
        Transverse optical direction cosines in object space (= n sin θ components; |T⊥| is the
        ray's numerical aperture).
    axis : (float, float)
        Optical axis of this objective in the array (rod centres).
    stop_radius : float, optional
        Clear radius of a stop on the back face of rod 1 (thesis §8.3.1: "aperture behind the first
        GRIN lens"); default: the stack's own ``stop_radius``.
    until_layer : int, optional
        Stop after this many layers (default: all but the final image gap).

    Returns
    -------
    RayState
        Rays on the plane where the final layer begins (the last surface), in its medium.
    """
    x = np.array(x0, dtype=np.float64) * np.ones(np.broadcast(x0, y0, tx0, ty0).shape)
    y = np.array(y0, dtype=np.float64) * np.ones_like(x)
    tx = np.array(tx0, dtype=np.float64) * np.ones_like(x)
    ty = np.array(ty0, dtype=np.float64) * np.ones_like(x)
    opl = np.zeros_like(x)
    alive = np.ones(x.shape, dtype=bool)
    stop = stack.stop_radius if stop_radius is None else stop_radius
    layers = stack.layers[:-1] if until_layer is None else stack.layers[:until_layer]
    max_r: dict[str, Array] = {}
    ax, ay = axis
    n_last = stack.layers[0].index
    for layer in layers:
        if layer.rod is None:
            x, y, opl, alive = _through_homogeneous(layer, x, y, tx, ty, opl, alive)
        else:
            x, y, tx, ty, opl, alive, max_r[layer.name] = _through_rod(layer, axis, x, y, tx, ty, opl, alive)
        if stop is not None and abs(layer.z1 - stack.stop_z) < 1e-12:
            alive &= (x - ax) ** 2 + (y - ay) ** 2 <= stop * stop
        n_last = layer.index
    final = stack.layers[len(layers)] if len(layers) < len(stack.layers) else stack.layers[-1]
    n_out = final.index
    alive &= n_out * n_out - (tx * tx + ty * ty) > 0
    del n_last
    return RayState(x, y, tx, ty, opl, alive, final.z0, n_out, max_r)
