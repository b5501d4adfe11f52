"""GRIN rod-lens objectives inside Mitsuba scenes (thesis ch. 7-8): Dr.Jit RKN tracer, integrator, pupil sensor.

Mitsuba has no gradient-index medium. Here every flat interface of the objective (cover glass,
air gaps, rod faces, AF32 substrates, B270 beam-splitter layer, object plane, image plane) is a
Mitsuba ``rectangle`` and every rod wall a ``cylinder``; Mitsuba's ``scene.ray_intersect`` finds
which surface a ray meets next. A per-shape table (gathered by shape id) says what the surface
is: its plane z, the indices on both sides, and whether a GRIN rod layer lies beyond it. When a
ray enters a rod, the Sharma-Kumar-Ghatak Runge-Kutta-Nystrom integrator (:func:`rkn_rod_dr`, a
``dr.while_loop``) carries it to the other face, integrating the optical path; the wall absorbs.
Rays that all start on the object or the image plane (a sequential trace: images, forward traces) meet the planes
in an order known before tracing (:meth:`GrinScene.planes_per_event`); with ``sequential=True`` (images) each plane
is then intersected directly, the same hit Mitsuba's intersection finds, without the query (the queries
were 80-85 % of an image's time).

Precision: ``"float32"`` runs the whole path in single precision (fast, for images);
``"float64"`` keeps the ray state in ``Float64`` and takes from Mitsuba's float32 intersection
only *which* plane is hit, recomputing the hit point exactly from the plane's z (for analysis).

Plugins (registered idempotently, per thread and variant, by :func:`register`; importing this module sets no
variant: every builder and renderer takes ``variant``, default ``choose("mono")``):

* integrator ``scopetwin_grin`` -- traces sensor rays backwards through the objective to the object
  plane and returns the transmission of the test target there (a Lambertian backlight of radiance 1);
* sensor ``scopetwin_grin_pupil`` -- a bare sensor at the image plane that samples, for each pixel
  sample, a point on the image-side face of the nearest objective's second rod (the exit pupil of
  the realized system) with weight A cos θ cos θ' / d², so the image is the irradiance.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any, Literal

import drjit as _drjit
import mitsuba as _mitsuba
import numpy as np

from scopetwin.scenes.camera import PixelGrid
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.grin.profiles import RadialProfile
from scopetwin.scenes.grin.rkn import rkn_step, rod_steps
from scopetwin.scenes.grin.setup import GrinSetup, Layer, Stack
from scopetwin.scenes.grin.targets import Target
from scopetwin.scenes.limits import check_render
from scopetwin.scenes.mitsuba.variant import mitsuba, register_plugin, render_complete, resolve

Precision = Literal["float32", "float64"]
Sampler = Literal["independent", "multijitter"]

# The mitsuba module, no variant set: its variant-dependent names (mi.Float, mi.Sensor, ...) are looked
# up when a function runs, after that function has set its variant (no variant is set at import).
mi: Any = _mitsuba  # typed Any: its names are built per variant at run time (pyproject.toml [tool.mypy])
dr: Any = _drjit

#: Dr.Jit namespace for the profile formulas of scenes.grin.profiles.
DR = SimpleNamespace(
    sqrt=dr.sqrt,
    tanh=dr.tanh,
    cosh=dr.cosh,
    where=dr.select,
    maximum=dr.maximum,
    floor=dr.floor,
    abs=dr.abs,
    minimum=dr.minimum,
)

KIND_INTERFACE, KIND_OBJECT, KIND_IMAGE, KIND_WALL = 0, 1, 2, 3
_EPS = {"float32": 2e-4, "float64": 2e-4}


def float_type(precision: Precision, variant: str | None = None) -> type:
    """Dr.Jit float type of the ray state in ``variant`` (default ``choose("mono")``; the variant is set)."""
    if precision not in ("float32", "float64"):
        raise ScopetwinError(f"precision must be 'float32' or 'float64', got {precision!r}")
    m = mitsuba(resolve(variant, "mono"))
    return m.Float64 if precision == "float64" else m.Float


# -- the integrator core -------------------------------------------------------------------------
def _rkn_state_step(state: tuple[Any, ...], dt: Any, profile: RadialProfile, rr: float) -> tuple[Any, ...]:
    """The loop state (x, y, tx, ty, opl, n2, k, alive) after one :func:`scopetwin.scenes.grin.rkn.rkn_step` on Dr.Jit
    arrays."""
    x, y, tx, ty, opl, n2, k, alive = state
    x, y, tx, ty, opl, n2, k, r2 = rkn_step(x, y, tx, ty, opl, n2, k, dt, profile, DR)
    return x, y, tx, ty, opl, n2, k, alive & (r2 <= rr)


def _split_groups(inputs: list[Any], groups: int, n: int, UInt: type) -> tuple[list[list[Any]], int]:
    """The ray arrays ``inputs`` gathered into ``groups`` groups of equal size (the last padded), and that size."""
    if groups > 1:
        size = -(-n // groups)
        parts = []
        for g in range(groups):
            idx = dr.minimum(dr.arange(UInt, size) + g * size, n - 1)
            parts.append([dr.gather(type(v), v, idx) for v in inputs])
    else:
        size = n
        parts = [inputs]
    return parts, size


def _merge_groups(res: list[list[Any]], n: int, size: int, UInt: type) -> tuple[Any, ...]:
    """The per-group results ``res`` (evaluated first) put back in ray order (inverse of :func:`_split_groups`)."""
    groups = len(res)
    dr.eval(*[v for r in res for v in r])
    idx = dr.arange(UInt, n)
    g_of = idx // size
    local = idx - g_of * size
    merged = []
    for j in range(6):
        v = dr.gather(type(res[0][j]), res[0][j], local)
        for g in range(1, groups):
            v = dr.select(g_of == g, dr.gather(type(res[g][j]), res[g][j], local), v)
        merged.append(v)
    return tuple(merged)


def rkn_rod_dr(
    x: Any,
    y: Any,
    tx: Any,
    ty: Any,
    tz: Any,
    profile: RadialProfile,
    length: float,
    steps: int,
    radius: float,
    active: Any = True,
    interleave: int = 1,
) -> tuple[Any, Any, Any, Any, Any, Any]:
    """Sharma-Kumar-Ghatak RKN through one rod in a ``dr.while_loop`` (thesis §7.5.1 profile).

    Same equations and arguments as :func:`scopetwin.scenes.grin.rkn.rkn_rod`, and the same step: the loop body calls
    :func:`scopetwin.scenes.grin.rkn.rkn_step` with the Dr.Jit namespace. The arrays are Dr.Jit arrays of any float type
    (float32 or float64 state). Returns (x, y, tx, ty, opl, alive) on the exit face.

    ``interleave`` > 1 splits the rays into that many groups advanced side by side in one loop body.
    One RKN step is a long chain of dependent operations, so a SIMD packet waits on latency; independent
    groups give the CPU other work meanwhile (instruction-level parallelism). Dr.Jit's LLVM packet is 16
    lanes for both types on AVX-512, so a float64 op is already two independent 8-lane halves, which is why
    float32 was no faster than float64 with ``interleave=1``. Splitting gathers the inputs (they are
    evaluated) and the results are put back in ray order, so use it on whole batches (benchmarks, analysis),
    not inside a render kernel.
    """
    Float = type(x)
    UInt = dr.uint32_array_t(Float)
    Bool = dr.mask_t(Float)
    n = dr.width(x)
    rr = radius * radius
    groups = max(1, int(interleave))
    if groups > 1 and n < 2 * groups:
        groups = 1
    inputs = [x, y, tx, ty, tz, Bool(active) & dr.full(Bool, True, n)]
    parts, size = _split_groups(inputs, groups, n, UInt)
    state: list[Any] = [dr.zeros(UInt, size)]
    dts = []
    for gx, gy, gtx, gty, gtz, gact in parts:
        dt = Float(length / steps) / gtz
        r2 = gx * gx + gy * gy
        n2, k = profile.sharma(r2, DR)
        dts.append(dt)
        state += [gx, gy, gtx, gty, dr.zeros(Float, size), n2, k, gact & (r2 <= rr)]

    def cond(i: Any, *rest: Any) -> Any:
        go = rest[7]
        for g in range(1, groups):
            go = go | rest[8 * g + 7]
        return (i < steps) & go

    def body(i: Any, *rest: Any) -> tuple[Any, ...]:
        out: list[Any] = [i + 1]
        for g in range(groups):
            out += _rkn_state_step(tuple(rest[8 * g : 8 * g + 8]), dts[g], profile, rr)
        return tuple(out)

    final = dr.while_loop(state=tuple(state), cond=cond, body=body)
    res = [[final[1 + 8 * g + j] for j in (0, 1, 2, 3, 4, 7)] for g in range(groups)]
    if groups == 1:
        return tuple(res[0])
    return _merge_groups(res, n, size, UInt)


# -- the scene -------------------------------------------------------------------------------------
def _square_mesh(name: str, z: float, half: float) -> Any:
    """A two-triangle mesh for the square |x|, |y| <= ``half`` at height ``z``.

    Embree intersects triangles natively; a ``rectangle`` shape goes through a user-geometry callback
    (measured ~15-25 % slower per ray here). Only the shape id of a hit is used, so the mesh is exact.
    """
    mesh = mi.Mesh(name, 4, 2)
    params = mi.traverse(mesh)
    params["vertex_positions"] = dr.ravel(mi.Point3f([-half, half, half, -half], [-half, -half, half, half], [z] * 4))
    params["faces"] = dr.ravel(mi.Vector3u([0, 0], [1, 2], [2, 3]))
    params.update()
    return mesh


@dataclass
class _RodLayer:
    profile: RadialProfile
    length: float
    radius: float
    steps: int
    z0: float
    z1: float
    n_before: float
    n_after: float


def _rod_layers(layers: tuple[Layer, ...], step_mm: float | None) -> list[_RodLayer]:
    """The GRIN rods of a stack with their RKN steps (``step_mm`` overrides the rods' own) and outer indices."""
    rods: list[_RodLayer] = []
    for i, layer in enumerate(layers):
        if layer.rod is None:
            continue
        assert layer.profile is not None  # a rod layer carries its profile (build_stack)
        steps = rod_steps(layer.rod.length, step_mm or layer.rod.step_mm)
        rods.append(
            _RodLayer(
                layer.profile,
                layer.rod.length,
                layer.rod.radius,
                steps,
                layer.z0,
                layer.z1,
                layers[i - 1].index if i > 0 else 1.0,
                layers[i + 1].index if i + 1 < len(layers) else 1.0,
            )
        )
    return rods


def _stack_planes(layers: tuple[Layer, ...]) -> list[dict[str, Any]]:
    """The planes of a stack: z, kind, the indices and rods (-1: none) on both sides; a zero-thickness layer raises.

    One plane at z = 0 (object), one between consecutive layers, one at the image plane.
    """
    rod_index = {i: j for j, i in enumerate(i for i, layer in enumerate(layers) if layer.rod is not None)}
    planes: list[dict[str, Any]] = []
    for b in range(len(layers) + 1):
        below = layers[b - 1] if b > 0 else None
        above = layers[b] if b < len(layers) else None
        if above is not None:
            z = above.z0
        else:
            assert below is not None  # b = len(layers) >= 1
            z = below.z1
        kind = KIND_OBJECT if below is None else (KIND_IMAGE if above is None else KIND_INTERFACE)
        planes.append(
            {
                "z": z,
                "kind": kind,
                "n_minus": below.index if below is not None else 1.0,
                "n_plus": above.index if above is not None else 1.0,
                "rod_minus": rod_index.get(b - 1, -1) if below is not None else -1,
                "rod_plus": rod_index.get(b, -1) if above is not None else -1,
            }
        )
    zs = [p["z"] for p in planes]
    if any(b - a <= 1e-9 for a, b in zip(zs[:-1], zs[1:], strict=True)):
        raise ScopetwinError(
            "GRIN stack has a layer of zero or negative thickness (two planes at one z): "
            f"plane z = {[round(z, 6) for z in zs]}"
        )
    return planes


def _scene_dict(planes: list[dict[str, Any]], rods: list[_RodLayer], axes: np.ndarray, half: float) -> dict[str, Any]:
    """The scene dictionary: a square mesh of side 2 ``half`` per plane, a cylinder per rod wall and objective."""
    scene: dict[str, Any] = {"type": "scene"}
    for k, p in enumerate(planes):
        scene[f"plane_{k:02d}"] = _square_mesh(f"plane_{k:02d}", p["z"], half)
    for j, rod in enumerate(rods):
        for a, (ax, ay) in enumerate(axes):
            scene[f"wall_{j}_{a}"] = {
                "type": "cylinder",
                "p0": [ax, ay, rod.z0],
                "p1": [ax, ay, rod.z1],
                "radius": rod.radius,
            }
    return scene


def _shape_tables(
    scene: Any, planes: list[dict[str, Any]]
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], np.ndarray]:
    """The per-shape tables (by shape id) of the loaded scene: plane z and indices, rods beyond, kind (walls else)."""
    ids = np.asarray(dr.reinterpret_array(mi.UInt32, scene.shapes_dr()), dtype=np.int64)
    size = int(ids.max()) + 1
    tab = {k: np.zeros(size) for k in ("z", "n_minus", "n_plus")}
    itab = {k: np.full(size, -1, dtype=np.int32) for k in ("rod_minus", "rod_plus")}
    kinds = np.full(size, KIND_WALL, dtype=np.int32)
    for sid, shape in zip(ids, scene.shapes(), strict=True):
        name = shape.id()
        if name.startswith("plane_"):
            p = planes[int(name[6:])]
            for key in tab:
                tab[key][sid] = p[key]
            for key in itab:
                itab[key][sid] = p[key]
            kinds[sid] = p["kind"]
    return tab, itab, kinds


