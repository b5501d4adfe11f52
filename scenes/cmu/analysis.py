"""Image-quality analyses of the microscope unit (thesis §5.1.2): refocus, magnification, spots, astigmatism,
wavefront PSF/MTF and the 4 mm aperture stop.

* **Refocus** (the thesis's "adjusting the image distance"): the tube-lens-to-image distance b that minimises the
  RMS spot radius summed over the fields axis, 0.7 and 1.0 of the field's half diagonal (Zemax's default
  RMS-spot focus). After the tube lens rays are straight, so each spot's centred second moment is a quadratic in
  b and the minimum is closed form.
* **Magnification**: spot centroids of a 3x3 grid of object points (+-0.25 mm, the Siemens-star frame) on the
  refocused plane, fitted by an affine map; m = sqrt|det A| (m_x, m_y: the singular values).
* **Spots**: RMS radius about the centroid (:func:`scopetwin.scenes.spots.rms_radius`, pupil sampled by
  :func:`scopetwin.scenes.spots.pupil_disk`, as for the GRIN objectives); "outer bound" = the corner of the 0.8978 x
  0.6708 mm
  field.
* **Astigmatism**: best focus of the pupil x-fan and y-fan separately; their difference.
* **Wavefront PSF/MTF**: the object point's plane wave after the perfect objective is traced through the plates
  to a plane normal to the beam at the tube lens; its optical path (piston and tilt removed) is the pupil phase;
  the perfect tube lens turns it into the image-plane field, |FFT|^2 gives the PSF, |FFT(PSF)| the MTF.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from scopetwin.scenes.cmu.layout import CmuSetup
from scopetwin.scenes.cmu.plates import fused_silica_index, plate_heightmap
from scopetwin.scenes.cmu.trace import PerfectLens, Rays, Stop, Surface, System, axis_frame
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.geometry import Array, Frame, normalize
from scopetwin.scenes.spots import pupil_disk, rms_radius
from scopetwin.scenes.surface import HeightMap

#: Emission-band centres of Table 3.1, nm (the wavelength of each channel's analysis).
CHANNEL_WAVELENGTH_NM = {"blue": 455.0, "green": 525.0, "red": 620.0, "nir": 785.0}
FIELD_FRACTIONS = (0.0, 0.7, 1.0)


@dataclass
class Optics:
    """A traced configuration: objective, the elements in between, optional stop, the tube lens."""

    objective: PerfectLens
    middle: list
    tube: PerfectLens
    stop: Stop | None
    wavelength_nm: float

    def system(self, with_tube: bool = True) -> System:
        els = [self.objective, *self.middle]
        if self.stop is not None:
            els.append(self.stop)
        if with_tube:
            els.append(self.tube)
        return System(els)


def _plate_surfaces(frame: Frame, hm: HeightMap | None, mode: str, setup: CmuSetup, n_glass: float) -> list:
    pw, ph, t = 0.5 * setup.plate.width, 0.5 * setup.plate.height, setup.plate.thickness
    if mode == "R":
        return [Surface(frame, hm, "R", 1.0, 0.0, pw, ph)]
    return [Surface(frame, hm, "T", n_glass, 0.0, pw, ph), Surface(frame, hm, "T", 1.0, -t, pw, ph)]


def channel_optics(
    setup: CmuSetup,
    channel: str,
    maps: dict[str, HeightMap] | None = None,
    stop: bool = False,
    wavelength_nm: float | None = None,
    flat: bool = False,
) -> Optics:
    """The channel's emission path (§4.1.3) as traceable elements.

    ``maps`` overrides plate height maps by element name; ``flat`` makes every plate a perfect flat.
    """
    if channel not in setup.channels:
        raise ScopetwinError(f"unknown channel {channel!r} (channels: {', '.join(setup.channels)})")
    ch = setup.channels[channel]
    wl = wavelength_nm or CHANNEL_WAVELENGTH_NM[channel]
    n_glass = float(fused_silica_index(wl))
    f_o = setup.objective.focal_length
    obj = PerfectLens(
        axis_frame(np.array([0.0, 0.0, f_o]), np.array([0.0, 0.0, 1.0])), f_o, 0.5 * setup.objective.beam_diameter
    )
    middle: list = []
    for name, mode in ch.steps():
        spec = setup.element(name)
        hm = None if flat else (maps or {}).get(name) or plate_heightmap(spec, setup.plate)
        middle += _plate_surfaces(spec.frame(), hm, mode, setup, n_glass)
    axis = normalize(np.asarray(ch.tube_axis, dtype=np.float64))
    centre = np.asarray(ch.tube_center, dtype=np.float64)
    tube = PerfectLens(axis_frame(centre, axis), setup.tube.focal_length)
    st = Stop(axis_frame(centre - setup.tube.stop_gap * axis, axis), 0.5 * setup.tube.stop_diameter) if stop else None
    return Optics(obj, middle, tube, st, wl)


def perpendicular_optics(
    setup: CmuSetup, mirror: HeightMap | None, distance: float = 40.0, stop: bool = False, wavelength_nm: float = 550.0
) -> Optics:
    """§5.1.2 / Fig. 5.2: a mirror (perfect, or a splitter's map) perpendicular to the beam, ``distance`` behind
    the objective, and the tube lens ``distance`` after it on the reflected beam (a sequential model, like Zemax's).
    The distance is not in the thesis; 40 mm is the unit's element spacing (thesis-cmu)."""
    f_o = setup.objective.focal_length
    obj = PerfectLens(
        axis_frame(np.array([0.0, 0.0, f_o]), np.array([0.0, 0.0, 1.0])), f_o, 0.5 * setup.objective.beam_diameter
    )
    mframe = Frame(
        np.array([0.0, 0.0, f_o + distance]),
        np.array([0.0, 1.0, 0.0]),
        np.array([1.0, 0.0, 0.0]),
        np.array([0.0, 0.0, -1.0]),
    )
    mirror_surface = Surface(mframe, mirror, "R", 1.0, 0.0, 0.5 * setup.plate.width, 0.5 * setup.plate.height)
    axis = np.array([0.0, 0.0, -1.0])
    centre = np.array([0.0, 0.0, f_o])
    tube = PerfectLens(axis_frame(centre, axis), setup.tube.focal_length)
    st = Stop(axis_frame(centre - setup.tube.stop_gap * axis, axis), 0.5 * setup.tube.stop_diameter) if stop else None
    return Optics(obj, [mirror_surface], tube, st, wavelength_nm)


# -- ray bundles ------------------------------------------------------------------------------------------
@dataclass
class ImageRays:
    """Rays after the tube lens in its frame: u = u0 + b su, v = v0 + b sv on the plane at distance b."""

    u0: Array
    v0: Array
    su: Array
    sv: Array

    def at(self, b: float) -> tuple[Array, Array]:
        return self.u0 + b * self.su, self.v0 + b * self.sv


def image_rays(opt: Optics, x0: float, y0: float, px: Array, py: Array) -> ImageRays:
    """Trace object point (x0, y0) through pupil points (px, py) (units of the objective's clear radius)."""
    a = opt.objective.radius
    f_o = opt.objective.f
    o = np.column_stack([np.full(px.shape, x0), np.full(px.shape, y0), np.zeros(px.shape)])
    target = np.column_stack([px * a, py * a, np.full(px.shape, f_o)])
    r = opt.system().trace(Rays.start(o, target - o))
    fr = opt.tube.frame
    loc = fr.to_local(r.o[r.alive])
    d = fr.vectors_to_local(r.d[r.alive])
    return ImageRays(loc[:, 0], loc[:, 1], d[:, 0] / d[:, 2], d[:, 1] / d[:, 2])


def best_focus(bundles: list[ImageRays]) -> float:
    """b minimising the summed centred second moments of the bundles (closed form)."""
    num = den = 0.0
    for r in bundles:
        u0, v0, su, sv = (a - a.mean() for a in (r.u0, r.v0, r.su, r.sv))
        num += np.mean(u0 * su + v0 * sv)
        den += np.mean(su * su + sv * sv)
    return float(-num / den)


def field_points(setup: CmuSetup) -> dict[str, tuple[float, float]]:
    """Object points axis, 0.7 and 1.0 of the half diagonal ("outer bound" = the field corner)."""
    w, h = setup.field_mm
    return {f"{f:.1f}": (0.5 * w * f, 0.5 * h * f) for f in FIELD_FRACTIONS}


@dataclass
class ChannelResult:
    """What :func:`analyse` measures for one configuration (lengths mm unless the name says µm)."""

    image_distance_mm: float
    magnification: float
    magnification_xy: tuple[float, float]
    rms_spot_um: dict[str, float]
    astigmatism_mm: float
    transmitted_fraction: float
    psf: dict | None = None

    def to_json(self) -> dict:
        out = {
            "image_distance_mm": self.image_distance_mm,
            "magnification": self.magnification,
            "magnification_xy": list(self.magnification_xy),
            "rms_spot_um": self.rms_spot_um,
            "astigmatism_mm": self.astigmatism_mm,
            "transmitted_fraction": self.transmitted_fraction,
        }
        if self.psf is not None:
            out["psf"] = {k: v for k, v in self.psf.items() if not isinstance(v, np.ndarray)}
        return out


def magnification(opt: Optics, b: float, half: float = 0.25, n_pupil: int = 15) -> tuple[float, tuple[float, float]]:
    """Affine fit of spot centroids of a 3x3 object grid (+-``half`` mm) on the plane b.

    Returns (sqrt|det A|, singular values of A)."""
    px, py = pupil_disk(n_pupil)
    obj, img = [], []
    for x0 in (-half, 0.0, half):
        for y0 in (-half, 0.0, half):
            u, v = image_rays(opt, x0, y0, px, py).at(b)
            obj.append((x0, y0, 1.0))
            img.append((u.mean(), v.mean()))
    coef, *_ = np.linalg.lstsq(np.asarray(obj), np.asarray(img), rcond=None)
    a = coef[:2].T
    sv = np.linalg.svd(a, compute_uv=False)
    return float(np.sqrt(abs(np.linalg.det(a)))), (float(sv[0]), float(sv[1]))


def astigmatism(opt: Optics, x0: float, y0: float, n: int = 41) -> float:
    """Distance between the foci of the pupil x-fan and y-fan of one object point, mm."""
    g = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    z = np.zeros_like(g)
    fx, fy = image_rays(opt, x0, y0, g, z), image_rays(opt, x0, y0, z, g)
    if min(len(fx.u0), len(fy.u0)) < 3:  # a stop away from the pupil's centre lines: measure without it
        return astigmatism(Optics(opt.objective, opt.middle, opt.tube, None, opt.wavelength_nm), x0, y0, n)
    return best_focus([fx]) - best_focus([fy])


def analyse(
    setup: CmuSetup, opt: Optics, n_pupil: int = 41, with_psf: bool = False, image_distance: float | None = None
) -> ChannelResult:
    """Refocus, magnification, RMS spots, astigmatism (and the wavefront PSF at the field corner)."""
    px, py = pupil_disk(n_pupil)
    fields = field_points(setup)
    bundles = {k: image_rays(opt, x, y, px, py) for k, (x, y) in fields.items()}
    b = best_focus(list(bundles.values())) if image_distance is None else image_distance
    rms = {k: rms_radius(*r.at(b)) * 1e3 for k, r in bundles.items()}
    m, mxy = magnification(opt, b)
    corner = fields["1.0"]
    ast = astigmatism(opt, *corner)
    frac = len(bundles["0.0"].u0) / len(px)
    psf = wavefront_psf(opt, *corner, defocus=b - opt.tube.f) if with_psf else None
    return ChannelResult(b, m, mxy, rms, ast, frac, psf)


# -- wavefront ------------------------------------------------------------------------------------------
def pupil_wavefront(opt: Optics, x0: float, y0: float, n: int = 128) -> dict[str, Any]:
    """Optical path (mm) of the object point's plane wave from the objective to the plane through the tube lens
    normal to the beam, on an n x n grid over the objective's clear aperture; NaN outside the (stopped) pupil.

    Returns ``opl`` (n, n), ``q2`` (squared distance from the tube axis on that plane, mm^2), ``dx`` (grid step)."""
    a = opt.objective.radius
    g = (np.arange(n) + 0.5) / n * 2.0 - 1.0
    gx, gy = np.meshgrid(g * a, g * a)
    f_o = opt.objective.f
    d0 = normalize(np.array([-x0 / f_o, -y0 / f_o, 1.0]))  # the perfect objective's plane wave
    o = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, f_o)])
    r = Rays.start(o, np.broadcast_to(d0, o.shape))
    r.alive &= (gx.ravel() ** 2 + gy.ravel() ** 2) <= a * a
    System([*opt.middle, *([opt.stop] if opt.stop is not None else [])]).trace(r)
    dmean = normalize(r.d[r.alive].mean(axis=0))
    centre = opt.tube.frame.origin
    lam = ((centre - r.o) @ dmean) / (r.d @ dmean)
    r.advance(lam)
    loc = opt.tube.frame.to_local(r.o)
    opl = np.where(r.alive, r.opl, np.nan).reshape(n, n)
    q2 = (loc[:, 0] ** 2 + loc[:, 1] ** 2).reshape(n, n)
    return {"opl": opl, "q2": q2, "dx": 2.0 * a / n}


