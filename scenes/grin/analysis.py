"""Deterministic ray-bundle analysis of a GRIN objective (thesis §7.5.2, §8.3): paraxial data, NA, spots, Airy, OPD.

Conventions (chosen to be close to what a Zemax spot diagram reports, and stated because the
thesis does not say how its figures were set up):

* Object-space aperture: rays leave each object point with transverse optical direction cosines
  (T_x, T_y) = n sin θ (cos φ, sin φ) filling a disk of radius NA around the *chief ray*, the ray
  through the centre of the stop (the back face of rod 1, where §8.3.1 puts its aperture; for the
  realized system without aperture the same plane). Rays that hit a rod wall or the stop are
  vignetted (dropped), as in a real-ray trace.
* Object-side NA: the largest on-axis NA that passes (bisection on a meridional real ray); with an
  aperture spec (``aperture.na_object``) the stop radius is the height of that NA's marginal ray on
  rod 1's back face.
* RMS spot radius: about the centroid of the surviving rays, on the image plane.
* Image plane ("best focus"): the distance from the last surface that minimises the sum of the
  squared RMS radii over the field points 0, 0.7 and 1 of the field radius (closed form: the
  RMS² of a fixed ray set is quadratic in the plane distance), i.e. an image-distance
  optimisation for the RMS spot as in §8.3.2 -- with our layout, never with the thesis's numbers.
* Airy radius: 0.61 λ / NA_image, NA_image the image-space sine of the on-axis marginal ray.

The pupil sampling, the RMS spot radius and the Airy radius are those of :mod:`scopetwin.scenes.spots`, shared with the
microscope unit's analysis (:mod:`scopetwin.scenes.cmu.analysis`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.grin.paraxial import RodParaxial, rod_paraxial, system_paraxial
from scopetwin.scenes.grin.rkn import RayState, trace_stack
from scopetwin.scenes.grin.setup import GrinSetup, Stack
from scopetwin.scenes.spots import airy_radius, pupil_disk, rms_radius

Array = NDArray[np.float64]
FIELDS = (0.0, 0.7, 1.0)


def _stop_layer_count(stack: Stack) -> int:
    return next(i for i, layer in enumerate(stack.layers) if layer.name == "rod1") + 1


def marginal_na(stack: Stack, iterations: int = 50) -> float:
    """Largest on-axis object-space NA that passes the objective (bisection on a meridional real ray)."""
    lo, hi = 0.0, 0.999
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        st = trace_stack(stack, np.zeros(1), np.zeros(1), np.zeros(1), np.array([mid]))
        if st.alive[0]:
            lo = mid
        else:
            hi = mid
    return lo


def stop_radius_for_na(stack: Stack, na: float) -> float:
    """Height of the on-axis marginal ray of NA ``na`` on the back face of rod 1 (the §8.3.1 aperture)."""
    st = trace_stack(
        stack.with_stop_radius(None),
        np.zeros(1),
        np.zeros(1),
        np.zeros(1),
        np.array([na]),
        until_layer=_stop_layer_count(stack),
    )
    return float(abs(st.y[0]))


def best_focus(bundles: list[Bundle]) -> float:
    """Image distance minimising Σ RMS² over the bundles (closed form, RMS² is quadratic in the distance)."""
    num = den = 0.0
    for b in bundles:
        st = b.state
        keep = st.alive
        tz = st.tz[keep]
        for pos, t in ((st.x[keep], st.tx[keep]), (st.y[keep], st.ty[keep])):
            u = t / tz
            du = u - u.mean()
            num += float(np.mean((pos - pos.mean()) * du))
            den += float(np.mean(du * du))
    return -num / den


def chief_ray(stack: Stack, height: float, iterations: int = 40) -> float:
    """T_y of the ray from object height ``height`` (along y) through the centre of the stop plane."""
    n = _stop_layer_count(stack)

    def y_at_stop(t: float) -> float:
        st = trace_stack(
            stack.with_stop_radius(None), np.zeros(1), np.array([height]), np.zeros(1), np.array([t]), until_layer=n
        )
        return float(st.y[0])

    a, b = 0.0, -0.1 * np.sign(height) if height else 0.0
    if height == 0.0:
        return 0.0
    fa, fb = y_at_stop(a), y_at_stop(b)
    for _ in range(iterations):
        if fb == fa:
            break
        c = b - fb * (b - a) / (fb - fa)
        a, fa = b, fb
        b, fb = c, y_at_stop(c)
        if abs(fb) < 1e-13:
            break
    return float(b)


@dataclass
class Bundle:
    """Rays of one object point after the last surface, with the pupil coordinates they came from."""

    height: float
    state: RayState
    px: Array
    py: Array

    def spot(self, image_distance: float) -> tuple[Array, Array]:
        """Surviving ray heights (x, y) on the image plane ``image_distance`` past the last surface (mm)."""
        x, y = self.state.at(image_distance)
        keep = self.state.alive
        return x[keep], y[keep]


def bundle(stack: Stack, height: float, na: float, samples: int = 48) -> Bundle:
    """Trace a pupil-filling bundle from object height ``height`` (along y) at NA ``na`` about the chief ray."""
    px, py = pupil_disk(samples)
    t_chief = chief_ray(stack, height)
    st = trace_stack(stack, np.zeros_like(px), np.full_like(px, height), na * px, t_chief + na * py)
    return Bundle(height, st, px, py)


def opd_waves(b: Bundle, image_distance: float, wavelength_nm: float) -> tuple[float, float]:
    """RMS and peak-to-valley wavefront OPD (waves) about a reference sphere centred on the spot centroid.

    The sphere passes through the last surface where the chief-ray-nearest ray (pupil centre) meets it;
    each ray's OPL is continued in the image medium to the sphere.
    """
    st = b.state
    keep = st.alive
    x, y = st.x[keep], st.y[keep]
    tz = st.tz[keep]
    n = st.n
    ux, uy, uz = st.tx[keep] / n, st.ty[keep] / n, tz / n
    ix, iy = b.spot(image_distance)
    cx, cy, cz = ix.mean(), iy.mean(), image_distance
    dx, dy, dz = x - cx, y - cy, 0.0 - cz
    centre = int(np.argmin(b.px[keep] ** 2 + b.py[keep] ** 2))
    radius = np.sqrt(dx[centre] ** 2 + dy[centre] ** 2 + dz**2)
    # |p + s u - c| = R  ->  s² + 2 s (u.(p-c)) + |p-c|² - R² = 0, root with the sphere ahead of p
    bq = ux * dx + uy * dy + uz * dz
    cq = dx * dx + dy * dy + dz * dz - radius * radius
    s = -bq - np.sqrt(np.maximum(bq * bq - cq, 0.0))
    s = np.where(
        np.abs(s) > np.abs(-bq + np.sqrt(np.maximum(bq * bq - cq, 0.0))),
        -bq + np.sqrt(np.maximum(bq * bq - cq, 0.0)),
        s,
    )
    opl = st.opl[keep] + n * s
    opd = (opl - opl[centre]) / (wavelength_nm * 1e-6)
    opd = opd - opd.mean()
    return float(np.sqrt(np.mean(opd**2))), float(opd.max() - opd.min())


@dataclass
class GrinReport:
    """Everything ``scopetwin optics grin`` prints and writes (lengths mm, ``_um`` in µm)."""

    efl_mm: float
    magnification: float
    magnification_real: float
    na_object: float
    na_image: float
    airy_um: float
    rms_spot_um: dict[str, float]
    rms_spot_at_seed_plane_um: dict[str, float]
    object_distance_mm: float
    image_distance_mm: float
    paraxial_image_distance_mm: float
    stop_radius_mm: float | None
    opd_rms_waves: dict[str, float]
    opd_pv_waves: dict[str, float]
    rods: dict[str, dict[str, float]]
    wavelength_nm: float
    section: str
    seed: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        """The contract's keys first (docs/contract.md, ``optics grin``), then the extras."""
        d = asdict(self)
        head = {
            k: d.pop(k)
            for k in (
                "efl_mm",
                "magnification",
                "na_object",
                "airy_um",
                "rms_spot_um",
                "object_distance_mm",
                "image_distance_mm",
            )
        }
        return head | d