def _plane_shape_ids(scene: Any, count: int) -> list[int]:
    """The shape id of each of the ``count`` planes ``plane_{k:02d}`` of the loaded scene."""
    ids = np.asarray(dr.reinterpret_array(mi.UInt32, scene.shapes_dr()), dtype=np.int64)
    by_name = {shape.id(): int(sid) for sid, shape in zip(ids, scene.shapes(), strict=True)}
    return [by_name[f"plane_{k:02d}"] for k in range(count)]


@dataclass
class _Rays:
    """The state of the rays of :meth:`GrinScene.trace`: position, T, index, OPL, fate (Dr.Jit arrays)."""

    px: Any
    py: Any
    pz: Any
    tx: Any
    ty: Any
    tz: Any
    n_cur: Any
    opl: Any
    alive: Any
    done: Any
    term_kind: Any

    @classmethod
    def start(cls, F: type, p: tuple[Any, Any, Any], t: tuple[Any, Any, Any], n_start: float, active: Any) -> _Rays:
        """Rays at ``p`` with optical direction cosines ``t`` in a medium of index ``n_start``, none ended yet."""
        px, py, pz = (F(v) for v in p)
        tx, ty, tz = (F(v) for v in t)
        n_cur = dr.zeros(F, dr.width(px)) + n_start
        opl = dr.zeros(F, dr.width(px))
        alive = dr.mask_t(F)(active) & dr.full(dr.mask_t(F), True, dr.width(px))
        done = dr.full(dr.mask_t(F), False, dr.width(px))
        term_kind = dr.zeros(mi.Int32, dr.width(px))
        return cls(px, py, pz, tx, ty, tz, n_cur, opl, alive, done, term_kind)

    def arrays(self) -> tuple[Any, ...]:
        """The state's arrays, in the order the trace evaluates them."""
        return (
            self.px,
            self.py,
            self.pz,
            self.tx,
            self.ty,
            self.tz,
            self.n_cur,
            self.opl,
            self.alive,
            self.done,
            self.term_kind,
        )


