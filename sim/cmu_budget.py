"""The four-channel unit's speed claim, computed (``scopetwin optics cmu --budget``): photon budget, lasers, time.

Three tables and a plot, from :mod:`scopetwin.scenes.cmu.photon_budget` and :mod:`scopetwin.sim.field_time`:

1. :func:`seed_table`: per channel the photoelectrons per pixel per ms and the exposure for the stated SNR, at the
   labelling density that the blue channel's 80 ms implies, beside the thesis's 80 / 4000 / 9800 / 6000 ms (§5.2.3);
   and the density each channel's own exposure implies (does it follow from the blue one?).
2. :func:`laser_table`: the lasers the thesis proposes (§5.2.3) on the same sample (each stain at the density its
   thesis exposure implies): the exposures they give, when the full well fills and how fast the proteins bleach.
3. :func:`timing`: time per field and per slide, the unit against a sequential microscope, with the thesis's
   sources and with the lasers.

:func:`render_cells` renders the dummy cells through each channel (Mitsuba) and scales them to the budget's
photoelectrons, so that the images are as bright, as noisy and as dark as the budget says at a given exposure.
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from scopetwin.scenes.cmu import photon_budget as pb
from scopetwin.scenes.cmu import spectra
from scopetwin.sim import field_time

#: The SNR a fluorescence image must reach on the labelled structure (our criterion; the thesis names none).
DEFAULT_SNR = 10.0
#: Thickness of a nucleus, µm, to express a density as a concentration (a typical adherent cell's; not in the thesis).
NUCLEUS_UM = 5.0
#: Side of the square window of the budget's cell renders, px (the camera's centre).
DEFAULT_WINDOW_PX = 256


def seed_table(snr: float = DEFAULT_SNR) -> dict[str, dict[str, Any]]:
    """Per channel, at the density the blue channel's 80 ms implies: the budget beside the thesis's exposures."""
    comp = pb.seed_comparison(snr)
    rho = comp["blue"]["implied_density_per_um2"]
    out = {}
    for ch, b in pb.budget(rho, snr).items():
        out[ch] = {
            "stain": b.stain,
            "source": b.source,
            "power_mw": b.power_mw,
            "excitation_per_s": b.excitation_per_s,
            "detection_e_per_photon": b.detection_e_per_photon,
            "e_per_px_per_ms": b.e_per_px_per_ms,
            "density_per_um2": rho,
            **comp[ch],
        }
    return out


def _limit(b: pb.ChannelBudget) -> str:
    """What ends a longer exposure first: the full well filling, the stain bleaching (to 1/e) or the camera's longest
    exposure (9800 ms, the thesis, §5.2.3)."""
    limits = {
        f"full well at {b.saturation_ms:.4g} ms": b.saturation_ms,
        f"the camera's longest exposure, {pb.MAX_EXPOSURE_MS:g} ms": pb.MAX_EXPOSURE_MS,
    }
    if b.bleach_tau_s is not None:
        limits[f"bleaching (1/e) at {b.bleach_tau_s:.4g} s"] = 1e3 * b.bleach_tau_s
    return min(limits, key=lambda k: limits[k])


def laser_table(snr: float = DEFAULT_SNR) -> dict[str, dict[str, Any]]:
    """The thesis's lasers (§5.2.3) on the thesis's sample: each stain at the density its thesis exposure implies.

    Per channel: the laser, the power that reaches the object plane through the channel's excitation path, the
    photoelectrons per pixel per ms, the exposure for ``snr`` (and the speed-up over the thesis's exposure), the
    exposure that fills the full well, the bleaching time and the fraction bleached in the exposure, and which of
    the two limits a longer exposure first. The red channel's thesis image was underexposed at 9800 ms, so its
    density is an upper bound and its laser exposure a lower bound.
    """
    out = {}
    for ch in spectra.CHANNELS:
        rho = pb.implied_density(ch, pb.SEED_EXPOSURE_MS[ch], snr)
        laser = pb.SEED_LASERS[ch]
        b = pb.channel_budget(ch, rho, snr, laser)
        out[ch] = {
            "laser_nm": laser.wavelength_nm,
            "laser_mw": laser.power_mw,
            "product": laser.product,
            "power_mw": b.power_mw,
            "density_per_um2": rho,
            "excitation_per_s": b.excitation_per_s,
            "e_per_px_per_ms": b.e_per_px_per_ms,
            "exposure_ms": b.exposure_ms,
            "speedup": pb.SEED_EXPOSURE_MS[ch] / b.exposure_ms,
            "saturation_ms": b.saturation_ms,
            "bleach_tau_s": b.bleach_tau_s,
            "bleached_fraction": b.bleached_fraction(b.exposure_ms),
            "limit": _limit(b),
        }
    return out


def timing(lasers: dict[str, dict[str, Any]], model: field_time.TimingModel | None = None) -> dict[str, Any]:
    """Time per field and per slide, the unit against a sequential microscope, with the thesis's exposures, with the
    lasers' (``lasers``: :func:`laser_table`) and with the lasers' but without the NIR channel (the slowest)."""
    m = model or field_time.TimingModel()
    laser_ms = {ch: float(r["exposure_ms"]) for ch, r in lasers.items()}
    scenarios = {
        "thesis sources": dict(pb.SEED_EXPOSURE_MS),
        "lasers": laser_ms,
        "lasers, no NIR": {ch: t for ch, t in laser_ms.items() if ch != "nir"},
    }
    return {
        "fields": m.fields,
        "raster": [m.columns, m.rows],
        "exposures_ms": scenarios,
        "scenarios": field_time.comparison(m, scenarios),
        "model": asdict(m),
        "sources": field_time.TERM_SOURCES,
    }


def report(snr: float = DEFAULT_SNR, model: field_time.TimingModel | None = None) -> dict[str, Any]:
    """All three tables (JSON-ready)."""
    lasers = laser_table(snr)
    return {
        "snr": snr,
        "pixel_area_um2": pb.pixel_area_um2(),
        "collection": pb.collection_fraction(0.45),
        "camera": {"full_well_e": pb.CAMERA.full_well_e, "dark_noise_e": pb.CAMERA.dark_noise_e},
        "fluorophores": {name: asdict(d) for name, d in pb.FLUOROPHORE_DATA.items()},
        "seed": seed_table(snr),
        "lasers": lasers,
        "timing": timing(lasers, model),
    }


# -- the printed tables -----------------------------------------------------------------------------------------------
def _seed_lines(rows: dict[str, dict[str, Any]], snr: float) -> list[str]:
    rho = rows["blue"]["density_per_um2"]
    lines = [
        f"photon budget, thesis sources (Table 4.1); one labelling density for all four stains: {rho:.4g} molecules/µm²"
        f" (what the blue channel's 80 ms implies at SNR {snr:g}; {pb.micromolar(rho, NUCLEUS_UM):.2g} µM through a "
        f"{NUCLEUS_UM:g} µm nucleus)",
        "channel  stain          P_obj (mW)  exc/s/molec  e-/photon  e-/px/ms   t(SNR) ms  thesis ms  ratio    "
        "implied density /µm²  (x blue)",
    ]
    for ch, r in rows.items():
        lines.append(
            f"{ch:7s}  {r['stain']:13s}  {r['power_mw']:9.3g}  {r['excitation_per_s']:11.4g}  "
            f"{r['detection_e_per_photon']:9.3g}  {r['e_per_px_per_ms']:9.3g}  {r['predicted_ms']:9.4g}  "
            f"{r['seed_ms']:9.4g}  {r['ratio']:7.3g}  {r['implied_density_per_um2']:20.4g}  {r['density_ratio']:8.3g}"
        )
    return lines


def _laser_lines(rows: dict[str, dict[str, Any]], snr: float) -> list[str]:
    lines = [
        f"lasers of §5.2.3 on the thesis's sample (each stain at the density its thesis exposure implies), SNR {snr:g}",
        "channel  laser            P_obj (mW)  exc/s/molec  e-/px/ms   t(SNR) ms  speed-up  tau_bleach  bleached  "
        "first limit",
    ]
    for ch, r in rows.items():
        none = r["bleached_fraction"] is None
        bleached = "-" if none else f"{100 * r['bleached_fraction']:.2g} %"
        tau = "-" if none else f"{r['bleach_tau_s']:.3g} s"
        lines.append(
            f"{ch:7s}  {r['laser_nm']:3.0f} nm {r['laser_mw']:6.0f} mW  {r['power_mw']:9.4g}  "
            f"{r['excitation_per_s']:11.4g}  {r['e_per_px_per_ms']:9.3g}  {r['exposure_ms']:9.3g}  "
            f"{r['speedup']:8.3g}  {tau:>10s}  {bleached:>8s}  {r['limit']}"
        )
    return lines


#: The timing table's columns: (key in field_time.comparison, header).
_TIMING_COLUMNS = (("cmu", "CMU"), ("sequential_map", "seq.+map"), ("sequential", "seq."))
#: The timing table's rows and the sources (keys of field_time.TERM_SOURCES) of each.
_TIMING_ROWS = {
    "move": "field, x, y",
    "focus": "piezo (CMU, seq.+map); autofocus (seq.)",
    "exposure": "exposure",
    "filters_readout": "filter, readout",
    "total": "",
}


def _timing_lines(t: dict[str, Any]) -> list[str]:
    names = list(t["scenarios"])
    width = 10 * len(_TIMING_COLUMNS)
    lines = [
        f"time per field (s) and per slide ({t['fields']} fields, {t['raster'][0]} x {t['raster'][1]}): "
        "the unit (CMU) against a sequential microscope with Part I's focus map (seq.+map) and with a focus search",
        f"{'':16s}" + "".join(f"{n:>{width}s}" for n in names),
        f"{'term':16s}" + "".join(f"{h:>10s}" for _ in names for _, h in _TIMING_COLUMNS) + "   sources",
    ]
    for term, src in _TIMING_ROWS.items():
        cells = "".join(f"{t['scenarios'][n][k + '_s'][term]:10.3f}" for n in names for k, _ in _TIMING_COLUMNS)
        lines.append(f"{term:16s}{cells}" + (f"   {src}" if src else ""))
    cells = "".join(f"{t['scenarios'][n][k + '_slide_h']:10.2f}" for n in names for k, _ in _TIMING_COLUMNS)
    lines.append(f"{'slide (h)':16s}{cells}")
    cells = "".join(
        f"{'':10s}{t['scenarios'][n]['speedup_map']:10.2f}{t['scenarios'][n]['speedup']:10.2f}" for n in names
    )
    lines.append(f"{'seq. / CMU':16s}{cells}")
    lines += [f"  {k}: {v}" for k, v in t["sources"].items()]
    return lines


def format_report(result: dict[str, Any]) -> list[str]:
    """The printed form of :func:`report`: the three tables and the timing terms' sources."""
    snr = result["snr"]
    return [
        *_seed_lines(result["seed"], snr),
        "",
        *_laser_lines(result["lasers"], snr),
        "",
        *_timing_lines(result["timing"]),
    ]


# -- the plot ---------------------------------------------------------------------------------------------------------
def _plot_exposures(ax: Any, result: dict[str, Any]) -> None:
    chans = list(spectra.CHANNELS)
    x = np.arange(len(chans))
    seed_ms = [result["seed"][c]["seed_ms"] for c in chans]
    ax.bar(x, seed_ms, 0.6, color="0.8", label="the thesis (§5.2.3)")
    ax.plot(x, [result["seed"][c]["predicted_ms"] for c in chans], "o", color="C0", label="budget, one density")
    ax.plot(
        x,
        [result["lasers"][c]["exposure_ms"] for c in chans],
        "s",
        color="C3",
        label="budget, lasers (the thesis's sample)",
    )
    ax.axhline(pb.MAX_EXPOSURE_MS, color="k", lw=0.8, ls="--", label="the camera's longest exposure")
    ax.set_yscale("log")
    ax.set_xticks(x, [f"{c}\n{result['seed'][c]['stain']}" for c in chans])
    ax.set_ylabel(f"exposure for SNR {result['snr']:g} (ms)")
    ax.set_title("exposure per channel")
    ax.legend(fontsize=7)


def _plot_field_times(ax: Any, result: dict[str, Any]) -> None:
    scen = result["timing"]["scenarios"]
    labels, stacks = [], []
    for name, row in scen.items():
        for key, head in _TIMING_COLUMNS:
            labels.append(f"{name}\n{head}")
            stacks.append(row[f"{key}_s"])
    x = np.arange(len(labels))
    bottom = np.zeros(len(labels))
    for term in ("move", "focus", "exposure", "filters_readout"):
        vals = np.array([s[term] for s in stacks])
        ax.bar(x, vals, 0.7, bottom=bottom, label=term)
        bottom += vals
    for xi, total in zip(x, bottom, strict=True):
        ax.text(xi, total, f"{total:.2f}", ha="center", va="bottom", fontsize=6)
    ax.set_xticks(x, labels, fontsize=6)
    ax.set_ylabel("time per field (s)")
    ax.set_title(f"time per field ({result['timing']['fields']} fields a slide)")
    ax.legend(fontsize=7)


def write_plot(result: dict[str, Any], path: Path) -> Path:
    """A PNG of :func:`report`: exposures per channel (thesis, budget, lasers) and the time per field by term."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(13, 4.8), gridspec_kw={"width_ratios": [1, 1.6]})
    _plot_exposures(axes[0], result)
    _plot_field_times(axes[1], result)
    fig.tight_layout()
    from scopetwin.scenes.io import atomic_path

    with atomic_path(path) as tmp:  # written beside it and renamed: never through a link at ``path``
        fig.savefig(tmp, format="png", dpi=120)
    plt.close(fig)
    return path


# -- cell images at the budget's photon counts ------------------------------------------------------------------------
def window_texture_mean(setup: Any, side_px: int, magnification: float) -> float:
    """Mean of the dummy cells' texture (nuclei 1, cytoplasm 0.4) over the object square a centred window of
    ``side_px`` pixels sees at ``magnification``: the budget's density times this is the window's mean density."""
    from scopetwin.scenes.cmu.targets import dummy_cells

    tex, x0, y0 = dummy_cells(setup.cells, setup.field_mm)
    texel = 0.5e-3  # mm, the renderer's lookup step (scenes.mitsuba.cmu)
    half = 0.5 * side_px * setup.camera.pixel_um * 1e-3 / magnification
    xs = x0 + (np.arange(tex.shape[1]) + 0.5) * texel
    ys = y0 + (np.arange(tex.shape[0]) + 0.5) * texel
    inside = np.ix_(np.abs(ys) < half, np.abs(xs) < half)
    return float(tex[inside].mean())


def _densities(density: float | str | None, snr: float) -> dict[str, float]:
    """Per channel density: one value for all; ``"implied"``: each channel's thesis exposure's; None: the blue one's."""
    if density == "implied":
        return {ch: pb.implied_density(ch, pb.SEED_EXPOSURE_MS[ch], snr) for ch in spectra.CHANNELS}
    rho = pb.implied_density("blue", pb.SEED_EXPOSURE_MS["blue"], snr) if density is None else float(density)
    return dict.fromkeys(spectra.CHANNELS, rho)


def _write_previews(path: Path, dn: np.ndarray, max_dn: int) -> dict[str, str]:
    """Two PNGs of a DN image: auto-contrast (shows structure and noise) and linear over the ADC's range (shows how
    dark it is)."""
    import cv2

    from scopetwin.scenes.io import atomic_path
    from scopetwin.sim.measurement import write_preview

    auto = path.with_suffix(".png")
    write_preview(auto, dn)
    full = path.with_name(path.stem + "_fullscale.png")
    data = cv2.imencode(".png", np.clip(255.0 * dn / max_dn, 0, 255).astype(np.uint8))[1]
    with atomic_path(full) as tmp:  # written beside it and renamed: never through a link at ``full``
        tmp.write_bytes(data.tobytes())
    return {"preview": str(auto), "fullscale": str(full)}


def _centre_window(setup: Any, side_px: int) -> tuple[int, int, int, int]:
    """(row0, col0, height, width) of a square of ``side_px`` at the sensor's centre."""
    cam = setup.camera
    side = min(side_px, cam.width_px, cam.height_px)
    return (cam.height_px - side) // 2, (cam.width_px - side) // 2, side, side


def electrons_per_unit_ms(setup: Any, channel: str, budget: pb.ChannelBudget, image_distance_mm: float) -> float:
    """Photoelectrons per ms per unit of a rendered cell image (:func:`scopetwin.scenes.mitsuba.cmu.render_channel`):
    a texel of value 1 then gives the budget's ``e_per_px_per_ms`` on the axis.

    The renderer draws each channel's wavelengths from its :data:`~scopetwin.scenes.cmu.spectra.CHANNEL_FLUOROPHORE`
    (DAPI in the blue channel) and the budget counts the stain of §5.2.3 (Hoechst 33258): the scale divides by the
    renderer's own unit response, so the image's mean is the budget's count whatever the spectrum it was drawn from.
    """
    from scopetwin.scenes.mitsuba.cmu import unit_texel_irradiance

    return budget.e_per_px_per_ms / unit_texel_irradiance(setup, channel, image_distance_mm)


def render_channel_electrons(
    setup: Any,
    channel: str,
    budget: pb.ChannelBudget,
    exposure_ms: float,
    spp: int = 16,
    window_px: int = DEFAULT_WINDOW_PX,
    seed: int = 0,
    scene: Any = None,
) -> dict[str, Any]:
    """Render the dummy cells through ``channel`` at its refocused image distance and expose them on the camera.

    The image is scaled by :func:`electrons_per_unit_ms` (the nuclei, texel 1, carry the budget's density) and captured
    with the EMVA 1288 camera (:data:`~scopetwin.scenes.cmu.photon_budget.CAMERA`: shot noise, dark noise, full well,
    12-bit ADC). Returns the DN image (``dn``), the mean photoelectrons the budget predicts for the window
    (``predicted_mean_e``: rate x exposure x the texture's mean) and the ones measured from the DN
    (``measured_mean_e``), the nuclei's electrons and SNR, the fraction of saturated pixels.
    """
    from scopetwin.scenes.cmu.analysis import analyse, channel_optics
    from scopetwin.scenes.mitsuba.cmu import CameraPose, render_channel

    res = analyse(setup, channel_optics(setup, channel, {}))
    win = _centre_window(setup, window_px)
    img = render_channel(
        setup, channel, CameraPose(res.image_distance_mm), "cells", spp=spp, window=win, seed=seed, scene=scene
    )
    scale = electrons_per_unit_ms(setup, channel, budget, res.image_distance_mm)
    cam = pb.CAMERA
    dn = cam.capture(img, photons_per_unit_s=scale * 1e3, exposure_s=exposure_ms * 1e-3, rng=seed)
    nucleus_e = budget.electrons(exposure_ms)
    return {
        "dn": dn,
        "exposure_ms": exposure_ms,
        "density_per_um2": budget.molecules_per_px / pb.pixel_area_um2(),
        "e_per_px_per_ms": budget.e_per_px_per_ms,
        "nucleus_e": nucleus_e,
        "nucleus_snr": float(pb.snr_of(min(nucleus_e, cam.full_well_e), cam.dark_noise_e)),
        "nucleus_adc_fraction": min(nucleus_e, cam.full_well_e) * cam.gain_dn_per_e / cam.max_dn,
        "predicted_mean_e": nucleus_e * window_texture_mean(setup, win[3], res.magnification),
        "measured_mean_e": float((dn.mean() - cam.black_level_dn) / cam.gain_dn_per_e),
        "saturated_fraction": float(np.mean(dn >= cam.black_level_dn + cam.gain_dn_per_e * cam.full_well_e - 0.5)),
        "window": list(win),
        "spp": spp,
    }


def render_cells(
    setup: Any,
    out: Path,
    snr: float = DEFAULT_SNR,
    exposures_ms: dict[str, float] | None = None,
    density: float | str | None = None,
    spp: int = 16,
    window_px: int = DEFAULT_WINDOW_PX,
    seed: int = 0,
) -> dict[str, dict[str, Any]]:
    """The dummy cells through each channel at the budget's photon counts: ``cells_<channel>.exr`` (DN) with PNGs.

    ``exposures_ms`` defaults to the thesis's (§5.2.3); ``density`` (molecules/µm^2 of the nuclei) to the one the
    blue channel's 80 ms implies at ``snr`` (one for all), ``"implied"`` for each channel's own. Returns per channel
    :func:`render_channel_electrons`'s numbers (without the image) and the files written.
    """
    from scopetwin.scenes.io import write_image
    from scopetwin.scenes.mitsuba.cmu import unit_scene
    from scopetwin.sim.measurement import _refuse_link

    _refuse_link(Path(out))  # a folder of its own: a link to another folder is not written through
    exposures = exposures_ms or dict(pb.SEED_EXPOSURE_MS)
    rho = _densities(density, snr)
    scene = unit_scene(setup, {})
    out.mkdir(parents=True, exist_ok=True)
    result = {}
    for i, ch in enumerate(setup.channels):
        b = pb.channel_budget(ch, rho[ch], snr)
        r = render_channel_electrons(setup, ch, b, exposures[ch], spp, window_px, seed + i, scene)
        dn = r.pop("dn")
        path = out / f"cells_{ch}.exr"
        prov = {"section": "§5.2.3", "channel": ch, "spp": spp, "exposure_ms": exposures[ch], "units": "DN"}
        write_image(path, dn, setup.to_json(), prov)
        result[ch] = r | {"files": {"exr": str(path), **_write_previews(path, dn, pb.CAMERA.max_dn)}}
    return result


def render_lines(rows: dict[str, dict[str, Any]]) -> list[str]:
    """The printed summary of :func:`render_cells`."""
    lines = [
        "cell images at the budget's photon counts (window at the sensor's centre; nuclei at the stated density)",
        "channel  exposure ms  density /µm²  nuclei e-  nuclei SNR  nuclei % of ADC  window mean e- (budget / image)",
    ]
    for ch, r in rows.items():
        lines.append(
            f"{ch:7s}  {r['exposure_ms']:11.5g}  {r['density_per_um2']:12.4g}  {r['nucleus_e']:9.4g}  "
            f"{r['nucleus_snr']:10.3g}  {100 * r['nucleus_adc_fraction']:15.3g}  "
            f"{r['predicted_mean_e']:.4g} / {r['measured_mean_e']:.4g}"
        )
    return lines
