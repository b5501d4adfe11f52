"""The ``inverse`` study: inverse rendering beside the centroid method and the pixels' Cramér-Rao bound.

For §1.9 surfaces at 3-20 mm correlation (the Gaussian family, and the PSD family of :mod:`scopetwin.sim.surfaces` when
it
is there), with and without the EMVA 1288 sensor model, the §1.10 measurement is rendered with Mitsuba and
reconstructed by the centroid method (:mod:`scopetwin.recon.reconstruct`) and by inverse rendering
(:mod:`scopetwin.recon.inverse`,
started from the centroid result, or where that fails from :func:`scopetwin.recon.strategy.inverse_start`'s next choice
— the
centroid method without its bias step, a coarse fit of the markers, a plane); each Gauss-Newton step's
surface is compared with the truth (shape and absolute error against the step's time). Beside them: the
Cramér-Rao bound on the shape RMS, from the Fisher information J^T W J of the render with respect to the B-spline
coefficients at the truth (the mean height fixed as in the fit, the fit's thin-plate prior included), with W the
EMVA 1288 pixel variances of the image a camera would give at the study's exposure; and the Bayesian (Van Trees)
bound of the same pixels under the surface family's prior (:func:`family_prior`), which bounds both methods.
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

import numpy as np

from scopetwin.sim.studies.context import StudyContext, StudyResult, error_text, failed, require
from scopetwin.sim.studies.tables import Table, jsonable

if TYPE_CHECKING:  # the reconstruction is imported lazily at run time
    from scopetwin.recon.inverse import InverseReconstructor

INVERSE_MODULES = {
    "scopetwin.recon.markers": "marker detection and indexing",
    "scopetwin.recon.reconstruct": "the centroid method",
    "scopetwin.recon.inverse": "inverse rendering",
}

#: (correlation length mm, range µm) of the study's surfaces: the thesis's kind and two steeper kinds.
CASES = ((20.0, 40.0), (12.0, 40.0), (5.0, 40.0), (3.0, 60.0))


def emva_variance_irradiance(irradiance: Any, setup: Any) -> Any:
    """Per-pixel variance (irradiance units^2) of the image a camera would give at the setup's exposure (EMVA 1288)."""
    sensor = setup.sensor.sensor()
    img = np.asarray(irradiance, dtype=np.float64)
    exposure = setup.sensor.exposure_s or sensor.exposure_for(
        float(img.max()), setup.sensor.photons_per_unit_s, setup.sensor.fill_fraction
    )
    k = sensor.gain_dn_per_e
    gain = k * sensor.quantum_efficiency * setup.sensor.photons_per_unit_s * exposure  # DN per irradiance unit
    var_dn = k * k * sensor.dark_noise_e**2 + gain * np.maximum(img, 0.0) * k + 1.0 / 12.0
    return var_dn / gain**2


def shape_crb_um(rec: Any, surf: Any, var: Any, sub: int = 3, probes: int = 32) -> float:
    """Cramér-Rao bound on the ROI shape RMS, µm (:meth:`scopetwin.recon.inverse.InverseReconstructor.shape_std_um`)."""
    return float(rec.shape_std_um(surf, var, sub, probes))


def family_prior(setup: Any, spacing: float, draws: int = 400, seed0: int = 10_000) -> Any:
    """Square root X of the prior covariance X X^T of the B-spline coefficients of the setup's surface family.

    ``draws`` surfaces of the setup's kind, correlation length and range (seeds ``seed0`` on, none of them a study
    surface) are fitted by the inverse fit's B-spline (knot spacing ``spacing``, mm); X is their centred
    coefficients over sqrt(draws - 1), (n, draws). The family's prior as the generator makes it (levelled on the
    frame and scaled to the range), for :meth:`scopetwin.recon.inverse.InverseReconstructor.shape_bayes_bound_um`.
    """
    from scopetwin.recon.inverse import SplineSurface
    from scopetwin.recon.substrate import Substrate2D
    from scopetwin.sim.surfaces import make_surface

    sub = Substrate2D.from_setup(setup)
    spec = setup.substrate.surface
    maps = [make_surface(spec.model_copy(update={"seed": seed0 + k}), setup.substrate) for k in range(draws)]

    def values(x: Any, y: Any) -> Any:
        return np.stack([m.height(x, y).ravel() for m in maps], axis=1)

    coef = SplineSurface.fit_columns(values, sub, spacing)
    coef -= coef.mean(axis=1, keepdims=True)
    return coef / np.sqrt(draws - 1.0)


