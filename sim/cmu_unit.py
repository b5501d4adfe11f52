"""The compact microscope unit (CMU, the thesis's own name for the four-channel unit of ch. 3-5), analysed and rendered.

The analyses behind ``scopetwin optics cmu``, each returning JSON-ready dicts (the command prints them beside the
seed): the §5.1.2 Zemax checks (:func:`section_5_1_2`), per channel the refocused image distance, magnification
(Table 5.1), RMS spots, astigmatism and wavefront PSF (:func:`channel_table`), the excitation/emission crosstalk
(:func:`crosstalk`), and the Siemens star and dummy cells rendered through each channel (Mitsuba, spectral) and
measured with :mod:`scopetwin.calib.channels` (:func:`render_and_measure`, Tables 5.1-5.4).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

SEED_TABLE_5_1 = {"blue": 9.82, "green": 9.92, "red": 9.95, "nir": 10.0}
SEED_TABLE_5_2_UM = {"blue": 2.20, "green": 2.53, "red": 2.70, "nir": "< 1"}
SEED_TABLE_5_3_PX = {"blue": (-18, -225), "green": (35, -95), "red": (-138, -610)}
SEED_TABLE_5_4_DEG = {"blue": 0.13, "green": -0.01, "red": 0.07}
SEED_5_1_2 = {
    "mirror_magnification": 10.0,
    "bs3_perpendicular_magnification": 9.90,
    "bs3_45_rms_um": 43.499,
    "bs3_45_stop_rms_um": 8.826,
}


def section_5_1_2(setup: Any, maps: dict[str, Any]) -> dict[str, float]:
    """The §5.1.2 Zemax checks: perfect mirror and beam splitter 3 perpendicular; beam splitter 3 at 45° (the red
    channel: 770DCXR in reflection, flat mirror) without and with the 4 mm stop."""
    from scopetwin.scenes.cmu.analysis import analyse, channel_optics, perpendicular_optics
    from scopetwin.scenes.cmu.plates import plate_heightmap

    bs3 = maps.get("770DCXR") or plate_heightmap(setup.splitters["770DCXR"], setup.plate)
    mirror = analyse(setup, perpendicular_optics(setup, None))
    perp = analyse(setup, perpendicular_optics(setup, bs3))
    r45 = analyse(setup, channel_optics(setup, "red", maps))
    r45s = analyse(setup, channel_optics(setup, "red", maps, stop=True))
    return {
        "mirror_magnification": mirror.magnification,
        "mirror_rms_um": mirror.rms_spot_um["1.0"],
        "bs3_perpendicular_magnification": perp.magnification,
        "bs3_perpendicular_rms_um": perp.rms_spot_um["1.0"],
        "bs3_45_rms_um": r45.rms_spot_um["1.0"],
        "bs3_45_stop_rms_um": r45s.rms_spot_um["1.0"],
        "stop_transmitted_fraction": r45s.transmitted_fraction,
    }


def channel_table(setup: Any, maps: dict[str, Any], stop: bool) -> dict[str, dict[str, Any]]:
    """Per channel: refocus, magnification, spots, astigmatism, wavefront PSF (axis and corner)."""
    from scopetwin.scenes.cmu.analysis import airy_radius_um, analyse, channel_optics, field_points, wavefront_psf

    out = {}
    for ch in setup.channels:
        opt = channel_optics(setup, ch, maps, stop=stop)
        res = analyse(setup, opt)
        psf_axis = wavefront_psf(
            opt, 0.0, 0.0, defocus=res.image_distance_mm - opt.tube.f, object_magnification=res.magnification
        )
        corner = field_points(setup)["1.0"]
        psf_edge = wavefront_psf(
            opt, *corner, defocus=res.image_distance_mm - opt.tube.f, object_magnification=res.magnification
        )
        nyquist_um = setup.camera.pixel_um / res.magnification  # half period at the pixel Nyquist limit
        out[ch] = {
            "magnification": res.magnification,
            "magnification_xy": list(res.magnification_xy),
            "rms_spot_um": {
                "axis": res.rms_spot_um["0.0"],
                "0.7": res.rms_spot_um["0.7"],
                "edge": res.rms_spot_um["1.0"],
            },
            "delta_x_um": max(psf_axis["delta_x_um"], nyquist_um),
            "delta_x_optics_um": psf_axis["delta_x_um"],
            "image_distance_mm": res.image_distance_mm,
            "astigmatism_mm": res.astigmatism_mm,
            "strehl": {"axis": psf_axis["strehl"], "edge": psf_edge["strehl"]},
            "wavefront_rms_waves": {"axis": psf_axis["wavefront_rms_waves"], "edge": psf_edge["wavefront_rms_waves"]},
            "ee80_radius_um": {"axis": psf_axis["ee80_radius_um"], "edge": psf_edge["ee80_radius_um"]},
            "airy_um": airy_radius_um(opt),
            "wavelength_nm": opt.wavelength_nm,
        }
    return out


#: Provenance seed id written with every CMU render.
_RENDER_SEED_ID = "000_a2b7d38b4750eb48"


def _render_star(
    setup: Any, ch: str, pose: Any, out: Path, spp: int, stop: bool, scene: Any, report: Callable[[str], None]
) -> tuple[Path, Any]:
    """Render, write (``star_<ch>.exr``) and measure channel ``ch``'s Siemens star; the path and the measurement."""
    from scopetwin.calib.channels import measure_channel
    from scopetwin.scenes.io import write_image
    from scopetwin.scenes.mitsuba.cmu import render_channel

    t0 = time.perf_counter()
    img = render_channel(setup, ch, pose, "star", spp=spp, stop=stop, scene=scene)
    secs = time.perf_counter() - t0
    path = out / f"star_{ch}.exr"
    write_image(
        path,
        img,
        setup.to_json(),
        {"seed": _RENDER_SEED_ID, "section": "§5.2.2", "spp": spp, "channel": ch},
        image_distance_mm=float(pose.image_distance),
    )
    meas = measure_channel(
        img,
        setup.camera.pixel_um,
        setup.target.frame_side * 1e3,
        setup.target.star_radius * 1e3,
        setup.target.spokes,
    )
    report(f"rendered star, {ch}: {img.shape[1]}x{img.shape[0]} px, {spp} spp, {secs:.1f} s -> {path}")
    return path, meas