def _embree_hit(scene: Any, rays: _Rays, run: Any, eps: float) -> tuple[Any, Any]:
    """Shape id and validity of the next surface the running rays ``run`` meet, from Mitsuba's ray intersection."""
    inv_n = 1.0 / rays.n_cur
    dx, dy, dz = rays.tx * inv_n, rays.ty * inv_n, rays.tz * inv_n
    o = mi.Point3f(mi.Float(rays.px + eps * dx), mi.Float(rays.py + eps * dy), mi.Float(rays.pz + eps * dz))
    ray = mi.Ray3f(o, mi.Vector3f(mi.Float(dx), mi.Float(dy), mi.Float(dz)))
    # only the shape id is needed (the hit point is recomputed from the plane's z): the preliminary
    # intersection skips the per-shape surface-interaction call
    si = scene.ray_intersect_preliminary(ray, coherent=True, active=run)
    return dr.reinterpret_array(mi.UInt32, si.shape), run & si.is_valid()


def _known_plane_hit(rays: _Rays, run: Any, plane: dict[str, Any]) -> tuple[Any, Any]:
    """Shape id and validity when the plane met next is known (a sequential trace, :meth:`GrinScene.known_planes`).

    ``plane``: its row of :attr:`GrinScene.planes` with its shape id ``sid`` and the half side ``half`` of its
    square. A ray meets it where it crosses z inside the square and ahead of it — what Mitsuba's intersection
    finds too: no other surface lies between consecutive planes outside the rods, whose walls span only the rod
    layers that the RKN jump crosses —, so no intersection query is needed.
    """
    half = plane["half"]
    s = (plane["z"] - rays.pz) / rays.tz
    hx = rays.px + s * rays.tx
    hy = rays.py + s * rays.ty
    valid = run & (s > 0) & (dr.abs(hx) <= half) & (dr.abs(hy) <= half)
    return dr.full(mi.UInt32, plane["sid"], dr.width(rays.px)), valid


def _lookup(tab: dict[str, Any], key: str, T: type, sid: Any, mask: Any, plane: dict[str, Any] | None) -> Any:
    """Column ``key`` of the shape table at the shape ids ``sid`` (0 outside ``mask``), or the known plane's value.

    Callers use the result only inside ``mask``.
    """
    return dr.gather(T, tab[key], sid, mask) if plane is None else T(plane[key])