def untilted_shape_um(surface_height: Any, truth: Any, sub: Any, step: float = 0.2) -> float:
    """RMS over the ROI of the error after removing its best-fit plane, µm.

    The shape error (std of the error) carries the tilt that an error of the start height forces on every
    reconstruction (the traced rays meet the surface at the wrong height; on a 3 mm / 60 µm surface ~9 µrad per
    µm of absolute error); this part is what the method itself gets wrong.
    """
    from scopetwin.recon.inverse import without_plane

    xs = np.linspace(-0.5 * sub.size_x, 0.5 * sub.size_x, int(round(sub.size_x / step)) + 1)
    ys = np.linspace(-0.5 * sub.roi_length, 0.5 * sub.roi_length, int(round(sub.roi_length / step)) + 1)
    xx, yy = np.meshgrid(xs, ys[1:-1])
    err = (np.asarray(surface_height(xx, yy)) - np.asarray(truth.height(xx, yy))).ravel() * 1e3
    return float(np.std(without_plane(xx.ravel(), yy.ravel(), err)))


def inverse_task(
    kind: str,
    corr: float,
    range_um: float,
    seed: int,
    noise: bool,
    spp: int,
    config: dict[str, Any] | None = None,
    bounds: bool = True,
) -> dict[str, Any]:
    """One surface: render, centroid method, inverse rendering step by step, the Cramér-Rao bound (JSON-ready).

    ``bounds=False`` leaves out the Cramér-Rao and Bayesian bounds (the family prior's hundreds of draws).
    """
    from scopetwin.recon.inverse import InverseConfig, InverseReconstructor
    from scopetwin.recon.strategy import inverse_start
    from scopetwin.recon.substrate import Substrate2D
    from scopetwin.scenes.errors import ScopetwinError
    from scopetwin.sim.pipeline import roi_errors

    setup, truth, clean, image = _render_case(kind, corr, range_um, seed, noise, spp)
    sub = Substrate2D.from_setup(setup)
    row: dict[str, Any] = {"kind": kind, "correlation_mm": corr, "range_um": range_um, "noise": noise, "seed": seed}
    t0 = time.perf_counter()
    begin = inverse_start(image, setup)  # the centroid method, or what is left where it fails
    row |= _start_row(begin, truth, sub)
    row["centroid_s"] = time.perf_counter() - t0
    cfg = {"absolute": begin.absolute} | (config or {})
    rec = InverseReconstructor(setup, image, InverseConfig(**cfg))
    steps = _trace_steps(rec, truth, sub)
    try:
        out = rec.run(begin.surface, begin.absolute_std_um)
    except ScopetwinError as exc:
        row["inverse_error"] = f"{type(exc).__name__}: {exc}"
        return row
    e = roi_errors(out.surface.height, truth, sub)
    row |= {
        "inverse_shape_um": e["roi_shape_um"],
        "inverse_abs_um": e["roi_absolute_um"],
        "inverse_untilted_um": untilted_shape_um(out.surface.height, truth, sub),
        "inverse_s": out.seconds,
        "inverse_std_um": out.shape_std_um,
        "steps": steps,
    }
    if not bounds:
        return row
    return row | _bounds_row(rec, setup, truth, sub, clean, corr)


