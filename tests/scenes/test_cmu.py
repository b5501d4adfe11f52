"""Truth tests of the microscope unit's numpy models (thesis ch. 3-5): spectra, layout, plates, tracer, analyses."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.scenes.cmu import spectra
from scopetwin.scenes.cmu.analysis import (
    analyse,
    best_focus,
    channel_optics,
    image_rays,
    perpendicular_optics,
    wavefront_psf,
)
from scopetwin.scenes.cmu.layout import load_cmu_setup
from scopetwin.scenes.cmu.plates import bow_radius, fused_silica_index, plate_heightmap
from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.spots import pupil_disk
from scopetwin.scenes.surface import HeightMap


@pytest.fixture(scope="module")
def setup():
    return load_cmu_setup("thesis-cmu")


# -- spectra ---------------------------------------------------------------------------------------------
def test_channel_bands_match_table_3_1() -> None:
    """Emission bands (50 % of path x QE) lie within 3 nm of Table 3.1's; excitation peaks inside its bands."""
    for ch in spectra.CHANNELS:
        lo, hi = spectra.band_limits(spectra.detection_response(ch))
        c, hw = spectra.TABLE_3_1[ch]["emission"]
        assert lo == pytest.approx(c - hw, abs=3.0) and hi == pytest.approx(c + hw, abs=3.0)
        ex = spectra.excitation_at_object(ch)
        c, hw = spectra.TABLE_3_1[ch]["excitation"]
        peak = spectra.GRID_NM[np.argmax(ex)]
        assert c - hw <= peak <= c + hw


def test_object_plane_power_is_table_4_1() -> None:
    for ch, p in spectra.TABLE_4_1_MW.items():
        assert np.trapezoid(spectra.excitation_at_object(ch), spectra.GRID_NM) == pytest.approx(p, rel=1e-9)


def test_fluorophore_peaks_and_band_shape() -> None:
    for f in spectra.FLUOROPHORES.values():
        assert spectra.GRID_NM[np.argmax(f.excitation())] == pytest.approx(f.excitation_nm, abs=0.5)
        em = f.emission()
        assert spectra.GRID_NM[np.argmax(em)] == pytest.approx(f.emission_nm, abs=0.5)
        assert np.trapezoid(em, spectra.GRID_NM) == pytest.approx(1.0, rel=1e-6)
    # zero skew is a Gaussian of the given FWHM in wavenumber
    wl = np.array([500.0])
    nu_half = 1 / 500.0 + 0.5 * 20.0 / 500.0**2
    assert spectra.fraser_suzuki(1 / np.array([nu_half]), 500.0, 20.0, 0.0) == pytest.approx(0.5, rel=1e-9)
    assert spectra.fraser_suzuki(wl, 500.0, 20.0, 0.2) == pytest.approx(1.0)


def test_filters_and_dichroics() -> None:
    t = spectra.bandpass("HQ485/15X", np.array([485.0, 477.5, 492.5, 400.0]))
    assert t[0] == pytest.approx(0.9, rel=5e-3) and t[1] == pytest.approx(0.45, rel=0.02)
    assert t[2] == pytest.approx(0.45, rel=0.02) and t[3] == pytest.approx(1e-5)
    wl = np.array([500.0, 550.0, 600.0])
    assert spectra.dichroic("565DCXR", "T", wl)[0] < 1e-3 < spectra.dichroic("565DCXR", "T", wl)[2]
    assert spectra.dichroic("565DCXR", "R", wl)[0] > 0.97
    assert spectra.dichroic("565DCXR", "T", np.array([565.0]))[0] == pytest.approx(0.475)
    with pytest.raises(spectra.SpectrumError):
        spectra.bandpass("XYZ")
    with pytest.raises(spectra.SpectrumError):
        spectra.dichroic("565ABC", "T")


def test_excitation_crosstalk_matrix() -> None:
    x = spectra.excitation_crosstalk()
    assert x.shape == (4, 4)
    assert np.allclose(np.diag(x), 1.0)
    assert np.all(x >= 0) and np.all(x[~np.eye(4, dtype=bool)] < 0.05)


# -- layout and plates -----------------------------------------------------------------------------------
def test_preset_and_validation(setup) -> None:
    assert setup.kind == "cmu" and setup.field_mm == pytest.approx((0.89784, 0.6708))
    with pytest.raises(SetupError, match="long_axis"):
        load_cmu_setup("thesis-cmu", {"splitters": {"565DCXR": {"long_axis": [1.0, 0.0, -1.0]}}})
    with pytest.raises(SetupError, match="unknown element"):
        load_cmu_setup("thesis-cmu", {"channels": {"nir": {"path": ["999DCXR:T"]}}})
    with pytest.raises(SetupError):
        load_cmu_setup("thesis-2.8.1-angular")


