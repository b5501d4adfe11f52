"""The §1.9 surface generator and the analytic test surfaces keep the a-priori conditions."""

import numpy as np
import pytest

from scenes.setup import SubstrateSpec, SurfaceSpec
from sim.surfaces import lowpass_noise, make_surface


@pytest.mark.parametrize("kind", ["random", "sphere", "cylinder", "saddle"])
def test_frame_maxima_are_zero_and_range_is_exact(kind):
    sub = SubstrateSpec(surface=SurfaceSpec(kind=kind, range_um=40.0, seed=3, grid=(64, 128)))
    hm = make_surface(sub.surface, sub)
    y = hm.y_nodes[:, None] * np.ones((1, hm.z.shape[1]))
    r1 = hm.z[y <= -24.0]
    r2 = hm.z[y >= 24.0]
    assert abs(r1.max()) < 1e-15 and abs(r2.max()) < 1e-15
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
