"""Renderers without hidden state: explicit variants, no module-global tables, no order dependence.

The four-channel unit renders in ``llvm_ad_spectral``, the Part I scenes and the GRIN objectives in
``llvm_ad_mono`` (``cuda_*`` with a GPU). Importing a renderer sets no variant; each builder and renderer sets
its own for the call, so interleaving them in one process (a test session, a dataset worker) gives each the same
image as when it runs alone; and a CMU scene owns its plate tables, so building it again and again does not grow
the process.
"""

from __future__ import annotations

import contextlib
import gc
import io
import re
import tracemalloc

import numpy as np
import pytest

from scopetwin.scenes.setup import load_setup

pytestmark = pytest.mark.mitsuba

_UNITS = {"B": 1, "KiB": 2**10, "MiB": 2**20, "GiB": 2**30, "TiB": 2**40}


def _jit_storage_bytes() -> float:
    """Bytes held by live Dr.Jit variables (``dr.whos()``: "Storage : X on device")."""
    import drjit as dr

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        dr.whos()
    m = re.search(r"Storage\s*:\s*([\d.]+)\s*(\w+) on device", out.getvalue())
    assert m is not None, out.getvalue()[-500:]
    return float(m.group(1)) * _UNITS[m.group(2)]


def _small_part1():
    return load_setup("thesis-2.8.1-perpendicular", {"camera": {"pixels": [68, 51], "pixel_pitch": 0.093}})


def test_part1_render_is_the_same_after_the_other_renderers_ran(mono_variant, spectral_variant):
    """Part I, then every other renderer imported and run once, then Part I again: the same bytes, in mono."""
    import mitsuba as mi

    from scopetwin.scenes.mitsuba.render import render_setup

    part1 = _small_part1()
    before = render_setup(part1, spp=4, seed=3, variant=mono_variant)
    assert mi.variant() == mono_variant

    from scopetwin.scenes.cmu.layout import load_cmu_setup
    from scopetwin.scenes.grin.setup import load_grin_setup
    from scopetwin.scenes.grin.targets import target
    from scopetwin.scenes.mitsuba import cmu, grin, widefield

    assert widefield.render_tile is not None  # imported: it must not change anything either
    unit = load_cmu_setup("thesis-cmu")
    cmu.render_channel(unit, "nir", cmu.CameraPose(164.5), "star", spp=1, window=(480, 656, 16, 16), flat=True)
    assert mi.variant() == spectral_variant
    rod = load_grin_setup("thesis-8.3.2-grin-realized", {"camera": {"pixel_um": 10.0}})
    grin.render_image(rod, rod.stack(image_distance=11.4), target("grid-25"), spp=1, width=16, height=16)

    after = render_setup(part1, spp=4, seed=3)  # default variant: resolved now, not "whatever is current"
    assert mi.variant() == mono_variant
    if mono_variant.startswith("llvm"):
        assert mi.variant() == "llvm_ad_mono" or mono_variant != "llvm_ad_mono"
    assert after.dtype == before.dtype and after.shape == before.shape
    assert after.tobytes() == before.tobytes()


def test_renderers_reselect_their_variant_when_interleaved(mono_variant, spectral_variant):
    from scopetwin.scenes.cmu.layout import load_cmu_setup
    from scopetwin.scenes.grin.setup import load_grin_setup
    from scopetwin.scenes.grin.targets import target
    from scopetwin.scenes.mitsuba import cmu, grin
    from scopetwin.scenes.mitsuba.render import render_setup

    part1 = _small_part1()
    unit = load_cmu_setup("thesis-cmu")
    rod = load_grin_setup("thesis-8.3.2-grin-realized", {"camera": {"pixel_um": 10.0}})
    stack = rod.stack(image_distance=11.4)

    def star():
        return cmu.render_channel(
            unit,
            "nir",
            cmu.CameraPose(164.5),
            "star",
            spp=2,
            window=(480, 656, 48, 48),
            flat=True,
            variant=spectral_variant,
        )

    def rods():
        return grin.render_image(
            rod, stack, target("grid-25"), spp=2, width=32, height=32, center=rod.array.axes()[0], variant=mono_variant
        )

    first = [render_setup(part1, spp=4, seed=0, variant=mono_variant), star(), rods()]
    again = [rods(), star(), render_setup(part1, spp=4, seed=0, variant=mono_variant)][::-1]
    for a, b in zip(first, again, strict=True):
        assert a.shape == b.shape
        np.testing.assert_array_equal(a, b)


@pytest.mark.slow
def test_cmu_scene_builds_do_not_grow_memory(spectral_variant):
    """Build and render the CMU scene 20 times: Dr.Jit storage and Python allocations stay flat (< 5 MB).

    Each build used to add ~4.5 MB of plate tables to a module-global dict that was never freed. The tables now
    travel in the scene dictionary and belong to the plates' BSDFs. Measured after a warm-up build: the bytes of
    all live Dr.Jit variables (``dr.whos``: where the BSDFs' tables live) and the Python/numpy heap (tracemalloc).
    """
    import drjit as dr

    from scopetwin.scenes.cmu.layout import load_cmu_setup
    from scopetwin.scenes.cmu.plates import plate_heightmap
    from scopetwin.scenes.mitsuba import cmu

    setup = load_cmu_setup("thesis-cmu")
    maps = {name: plate_heightmap(spec, setup.plate) for name, spec in (setup.splitters | setup.mirrors).items()}
    pose = cmu.CameraPose(164.5)

    def build_and_render() -> float:
        scene = cmu.unit_scene(setup, maps, variant=spectral_variant)
        img = cmu.render_channel(
            setup, "green", pose, "star", spp=1, window=(512, 688, 8, 8), scene=scene, variant=spectral_variant
        )
        del scene
        return float(img.sum())

    build_and_render()  # warm-up: kernels compiled, caches filled
    gc.collect()
    dr.flush_malloc_cache()
    jit0 = _jit_storage_bytes()
    tracemalloc.start()
    try:
        heap0 = tracemalloc.get_traced_memory()[0]
        values = [build_and_render() for _ in range(20)]
        gc.collect()
        dr.flush_malloc_cache()
        heap_growth = tracemalloc.get_traced_memory()[0] - heap0
    finally:
        tracemalloc.stop()
    jit_growth = _jit_storage_bytes() - jit0
    assert len(set(values)) == 1  # the same image every time
    assert jit_growth < 5e6, f"Dr.Jit storage grew by {jit_growth / 1e6:.1f} MB over 20 builds"
    assert heap_growth < 5e6, f"the Python heap grew by {heap_growth / 1e6:.1f} MB over 20 builds"


def test_a_render_mitsuba_cut_short_is_refused():
    """Mitsuba's own SIGINT handler cancels the integrator and mi.render returns a partial image: refused."""
    from types import SimpleNamespace

    import pytest

    from scopetwin.scenes.mitsuba.variant import RenderInterruptedError, render_complete

    def scene_stopped(stopped: bool) -> SimpleNamespace:
        return SimpleNamespace(integrator=lambda: SimpleNamespace(should_stop=lambda: stopped))

    fake_mi = SimpleNamespace(render=lambda scene, **kw: "image")
    assert render_complete(fake_mi, scene_stopped(False), spp=1) == "image"
    with pytest.raises(RenderInterruptedError, match="interrupted"):
        render_complete(fake_mi, scene_stopped(True), spp=1)
