"""The one-bounce mirror trace of the Part I scenes on Dr.Jit arrays (thesis §1.6.5): where a camera ray's light
comes from on the pattern, and its radiance.

A camera ray meets its first surface (Mitsuba's ray intersection, preliminary: the distance, the shape and the
triangle's barycentric coordinates only). On a perfect mirror (a shape with a delta-reflection BSDF: the substrate's
region of interest, the flat mirror) it is reflected about the shading normal, r_out = r_in - 2 (r_in.N) N (eq. 1.7),
from ``p + eps*r_out`` (along the reflected ray, docs/rendering.md); on the pattern it is seen directly; anything else
is black. The pattern is the scene's one emitter, a rectangle emitting on the side of its N_z: the ray (direct or
reflected) meets its plane there and the emitter is evaluated at that point's uv.

What Mitsuba's full surface interaction would compute is computed here from the shapes' own data, with no call that
dispatches over the scene's shapes:

* a mirror mesh's hit point and shading normal from its faces, vertex positions and vertex normals, interpolated with
  the hit's barycentric coordinates as Mitsuba's mesh does;
* a flat mirror's (rectangle's) normal from its transform, its hit point on the ray;
* the pattern point as the ray's intersection with the pattern plane, its uv as the rectangle's, (local + 1) / 2.

A reflected ray is traced through the scene only where it could meet something other than the pattern. The
non-emitting shapes of a Part I scene are one surface over the base plane, z = h(x, y) (the substrate's region of
interest and its holding-frame regions, which continue the same surface, or the flat mirror), whose triangles are
nowhere steeper than a slope s (:attr:`MirrorScene.slope`, measured on the meshes). A ray leaving that surface upward
and rising faster than s, r_out.z > s |r_out.xy|, stays above it: every point of the surface at horizontal distance
d from the start lies at most s*d above it, the ray s'*d with s' > s. Such a ray meets nothing before the pattern's
plane, so the plane is intersected directly; every other reflected ray (a steep surface, a grazing reflection) is
traced by Mitsuba as before.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from scopetwin.scenes.errors import SetupError

#: Relative and absolute headroom on the measured slope bound (float32 rounding of the ray's rise).
_SLOPE_HEADROOM = (1.01, 1e-5)


@dataclass(frozen=True)
class MirrorMesh:
    """A mirror mesh: its shape pointer and the buffers its hit points and shading normals are interpolated from."""

    ptr: Any
    faces: Any
    positions: Any
    normals: Any


@dataclass(frozen=True)
class FlatMirror:
    """A flat mirror (a rectangle): its shape pointer and unit normal."""

    ptr: Any
    normal: Any


@dataclass(frozen=True)
class MirrorScene:
    """What the trace needs of a loaded Part I scene (:func:`mirror_scene`), as Dr.Jit values.

    The pattern's placement and the slope bound are opaque variables, so a scene with another pattern pose or surface
    reuses the compiled kernels.

    Attributes
    ----------
    mi : module
        The ``mitsuba`` module of the scene's variant.
    pattern : ShapePtr
        The pattern (the scene's one emitter, a rectangle).
    emitter : mitsuba.Emitter
        Its area emitter.
    rows : tuple
        The first two rows of the rectangle's world-to-local matrix (8 opaque Floats): local x, y in [-1, 1].
    normal, origin : Vector3f, Point3f
        The pattern's unit N_z and its centre.
    meshes, flats : tuple
        The perfect mirrors: meshes with vertex normals (:class:`MirrorMesh`), rectangles (:class:`FlatMirror`).
    slope : float
        The steepest triangle of the non-emitting shapes, |grad h| (inf where a shape is not a surface over the base
        plane facing up): reflected rays rising faster than this are not traced through the scene.
    rise : Float
        The slope with headroom, opaque.
    eps : float
        Start offset of reflected rays along their own direction, mm.
    memo : dict
        What renderers derive from the scene alone and keep with it (:func:`scopetwin.scenes.mitsuba.lit.render_lit`:
        the pixels that can see a marker).
    """

    mi: Any
    pattern: Any
    emitter: Any
    rows: tuple[Any, ...]
    normal: Any
    origin: Any
    meshes: tuple[MirrorMesh, ...]
    flats: tuple[FlatMirror, ...]
    slope: float
    rise: Any
    eps: float
    memo: dict[Any, Any] = field(default_factory=dict, compare=False, repr=False)


def _is_mirror(mi: Any, shape: Any) -> bool:
    bsdf = shape.bsdf()
    return bsdf is not None and bool(mi.has_flag(bsdf.flags(), mi.BSDFFlags.DeltaReflection))


def _matrix(mi: Any, shape: Any) -> Any:
    """The shape's to_world as a float64 numpy 4 x 4 matrix."""
    import numpy as np

    return np.array(mi.traverse(shape)["to_world"].matrix, dtype=np.float64).reshape(4, 4)


def _mesh_slope(mi: Any, mesh: Any) -> float:
    """|grad h| of the mesh's steepest triangle; inf where a triangle does not face up (not a height field)."""
    import drjit as dr

    faces, pos = mesh.faces_buffer(), mesh.vertex_positions_buffer()
    k = dr.arange(mi.UInt32, mesh.face_count()) * 3
    v = [dr.gather(mi.Point3f, pos, dr.gather(mi.UInt32, faces, k + j)) for j in range(3)]
    n = dr.cross(v[1] - v[0], v[2] - v[0])
    if dr.any(n.z <= 0):
        return float("inf")
    return float(dr.max(dr.sqrt(dr.fma(n.x, n.x, n.y * n.y)) / n.z)[0])


def _flat_slope(normal: Any) -> float:
    return float("inf") if normal[2] <= 0 else float((normal[0] ** 2 + normal[1] ** 2) ** 0.5 / normal[2])


def _pattern_fields(mi: Any, shape: Any) -> tuple[tuple[Any, ...], Any, Any]:
    """The rectangle's world-to-local rows, unit normal and centre, as opaque Dr.Jit values."""
    import drjit as dr
    import numpy as np

    m = _matrix(mi, shape)
    inv = np.linalg.inv(m)
    nz = np.linalg.inv(m[:3, :3]).T @ [0.0, 0.0, 1.0]
    nz /= np.linalg.norm(nz)

    def opaque(x: float) -> Any:
        return dr.opaque(mi.Float, float(x))

    rows = tuple(opaque(inv[r, c]) for r in range(2) for c in range(4))
    return rows, mi.Vector3f(*(opaque(x) for x in nz)), mi.Point3f(*(opaque(x) for x in m[:3, 3]))


def _pointer(mi: Any, shape: Any) -> Any:
    """The shape's pointer as an opaque value: kernels compare shapes with it, and a scene loaded anew (another
    surface) has new pointers, which as literal constants would compile every kernel anew."""
    import drjit as dr

    ptr = mi.ShapePtr(shape)
    dr.make_opaque(ptr)
    return ptr


def _shapes(mi: Any, scene: Any) -> tuple[list[MirrorMesh], list[FlatMirror], float]:
    """The scene's perfect mirrors (meshes with vertex normals, rectangles) and the steepest slope of its
    non-emitting shapes."""
    import numpy as np

    meshes, flats, slope = [], [], 0.0
    for s in scene.shapes():
        if s.is_emitter():
            continue
        if s.is_mesh():
            slope = max(slope, _mesh_slope(mi, s))
            if _is_mirror(mi, s):
                if not s.has_vertex_normals():
                    raise SetupError(f"the mirror mesh {s.id()!r} has no vertex normals")
                buffers = (s.faces_buffer(), s.vertex_positions_buffer(), s.vertex_normals_buffer())
                meshes.append(MirrorMesh(_pointer(mi, s), *buffers))
            continue
        if s.shape_type() != mi.ShapeType.Rectangle:
            raise SetupError(f"the mirror trace knows meshes and rectangles, not {s.id()!r}")
        normal = np.linalg.inv(_matrix(mi, s)[:3, :3]).T @ [0.0, 0.0, 1.0]
        normal /= np.linalg.norm(normal)
        slope = max(slope, _flat_slope(normal))
        if _is_mirror(mi, s):
            flats.append(FlatMirror(_pointer(mi, s), mi.Vector3f(*(float(x) for x in normal))))
    return meshes, flats, slope


def mirror_scene(mi: Any, scene: Any, eps: float) -> MirrorScene:
    """The trace's view of a loaded scene: its pattern, its perfect mirrors and the slope bound.

    Raises
    ------
    SetupError
        The scene has not exactly one emitter, a rectangle, or a mirror mesh lacks vertex normals, or a shape is
        neither a mesh nor a rectangle.
    """
    import drjit as dr

    emitters = [s for s in scene.shapes() if s.is_emitter()]
    if len(emitters) != 1 or emitters[0].shape_type() != mi.ShapeType.Rectangle:
        raise SetupError("the mirror trace needs exactly one emitter, a rectangle (the pattern)")
    meshes, flats, slope = _shapes(mi, scene)
    rows, nz, origin = _pattern_fields(mi, emitters[0])
    rise = min(slope * _SLOPE_HEADROOM[0] + _SLOPE_HEADROOM[1], 3.0e38)  # inf: every reflected ray is traced
    return MirrorScene(
        mi=mi,
        pattern=_pointer(mi, emitters[0]),
        emitter=emitters[0].emitter(),
        rows=rows,
        normal=nz,
        origin=origin,
        meshes=tuple(meshes),
        flats=tuple(flats),
        slope=slope,
        rise=dr.opaque(mi.Float, rise),
        eps=float(eps),
    )


def _mirror_hit(ms: MirrorScene, ray: Any, pi: Any, hit: Any) -> tuple[Any, Any, Any]:
    """Where the ray meets a perfect mirror: the mask, the hit point and the unit shading normal."""
    import drjit as dr

    mi = ms.mi
    on = dr.zeros(mi.Bool, dr.width(hit))
    p = ray(pi.t)
    n = mi.Vector3f(0.0, 0.0, 1.0)
    for flat in ms.flats:
        here = hit & (pi.shape == flat.ptr)
        on |= here
        n = dr.select(here, flat.normal, n)
    b1, b2 = pi.prim_uv.x, pi.prim_uv.y
    b0 = 1.0 - b1 - b2
    for mesh in ms.meshes:
        here = hit & (pi.shape == mesh.ptr)
        on |= here
        tri = pi.prim_index * 3
        idx = [dr.gather(mi.UInt32, mesh.faces, tri + k, here) for k in range(3)]

        def lerp(buf: Any, idx: list[Any] = idx, here: Any = here) -> Any:
            v = [dr.gather(mi.Vector3f, buf, i, here) for i in idx]
            return dr.fma(v[2], b2, dr.fma(v[1], b1, v[0] * b0))

        p = dr.select(here, mi.Point3f(lerp(mesh.positions)), p)
        n = dr.select(here, dr.normalize(lerp(mesh.normals)), n)
    return on, p, n


def _reflected_reach(ms: MirrorScene, scene: Any, start: Any, wo: Any, on: Any) -> Any:
    """Whether reflected rays leaving the mirror can reach the pattern: those rising faster than any slope of the
    surface, and those Mitsuba's intersection sends to the pattern."""
    import drjit as dr

    mi = ms.mi
    free = wo.z > ms.rise * dr.sqrt(dr.fma(wo.x, wo.x, wo.y * wo.y))
    check = on & ~free
    pi = scene.ray_intersect_preliminary(mi.Ray3f(start, wo), False, check)
    return on & (free | (pi.is_valid() & (pi.shape == ms.pattern)))


def landing(ms: MirrorScene, scene: Any, ray: Any, active: Any = True, on_plate: bool = True) -> tuple[Any, Any, Any]:
    """Where camera rays' light comes from on the pattern: its local (x, y) in [-1, 1]^2 and the mask ``seen``.

    ``seen``: the ray (directly, or reflected once by a perfect mirror) meets the pattern's plane from its emitting
    side; with ``on_plate`` also within the plate (where the rectangle is), else the plane's point wherever it lies
    (a continuous map across the plate's edge).
    """
    import drjit as dr

    mi = ms.mi
    pi = scene.ray_intersect_preliminary(ray, True, active)
    hit = mi.Bool(active) & pi.is_valid()
    direct = hit & (pi.shape == ms.pattern)
    on, p, n = _mirror_hit(ms, ray, pi, hit)
    wo = ray.d - 2.0 * dr.dot(ray.d, n) * n
    start = dr.fma(wo, ms.eps, p)
    reach = _reflected_reach(ms, scene, start, wo, on)
    o = dr.select(direct, ray.o, start)
    d = dr.select(direct, ray.d, wo)
    cos = dr.dot(d, ms.normal)
    t = dr.dot(ms.origin - o, ms.normal) / cos
    seen = (direct | reach) & (cos < 0) & (t > 0)
    q = dr.fma(d, t, o)
    r = ms.rows
    lx = r[0] * q.x + r[1] * q.y + r[2] * q.z + r[3]
    ly = r[4] * q.x + r[5] * q.y + r[6] * q.z + r[7]
    if on_plate:
        seen &= (dr.abs(lx) <= 1.0) & (dr.abs(ly) <= 1.0)
    return lx, ly, seen


def radiance(ms: MirrorScene, scene: Any, ray: Any, active: Any = True) -> tuple[Any, Any]:
    """The radiance camera rays see (the pattern's, directly or in a mirror; 0 elsewhere) and whether they hit
    anything."""
    import drjit as dr

    mi = ms.mi
    lx, ly, seen = landing(ms, scene, ray, active)
    si = dr.zeros(mi.SurfaceInteraction3f)
    si.uv = mi.Point2f(dr.fma(lx, 0.5, 0.5), dr.fma(ly, 0.5, 0.5))
    si.wi = mi.Vector3f(0.0, 0.0, 1.0)  # the emitting side (checked above)
    value = dr.select(seen, ms.emitter.eval(si, seen)[0], 0.0)
    return value, seen
