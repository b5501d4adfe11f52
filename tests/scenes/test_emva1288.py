"""EMVA 1288 sensor model: mean, variance (photon transfer), saturation, determinism."""

import numpy as np
import pytest

from scopetwin.scenes.emva1288 import EmvaSensor
from scopetwin.scenes.errors import GeometryError


def test_photon_transfer_mean_and_variance():
    s = EmvaSensor(
        quantum_efficiency=0.5, full_well_e=20000, dark_noise_e=8, gain_dn_per_e=0.2, black_level_dn=40, bit_depth=12
    )
    flat = np.full((400, 400), 0.5)
    img = s.capture(flat, photons_per_unit_s=2e4, exposure_s=1.0, rng=3)
    mu_e = 0.5 * 0.5 * 2e4  # 5000 e-
    assert img.mean() == pytest.approx(40 + 0.2 * mu_e, rel=2e-3)
    # variance of DN = K^2 (mu_e + sigma_d^2) + quantisation 1/12
    assert img.var() == pytest.approx(0.04 * (mu_e + 64) + 1 / 12, rel=0.03)


def test_saturation_and_determinism():
    s = EmvaSensor()
    img = s.capture(np.full((10, 10), 100.0), 1e6, 1.0, rng=1)
    assert img.max() <= s.max_dn
    assert np.allclose(img, s.black_level_dn + s.gain_dn_per_e * s.full_well_e, atol=6 * 0.23 * s.dark_noise_e)
    a = s.capture(np.full((5, 5), 0.3), 1e4, 0.5, rng=7)
    b = s.capture(np.full((5, 5), 0.3), 1e4, 0.5, rng=7)
    assert a.tobytes() == b.tobytes()


def test_exposure_for_fills_the_requested_fraction():
    s = EmvaSensor()
    t = s.exposure_for(0.8, 1e6, 0.7)
    assert s.quantum_efficiency * 0.8 * 1e6 * t == pytest.approx(0.7 * s.full_well_e)


def test_bad_sensor_input():
    with pytest.raises(GeometryError, match="quantum_efficiency"):
        EmvaSensor(quantum_efficiency=1.5)
    with pytest.raises(GeometryError, match="finite"):
        EmvaSensor().capture(np.array([[np.nan]]), 1.0, 1.0)
