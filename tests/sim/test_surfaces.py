"""The §1.9 surface generator and the analytic test surfaces keep the a-priori conditions."""

import numpy as np
import pytest

from scopetwin.scenes.setup import SubstrateSpec, SurfaceSpec
from scopetwin.sim.surfaces import lowpass_noise, make_surface


def _frame_maxima(hm):
    """Maxima over both frame regions: the nodes with |y| >= 24 and the interpolated inner edges y = -+24."""
    y = hm.y_nodes[:, None] * np.ones((1, hm.z.shape[1]))
    e1 = hm.height(hm.x_nodes, np.full(len(hm.x_nodes), -24.0))
    e2 = hm.height(hm.x_nodes, np.full(len(hm.x_nodes), 24.0))
    return max(hm.z[y <= -24.0].max(), e1.max()), max(hm.z[y >= 24.0].max(), e2.max())


def test_frame_maxima_include_the_regions_inner_edges():
    """The frame regions start at |y| = 24 mm, between nodes: a surface rising toward the ROI peaks on that edge."""
    sub = SubstrateSpec(surface=SurfaceSpec(seed=2))
    hm = make_surface(sub.surface, sub)
    edge = hm.height(hm.x_nodes, np.full(len(hm.x_nodes), 24.0)).max()
    assert abs(edge) < 1e-12  # seed 2 has its region-2 maximum on the edge (0.05 µm above the nodes' before)
    assert hm.z[hm.y_nodes >= 24.0].max() < -1e-6


@pytest.mark.parametrize("kind", ["random", "sphere", "cylinder", "saddle"])
def test_frame_maxima_are_zero_and_range_is_exact(kind):
    sub = SubstrateSpec(surface=SurfaceSpec(kind=kind, range_um=40.0, seed=3, grid=(64, 128)))
    hm = make_surface(sub.surface, sub)
    m1, m2 = _frame_maxima(hm)
    assert abs(m1) < 1e-12 and abs(m2) < 1e-12
    assert np.ptp(hm.z) == pytest.approx(0.040, rel=1e-12)
    assert (hm.x_min, hm.x_max, hm.y_min, hm.y_max) == (-12.6, 12.6, -28.5, 28.5)


def test_random_surface_is_seeded_and_smooth():
    sub = SubstrateSpec()
    a = make_surface(SurfaceSpec(seed=5, grid=(64, 128)), sub)
    b = make_surface(SurfaceSpec(seed=5, grid=(64, 128)), sub)
    c = make_surface(SurfaceSpec(seed=6, grid=(64, 128)), sub)
    assert a.z.tobytes() == b.z.tobytes() and not np.array_equal(a.z, c.z)
    # low-pass: neighbouring nodes differ by a small fraction of the range
    assert np.abs(np.diff(a.z, axis=0)).max() < 0.02 * np.ptp(a.z) * 10


def test_lowpass_filter_sets_the_correlation_length():
    short = lowpass_noise((256, 256), (0.1, 0.1), 0.5, seed=1)
    long = lowpass_noise((256, 256), (0.1, 0.1), 3.0, seed=1)

    def corr_at(z, lag):
        z = z - z.mean()
        return float((z[:, :-lag] * z[:, lag:]).mean() / z.var())

    # Gaussian smoothing with sigma s gives a Gaussian autocorrelation exp(-lag^2 / (4 s^2))
    assert corr_at(short, 10) == pytest.approx(np.exp(-1.0 / (4 * 0.25)), abs=0.1)
    assert corr_at(long, 10) == pytest.approx(np.exp(-1.0 / (4 * 9.0)), abs=0.05)


def test_plane_is_flat():
    sub = SubstrateSpec(surface=SurfaceSpec(kind="plane"))
    assert np.all(make_surface(sub.surface, sub).z == 0)


def _radial_periodogram(z, d):
    """Radially averaged periodogram of a square field (Hann window), frequencies 1/mm."""
    n = z.shape[0]
    w = np.outer(np.hanning(n), np.hanning(n))
    p = np.abs(np.fft.fft2((z - z.mean()) * w)) ** 2
    f = np.hypot(*np.meshgrid(np.fft.fftfreq(n, d), np.fft.fftfreq(n, d)))
    edges = np.linspace(0, 0.5 / d, 60)
    k = np.digitize(f.ravel(), edges)
    fc = np.array([f.ravel()[k == i].mean() for i in range(2, 50)])
    pc = np.array([p.ravel()[k == i].mean() for i in range(2, 50)])
    return fc, pc


@pytest.mark.parametrize(("b", "c"), [(2.0, 3.0), (5.0, 4.0)])
def test_psd_noise_matches_the_requested_abc_spectrum(b, c):
    from scipy.optimize import curve_fit

    from scopetwin.sim.surfaces import abc_psd, psd_noise

    d = 0.1
    z = psd_noise((512, 512), (d, d), lambda f: abc_psd(f, b, c), seed=2)
    fc, pc = _radial_periodogram(z, d)

    def model(f, log_a, bb, cc):
        return log_a - 0.5 * cc * np.log1p((bb * f) ** 2)

    (_, b_fit, c_fit), _ = curve_fit(model, fc, np.log(pc), p0=(np.log(pc[0]), 1.0, 2.0))
    assert b_fit == pytest.approx(b, rel=0.15) and c_fit == pytest.approx(c, rel=0.1)