def _render_case(
    kind: str, corr: float, range_um: float, seed: int, noise: bool, spp: int
) -> tuple[Any, Any, Any, Any]:
    """The study's setup for one surface, the truth, its Mitsuba render and the image (EMVA 1288 noise if asked)."""
    from scopetwin.scenes.setup import load_setup
    from scopetwin.sim.measurement import render_measurement
    from scopetwin.sim.studies.tasks import THESIS_DEFLECTOMETRY, quiet
    from scopetwin.sim.surfaces import surface_for

    quiet()
    over = {
        "substrate": {"surface": {"kind": kind, "correlation_length": corr, "range_um": range_um, "seed": seed}},
        "render": {"spp": spp, "seed": 1, "noise": noise},
    }
    setup = load_setup(THESIS_DEFLECTOMETRY, over)
    truth = surface_for(setup)
    assert truth is not None
    clean, _ = render_measurement(setup, truth, spp, 1, False)
    image = clean
    if noise:
        from scopetwin.sim.measurement import apply_sensor

        image = apply_sensor(setup, clean, 1)
    return setup, truth, clean, image


def _start_row(begin: Any, truth: Any, sub: Any) -> dict[str, Any]:
    """The inverse fit's start (:func:`scopetwin.recon.strategy.inverse_start`): its kind, markers and errors."""
    from scopetwin.sim.pipeline import roi_errors

    row: dict[str, Any] = {"start": begin.kind}
    if begin.markers is not None:
        row |= {"markers": len(begin.markers), "indexing": begin.markers.indexing}
    if begin.note:
        row["centroid_error"] = begin.note
    if begin.kind == "centroid":
        e = roi_errors(begin.surface.height, truth, sub)
        row |= {
            "centroid_shape_um": e["roi_shape_um"],
            "centroid_abs_um": e["roi_absolute_um"],
            "centroid_untilted_um": untilted_shape_um(begin.surface.height, truth, sub),
        }
    elif begin.surface is not None:
        e = roi_errors(begin.surface.height, truth, sub)
        row |= {"start_shape_um": e["roi_shape_um"], "start_abs_um": e["roi_absolute_um"]}
    return row


def _trace_steps(rec: InverseReconstructor, truth: Any, sub: Any) -> list[dict[str, float]]:
    """Wrap ``rec.fit_level`` to take one Gauss-Newton step per call and record each step's errors; the record."""
    from scopetwin.sim.pipeline import roi_errors

    steps: list[dict[str, float]] = []
    fit_level = rec.fit_level

    def traced(lev: Any, surf: Any, h: float, iterations: int, index: int) -> Any:
        for _ in range(iterations):
            surf = fit_level(lev, surf, h, 1, index)
            e = roi_errors(surf.height, truth, sub)
            steps.append(
                {
                    "seconds": rec.history[-1].seconds,
                    "level": index,
                    "chi2": rec.history[-1].chi2,
                    "shape_um": e["roi_shape_um"],
                    "abs_um": e["roi_absolute_um"],
                }
            )
        return surf

    rec.fit_level = traced  # type: ignore[method-assign]
    return steps


def _bounds_row(rec: InverseReconstructor, setup: Any, truth: Any, sub: Any, clean: Any, corr: float) -> dict[str, Any]:
    """The Cramér-Rao bound of the free spline at the truth and the Bayesian bounds under the family's prior."""
    from scopetwin.recon.inverse import SplineSurface
    from scopetwin.sim.pipeline import roi_errors

    exact = SplineSurface.fit(truth.height, sub, rec.config.spacing)
    rec._span = None  # the Cramér-Rao column is the free spline's
    row: dict[str, Any] = {
        "spline_shape_um": roi_errors(exact.height, truth, sub)["roi_shape_um"],
        "crb_shape_um": shape_crb_um(rec, exact, emva_variance_irradiance(clean, setup)),
    }
    # draws of the family: the bound converges by ~100 at 12 mm (0.00131 / 0.00132 µm with 100 / 200) and slowly at
    # 3 mm (0.00130 / 0.00145 / 0.00152 with 100 / 200 / 400: the short-correlated family has more modes)
    prior = family_prior(setup, rec.config.spacing, 400 if corr < 8.0 else 100)
    var = emva_variance_irradiance(clean, setup)
    row["bayes_bound_um"] = rec.shape_bayes_bound_um(exact, prior, var)
    row["bayes_untilted_um"] = rec.shape_bayes_bound_um(exact, prior, var, untilted=True)
    return row