def _to_next_plane(
    scene: Any, rays: _Rays, tab: dict[str, Any], F: type, eps: float, plane: dict[str, Any] | None = None
) -> tuple[Any, Any, Any]:
    """Move the running rays to the next plane (hit point recomputed from its z); returns hit, its kind, shape id.

    ``plane``: the plane met next when it is known (:func:`_known_plane_hit`), else Mitsuba's ray intersection
    finds it (:func:`_embree_hit`). Rays that meet nothing or a rod wall are absorbed.
    """
    run = rays.alive & ~rays.done
    sid, valid = _embree_hit(scene, rays, run, eps) if plane is None else _known_plane_hit(rays, run, plane)
    inv_n = 1.0 / rays.n_cur
    dx, dy, dz = rays.tx * inv_n, rays.ty * inv_n, rays.tz * inv_n
    kind = _lookup(tab, "kind", mi.Int32, sid, valid, plane)
    rays.alive &= ~run | (valid & (kind != KIND_WALL))
    hit = run & rays.alive
    zp = _lookup(tab, "z", F, sid, hit, plane)
    s = (zp - rays.pz) / dz
    rays.px = dr.select(hit, rays.px + s * dx, rays.px)
    rays.py = dr.select(hit, rays.py + s * dy, rays.py)
    rays.pz = dr.select(hit, zp, rays.pz)
    rays.opl = dr.select(hit, rays.opl + rays.n_cur * s, rays.opl)
    return hit, kind, sid