def test_plate_bow_range_and_radius(setup) -> None:
    spec = setup.splitters["770DCXR"].model_copy(update={"residual_rms_um": 0.0})
    hm = plate_heightmap(spec, setup.plate)
    assert np.ptp(hm.z) * 1e3 == pytest.approx(10.2, rel=1e-3)
    r = bow_radius(10.2, 25.5, 36.0)
    hx, _ = hm.gradient(np.array([5.0]), np.array([0.0]))
    assert hx[0] == pytest.approx(5.0 / r, rel=1e-4)
    assert fused_silica_index(587.6) == pytest.approx(1.4585, abs=2e-4)


# -- tracer and analyses ---------------------------------------------------------------------------------
def test_perfect_lenses_image_exactly(setup) -> None:
    """Perfect mirror perpendicular: m = 10.00, zero spots, focus at f_tube (thesis §5.1.2, Fig. 5.2a)."""
    res = analyse(setup, perpendicular_optics(setup, None), n_pupil=21)
    assert res.magnification == pytest.approx(10.0, rel=1e-6)
    assert res.image_distance_mm == pytest.approx(164.5, abs=1e-6)
    assert max(res.rms_spot_um.values()) < 1e-6


def test_spherical_mirror_refocus_matches_thin_lens_formula(setup) -> None:
    """A spherical mirror (power 2/R) d in front of the tube lens: b and m from the two-lens formula."""
    r = 20000.0
    hm = HeightMap.from_function(lambda x, y: (x**2 + y**2) / (2 * r), -12.75, 12.75, -18, 18, 52, 73)
    opt = perpendicular_optics(setup, hm, distance=40.0)
    res = analyse(setup, opt, n_pupil=15)
    phi, f, d = 2 / r, 164.5, 40.0
    big_f = 1 / (phi + 1 / f - d * phi / f)
    bfd = big_f * (1 - d * phi)
    assert res.image_distance_mm == pytest.approx(bfd, abs=2e-3)
    assert res.magnification == pytest.approx(big_f / 16.45, rel=2e-4)


def test_45_degree_astigmatism_from_coddington(setup) -> None:
    """A sphere at 45°: tangential/sagittal focal powers 2/(R cos45), 2 cos45/R; focal difference ~ f^2 dphi."""
    s = setup.model_copy(
        update={"splitters": {k: v.model_copy(update={"residual_rms_um": 0.0}) for k, v in setup.splitters.items()}}
    )
    opt = channel_optics(s, "red")
    g = (np.arange(41) + 0.5) / 41 * 0.2 - 0.1  # paraxial fans
    z = np.zeros_like(g)
    bx = best_focus([image_rays(opt, 0.0, 0.0, g, z)])
    by = best_focus([image_rays(opt, 0.0, 0.0, z, g)])
    r = bow_radius(10.2, 25.5, 36.0)
    dphi = 2 / (r * np.cos(np.pi / 4)) - 2 * np.cos(np.pi / 4) / r
    assert abs(bx - by) == pytest.approx(164.5**2 * dphi, rel=0.03)


def test_channels_follow_tables_5_1_and_5_2(setup) -> None:
    """NIR (transmission only) stays at m = 10 and diffraction limited; the reflected channels shrink and blur."""
    nir = analyse(setup, channel_optics(setup, "nir"), n_pupil=15)
    assert nir.magnification == pytest.approx(10.0, rel=1e-3)
    assert nir.rms_spot_um["1.0"] < 1.0
    for ch in ("blue", "red"):
        r = analyse(setup, channel_optics(setup, ch), n_pupil=15)
        assert r.magnification < 9.95 and r.rms_spot_um["1.0"] > 10.0


def test_wavefront_psf_limits(setup) -> None:
    """Flat system: Strehl 1 and the Airy pattern's EE80 radius; a stop scales the PSF by the aperture ratio."""
    opt = channel_optics(setup, "nir", flat=True)
    p = wavefront_psf(opt, 0.0, 0.0, n=64, pad=4)
    assert p["strehl"] == pytest.approx(1.0, abs=1e-6)
    from scipy.optimize import brentq
    from scipy.special import j0, j1

    v80 = brentq(lambda v: 1 - j0(v) ** 2 - j1(v) ** 2 - 0.8, 1.0, 3.8)  # Airy encircled energy = 80 %
    ee80 = v80 * 785e-6 * (164.5 / 20.0) / np.pi * 1e3
    assert p["ee80_radius_um"] == pytest.approx(ee80, rel=0.1)
    defocused = wavefront_psf(opt, 0.0, 0.0, defocus=2.0, n=64, pad=4)
    assert defocused["strehl"] < 0.2


def test_pupil_disk_uniform() -> None:
    px, py = pupil_disk(40)
    assert np.all(px**2 + py**2 <= 1.0)
    assert np.mean(px**2 + py**2) == pytest.approx(0.5, rel=0.02)