def _render_cells(setup: Any, ch: str, pose: Any, out: Path, spp: int, stop: bool, scene: Any) -> Path:
    """Render and write (``cells_<ch>.exr``) the dummy cells through channel ``ch``; the path."""
    from scopetwin.scenes.io import write_image
    from scopetwin.scenes.mitsuba.cmu import render_channel

    cimg = render_channel(setup, ch, pose, "cells", spp=spp, stop=stop, scene=scene)
    cpath = out / f"cells_{ch}.exr"
    write_image(
        cpath,
        cimg,
        setup.to_json(),
        {"seed": _RENDER_SEED_ID, "section": "§5.1.2", "spp": spp, "channel": ch},
    )
    return cpath


def _measured(meas: dict[str, Any], pixel_um: float) -> dict[str, dict[str, Any]]:
    """Per channel the star's measurement, plus offset and tilt relative to the NIR channel (Tables 5.3, 5.4)."""
    from scopetwin.calib.channels import relative_pose

    ref = meas.get("nir")
    result = {}
    for ch, m in meas.items():
        entry = {
            "magnification": m.magnification,
            "delta_x_um": m.delta_x_um,
            "r_min_um": m.r_min_um,
            "resolved_to_limit": m.resolved_to_limit,
            "frame_center_px": list(m.frame.center),
        }
        if ref is not None and ch != "nir":
            entry |= relative_pose(m, ref, pixel_um)
        result[ch] = entry
    return result


def render_and_measure(
    setup: Any,
    maps: dict[str, Any],
    table: dict[str, Any],
    out: Path,
    spp: int,
    stop: bool,
    cells: bool,
    report: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Render star (and cells) per channel at its refocused distance, write EXR, measure with calib.channels.

    Parameters
    ----------
    setup : CmuSetup
        The unit.
    maps : dict
        Height maps replacing the modelled surface of a splitter or mirror (by element name).
    table : dict
        :func:`channel_table` (its ``image_distance_mm`` places each camera).
    out : Path
        Folder of the EXR files (``star_<channel>.exr``, ``cells_<channel>.exr``).
    spp : int
        Samples per pixel.
    stop : bool
        The 4 mm aperture in front of every tube lens (thesis §5.1.2).
    cells : bool
        Also render the dummy cells.
    report : callable
        Gets one line per rendered star image.

    Returns
    -------
    dict
        ``{"measured": {channel: {magnification, delta_x_um, r_min_um, ...}}, "files": {name: path}}``; offset and
        tilt relative to the NIR channel (Tables 5.3, 5.4).
    """
    from scopetwin.scenes.mitsuba.cmu import CameraPose, unit_scene
    from scopetwin.sim.measurement import _refuse_link

    _refuse_link(Path(out))  # a folder of its own: a link to another folder is not written through
    scene = unit_scene(setup, maps)
    meas, files = {}, {}
    for ch in setup.channels:
        pose = CameraPose(table[ch]["image_distance_mm"])
        path, meas[ch] = _render_star(setup, ch, pose, out, spp, stop, scene, report)
        files[f"star_{ch}"] = str(path)
        if cells:
            files[f"cells_{ch}"] = str(_render_cells(setup, ch, pose, out, spp, stop, scene))
    return {"measured": _measured(meas, setup.camera.pixel_um), "files": files}


def crosstalk() -> dict[str, Any]:
    """The excitation and emission crosstalk of the four channels and the channel signal matrix (thesis Part II)."""
    from scopetwin.scenes.cmu import spectra

    return {
        "excitation_crosstalk": spectra.excitation_crosstalk().tolist(),
        "emission_crosstalk": spectra.emission_crosstalk().tolist(),
        "channel_signal_matrix": spectra.channel_signal_matrix().tolist(),
        "crosstalk_order": list(spectra.CHANNELS),
    }