class GrinScene:
    """A Mitsuba scene of a GRIN objective array, with the tables the tracer gathers from.

    Parameters
    ----------
    setup : GrinSetup
        The design (layers, array, camera).
    stack : Stack
        Its layer stack at the wavelength wanted, including the image gap (the image plane is its end).
    step_mm : float, optional
        RKN step length overriding the rods' own ``step_mm`` (coarser steps for images).
    sensor : dict, optional
        A Mitsuba sensor dictionary to put in the scene (the pupil sensor for images).
    integrator : dict, optional
        A Mitsuba integrator dictionary.
    variant : str, optional
        The Mitsuba variant the scene is built and traced in (default ``choose("mono")``, resolved now).
    """

    def __init__(
        self,
        setup: GrinSetup,
        stack: Stack,
        step_mm: float | None = None,
        sensor: dict[str, Any] | None = None,
        integrator: dict[str, Any] | None = None,
        variant: str | None = None,
    ) -> None:
        self.variant = resolve(variant, "mono")
        mitsuba(self.variant)
        if sensor is not None or integrator is not None:
            register(self.variant)
        self.setup = setup
        self.stack = stack
        self.axes = np.array(setup.array.axes(), dtype=np.float64)
        half = 0.5 * setup.array.substrate_side
        self.rods: list[_RodLayer] = _rod_layers(stack.layers, step_mm)
        planes = _stack_planes(stack.layers)
        self.planes = planes
        scene = _scene_dict(planes, self.rods, self.axes, half)
        if sensor is not None:
            scene["sensor"] = sensor
        if integrator is not None:
            scene["integrator"] = integrator
        self.scene = mi.load_dict(scene)
        self._tab_np, self._itab_np, self._kind_np = _shape_tables(self.scene, planes)
        self.half = half
        #: the shape id of each plane (the scene's plane_{k:02d})
        self._plane_sid = _plane_shape_ids(self.scene, len(planes))
        self.stop_z = stack.stop_z
        self.stop_radius = stack.stop_radius
        self.z_image = planes[-1]["z"]
        self.z_pupil = self.rods[-1].z1 if self.rods else stack.last_surface_z
        self._tables: dict[str, dict[str, Any]] = {}

    def tables(self, precision: Precision) -> dict[str, Any]:
        """Dr.Jit copies of the shape tables in the state's float type."""
        if precision not in self._tables:
            F = float_type(precision, self.variant)
            t = {k: F(v) for k, v in self._tab_np.items()}
            t |= {k: mi.Int32(v) for k, v in self._itab_np.items()}
            t["kind"] = mi.Int32(self._kind_np)
            self._tables[precision] = t
        return self._tables[precision]

    def nearest_axis(self, x: Any, y: Any) -> tuple[Any, Any]:
        """Optical axis (ax, ay) of the objective nearest to (x, y) (regular grid, §8.2.2)."""
        arr = self.setup.array
        x0 = -0.5 * (arr.nx - 1) * arr.pitch
        y0 = -0.5 * (arr.ny - 1) * arr.pitch
        ix = dr.clip(dr.round((x - x0) / arr.pitch), 0, arr.nx - 1)
        iy = dr.clip(dr.round((y - y0) / arr.pitch), 0, arr.ny - 1)
        return x0 + ix * arr.pitch, y0 + iy * arr.pitch

    def planes_per_event(self, start: Literal["object", "image"] | None) -> list[int]:
        """The plane (index into :attr:`planes`) met at each event of a sequential trace, -1 past the last plane.

        Rays run monotonically in z and meet every plane once, except the far faces of the rods (the RKN
        jump), so for rays that all start on the object plane (``"object"``, going +z) or on the image plane
        (``"image"``, going -z) the plane met at event k is known before tracing. ``None`` (rays starting
        anywhere): -1 at every event.
        """
        events = len(self.planes) - 1 - len(self.rods)
        if start is None:
            return [-1] * events
        step = 1 if start == "object" else -1
        plane = 0 if start == "object" else len(self.planes) - 1
        out: list[int] = []
        for _ in range(events):
            plane += step
            if not 0 <= plane < len(self.planes):
                out.append(-1)
                continue
            out.append(plane)
            plane += step if self.planes[plane]["rod_plus" if step > 0 else "rod_minus"] >= 0 else 0
        return out

    def rods_per_event(self, start: Literal["object", "image"] | None) -> list[list[int]]:
        """Rods a ray can enter at each event of a sequential trace (:meth:`planes_per_event`).

        For ``start`` ``"object"`` or ``"image"`` the plane met at event k, and hence the one rod that can be
        entered there, is known: one RKN loop per rod in the kernel instead of one per rod and event. ``None``:
        every rod at every event (rays starting anywhere).
        """
        if start is None:
            return [list(range(len(self.rods)))] * len(self.planes_per_event(None))
        side = "rod_plus" if start == "object" else "rod_minus"
        out: list[list[int]] = []
        for plane in self.planes_per_event(start):
            j = self.planes[plane][side] if plane >= 0 else -1
            out.append([j] if j >= 0 else [])
        return out

    def known_planes(self, start: Literal["object", "image"] | None) -> list[dict[str, Any] | None]:
        """Per event of a sequential trace, the plane met (None: not known): its row of :attr:`planes` with its
        shape id ``sid`` and the half side ``half`` of its square.

        What :func:`_known_plane_hit` takes instead of asking Mitsuba's ray intersection.
        """
        return [
            None if k < 0 else self.planes[k] | {"sid": self._plane_sid[k], "half": self.half}
            for k in self.planes_per_event(start)
        ]

    def trace(
        self,
        p: tuple[Any, Any, Any],
        t: tuple[Any, Any, Any],
        n_start: float,
        precision: Precision = "float64",
        active: Any = True,
        max_events: int | None = None,
        eval_each: bool = False,
        start: Literal["object", "image"] | None = None,
        sequential: bool = False,
    ) -> dict[str, Any]:
        """Trace rays from positions ``p`` with optical direction cosines ``t`` (|t| = n_start) until they meet the
        object or the image plane.

        ``start``: all rays start on the object plane going +z (``"object"``) or on the image plane going
        -z (``"image"``); lets the kernel hold one RKN loop per rod (:meth:`rods_per_event`).
        ``sequential`` (with ``start``): the plane met at each event is known (:meth:`known_planes`), so it is
        intersected directly instead of through Mitsuba's ray intersection (the same hits; the images' path).

        Returns a dict with ``x, y, z`` (hit point on the terminal plane), ``tx, ty, tz``, ``opl``,
        ``alive`` (reached a terminal plane unabsorbed) and ``kind`` (KIND_OBJECT / KIND_IMAGE).
        """
        F = float_type(precision, self.variant)
        tab = self.tables(precision)
        rays = _Rays.start(F, p, t, n_start, active)
        eps = _EPS[precision]
        stop_r2 = None if self.stop_radius is None else self.stop_radius**2
        # a sequential path meets every plane once, except the far faces of the rods (reached by the RKN jump)
        plan = self.rods_per_event(start)
        events = max_events or len(plan)
        plan = (plan + [list(range(len(self.rods)))] * events)[:events]
        known = self.known_planes(start if sequential else None)
        known = (known + [None] * events)[:events]
        for event in range(events):
            self._event(rays, tab, F, eps, stop_r2, plan[event], known[event])
            if eval_each:
                dr.eval(*rays.arrays())
        rays.alive &= rays.done
        return {
            "x": rays.px,
            "y": rays.py,
            "z": rays.pz,
            "tx": rays.tx,
            "ty": rays.ty,
            "tz": rays.tz,
            "opl": rays.opl,
            "alive": rays.alive,
            "kind": rays.term_kind,
            "n": rays.n_cur,
        }

    def _event(
        self,
        rays: _Rays,
        tab: dict[str, Any],
        F: type,
        eps: float,
        stop_r2: float | None,
        rods: list[int],
        plane: dict[str, Any] | None = None,
    ) -> None:
        """One event of the trace: running rays move to the next plane and end there, cross it, or enter a rod.

        ``plane``: the plane met, when known (:meth:`known_planes`).
        """
        hit, kind, sid = _to_next_plane(self.scene, rays, tab, F, eps, plane)
        up = rays.tz > 0
        n_plus, n_minus = (_lookup(tab, k, F, sid, hit, plane) for k in ("n_plus", "n_minus"))
        rod_plus, rod_minus = (_lookup(tab, k, mi.Int32, sid, hit, plane) for k in ("rod_plus", "rod_minus"))
        n_next = dr.select(up, n_plus, n_minus)
        rod_next = dr.select(up, rod_plus, rod_minus)
        rod_prev = dr.select(up, rod_minus, rod_plus)
        term = hit & ((kind == KIND_OBJECT) | (kind == KIND_IMAGE))
        rays.done |= term
        rays.term_kind = dr.select(term, kind, rays.term_kind)
        cont = hit & ~term
        # rays that reached a plane through a rod layer outside the rods met the holders: absorbed
        rays.alive &= ~cont | (rod_prev < 0)
        cont &= rays.alive
        ax, ay = self.nearest_axis(rays.px, rays.py)
        lx, ly = rays.px - ax, rays.py - ay
        r2 = lx * lx + ly * ly
        if stop_r2 is not None:
            at_stop = cont & (dr.abs(rays.pz - self.stop_z) < 1e-6)
            rays.alive &= ~at_stop | (r2 <= stop_r2)
            cont &= rays.alive
        plain = cont & (rod_next < 0)
        tz2 = n_next * n_next - rays.tx * rays.tx - rays.ty * rays.ty
        rays.alive &= ~plain | (tz2 > 0)
        plain &= rays.alive
        sign = dr.select(up, F(1.0), F(-1.0))
        rays.tz = dr.select(plain, sign * dr.sqrt(dr.maximum(tz2, 0.0)), rays.tz)
        rays.n_cur = dr.select(plain, n_next, rays.n_cur)
        for j in rods:
            self._through_rod(rays, j, cont & (rod_next == j), (lx, ly, r2), (ax, ay), up, sign, F, stop_r2)

    def _through_rod(
        self,
        rays: _Rays,
        j: int,
        m: Any,
        local: tuple[Any, Any, Any],
        axis: tuple[Any, Any],
        up: Any,
        sign: Any,
        F: type,
        stop_r2: float | None,
    ) -> None:
        """Carry the rays ``m`` from rod ``j``'s entry face (at ``local`` = (x, y, r²) from ``axis``) to its exit."""
        rod = self.rods[j]
        lx, ly, r2 = local
        ax, ay = axis
        rays.alive &= ~m | (r2 <= rod.radius**2)
        m &= rays.alive
        n_in = rod.profile.index(dr.minimum(r2, rod.radius**2), DR)
        tzi2 = n_in * n_in - rays.tx * rays.tx - rays.ty * rays.ty
        tz_in = dr.sqrt(dr.maximum(tzi2, 1e-12))
        ox, oy, otx, oty, dopl, ok = rkn_rod_dr(
            lx, ly, rays.tx, rays.ty, tz_in, rod.profile, rod.length, rod.steps, rod.radius, m
        )
        rays.alive &= ~m | ok
        m &= rays.alive
        rays.px = dr.select(m, ox + ax, rays.px)
        rays.py = dr.select(m, oy + ay, rays.py)
        rays.pz = dr.select(m, dr.select(up, F(rod.z1), F(rod.z0)), rays.pz)
        rays.opl = dr.select(m, rays.opl + dopl, rays.opl)
        rays.tx = dr.select(m, otx, rays.tx)
        rays.ty = dr.select(m, oty, rays.ty)
        n_b = dr.select(up, F(rod.n_after), F(rod.n_before))
        tzo2 = n_b * n_b - rays.tx * rays.tx - rays.ty * rays.ty
        rays.alive &= ~m | (tzo2 > 0)
        m &= rays.alive
        if stop_r2 is not None:
            at_stop = m & (dr.abs(rays.pz - self.stop_z) < 1e-6)
            rays.alive &= ~at_stop | (ox * ox + oy * oy <= stop_r2)
            m &= rays.alive
        rays.tz = dr.select(m, sign * dr.sqrt(dr.maximum(tzo2, 0.0)), rays.tz)
        rays.n_cur = dr.select(m, n_b, rays.n_cur)