def _remove_plane(w: Array, n: int) -> Array:
    ok = np.isfinite(w)
    yy, xx = np.mgrid[0:n, 0:n]
    a = np.column_stack([np.ones(ok.sum()), xx[ok], yy[ok]])
    c, *_ = np.linalg.lstsq(a, w[ok], rcond=None)
    out = np.full_like(w, np.nan)
    out[ok] = w[ok] - a @ c
    return out


def wavefront_psf(
    opt: Optics,
    x0: float,
    y0: float,
    defocus: float = 0.0,
    n: int = 128,
    pad: int = 4,
    object_magnification: float | None = None,
) -> dict:
    """PSF and MTF from the ray-traced pupil phase (Fraunhofer, perfect tube lens of focal length f).

    Parameters
    ----------
    defocus : float
        Image plane distance from the tube lens's focal plane, mm (b - f); adds -defocus |q|^2 / (2 f^2).

    Returns
    -------
    dict with ``wavefront_rms_waves``, ``wavefront_pv_waves`` (piston/tilt removed, at the refocused plane),
    ``strehl``, ``ee80_radius_um`` (radius holding 80 % of the energy), ``psf_pixel_um``,
    ``mtf_10_object_lp_per_mm`` (the
    orientation-averaged MTF's 10 % frequency at the object), ``delta_x_um`` (= 1/(2 that): the Siemens-star
    resolution it predicts), and the arrays ``psf`` and ``mtf``.
    """
    wl_mm = opt.wavelength_nm * 1e-6
    f = opt.tube.f
    pw = pupil_wavefront(opt, x0, y0, n)
    w = _remove_plane(pw["opl"] - defocus * pw["q2"] / (2.0 * f * f), n)
    ok = np.isfinite(w)
    m = n * pad
    field = np.zeros((m, m), dtype=np.complex128)
    field[:n, :n] = np.where(ok, np.exp(2j * np.pi * np.where(ok, w, 0.0) / wl_mm), 0.0)
    psf = np.abs(np.fft.fftshift(np.fft.fft2(field))) ** 2
    ref = np.zeros((m, m), dtype=np.complex128)
    ref[:n, :n] = ok
    peak0 = (np.abs(np.fft.fft2(ref)) ** 2).max()
    strehl = float(psf.max() / peak0)
    psf /= psf.sum()
    du_mm = wl_mm * f / (m * pw["dx"])
    c = np.arange(m) - m // 2
    xx, yy = np.meshgrid(c * du_mm, c * du_mm)
    cx, cy = (psf * xx).sum(), (psf * yy).sum()
    r_sorted = np.sort(np.hypot(xx - cx, yy - cy).ravel())
    cum = np.cumsum(psf.ravel()[np.argsort(np.hypot(xx - cx, yy - cy).ravel())])
    ee80 = float(r_sorted[np.searchsorted(cum, 0.8)])
    mtf = np.abs(np.fft.fftshift(np.fft.fft2(np.fft.ifftshift(psf))))
    freq = c / (m * du_mm)  # cycles/mm at the image
    rr = np.hypot(*np.meshgrid(freq, freq))
    edges = np.arange(0, freq.max(), freq[1] - freq[0])
    idx = np.digitize(rr.ravel(), edges)
    prof = np.bincount(idx, mtf.ravel(), minlength=len(edges) + 1)[1 : len(edges)] / np.maximum(
        np.bincount(idx, minlength=len(edges) + 1)[1 : len(edges)], 1
    )
    nu = edges[:-1] + 0.5 * (freq[1] - freq[0])
    below = np.flatnonzero(prof < 0.1)
    nu10 = float(nu[below[0]]) if below.size else float(nu[-1])
    mag = object_magnification or f / opt.objective.f
    nu10_obj = nu10 * mag
    wv = w[ok] / wl_mm
    return {
        "wavefront_rms_waves": float(np.std(wv)),
        "wavefront_pv_waves": float(np.ptp(wv)),
        "strehl": strehl,
        "ee80_radius_um": ee80 * 1e3,
        "psf_pixel_um": du_mm * 1e3,
        "mtf_10_object_lp_per_mm": nu10_obj,
        "delta_x_um": 1e3 / (2.0 * nu10_obj),
        "wavelength_nm": opt.wavelength_nm,
        "psf": psf.astype(np.float32),
        "mtf_profile": np.column_stack([nu * mag, prof]),
    }


def airy_radius_um(opt: Optics) -> float:
    """Image-side Airy radius 1.22 lambda f / D of the beam (or the stop) at the tube lens, µm."""
    d = 2.0 * (opt.stop.radius if opt.stop is not None else opt.objective.radius)
    return 1.22 * opt.wavelength_nm * 1e-6 * opt.tube.f / d * 1e3