def analyse(setup: GrinSetup, samples: int = 48, stack: Stack | None = None) -> GrinReport:
    """Paraxial data, NA, Airy radius, RMS spots on axis and at the field edge, OPD (thesis §8.3 figures)."""
    st = setup.stack() if stack is None else stack
    stop = None
    if setup.aperture.na_object is not None:
        stop = stop_radius_for_na(st, setup.aperture.na_object)
        st = st.with_stop_radius(stop)
    na = marginal_na(st)
    if setup.aperture.na_object is not None:
        na = min(na, setup.aperture.na_object)
    par = system_paraxial(st)
    h = setup.object.field_radius
    bundles = [bundle(st, f * h, na, samples) for f in FIELDS]
    focus = best_focus(bundles)
    axis, edge = bundles[0], bundles[-1]
    rms = {"axis": rms_radius(*axis.spot(focus)) * 1e3, "edge": rms_radius(*edge.spot(focus)) * 1e3}
    seed_plane = setup.seed.image_distance or setup.image.distance
    rms_seed = (
        {"axis": rms_radius(*axis.spot(seed_plane)) * 1e3, "edge": rms_radius(*edge.spot(seed_plane)) * 1e3}
        if seed_plane
        else {}
    )
    marg = trace_stack(st, np.zeros(1), np.zeros(1), np.zeros(1), np.array([na * (1 - 1e-9)]))
    na_img = float(np.hypot(marg.tx[0], marg.ty[0]) / marg.n)
    airy = airy_radius(setup.wavelength_nm, na_img) * 1e3
    ex, ey = edge.spot(focus)
    m_real = float(ey.mean() / h)
    opd = [opd_waves(b, focus, setup.wavelength_nm) for b in (axis, edge)]
    rods: dict[str, dict[str, float]] = {}
    for key, prof, spec in (("rod1", setup.profile1(), setup.rod1), ("rod2", setup.profile2(), setup.rod2)):
        rp: RodParaxial = rod_paraxial(prof, spec.length)
        rods[key] = {
            "length_mm": spec.length,
            "n0": rp.n0,
            "g_per_mm": rp.g,
            "pitch_mm": rp.pitch,
            "efl_mm": float(rp.efl),
            "working_distance_mm": float(rp.bfl),
            "pitch_fraction": spec.length / rp.pitch,
        }
    seed = {k: v for k, v in setup.seed.model_dump().items() if v is not None}
    return GrinReport(
        efl_mm=float(par.efl),
        magnification=float(abs(par.magnification)),
        magnification_real=abs(m_real),
        na_object=float(na),
        na_image=na_img,
        airy_um=float(airy),
        rms_spot_um=rms,
        rms_spot_at_seed_plane_um=rms_seed,
        object_distance_mm=setup.object.distance,
        image_distance_mm=float(focus),
        paraxial_image_distance_mm=float(par.image_distance),
        stop_radius_mm=stop,
        opd_rms_waves={"axis": opd[0][0], "edge": opd[1][0]},
        opd_pv_waves={"axis": opd[0][1], "edge": opd[1][1]},
        rods=rods,
        wavelength_nm=setup.wavelength_nm,
        section=setup.section,
        seed=seed,
    )