# -- plugins -------------------------------------------------------------------------------------
def _integrator_class(mi: Any) -> type:
    """The integrator class of ``scopetwin_grin`` for the variant of ``mi`` (Mitsuba classes are per variant)."""

    class GrinIntegrator(mi.SamplingIntegrator):
        """Integrator ``scopetwin_grin``: backward trace through the GRIN objective to the target (thesis §8.5)."""

        def __init__(self, props: mi.Properties) -> None:
            super().__init__(props)
            self.precision = props.get("precision", "float32")
            #: the planes met are known (a sequential trace from the image plane): no Mitsuba ray intersection
            self.sequential = bool(props.get("sequential", True))
            #: (GrinScene, Target) of the render in progress, set by :func:`render_image` for the call only
            self.context: tuple[GrinScene, Target] | None = None

        def sample(
            self,
            scene: mi.Scene,
            sampler: mi.Sampler,
            ray: mi.RayDifferential3f,
            medium: Any = None,
            active: Any = True,
        ) -> tuple[Any, Any, list]:
            if self.context is None:
                raise ScopetwinError("scopetwin_grin renders only through scenes.mitsuba.grin.render_image")
            gs, target = self.context
            res = gs.trace(
                (ray.o.x, ray.o.y, ray.o.z),
                (ray.d.x, ray.d.y, ray.d.z),
                1.0,
                self.precision,
                active=active,
                start="image",
                sequential=self.sequential,
            )
            ok = res["alive"] & (res["kind"] == KIND_OBJECT)
            x, y = mi.Float(res["x"]), mi.Float(res["y"])
            ax, ay = gs.nearest_axis(x, y)
            value = target.transmission(x - ax, y - ay, DR)
            return mi.Spectrum(dr.select(ok, value, 0.0)), mi.Bool(ok), []

        def aov_names(self) -> list[str]:
            return []

        def to_string(self) -> str:
            return f"GrinIntegrator[precision={self.precision}, sequential={self.sequential}]"

    return GrinIntegrator


def _pupil_sensor_class(mi: Any) -> type:
    """The sensor class of ``scopetwin_grin_pupil`` for the variant of ``mi``."""

    class PupilSensor(mi.Sensor):
        """Sensor ``scopetwin_grin_pupil``: bare image plane sampling the exit-pupil disk of the nearest objective.

        Properties: ``z`` (image plane), ``z_pupil`` (plane of the pupil disk), ``pupil_radius``, ``pixel``
        (pitch, mm), ``nx``, ``ny``, ``pitch`` (objective grid), ``x0``, ``y0`` (the grid's first axis), ``cx``, ``cy``
        (image-plane point at the sensor's centre).
        Pixel (row, col) covers u in [(col - W/2) p, (col + 1 - W/2) p] + cx, v from the top row down
        (docs/contract.md, "Camera"; the convention of :class:`scopetwin.scenes.camera.PixelGrid`, whose ``uv_film``
        maps the film samples).
        """

        def __init__(self, props: mi.Properties) -> None:
            super().__init__(props)
            self.z = props.get("z", 0.0)
            self.z_pupil = props.get("z_pupil", 0.0)
            self.radius = props.get("pupil_radius", 1.0)
            self.pixel = props.get("pixel", 0.0022)
            self.center = (props.get("cx", 0.0), props.get("cy", 0.0))
            self.grid = (
                props.get("nx", 1),
                props.get("ny", 1),
                props.get("pitch", 1.0),
                props.get("x0", 0.0),
                props.get("y0", 0.0),
            )
            size = self.film().size()
            #: the camera's pixel grid, centred on the image-plane point (cx, cy) (scenes.camera.PixelGrid)
            self.pixel_grid = PixelGrid(int(size[0]), int(size[1]), self.pixel, self.center)
            self.width_mm = self.pixel_grid.width_mm
            self.height_mm = self.pixel_grid.height_mm

        def _axis(self, u: Any, v: Any) -> tuple[Any, Any]:
            nx, ny, pitch, x0, y0 = self.grid
            ix = dr.clip(dr.round((u - x0) / pitch), 0, nx - 1)
            iy = dr.clip(dr.round((v - y0) / pitch), 0, ny - 1)
            return x0 + ix * pitch, y0 + iy * pitch

        def sample_ray(
            self, time: Any, sample1: Any, sample2: Any, sample3: Any, active: Any = True
        ) -> tuple[Any, Any]:
            u, v = self.pixel_grid.uv_film(sample2.x, sample2.y)
            ax, ay = self._axis(u, v)
            r = self.radius * dr.sqrt(sample3.x)
            phi = 2.0 * dr.pi * sample3.y
            q = mi.Point3f(u, v, self.z)
            p = mi.Point3f(ax + r * dr.cos(phi), ay + r * dr.sin(phi), self.z_pupil)
            d = p - q
            dist2 = dr.squared_norm(d)
            d = d * dr.rsqrt(dist2)
            cos2 = d.z * d.z
            weight = dr.pi * self.radius * self.radius * cos2 / dist2
            return mi.Ray3f(q, d, time, []), mi.Spectrum(weight)

        def sample_ray_differential(
            self, time: Any, sample1: Any, sample2: Any, sample3: Any, active: Any = True
        ) -> tuple[Any, Any]:
            ray, w = self.sample_ray(time, sample1, sample2, sample3, active)
            return mi.RayDifferential3f(ray), w

        def bbox(self) -> mi.ScalarBoundingBox3f:
            return mi.ScalarBoundingBox3f(
                [-self.width_mm, -self.height_mm, self.z_pupil], [self.width_mm, self.height_mm, self.z]
            )

        def to_string(self) -> str:
            return f"PupilSensor[z={self.z}, z_pupil={self.z_pupil}, radius={self.radius}]"

    return PupilSensor


