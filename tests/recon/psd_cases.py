"""The six PSD surfaces with nm-level broadband content shared by the accuracy tests."""

from __future__ import annotations

from scopetwin.scenes.setup import Setup
from scopetwin.scenes.surface import HeightMap
from scopetwin.sim.surfaces import make_surface

#: (spectrum, B mm, C, range µm, broadband nm RMS, seed): K-correlation and power-law spectra with roll-off, not
#: the §1.9 generator the reconstruction's defaults were chosen on.
PSD_CASES = [
    ("abc", 12.0, 4.0, 40.0, 2.0, 11),
    ("abc", 16.0, 3.0, 30.0, 3.0, 12),
    ("abc", 9.0, 4.0, 25.0, 1.0, 13),
    ("power", 14.0, 3.0, 40.0, 2.0, 14),
    ("power", 18.0, 4.0, 50.0, 4.0, 15),
    ("power", 10.0, 3.0, 20.0, 1.5, 16),
]


def psd_surface(setup: Setup, case: tuple[str, float, float, float, float, int]) -> HeightMap:
    """The true height map of one case on the setup's substrate."""
    spectrum, b, c, range_um, bb, seed = case
    assert setup.substrate is not None
    spec = setup.substrate.surface.model_copy(
        update={
            "kind": "psd",
            "spectrum": spectrum,
            "correlation_length": b,
            "psd_exponent": c,
            "range_um": range_um,
            "broadband_rms_nm": bb,
            "seed": seed,
        }
    )
    return make_surface(spec, setup.substrate)
