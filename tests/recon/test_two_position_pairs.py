"""A second pattern position's image of another surface, or taken with another shift, is refused (thesis §1.3,
:func:`scopetwin.recon.two_positions.pair_excess`): one clear error naming the excess residual and its threshold.

Exact marker images (the project's own ray model, :func:`scopetwin.sim.truth.marker_truth`) with 0.01 px of centroid
noise, no render."""

from __future__ import annotations

import re

import numpy as np
import pytest

from scopetwin.recon.errors import MismatchedPairError, ReconstructionError
from scopetwin.recon.reconstruct import MarkerObservations
from scopetwin.recon.strategy import reconstruct_markers_pair
from scopetwin.recon.two_positions import TwoPositionConfig
from scopetwin.scenes.pattern_stage import shift_pattern
from scopetwin.scenes.setup import Setup, load_setup
from scopetwin.sim.surfaces import surface_for
from scopetwin.sim.truth import marker_truth

PRESET = "thesis-1.10-deflectometry"
SHIFT_MM = 40.0


def _markers(setup: Setup, seed: int, shift_mm: float, rng: np.random.Generator) -> MarkerObservations:
    """Exact marker images of the preset's surface drawn from ``seed``, the pattern moved ``shift_mm`` (0: not)."""
    heights = surface_for(load_setup(PRESET, {"substrate": {"surface": {"seed": seed}}}))
    t = marker_truth(shift_pattern(setup, shift_mm) if shift_mm else setup, heights, rim_points=8)
    v = t.visible
    return MarkerObservations(t.ij[v], t.center_px[v] + 0.01 * rng.standard_normal((int(v.sum()), 2)))


@pytest.fixture(scope="module")
def markers() -> tuple[Setup, MarkerObservations, MarkerObservations, MarkerObservations]:
    """The setup (surface seed 1), image 1's markers, the second position's of the same surface and of seed 2's."""
    setup = load_setup(PRESET, {"substrate": {"surface": {"seed": 1}}})
    rng = np.random.default_rng(36)
    return (
        setup,
        _markers(setup, 1, 0.0, rng),
        _markers(setup, 1, SHIFT_MM, rng),
        _markers(setup, 2, SHIFT_MM, rng),
    )


def test_a_true_pair_passes_with_no_excess(markers):
    setup, first, second, _ = markers
    est = reconstruct_markers_pair(setup, first, second, SHIFT_MM).estimate
    assert est.excess_urad < 0.1 * TwoPositionConfig().max_excess_urad, est
    assert np.isfinite(est.separate_urad) and est.summary()["excess_urad"] == est.excess_urad


def test_a_second_image_of_another_surface_is_one_clear_error(markers):
    setup, first, _, other = markers
    with pytest.raises(MismatchedPairError) as info:
        reconstruct_markers_pair(setup, first, other, SHIFT_MM)
    assert isinstance(info.value, ReconstructionError)
    text = str(info.value)
    assert "\n" not in text and "does not belong to the first" in text, text
    excess = float(re.search(r"leaves (\S+) µrad RMS", text).group(1))  # type: ignore[union-attr]
    assert excess > 10 * TwoPositionConfig().max_excess_urad, text
    assert f"at most {TwoPositionConfig().max_excess_urad:g} µrad" in text and "+40 mm" in text, text


def test_a_wrong_pattern_shift_is_refused(markers):
    setup, first, second, _ = markers
    with pytest.raises(MismatchedPairError, match="with the pattern moved \\+30 mm"):
        reconstruct_markers_pair(setup, first, second, 30.0)


def test_the_check_can_be_turned_off(markers):
    setup, first, _, other = markers
    est = reconstruct_markers_pair(setup, first, other, SHIFT_MM, tp=TwoPositionConfig(max_excess_urad=np.inf)).estimate
    assert est.excess_urad > 10 * TwoPositionConfig().max_excess_urad


@pytest.mark.slow
@pytest.mark.mitsuba
def test_reconstruct_refuses_a_second_image_of_another_substrate(tmp_path, capsys):
    """Rendered with Mitsuba (4 spp, EMVA sensor noise): ``reconstruct --second`` with the second image of another
    surface is one line, exit 2, no height map; with its own second image it reconstructs."""
    from scopetwin.cli import main

    rendered = {}
    for seed in (1, 2):
        toml = tmp_path / f"s{seed}.toml"
        toml.write_text(
            f'base = "{PRESET}"\n\n[pattern_stage]\nshift_mm = {SHIFT_MM}\n\n[render]\nspp = 4\nnoise = true\n\n'
            f"[substrate.surface]\nseed = {seed}\n"
        )
        assert main(["render", str(toml), "--out", str(tmp_path / f"r{seed}"), "-q"]) == 0
        rendered[seed] = toml, tmp_path / f"r{seed}"
    toml, r1 = rendered[1]
    out = tmp_path / "h.exr"
    argv = ["reconstruct", str(r1 / "image.exr"), "--setup", str(toml), "--out", str(out), "-q"]
    capsys.readouterr()
    assert main([*argv, "--second", str(rendered[2][1] / "shifted_image.exr")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "does not belong to the first" in err, err
    assert f"at most {TwoPositionConfig().max_excess_urad:g} µrad" in err, err
    assert not out.exists()
    assert main([*argv, "--second", str(r1 / "shifted_image.exr")]) == 0 and out.is_file()