def register(variant: str | None = None) -> None:
    """Register ``scopetwin_grin`` and ``scopetwin_grin_pupil`` for ``variant`` (default ``choose("mono")``) in this
    thread; idempotent per thread and variant."""
    variant = resolve(variant, "mono")
    register_plugin("integrator", "scopetwin_grin", _integrator_class, variant)
    register_plugin("sensor", "scopetwin_grin_pupil", _pupil_sensor_class, variant)


# -- high-level uses ------------------------------------------------------------------------------
def trace_forward(
    setup: GrinSetup,
    stack: Stack,
    x0: np.ndarray,
    y0: np.ndarray,
    tx0: np.ndarray,
    ty0: np.ndarray,
    precision: Precision = "float64",
    step_mm: float | None = None,
    variant: str | None = None,
) -> dict[str, np.ndarray]:
    """Rays from object points (z = 0, in the cover glass) to the image plane through the Mitsuba scene.

    Object points and results are relative to the first objective's axis (``setup.array.axes()[0]``).
    ``variant``: the Mitsuba variant (default ``choose("mono")``).

    Returns numpy arrays ``x, y`` on the image plane, ``tx, ty``, ``opl`` and ``alive``.
    """
    gs = GrinScene(setup, stack, step_mm, variant=variant)
    ax, ay = setup.array.axes()[0]
    n0 = stack.layers[0].index
    tz = np.sqrt(n0 * n0 - tx0**2 - ty0**2)
    res = gs.trace((x0 + ax, y0 + ay, np.zeros_like(x0)), (tx0, ty0, tz), n0, precision, start="object")
    ok = np.asarray(res["alive"]) & (np.asarray(res["kind"]) == KIND_IMAGE)
    out = {k: np.asarray(res[k], dtype=np.float64) for k in ("x", "y", "tx", "ty", "opl")}
    out["x"] -= ax
    out["y"] -= ay
    return out | {"alive": ok}


def _pupil_sensor(
    setup: GrinSetup,
    stack: Stack,
    size: tuple[int, int],
    center: tuple[float, float] | None,
    sampler: dict[str, Any],
) -> dict[str, Any]:
    """The ``scopetwin_grin_pupil`` sensor dictionary of :func:`render_image`: a film of ``size`` = (width, height)
    pixels centred on ``center``, the last rod's exit face as the pupil, and the ``sampler`` dictionary."""
    arr = setup.array
    last_rod = [layer for layer in stack.layers if layer.rod is not None][-1]
    assert last_rod.rod is not None
    return {
        "type": "scopetwin_grin_pupil",
        "z": stack.layers[-1].z1,
        "z_pupil": last_rod.z1,
        "pupil_radius": last_rod.rod.radius,
        "pixel": setup.camera.pitch_mm,
        "nx": arr.nx,
        "ny": arr.ny,
        "pitch": arr.pitch,
        "x0": -0.5 * (arr.nx - 1) * arr.pitch,
        "y0": -0.5 * (arr.ny - 1) * arr.pitch,
        "cx": (center or (0.0, 0.0))[0],
        "cy": (center or (0.0, 0.0))[1],
        "film": {
            "type": "hdrfilm",
            "width": size[0],
            "height": size[1],
            "rfilter": {"type": "box"},
            "pixel_format": "luminance",
            "component_format": "float32",
        },
        "sampler": sampler,
    }


def render_image(
    setup: GrinSetup,
    stack: Stack,
    target: Target,
    spp: int = 16,
    width: int | None = None,
    height: int | None = None,
    precision: Precision = "float32",
    step_mm: float = 0.9,
    center: tuple[float, float] | None = None,
    seed: int = 0,
    variant: str | None = None,
    sequential: bool = True,
    sampler: Sampler = "independent",
) -> np.ndarray:
    """Image of ``target`` through the objective array onto the camera (irradiance, float32, row 0 at the top).

    Uses the registered ``scopetwin_grin`` integrator and ``scopetwin_grin_pupil`` sensor with ``mi.render``.
    ``step_mm``: RKN step for images; 0.9 mm gives the 4-step minimum in both §8.3.2 rods, whose image-plane ray
    positions differ from 0.01 mm steps by 0.018 µm RMS, 0.035 µm max (float32: the same), 1/60 of a 2.2 µm
    pixel; 0.17 % of the rays at NA 0.45 change fate at the rod wall (the wall is tested at the step points).
    ``center``: the point of the image plane (mm) at the middle of the sensor; default the array's centre
    (the whole demonstrator image, Fig. 8.16); pass an objective's axis for a one-objective window.
    ``variant``: the Mitsuba variant (default ``choose("mono")``, resolved now). A size or ``spp`` below 1, or a
    render beyond the memory or time limit, is a :class:`scopetwin.scenes.limits.LimitError` before anything is
    allocated.
    ``sequential``: every path meets the planes in a known order, so they are intersected directly
    (:meth:`GrinScene.known_planes`); False asks Mitsuba's ray intersection at every plane (the same image, bit
    for bit, 5-7x slower: the intersection queries were 80-85 % of the render).
    ``sampler``: Mitsuba's sampler of the pixel and pupil samples. ``"independent"``; ``"multijitter"``
    (correlated multi-jittered: stratified pixel and pupil samples, the same image with less noise — on a
    348 x 260 window of the §8.3.2 grid image 25 spp have 7 % less per-pixel noise than 64 independent ones and
    36 spp 30 % less, ``benchmarks/grin_speed.py``) takes only the counts Mitsuba does not round
    (:func:`sampler_counts_exact`), others are a :class:`ScopetwinError`.
    """
    width = setup.camera.width_px if width is None else int(width)
    height = setup.camera.height_px if height is None else int(height)
    check_render(width, height, int(spp), f"GRIN image of {setup.name or setup.section}", "grin")
    if not sampler_counts_exact(sampler, int(spp)):
        ok = [n for n in range(max(1, spp - 16), spp + 17) if sampler_counts_exact(sampler, n)]
        raise ScopetwinError(f"the {sampler} sampler rounds {spp} spp up; take one of {ok}")
    variant = resolve(variant, "mono")
    sensor = _pupil_sensor(
        setup, stack, (width, height), center, {"type": sampler, "sample_count": int(spp), "seed": seed}
    )
    integrator = {"type": "scopetwin_grin", "precision": precision, "sequential": bool(sequential)}
    gs = GrinScene(setup, stack, step_mm, sensor=sensor, integrator=integrator, variant=variant)
    integ = gs.scene.integrator()
    integ.context = (gs, target)  # for this render only: the integrator must not keep the scene alive
    try:
        img = render_complete(mi, gs.scene, spp=spp)
        out = np.array(img, dtype=np.float32)[..., 0]
    finally:
        integ.context = None
    return out