def inverse(ctx: StudyContext, spp: int = 16, seed: int = 2) -> StudyResult:
    """Shape and absolute error of both methods, the inverse fit's history, and the Cramér-Rao bound."""
    require("inverse", INVERSE_MODULES)
    from typing import get_args

    from scopetwin.scenes.setup import SurfaceSpec

    known = get_args(SurfaceSpec.model_fields["kind"].annotation)
    kinds = ["random"] + (["psd"] if "psd" in known else [])  # the PSD family where sim.surfaces has it
    args = [(k, c, r, seed, n, spp) for k in kinds for c, r in CASES for n in (False, True)]
    # a second 3 mm / 60 µm surface (on the study's seed the flood indexed 12 markers; index_lattice numbers them now)
    args += [("random", c, r, seed + 1, n, spp) for c, r in CASES if c < 4.0 for n in (False, True)]
    rows = ctx.map(inverse_task, args, "inverse: render + reconstruct")
    notes = [f"case failed: {error_text(r)}" for r in rows if failed(r)]
    good = [r for r in rows if not failed(r)]
    cells = []
    for r in good:
        cells.append(_table_row(r))
        notes += [f"{r['correlation_mm']} mm: {r[k]}" for k in ("centroid_error", "inverse_error") if k in r]
    return StudyResult(
        "Study: inverse rendering",
        "The surface fitted to the whole image through a differentiable render, beside the centroid "
        "method and the Cramér-Rao bound of the pixels.",
        [_inverse_table(cells, spp)],
        [],
        {"rows": jsonable(good)},
        notes,
    )


def _table_row(r: dict[str, Any]) -> list[Any]:
    """One surface's cells of the study's table (:func:`_inverse_table`'s columns)."""
    return [
        r["kind"],
        r["seed"],
        r.get("start", "-"),
        r["correlation_mm"],
        r["range_um"],
        "EMVA" if r["noise"] else "none",
        r.get("centroid_shape_um"),
        r.get("centroid_untilted_um"),
        r.get("centroid_abs_um"),
        r.get("inverse_shape_um"),
        r.get("inverse_std_um"),
        r.get("inverse_untilted_um"),
        r.get("inverse_abs_um"),
        r.get("crb_shape_um"),
        r.get("bayes_bound_um"),
        r.get("bayes_untilted_um"),
        r.get("inverse_s"),
    ]


def _inverse_table(cells: list[list[Any]], spp: int) -> Table:
    """The study's table: both methods' errors beside the bounds, one row per surface."""
    return Table(
        "Inverse rendering beside the centroid method (ROI shape = std of the error, absolute = its mean)",
        columns=[
            "surface",
            "seed",
            "inverse start",
            "correlation (mm)",
            "range (µm)",
            "sensor noise",
            "centroid shape (µm)",
            "centroid shape, tilt removed (µm)",
            "centroid absolute (µm)",
            "inverse shape (µm)",
            "inverse shape uncertainty (µm)",
            "inverse shape, tilt removed (µm)",
            "inverse absolute (µm)",
            "Cramér-Rao shape, spline (µm)",
            "Bayesian bound, family prior (µm)",
            "Bayesian bound, tilt removed (µm)",
            "inverse seconds",
        ],
        cells=cells,
        note=f"§1.10 setup, Mitsuba {spp} spp; 'tilt removed': the error's best-fit plane removed (the tilt an "
        "absolute-height error forces on the traced rays, :func:`untilted_shape_um`); both bounds from the pixel "
        "data's Fisher information with the EMVA 1288 variances at the study's exposure (70 % full well at the "
        "peak). 'Cramér-Rao, spline': for estimators with the free B-spline's freedom (6490 coefficients, a weak "
        "thin-plate prior) — methods with a stronger prior may lie below it. 'Bayesian bound': the Van Trees bound "
        "under the surface family's own prior (100-400 draws of the generator, :func:`family_prior`), which bounds "
        "every method's mean-square shape error over the family, the centroid method's included; the mean ROI "
        "height is known in it (the frame criterion's error, and the tilt it forces, are not part of it). "
        "Noise-free rows carry only Mitsuba's sampling noise.",
    )
