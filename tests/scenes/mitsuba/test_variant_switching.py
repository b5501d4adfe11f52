"""One thread, three renderers, two variants: each renderer must reselect its own variant.

The four-channel unit renders in ``llvm_ad_spectral``, the Part I scenes and the GRIN objectives in
``llvm_ad_mono``. Interleaving them in one process (as a test session or a dataset worker does) must
give each the same image as when it runs alone.
"""

from __future__ import annotations

import numpy as np
import pytest

from scenes.setup import load_setup

pytestmark = pytest.mark.mitsuba


def test_renderers_reselect_their_variant_when_interleaved():
    from scenes.cmu.layout import load_cmu_setup
    from scenes.grin.setup import load_grin_setup
    from scenes.grin.targets import target
    from scenes.mitsuba import cmu, grin
    from scenes.mitsuba.render import render_setup

    part1 = load_setup("thesis-2.8.1-perpendicular", {"camera": {"pixels": [68, 51], "pixel_pitch": 0.093}})
    unit = load_cmu_setup("thesis-cmu")
    rod = load_grin_setup("thesis-8.3.2-grin-realized", {"camera": {"pixel_um": 10.0}})
    stack = rod.stack(image_distance=11.4)

    def star():
        return cmu.render_channel(
            unit, "nir", cmu.CameraPose(164.5), "star", spp=2, window=(480, 656, 48, 48), flat=True
        )

    def rods():
        return grin.render_image(rod, stack, target("grid-25"), spp=2, width=32, height=32, center=rod.array.axes()[0])

    first = [render_setup(part1, spp=4, seed=0), star(), rods()]
    again = [rods(), star(), render_setup(part1, spp=4, seed=0)][::-1]
    for a, b in zip(first, again, strict=True):
        assert a.shape == b.shape
        np.testing.assert_array_equal(a, b)