def sampler_counts_exact(sampler: Sampler, spp: int) -> bool:
    """Whether Mitsuba's ``sampler`` draws exactly ``spp`` samples per pixel (it rounds some counts up).

    ``multijitter`` lays the samples on an a x b grid with b = floor(sqrt(spp)) and a = ceil(spp / b) (Mitsuba
    3.9's ``MultijitterSampler::set_sample_count``; tests/scenes/test_grin_mitsuba.py checks the rule against the
    installed Mitsuba): exact when b divides ``spp`` (1-4, 6, 8, 9, 12, 15, 16, 20, 24, 25, 30, 35, 36, 42, ...).
    """
    if sampler == "independent":
        return spp >= 1
    if sampler == "multijitter":
        b = math.isqrt(spp) if spp >= 1 else 1
        return spp >= 1 and spp % b == 0
    raise ScopetwinError(f"sampler must be 'independent' or 'multijitter', got {sampler!r}")


def illuminate(
    setup: GrinSetup,
    n_rays: int = 1_000_000,
    grid: int = 101,
    precision: Precision = "float32",
    seed: int = 0,
    variant: str | None = None,
) -> dict[str, Any]:
    """Light-trace the §7.5.3 illumination path: irradiance map at the object plane and energy efficiency.

    LED points are uniform on the square, directions cosine-weighted (``mi.warp``: a Lambertian
    emitter); rays run through the unfolded illumination stack in the Mitsuba scene
    (:func:`scopetwin.scenes.grin.illumination.illumination_stack`). Every ray carries the transmission ``loss_factor``
    (Fresnel at normal incidence times the splitter reflectance).

    §7.5.3 gives "an energy efficiency of about 33 %" "considering the reflection and transmission loss" and
    says the main loss is the beam splitter, but not what the ratio is of. Two readings are returned:

    * ``efficiency`` -- power inside the 400 µm field of view / LED power (the LED's whole Lambertian
      hemisphere counts; most of it misses the illumination rod's face);
    * ``efficiency_of_accepted`` -- power inside the field / power entering the illumination rod's front face
      (a sequential Zemax analysis launches rays into the entrance pupil only, so the collection loss
      is not in its efficiency); ``accepted_fraction`` is that face's share of the LED power.

    Returns also ``object_plane_of_accepted`` (power anywhere on the object plane / accepted power),
    ``irradiance_mw_per_mm2`` (grid x grid over ±field radius, row 0 at +y), ``extent_mm`` and
    ``uniformity_min_over_max`` (inside the field circle).
    """
    from scopetwin.scenes.grin.illumination import fresnel_transmission, illumination_stack
    from scopetwin.scenes.grin.setup import ArraySpec

    ill = setup.illumination
    if ill is None:
        raise ScopetwinError(f"setup {setup.name or setup.section} has no [illumination] table")
    stack = illumination_stack(setup)
    single = setup.model_copy(
        update={"array": ArraySpec(nx=1, ny=1, pitch=setup.array.pitch, substrate_side=setup.array.substrate_side)}
    )
    gs = GrinScene(single, stack, variant=variant)
    sampler = mi.load_dict({"type": "independent", "seed": seed})
    sampler.seed(seed, n_rays)
    pos = sampler.next_2d()
    d = mi.warp.square_to_cosine_hemisphere(sampler.next_2d())
    x = (pos.x - 0.5) * ill.led_side
    y = (pos.y - 0.5) * ill.led_side
    res = gs.trace((x, y, dr.zeros(mi.Float, n_rays)), (d.x, d.y, d.z), 1.0, precision, start="object")
    ok = np.asarray(res["alive"]) & (np.asarray(res["kind"]) == KIND_IMAGE)
    # rays meeting the illumination rod's front face inside its radius (the first layer is the air gap)
    rod_in = gs.rods[0]
    s_face = rod_in.z0 / np.maximum(np.asarray(d.z, dtype=np.float64), 1e-12)
    fx = np.asarray(x, dtype=np.float64) + s_face * np.asarray(d.x, dtype=np.float64)
    fy = np.asarray(y, dtype=np.float64) + s_face * np.asarray(d.y, dtype=np.float64)
    accepted = float(np.mean(fx * fx + fy * fy <= rod_in.radius**2))
    hx = np.asarray(res["x"], dtype=np.float64)[ok]
    hy = np.asarray(res["y"], dtype=np.float64)[ok]
    loss = fresnel_transmission(stack) * ill.splitter_reflectance if ill.fresnel else ill.splitter_reflectance
    power_per_ray = ill.power_mw / n_rays * loss
    r = setup.object.field_radius
    inside = hx * hx + hy * hy <= r * r
    hist, _, _ = np.histogram2d(hy, hx, bins=grid, range=[[-r, r], [-r, r]])
    cell = (2 * r / grid) ** 2
    irr = hist[::-1] * power_per_ray / cell
    c = (np.arange(grid) + 0.5) / grid * 2 * r - r
    in_field = (c[None, :] ** 2 + c[:, None] ** 2) <= r * r
    field_irr = irr[in_field]
    eff = float(inside.sum() * power_per_ray / ill.power_mw)
    return {
        "efficiency": eff,
        "efficiency_of_accepted": eff / accepted if accepted > 0 else 0.0,
        "accepted_fraction": accepted,
        "reaching_object": float(ok.mean()),
        "object_plane_of_accepted": float(ok.mean()) * loss / accepted if accepted > 0 else 0.0,
        "loss_factor": loss,
        "fresnel": fresnel_transmission(stack),
        "splitter_reflectance": ill.splitter_reflectance,
        "irradiance_mw_per_mm2": irr.astype(np.float32),
        "extent_mm": r,
        "uniformity_min_over_max": float(field_irr.min() / field_irr.max()) if field_irr.max() > 0 else 0.0,
    }