# -- the published layout's ambiguities ---------------------------------------------------------
READINGS: dict[str, dict[str, Any]] = {
    "chosen": {},
    "substrate1 outer (faces the object)": {"layout": {"substrate1_side": "outer"}},
    "substrate2 outer (faces the camera)": {"layout": {"substrate2_side": "outer"}},
    "both substrates outer": {"layout": {"substrate1_side": "outer", "substrate2_side": "outer"}},
    "object distance includes cover glass": {"object": {"distance_includes_cover": True}},
    "no cover glass": {"object": {"cover_thickness": 0.0}},
    "rod values at 587.6 nm, dispersed": {
        "rod1": {"profile": {"wavelength_ref_nm": 587.56}},
        "rod2": {"profile": {"wavelength_ref_nm": 587.56}},
    },
    "rod values at 633 nm, dispersed": {
        "rod1": {"profile": {"wavelength_ref_nm": 632.8}},
        "rod2": {"profile": {"wavelength_ref_nm": 632.8}},
    },
}


def sensitivity(setup: GrinSetup, samples: int = 24) -> list[dict[str, Any]]:
    """Paraxial magnification and image distance, real best focus, NA and RMS spots under each reading."""
    import json

    from scopetwin.scenes.grin.setup import grin_setup_from_dict
    from scopetwin.scenes.setup import _merge

    base = json.loads(setup.model_dump_json())
    rows = []
    for label, change in READINGS.items():
        variant = grin_setup_from_dict(_merge(base, change), label)
        st = variant.stack()
        par = system_paraxial(st)
        rep = analyse(variant, samples=samples)
        rows.append(
            {
                "reading": label,
                "magnification_paraxial": abs(par.magnification),
                "paraxial_image_distance_mm": par.image_distance,
                "image_distance_mm": rep.image_distance_mm,
                "na_object": rep.na_object,
                "rms_axis_um": rep.rms_spot_um["axis"],
                "rms_edge_um": rep.rms_spot_um["edge"],
                "airy_um": rep.airy_um,
                "magnification_real": rep.magnification_real,
            }
        )
    return rows
