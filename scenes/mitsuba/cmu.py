"""The compact microscope unit in Mitsuba's spectral variant (thesis ch. 4-5): plugins and channel images.

Plugins (registered idempotently, per thread and variant, by :func:`register`; importing this module sets no
variant: every builder and renderer takes ``variant``, default ``choose("spectral")``):

* BSDF ``scopetwin_ideal_lens`` on a ``disk``: the perfect lens of :mod:`scopetwin.scenes.cmu.trace` (slopes
  s' = s - (x, y)/f in the lens frame), delta transmission, weight 1 - the objective (f = 16.45 mm) and the
  tube lenses (f = 164.5 mm) of §5.1.2.
* BSDF ``scopetwin_bowed_plate`` on a ``rectangle``: one face of a 25.5 x 36 x 1 mm splitter (or mirror). Its
  normal is perturbed by the plate's height map (bilinear in a table of the bicubic map's exact gradients; the
  back face carries the same map, as in :mod:`scopetwin.scenes.cmu.trace`). The coated front face (z_local = 0) picks
  reflection or transmission with probability proportional to the lane-mean R(lambda), T(lambda) of the dichroic
  (``NNNDCXR``, ``61002BS``) or mirror, and weights each of the four wavelengths by R/p or T/(1-p) - the dichroic
  works physically, per wavelength; a transmitted ray is refracted (Snell, air <-> fused silica at the hero
  wavelength). A splitter also has its uncoated back face (z_local = -thickness): refraction only, weight 1.
  So a transmitted ray refracts at both faces with each face's own normal at its own hit point and is displaced
  laterally inside the glass (0.33 mm at 45°), as in the exact tracer: with bowed plates the two slopes differ by
  ~1e-5 rad, which deviates the ray, and the shift moves the beam on later plates and on the objective's aperture
  (a direction-keeping plate put the thesis unit's images 0.3-0.9 px away from the exact tracer's). Residual
  against :mod:`scopetwin.scenes.cmu.trace` (reversed exact rays, tests/scenes/test_cmu_mitsuba.py): <= 0.008 px in
  image
  position, <= 0.03 px per ray. What remains: each face is its plane (z_local = 0 or -thickness) with the
  bowed normal, not the surface at z = h (a <= 5 µm hit-point error, <= 2e-7 rad of normal); one index per ray
  (the hero wavelength: across a channel's band the image moves < 0.002 px); float32.

Rendering (:func:`render_channel`): rays start on the camera's sensor (pixel area x tube-lens disk, weight
A cos^2/d^2: irradiance), carry four wavelengths drawn from the channel's fixed detection response (band pass,
mirror, camera QE) times the object's spectrum, and are traced backwards through the whole unit with
``scene.ray_intersect`` and the BSDFs above until they reach the object plane, where the test object
(Siemens star backlit by a halogen lamp, or fluorescent dummy cells) is evaluated. A pixel is the mean over
its samples: the monochrome camera's electrons per unit exposure (relative).
"""

from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace
from typing import Any, Literal

import drjit as _drjit
import mitsuba as _mitsuba
import numpy as np

from scopetwin.scenes.cmu import spectra
from scopetwin.scenes.cmu.analysis import channel_optics, image_rays
from scopetwin.scenes.cmu.layout import CmuSetup
from scopetwin.scenes.cmu.plates import fused_silica_index, plate_heightmap
from scopetwin.scenes.cmu.targets import dummy_cells, siemens_star
from scopetwin.scenes.cmu.trace import axis_frame
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.limits import check_render
from scopetwin.scenes.mitsuba.variant import mitsuba, register_plugin, resolve
from scopetwin.scenes.spots import pupil_disk
from scopetwin.scenes.surface import HeightMap

# The mitsuba module, no variant set: its variant-dependent names (mi.Float, mi.BSDF, ...) are looked up
# when a function runs, after that function has set its variant (no variant is set at import).
mi: Any = _mitsuba  # typed Any: its names are built per variant at run time (pyproject.toml [tool.mypy])
dr: Any = _drjit
DR = SimpleNamespace(sqrt=dr.sqrt, atan2=dr.atan2, sin=dr.sin, where=dr.select, abs=dr.abs, maximum=dr.maximum)
#: Spectral tables are sampled at 1 nm from WL0_NM.
WL0_NM, WL1_NM = 300.0, 1000.0


def _vec(props: mi.Properties, prefix: str) -> mi.ScalarVector3f:
    return mi.ScalarVector3f(*[props.get(f"{prefix}_{c}", 0.0) for c in "xyz"])