def test_broadband_noise_has_its_band_and_rms():
    from scopetwin.sim.surfaces import broadband_noise

    d = 0.1
    z = broadband_noise((512, 512), (d, d), 3e-6, (0.5, 4.0), seed=4)
    assert np.sqrt(np.mean(z**2)) == pytest.approx(3e-6, rel=1e-12)
    fc, pc = _radial_periodogram(z, d)
    inside = (fc > 1 / 4.0 + 0.05) & (fc < 1 / 0.5 - 0.1)
    outside = fc > 1 / 0.5 + 0.2
    assert pc[outside].max() < 0.02 * np.median(pc[inside])
    assert np.ptp(np.log(pc[inside])) < np.log(4.0)  # flat within the band (periodogram scatter)


@pytest.mark.parametrize("spectrum", ["abc", "power"])
def test_psd_surface_is_levelled_scaled_and_seeded(spectrum):
    spec = SurfaceSpec(kind="psd", spectrum=spectrum, range_um=30.0, correlation_length=10.0, seed=7, grid=(64, 128))
    sub = SubstrateSpec(surface=spec)
    a = make_surface(spec, sub)
    b = make_surface(spec, sub)
    c = make_surface(spec.model_copy(update={"seed": 8}), sub)
    assert a.z.tobytes() == b.z.tobytes() and not np.array_equal(a.z, c.z)
    m1, m2 = _frame_maxima(a)
    assert abs(m1) < 1e-12 and abs(m2) < 1e-12
    assert np.ptp(a.z) == pytest.approx(0.030, rel=1e-12)


def test_broadband_part_on_the_random_family_keeps_range_and_rms():
    plain = SurfaceSpec(seed=3, grid=(128, 256))
    rough = plain.model_copy(update={"broadband_rms_nm": 2.0})
    sub = SubstrateSpec()
    a, b = make_surface(plain, sub), make_surface(rough, sub)
    assert np.ptp(b.z) == pytest.approx(0.040, rel=1e-12)
    diff = b.z - a.z
    # the difference is the broadband part plus a tiny re-levelling tilt and rescale
    resid = diff - np.polyval(np.polyfit(b.y_nodes, diff.mean(axis=1), 1), b.y_nodes)[:, None]
    assert np.sqrt(np.mean(resid**2)) * 1e6 == pytest.approx(2.0, rel=0.1)


def test_surface_spec_rejects_bad_broadband_band():
    from pydantic import ValidationError

    with pytest.raises(ValidationError, match="broadband_min_wavelength_mm"):
        SurfaceSpec(kind="psd", broadband_min_wavelength_mm=5.0, broadband_wavelength_mm=4.0)
    with pytest.raises(ValidationError, match="broadband_rms_nm needs"):
        SurfaceSpec(kind="sphere", broadband_rms_nm=1.0)


def test_edge_rolloff_drops_the_edges_by_its_depth_with_its_slope():
    """A cut sheet's edge roll-off: ``depth`` at each edge, 3 x depth / width slope there, nothing inside."""
    from scopetwin.sim.surfaces import edge_rolloff

    x, y = np.meshgrid(np.linspace(-12.6, 12.6, 2521), np.linspace(-28.5, 28.5, 11))
    r = edge_rolloff(x, y, 0.01, 4.0)
    mid = 5  # y = 0: only the bands along x
    assert r[mid, 0] == pytest.approx(0.01) and r[mid, -1] == pytest.approx(0.01)
    assert r[mid, 1260] == 0.0 and r[mid, 400] == 0.0
    slope = (r[mid, 0] - r[mid, 1]) / (x[mid, 1] - x[mid, 0])
    assert slope == pytest.approx(3 * 0.01 / 4.0, rel=5e-3)  # one-sided difference of a cubic
    assert r[0, 0] == pytest.approx(0.02)  # a corner rolls off twice


def test_local_feature_has_its_depth_and_width():
    from scopetwin.scenes.setup import FeatureSpec
    from scopetwin.sim.surfaces import local_features

    x, y = np.meshgrid(np.linspace(-6, 6, 1201), np.array([1.0]))
    z = local_features(x, y, [FeatureSpec(x=0.0, y=1.0, width_mm=3.0, height_um=-2.0)])[0]
    assert z.min() == pytest.approx(-0.002)
    half = x[0][z <= -0.001]
    assert half.max() - half.min() == pytest.approx(3.0, abs=0.02)


def test_cut_sheet_surface_has_its_features_after_levelling():
    """Roll-off and features ride on the waviness; the frame maxima are zero again afterwards."""
    from scopetwin.sim.families import dimple_spec

    sub = SubstrateSpec()
    base = dimple_spec(depth_um=0.0)
    base.pop("features")
    plain = make_surface(SurfaceSpec(**base, grid=(128, 256)), sub)
    dimpled = make_surface(SurfaceSpec(**dimple_spec(), grid=(128, 256)), sub)
    d = dimpled.z - plain.z
    m1, m2 = _frame_maxima(dimpled)
    assert abs(m1) < 1e-12 and abs(m2) < 1e-12
    at = dimpled.height(np.array([2.0]), np.array([5.0])) - plain.height(np.array([2.0]), np.array([5.0]))
    far = np.median(d)
    assert float(at[0] - far) == pytest.approx(-0.002, abs=5e-5)
    with pytest.raises(ValueError, match="edge_rolloff_um needs surface kind"):
        SurfaceSpec(kind="sphere", edge_rolloff_um=5.0)


@pytest.mark.parametrize("family", ["gauss", "glass", "cut", "steep", "features"])
def test_families_are_fixed_by_their_seed_and_valid(family):
    from scopetwin.sim.families import family_spec

    a, b = family_spec(family, 11), family_spec(family, 11)
    assert a == b and a != family_spec(family, 12)
    spec = SurfaceSpec(**a, grid=(64, 128))
    hm = make_surface(spec, SubstrateSpec(surface=spec))
    assert np.isfinite(hm.z).all()
    with pytest.raises(ValueError, match="unknown surface family"):
        family_spec("bogus", 1)