def _lookup(table: Any, wl: Any) -> Any:
    """Linear interpolation of a 1 nm table (from WL0_NM) at wavelengths ``wl``."""
    t = dr.clip(wl - WL0_NM, 0.0, WL1_NM - WL0_NM - 1.001)
    i = mi.UInt32(dr.floor(t))
    w = t - dr.floor(t)
    return dr.gather(mi.Float, table, i) * (1.0 - w) + dr.gather(mi.Float, table, i + 1) * w


def _lookup_spectrum(table: Any, wavelengths: Any) -> Any:
    """:func:`_lookup` for each of the four wavelengths of a spectral sample."""
    return mi.Spectrum(*[_lookup(table, wavelengths[k]) for k in range(4)])


def _delta_sample(si: Any, wo_world: Any, flag: Any) -> Any:
    bs = dr.zeros(mi.BSDFSample3f)
    bs.wo = si.to_local(wo_world)
    bs.pdf = mi.Float(1.0)
    bs.eta = mi.Float(1.0)
    bs.sampled_type = mi.UInt32(+flag)
    bs.sampled_component = mi.UInt32(0)
    return bs


def _perfect_lens_class(mi: Any) -> type:
    """The BSDF class of ``scopetwin_ideal_lens`` for the variant of ``mi`` (Mitsuba classes are per variant)."""

    class PerfectLensBSDF(mi.BSDF):
        """BSDF ``scopetwin_ideal_lens``: the perfect lens (:class:`scopetwin.scenes.cmu.trace.PerfectLens`).

        Properties ``f`` (mm) and the lens frame ``c_*``, ``tx_*``, ``ty_*``, ``nz_*``.
        """

        def __init__(self, props: mi.Properties) -> None:
            super().__init__(props)
            self.f = props.get("f", 100.0)
            self.c, self.tx, self.ty, self.nz = (_vec(props, k) for k in ("c", "tx", "ty", "nz"))
            self.m_flags = mi.BSDFFlags.DeltaTransmission | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
            self.m_components = [self.m_flags]

        def sample(self, ctx: Any, si: Any, sample1: Any, sample2: Any, active: Any = True) -> tuple[Any, Any]:
            d = -si.to_world(si.wi)
            q = si.p - mi.Point3f(self.c)
            x, y = dr.dot(q, mi.Vector3f(self.tx)), dr.dot(q, mi.Vector3f(self.ty))
            dz = dr.dot(d, mi.Vector3f(self.nz))
            az = dr.maximum(dr.abs(dz), 1e-12)
            sx = dr.dot(d, mi.Vector3f(self.tx)) / az - x / self.f
            sy = dr.dot(d, mi.Vector3f(self.ty)) / az - y / self.f
            out = dr.normalize(
                sx * mi.Vector3f(self.tx) + sy * mi.Vector3f(self.ty) + dr.sign(dz) * mi.Vector3f(self.nz)
            )
            return _delta_sample(si, out, mi.BSDFFlags.DeltaTransmission), mi.Spectrum(1.0)

        def eval(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
            return mi.Spectrum(0.0)

        def pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
            return mi.Float(0.0)

        def eval_pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> tuple[Any, Any]:
            return mi.Spectrum(0.0), mi.Float(0.0)

        def to_string(self) -> str:
            return f"PerfectLensBSDF[f={self.f}]"

    return PerfectLensBSDF


def _plate_gradient(plate: Any, x: Any, y: Any) -> tuple[Any, Any]:
    """The gradient (h_x, h_y) of a ``scopetwin_bowed_plate`` at plate coordinates (x, y): bilinear in its tables."""
    fx = dr.clip((x - plate.x0) / plate.dx, 0.0, plate.nx - 1.001)
    fy = dr.clip((y - plate.y0) / plate.dy, 0.0, plate.ny - 1.001)
    ix, iy = mi.UInt32(dr.floor(fx)), mi.UInt32(dr.floor(fy))
    wx, wy = fx - dr.floor(fx), fy - dr.floor(fy)
    i00 = iy * plate.nx + ix
    out = []
    for tab in (plate.hx, plate.hy):
        a = dr.gather(mi.Float, tab, i00) * (1 - wx) + dr.gather(mi.Float, tab, i00 + 1) * wx
        b = dr.gather(mi.Float, tab, i00 + plate.nx) * (1 - wx) + dr.gather(mi.Float, tab, i00 + plate.nx + 1) * wx
        out.append(a * (1 - wy) + b * wy)
    return out[0], out[1]


def _refract(d: Any, n: Any, n_glass: Any, coated: bool) -> tuple[Any, Any]:
    """Snell's law at a plate face: air on the +N_z side of the front (``coated``) face, on the -N_z side of the back.

    Returns the refracted direction and a mask of rays that are not totally internally reflected."""
    from_plus = dr.dot(d, n) < 0.0
    into_glass = from_plus == coated
    eta = dr.select(into_glass, 1.0 / n_glass, n_glass)
    m = dr.select(from_plus, n, -n)  # the normal facing the incident side
    c = -dr.dot(d, m)
    k = 1.0 - eta * eta * (1.0 - c * c)
    return dr.normalize(eta * d + (eta * c - dr.sqrt(dr.maximum(k, 0.0))) * m), k >= 0.0


def _dichroic_sample(plate: Any, si: Any, sample1: Any, d: Any, n: Any, refracted: tuple[Any, Any]) -> tuple[Any, Any]:
    """The coated face's sample: reflect with probability p = mean R / (mean R + mean T), else transmit.

    Each wavelength is weighted by R/p or T/(1-p); ``refracted`` is the transmitted direction and its not-TIR mask.
    """
    d_t, ok = refracted
    r = _lookup_spectrum(plate.refl, si.wavelengths)
    t = _lookup_spectrum(plate.trans, si.wavelengths)
    rm, tm = dr.mean(r), dr.mean(t)
    p = rm / dr.maximum(rm + tm, 1e-12)
    reflect = sample1 < p
    d_r = d - 2.0 * dr.dot(d, n) * n
    wo = dr.select(reflect, d_r, d_t)
    flag = dr.select(reflect, mi.UInt32(+mi.BSDFFlags.DeltaReflection), mi.UInt32(+mi.BSDFFlags.DeltaTransmission))
    bs = _delta_sample(si, wo, mi.BSDFFlags.DeltaReflection)
    bs.sampled_type = flag
    bs.sampled_component = dr.select(reflect, mi.UInt32(0), mi.UInt32(1))
    w = dr.select(reflect, r / dr.maximum(p, 1e-12), dr.select(ok, t / dr.maximum(1.0 - p, 1e-12), 0.0))
    return bs, w


def _bowed_plate_class(mi: Any) -> type:
    """The BSDF class of ``scopetwin_bowed_plate`` for the variant of ``mi``."""

    class BowedPlate(mi.BSDF):
        """BSDF ``scopetwin_bowed_plate``: the plate's frame and tables come as properties (:func:`plate_tables`);
        ``face`` is ``"front"`` (coated: dichroic reflection/transmission, default) or ``"back"`` (uncoated:
        refraction only). The tables are the BSDF's own (Dr.Jit arrays), so they are freed with the scene."""

        def __init__(self, props: mi.Properties) -> None:
            super().__init__(props)
            self.key = props.get("name", "")
            self.c, self.tx, self.ty, self.nz = (_vec(props, k) for k in ("c", "tx", "ty", "nz"))
            self.x0, self.y0, self.dx, self.dy = (props.get(k) for k in ("x0", "y0", "dx", "dy"))
            self.nx, self.ny = props.get("nx"), props.get("ny")
            self.hx, self.hy = props.get("hx").array, props.get("hy").array
            self.refl, self.trans = props.get("R").array, props.get("T").array
            self.index = props.get("n_glass").array
            self.coated = props.get("face", "front") == "front"
            self.m_flags = (
                mi.BSDFFlags.DeltaReflection
                | mi.BSDFFlags.DeltaTransmission
                | mi.BSDFFlags.FrontSide
                | mi.BSDFFlags.BackSide
            )
            self.m_components = [
                mi.BSDFFlags.DeltaReflection | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide,
                mi.BSDFFlags.DeltaTransmission | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide,
            ]

        def sample(self, ctx: Any, si: Any, sample1: Any, sample2: Any, active: Any = True) -> tuple[Any, Any]:
            d = -si.to_world(si.wi)
            tx, ty, nz = mi.Vector3f(self.tx), mi.Vector3f(self.ty), mi.Vector3f(self.nz)
            q = si.p - mi.Point3f(self.c)
            hx, hy = _plate_gradient(self, dr.dot(q, tx), dr.dot(q, ty))
            n = dr.normalize(nz - hx * tx - hy * ty)
            d_t, ok = _refract(d, n, _lookup(self.index, si.wavelengths[0]), self.coated)
            if not self.coated:  # the uncoated back face: refraction only
                bs = _delta_sample(si, d_t, mi.BSDFFlags.DeltaTransmission)
                bs.sampled_component = mi.UInt32(1)
                return bs, dr.select(ok, mi.Spectrum(1.0), mi.Spectrum(0.0))
            return _dichroic_sample(self, si, sample1, d, n, (d_t, ok))

        def eval(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
            return mi.Spectrum(0.0)

        def pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> Any:
            return mi.Float(0.0)

        def eval_pdf(self, ctx: Any, si: Any, wo: Any, active: Any = True) -> tuple[Any, Any]:
            return mi.Spectrum(0.0), mi.Float(0.0)

        def to_string(self) -> str:
            return f"BowedPlate[{self.key}]"

    return BowedPlate


def register(variant: str | None = None) -> None:
    """Register ``scopetwin_ideal_lens`` and ``scopetwin_bowed_plate`` for ``variant`` (default
    ``choose("spectral")``) in this thread; idempotent per thread and variant."""
    variant = resolve(variant, "spectral")
    register_plugin("bsdf", "scopetwin_ideal_lens", _perfect_lens_class, variant)
    register_plugin("bsdf", "scopetwin_bowed_plate", _bowed_plate_class, variant)


# -- the scene ----------------------------------------------------------------------------------------------
def _grid_1nm(curve_on_grid: np.ndarray) -> np.ndarray:
    wl = np.arange(WL0_NM, WL1_NM + 0.5, 1.0)
    return np.interp(wl, spectra.GRID_NM, curve_on_grid)


def plate_tables(
    name: str,
    frame: Any,
    hm: HeightMap | None,
    setup: CmuSetup,
    is_mirror: bool,
    node_mm: float = 0.1,
    variant: str | None = None,
) -> dict[str, Any]:
    """The properties of one plate's ``scopetwin_bowed_plate`` BSDF: its frame, gradient and R/T tables.

    The tables travel in the scene dictionary (``mi.TensorXf`` of ``variant``, default ``choose("spectral")``), so
    the BSDF owns them and they are freed with the scene (nothing is kept in this module).
    """
    mi = mitsuba(resolve(variant, "spectral"))
    pw, ph = 0.5 * setup.plate.width, 0.5 * setup.plate.height
    xs = np.arange(-pw, pw + 1e-9, node_mm)
    ys = np.arange(-ph, ph + 1e-9, node_mm)
    xx, yy = np.meshgrid(xs, ys)
    if hm is None:
        hx = hy = np.zeros_like(xx)
    else:
        hx, hy = hm.gradient(xx, yy)
    if is_mirror:
        r = np.full(spectra.GRID_NM.shape, spectra.MIRROR_REFLECTANCE)
        t = np.zeros_like(r)
    else:
        r, t = spectra.dichroic(name, "R"), spectra.dichroic(name, "T")
    props: dict[str, Any] = {"type": "scopetwin_bowed_plate", "name": name}
    for k, v in (("c", frame.origin), ("tx", frame.tx), ("ty", frame.ty), ("nz", frame.nz)):
        props |= {f"{k}_x": float(v[0]), f"{k}_y": float(v[1]), f"{k}_z": float(v[2])}
    tables = {
        "x0": float(xs[0]),
        "y0": float(ys[0]),
        "dx": node_mm,
        "dy": node_mm,
        "nx": len(xs),
        "ny": len(ys),
        "hx": mi.TensorXf(hx.astype(np.float32)),
        "hy": mi.TensorXf(hy.astype(np.float32)),
        "R": mi.TensorXf(_grid_1nm(r).astype(np.float32)),
        "T": mi.TensorXf(_grid_1nm(t).astype(np.float32)),
        "n_glass": mi.TensorXf(fused_silica_index(np.arange(WL0_NM, WL1_NM + 0.5, 1.0)).astype(np.float32)),
    }
    return props | tables


def _lens_dict(frame: Any, f: float, radius: float) -> dict[str, Any]:
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = frame.tx * radius, frame.ty * radius, frame.nz, frame.origin
    props = {"type": "scopetwin_ideal_lens", "f": f}
    for k, v in (("c", frame.origin), ("tx", frame.tx), ("ty", frame.ty), ("nz", frame.nz)):
        props |= {f"{k}_x": float(v[0]), f"{k}_y": float(v[1]), f"{k}_z": float(v[2])}
    return {"type": "disk", "to_world": mi.ScalarTransform4f(m.tolist()), "bsdf": props}


def unit_scene(
    setup: CmuSetup,
    maps: dict[str, HeightMap] | None = None,
    tube_f: float | None = None,
    flat: bool = False,
    variant: str | None = None,
) -> tuple[Any, int]:
    """Mitsuba scene of the whole unit: objective, splitters (coated front and uncoated back face), mirrors, four
    tube lenses, object plane.

    Built in ``variant`` (default ``choose("spectral")``, resolved now). The plates' tables belong to the scene's
    BSDFs: dropping the scene frees them. Returns (scene, shape id of the object plane).
    """
    variant = resolve(variant, "spectral")
    register(variant)
    f_o = setup.objective.focal_length
    T = mi.ScalarTransform4f
    scene: dict[str, Any] = {"type": "scene"}
    scene["objective"] = _lens_dict(
        axis_frame(np.array([0, 0, f_o]), np.array([0, 0, 1.0])), f_o, 0.5 * setup.objective.beam_diameter
    )
    for group, is_mirror in ((setup.splitters, False), (setup.mirrors, True)):
        for name, spec in group.items():
            fr = spec.frame()
            hm = None if flat else (maps or {}).get(name) or plate_heightmap(spec, setup.plate)
            bsdf = plate_tables(name, fr, hm, setup, is_mirror, variant=variant)
            m = np.eye(4)
            m[:3, 0], m[:3, 1] = fr.tx * 0.5 * setup.plate.width, fr.ty * 0.5 * setup.plate.height
            m[:3, 2], m[:3, 3] = fr.nz, fr.origin
            scene[f"plate_{name}"] = {
                "type": "rectangle",
                "to_world": T(m.tolist()),
                "bsdf": bsdf,
            }
            if not is_mirror:  # the splitter's uncoated back face, one thickness behind the coated one
                m[:3, 3] = fr.origin - setup.plate.thickness * fr.nz
                scene[f"plate_{name}_back"] = {
                    "type": "rectangle",
                    "to_world": T(m.tolist()),
                    "bsdf": bsdf | {"face": "back"},
                }
    for cname, ch in setup.channels.items():
        fr = axis_frame(np.asarray(ch.tube_center, dtype=np.float64), np.asarray(ch.tube_axis, dtype=np.float64))
        scene[f"tube_{cname}"] = _lens_dict(fr, tube_f or setup.tube.focal_length, 12.5)
    scene["object"] = {"type": "rectangle", "to_world": T().scale([5.0, 5.0, 1.0]), "bsdf": {"type": "diffuse"}}
    sc = mi.load_dict(scene)
    ids = np.asarray(dr.reinterpret_array(mi.UInt32, sc.shapes_dr()), dtype=np.int64)
    obj_id = [int(i) for i, s in zip(ids, sc.shapes(), strict=True) if s.id() == "object"][0]
    return sc, obj_id


# -- the camera ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CameraPose:
    """Where a channel's camera sits: image distance b behind the tube lens, in-plane tilt and offset.

    The sensor's axes are the images of the object's +x (columns) and +y (rows up) through the perfect channel,
    so an untilted camera shows the object upright. ``tilt_deg``: the sensor is turned so that the image content
    appears rotated by +tilt (counter-clockwise as displayed, row 0 at the top); ``offset_px`` (col, row): the
    content appears shifted by +offset. These are what :mod:`scopetwin.calib.channels` measures.
    """

    image_distance: float
    tilt_deg: float = 0.0
    offset_px: tuple[float, float] = (0.0, 0.0)


def sensor_axes(setup: CmuSetup, channel: str) -> tuple[np.ndarray, np.ndarray]:
    """Unit 2-vectors (tube-lens frame) of the images of object +x and +y in the flat channel."""
    opt = channel_optics(setup, channel, flat=True)
    px, py = pupil_disk(5)
    out = []
    for x0, y0 in ((0.1, 0.0), (0.0, 0.1)):
        r = image_rays(opt, x0, y0, px, py)
        u, v = r.at(opt.tube.f)
        r0 = image_rays(opt, 0.0, 0.0, px, py)
        u0, v0 = r0.at(opt.tube.f)
        e = np.array([u.mean() - u0.mean(), v.mean() - v0.mean()])
        out.append(e / np.linalg.norm(e))
    return out[0], out[1]


Target = Literal["star", "cells"]


def _wavelength_table(setup: CmuSetup, channel: str, target: Target) -> tuple[np.ndarray, float]:
    """Sampling density (1 nm grid) of detection response x object spectrum, and its integral."""
    det = spectra.detection_response(channel, include_splitters=False)
    if target == "star":
        src = spectra.planck(spectra.GRID_NM, 3100.0)
    else:
        src = spectra.fluorophore(spectra.CHANNEL_FLUOROPHORE[channel]).emission(spectra.GRID_NM)
    pdf = _grid_1nm(det * src)
    return pdf, float(pdf.sum())


def unit_texel_irradiance(setup: CmuSetup, channel: str, image_distance_mm: float) -> float:
    """The value :func:`render_channel` gives on the axis for cells of texel value 1 everywhere (without the stop).

    Rays leave the sensor point at b = ``image_distance_mm`` behind the tube lens, which makes them parallel; those
    within the objective's beam radius R reach the object point, so the pixel is the projected solid angle
    pi R^2 / (R^2 + b^2) times the electrons per photon of the whole emission path (splitters, mirror, band pass,
    spectral quantum efficiency) averaged over the channel's emission spectrum (unit area). Pure numpy: the scale
    that turns a rendered cell image into photoelectrons (:mod:`scopetwin.sim.cmu_budget`). Uniform renders of the
    thesis unit (8-16 px windows on the axis, 256-1024 spp) come within 2 % of it in all four channels.
    """
    r = 0.5 * setup.objective.beam_diameter
    b = float(image_distance_mm)
    omega = np.pi * r * r / (r * r + b * b)
    em = spectra.fluorophore(spectra.CHANNEL_FLUOROPHORE[channel]).emission(spectra.GRID_NM)
    return float(omega * np.trapezoid(em * spectra.detection_response(channel), spectra.GRID_NM))


def _trace_to_object(
    sc: Any,
    obj_id: int,
    ray: Any,
    thr: Any,
    sampler: Any,
    stop_plane: tuple[np.ndarray, np.ndarray, float] | None = None,
    max_depth: int = 12,
    count: bool = False,
) -> tuple[Any, Any, Any, Any, Any]:
    """Follow rays (from the image side) through the unit's delta BSDFs until they meet the object plane.

    ``stop_plane`` (centre, axis, radius): a circular aperture met right after the first interaction (the tube
    lens), §5.1.2. Returns the object-plane points, the throughput there, the mask of rays that arrived, the
    number of reflections each ray took (a channel's own path has as many as its ``:R`` steps) and the number of
    surfaces it met before the object plane (tube lens, two faces per transmitted splitter, one per reflection,
    objective: a ray that misses the objective's aperture has one fewer); the two counts only with ``count``
    (they slow the renderer), else None.
    """
    alive = mi.Bool(True)
    hit = mi.Bool(False)
    p_obj = dr.zeros(mi.Point3f, dr.width(ray.o))
    n_refl = mi.UInt32(0)
    n_events = mi.UInt32(0)
    ctx = mi.BSDFContext()
    wl = ray.wavelengths
    for depth in range(max_depth):
        si = sc.ray_intersect(ray, alive)
        alive &= si.is_valid()
        is_obj = alive & (dr.reinterpret_array(mi.UInt32, si.shape) == obj_id)
        p_obj = dr.select(is_obj, si.p, p_obj)
        hit |= is_obj
        alive &= ~is_obj
        bsdf = si.bsdf(ray)
        bs, w = bsdf.sample(ctx, si, sampler.next_1d(alive), sampler.next_2d(alive), alive)
        wo = si.to_world(bs.wo)
        if depth == 0 and stop_plane is not None:
            c, axis, radius = stop_plane
            sc_v = mi.Point3f(*[float(v) for v in c])
            ax = mi.Vector3f(*[float(v) for v in axis])
            t_s = dr.dot(sc_v - si.p, ax) / dr.dot(wo, ax)
            alive &= dr.squared_norm(si.p + t_s * wo - sc_v) <= radius * radius
        if count:
            n_refl += dr.select(alive & mi.has_flag(bs.sampled_type, mi.BSDFFlags.DeltaReflection), 1, 0)
            n_events += dr.select(alive, 1, 0)
        thr = dr.select(alive, thr * w, thr)  # rays that arrived keep their throughput at the object
        alive &= dr.mean(w) > 0
        ray = mi.Ray3f(si.p + 1e-4 * wo, wo, 0.0, wl)
    return p_obj, thr, hit, (n_refl if count else None), (n_events if count else None)


@dataclass(frozen=True)
class Landing:
    """Where rays traced backwards through the unit meet the object plane (global mm, float64 copies), how many
    reflections they took and how many surfaces they met on the way (see :func:`_trace_to_object`)."""

    points: np.ndarray
    hit: np.ndarray
    reflections: np.ndarray
    events: np.ndarray
    throughput: np.ndarray


def land_rays(
    scene: tuple[Any, int],
    origins: np.ndarray,
    directions: np.ndarray,
    wavelength_nm: float,
    seed: int = 0,
    variant: str | None = None,
) -> Landing:
    """Trace rays from the image side (e.g. a camera plane) through the Mitsuba unit to the object plane.

    The renderer's own ray loop (:func:`render_channel` uses it), exposed for per-ray comparison with the float64
    tracer :mod:`scopetwin.scenes.cmu.trace`: reverse a traced ray at the image plane and it must land on its object
    point.

    Parameters
    ----------
    scene : (scene, object shape id) from :func:`unit_scene`
    origins, directions : (N, 3) arrays, global mm; directions point toward the unit
    wavelength_nm : float
        All four spectral lanes carry this wavelength (dichroic R/T and the glass index are taken there).
    seed : int
        Seed of the reflect/transmit choices at the splitters.
    variant : str, optional
        The variant the scene was built in (default ``choose("spectral")``).
    """
    mitsuba(resolve(variant, "spectral"))
    sc, obj_id = scene
    o = np.asarray(origins, dtype=np.float64)
    d = np.asarray(directions, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=1, keepdims=True)
    n = len(o)
    ray = mi.Ray3f(
        mi.Point3f(*[mi.Float(o[:, k]) for k in range(3)]),
        mi.Vector3f(*[mi.Float(d[:, k]) for k in range(3)]),
        0.0,
        mi.UnpolarizedSpectrum(float(wavelength_nm)),
    )
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed & 0xFFFFFFFF, n)
    p, thr, hit, n_refl, n_events = _trace_to_object(sc, obj_id, ray, mi.Spectrum(1.0), sampler, count=True)
    pts = np.column_stack([np.asarray(c, dtype=np.float64) for c in (p.x, p.y, p.z)])
    return Landing(
        pts,
        np.asarray(hit, dtype=bool),
        np.asarray(n_refl, dtype=np.int64),
        np.asarray(n_events, dtype=np.int64),
        np.asarray(dr.mean(thr), dtype=np.float64),
    )


def _check_channel(setup: CmuSetup, channel: str, spp: int) -> None:
    """Raise for a channel the setup does not have or fewer than one sample per pixel."""
    if channel not in setup.channels:
        raise ScopetwinError(f"unknown channel {channel!r} (channels: {', '.join(setup.channels)})")
    if spp < 1:
        raise ScopetwinError(f"spp must be >= 1, got {spp}")


def _cells_texture(setup: CmuSetup) -> tuple[Any, tuple[int, ...], float, float]:
    """The dummy cells' texture (a Dr.Jit array), its shape and its origin (x, y), mm."""
    tex, tx0, ty0 = dummy_cells(setup.cells, setup.field_mm)
    return mi.Float(tex.ravel()), tex.shape, tx0, ty0


def _sensor_rays(
    sampler: Any,
    idx: Any,
    window: tuple[int, int, int],
    grid: Any,
    pose: CameraPose,
    axes: tuple[np.ndarray, ...],
    lens_r: float,
    dist: Any,
) -> tuple[Any, Any]:
    """Rays from the sensor points of pixels ``idx`` to the tube-lens disk, four wavelengths each, and their weight.

    ``window`` is (row0, col0, width); ``axes`` the tube lens's origin, tx, ty, nz and the sensor axes ex, ey.
    The weight A cos^2 / d^2 makes the image the irradiance.
    """
    row0, col0, wid = window
    origin, tx, ty, nz, ex, ey = axes
    L0, LX, LY, LZ = (mi.ScalarVector3f(*[float(c) for c in v]) for v in (origin, tx, ty, nz))
    ang = np.deg2rad(pose.tilt_deg)
    row = mi.Float(idx // wid) + row0
    col = mi.Float(idx % wid) + col0
    s_pix = sampler.next_2d()
    # sensor coordinates of the pixel grid (cols along ex, rows against ey), content shifted by the offset
    a, b = grid.uv(col + s_pix.x, row + s_pix.y, shift_px=pose.offset_px)
    ca, sa = float(np.cos(-ang)), float(np.sin(-ang))
    a, b = ca * a - sa * b, sa * a + ca * b
    u = a * float(ex[0]) + b * float(ey[0])
    v = a * float(ex[1]) + b * float(ey[1])
    o_img = mi.Point3f(L0) + u * mi.Vector3f(LX) + v * mi.Vector3f(LY) + pose.image_distance * mi.Vector3f(LZ)
    s_lens = sampler.next_2d()
    rr = lens_r * dr.sqrt(s_lens.x)
    phi = 2.0 * dr.pi * s_lens.y
    p_lens = mi.Point3f(L0) + rr * dr.cos(phi) * mi.Vector3f(LX) + rr * dr.sin(phi) * mi.Vector3f(LY)
    d = p_lens - o_img
    d2 = dr.squared_norm(d)
    d = d * dr.rsqrt(d2)
    cosz = dr.abs(dr.dot(d, mi.Vector3f(LZ)))
    weight = dr.pi * lens_r * lens_r * cosz * cosz / d2
    u_wl = sampler.next_1d()
    lanes = [dist.sample(u_wl + q / 4.0 - dr.floor(u_wl + q / 4.0)) for q in range(4)]
    wl = mi.UnpolarizedSpectrum(*lanes)
    return mi.Ray3f(o_img, d, 0.0, wl), weight


def _object_value(
    target: Target, p_obj: Any, hit: Any, star: Any, tex: tuple[Any, tuple[int, ...], float, float] | None
) -> Any:
    """The test object at the object-plane points: the Siemens star ``star``, or the cells' texture ``tex``."""
    if target == "star":
        return siemens_star(p_obj.x, p_obj.y, star, DR)
    assert tex is not None  # the cells: render_channel made their texture
    tex_dr, tex_shape, tx0, ty0 = tex
    fx = dr.clip((p_obj.x - tx0) / 0.5e-3, 0, tex_shape[1] - 1)
    fy = dr.clip((p_obj.y - ty0) / 0.5e-3, 0, tex_shape[0] - 1)
    return dr.gather(mi.Float, tex_dr, mi.UInt32(fy) * tex_shape[1] + mi.UInt32(fx), hit)


def render_channel(
    setup: CmuSetup,
    channel: str,
    pose: CameraPose,
    target: Target = "star",
    spp: int = 16,
    window: tuple[int, int, int, int] | None = None,
    maps: dict[str, HeightMap] | None = None,
    tube_f: float | None = None,
    stop: bool = False,
    seed: int = 0,
    flat: bool = False,
    max_rays: int = 4_000_000,
    scene: tuple[Any, int] | None = None,
    variant: str | None = None,
) -> np.ndarray:
    """Image (float32, row 0 at the top) of the Siemens star or the dummy cells through one channel.

    Parameters
    ----------
    window : (row0, col0, height, width), optional
        Render only this part of the 1392 x 1040 sensor (pixel coordinates stay those of the full sensor).
    tube_f : float, optional
        Tube-lens focal length (default the setup's): a known magnification f_tube / f_objective.
    stop : bool
        The 4 mm aperture in front of the tube lens (§5.1.2).
    scene : optional
        A scene from :func:`unit_scene` to reuse (built in the same ``variant``).
    variant : str, optional
        Mitsuba variant (default ``choose("spectral")``, resolved now).
    """
    variant = resolve(variant, "spectral")
    mitsuba(variant)
    _check_channel(setup, channel, spp)
    cam = setup.camera
    row0, col0, hgt, wid = window or (0, 0, cam.height_px, cam.width_px)
    check_render(wid, hgt, spp, f"{setup.name or 'CMU'} {target} image, channel {channel}", "cmu")
    sc, obj_id = scene or unit_scene(setup, maps, tube_f, flat, variant)
    ch = setup.channels[channel]
    lens = axis_frame(np.asarray(ch.tube_center, dtype=np.float64), np.asarray(ch.tube_axis, dtype=np.float64))
    axes = (lens.origin, lens.tx, lens.ty, lens.nz, *sensor_axes(setup, channel))
    grid = cam.grid()
    pdf, norm = _wavelength_table(setup, channel, target)
    dist = mi.ContinuousDistribution([WL0_NM, WL1_NM], pdf + 1e-30)  # 701 nodes, one per nm of [300, 1000]
    tex = _cells_texture(setup) if target == "cells" else None
    lens_r = (0.5 * setup.tube.stop_diameter) if stop else 12.5
    stop_c = lens.origin - setup.tube.stop_gap * lens.nz
    stop_plane = (stop_c, lens.nz, 0.5 * setup.tube.stop_diameter) if stop else None
    n_pix = hgt * wid
    per_pass = max(1, min(spp, max_rays // max(n_pix, 1)))
    acc = np.zeros(n_pix, dtype=np.float64)
    done = 0
    pass_index = 0
    while done < spp:
        k = min(per_pass, spp - done)
        n = n_pix * k
        sampler = mi.load_dict({"type": "independent"})
        sampler.seed((seed * 100003 + pass_index) & 0xFFFFFFFF, n)  # the sampler takes a 32-bit seed
        idx = dr.arange(mi.UInt32, n) // k
        ray, weight = _sensor_rays(sampler, idx, (row0, col0, wid), grid, pose, axes, lens_r, dist)
        p_obj, thr, hit, _, _ = _trace_to_object(sc, obj_id, ray, mi.Spectrum(weight), sampler, stop_plane)
        tval = _object_value(target, p_obj, hit, setup.target, tex)
        value = dr.select(hit, dr.mean(thr) * tval, 0.0)
        vals = np.asarray(value, dtype=np.float64)
        acc += np.bincount(np.asarray(idx, dtype=np.int64), vals, minlength=n_pix)
        done += k
        pass_index += 1
    img = (acc / spp * norm).reshape(hgt, wid)
    return img.astype(np.float32)
