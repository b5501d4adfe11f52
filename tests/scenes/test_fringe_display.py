"""The fringe display and sequence (scenes/fringes.py): frame order, the display model against its own definition,
the texture against the model, the N-step decoding of the model, the setup's [fringes] table and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.fringes import FringeDisplay, FringeFrame, FringeSequence
from scopetwin.scenes.setup import load_setup


def decode(intensities: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """The textbook N-step phase of I_k = A + B cos(phi + delta_k): atan2(-sum I_k sin d_k, sum I_k cos d_k)."""
    s = np.tensordot(np.sin(shifts), intensities, axes=1)
    c = np.tensordot(np.cos(shifts), intensities, axes=1)
    return np.arctan2(-s, c)


def wrap(a: np.ndarray) -> np.ndarray:
    return np.angle(np.exp(1j * a))


def test_frames_come_in_the_documented_order():
    seq = FringeSequence((64.0, 8.0, 1.0), 4)
    frames = seq.frames()
    assert len(frames) == len(seq) == 24
    k = 0
    for d in ("x", "y"):
        for p_index, period in enumerate((64.0, 8.0, 1.0)):
            for step in range(4):
                assert frames[k] == FringeFrame(d, period, 2 * np.pi * step / 4)
                assert seq.index(d, p_index, step) == k
                k += 1
    assert FringeFrame.from_dict(frames[5].to_dict()) == frames[5]


def test_ideal_value_is_the_shared_interface():
    """I = 0.5 + 0.5 cos(2 pi u / period + shift), u along the frame's direction."""
    u, v = np.array([-3.0, 0.0, 1.25]), np.array([2.0, -7.0, 0.5])
    fx, fy = FringeFrame("x", 8.0, 0.3), FringeFrame("y", 8.0, 0.3)
    np.testing.assert_allclose(fx.ideal(u, v), 0.5 + 0.5 * np.cos(2 * np.pi * u / 8 + 0.3), atol=1e-15)
    np.testing.assert_allclose(fy.ideal(u, v), 0.5 + 0.5 * np.cos(2 * np.pi * v / 8 + 0.3), atol=1e-15)


def test_sharp_display_is_the_gamma_mapped_quantised_value_of_its_pixel_centre():
    """Without blur, every point of a display pixel emits black + (1 - black) * round(I(centre)^(1/gc) * 255)/255)^g."""
    display = FringeDisplay(0.05, (10.0, 6.0), 2.2, black_level=0.01, blur_px=0.0, bit_depth=8, gamma_correction=1.8)
    frame = FringeFrame("y", 3.0, 1.1)
    rng = np.random.default_rng(4)
    u, v = rng.uniform(-4.99, 4.99, 500), rng.uniform(-2.99, 2.99, 500)
    centre = (np.floor((v + 3.0) / 0.05) + 0.5) * 0.05 - 3.0
    code = np.round((0.5 + 0.5 * np.cos(2 * np.pi * centre / 3.0 + 1.1)) ** (1 / 1.8) * 255) / 255
    np.testing.assert_allclose(display.radiance(u, v, frame), 0.01 + 0.99 * code**2.2, atol=1e-12)
    assert np.all(display.radiance([5.01, 0.0], [0.0, 3.01], frame) == 0)  # off the active area


def test_blur_keeps_the_light_and_halves_the_edge():
    """The Gaussian blur moves light but keeps it: the integral over the display and beyond is unchanged (to 1e-5,
    the Riemann sum's error at the sharp display's pixel edges), and at the edge of the active area the radiance is
    half the interior's."""
    sharp = FringeDisplay(0.05, (4.0, 4.0), blur_px=0.0)
    soft = FringeDisplay(0.05, (4.0, 4.0), blur_px=1.5)
    frame = FringeFrame("x", 4.0, 0.7)
    u = np.linspace(-2.5, 2.5, 200001)
    du = u[1] - u[0]
    total = sharp.radiance(u, 0.0, frame).sum() * du
    assert total > 1.0 and abs(soft.radiance(u, 0.0, frame).sum() * du / total - 1) < 1e-5
    flat = FringeDisplay(0.05, (4.0, 4.0), blur_px=1.5, black_level=0.2)
    edge = flat.radiance(0.0, [2.0, 0.0], FringeFrame("x", 4.0, 0.0))
    assert abs(edge[0] / edge[1] - 0.5) < 1e-12


@pytest.mark.parametrize("direction", ["x", "y"])
@pytest.mark.parametrize("blur", [0.0, 0.5])
def test_texture_equals_the_model_at_its_texel_centres(direction, blur):
    display = FringeDisplay(0.05, (6.0, 4.0), blur_px=blur)
    frame = FringeFrame(direction, 1.0, 2.0)
    tex = display.texture(frame, 0.0125)
    u, v = display.texel_centres(0.0125)
    assert tex.dtype == np.float32 and tex.shape == (len(v), len(u)) == (320, 480)
    assert u[0] < 0 and v[0] < 0  # row 0 / column 0: the (-x, -y) corner
    model = display.radiance(u[None, :], v[:, None], frame)
    np.testing.assert_allclose(tex, model, rtol=2e-7, atol=1e-7)
    assert tex.max() <= 1.0 and tex[40:-40, 40:-40].min() >= display.black_level - 1e-7


@pytest.mark.parametrize("period", [64.0, 8.0, 1.0])
def test_default_display_decodes_to_the_phase_within_quantisation(period):
    """The preset display (gamma 2.2 corrected by the look-up table, 8 bits, blur 0.5 px): the 4-step phase of the
    emitted radiance equals 2 pi u / period within 0.005 rad (8-bit quantisation: 0.002 rad RMS)."""
    display, seq = FringeDisplay(), FringeSequence((64.0, 8.0, 1.0), 4)
    p = seq.periods_mm.index(period)
    u = np.linspace(-22.0, 22.0, 8001)
    frames = [seq.frames()[seq.index("x", p, k)] for k in range(4)]
    phase = decode(np.stack([display.radiance(u, 0.0, f) for f in frames]), seq.shifts())
    err = wrap(phase - 2 * np.pi * u / period)
    print(f"period {period} mm: phase error RMS {err.std():.4f}, max {np.abs(err).max():.4f} rad")
    assert np.abs(err).max() < 0.005 and err.std() < 0.003


def test_uncorrected_gamma_harmonics_are_rejected_by_more_steps():
    """An uncorrected gamma of 2.2 distorts the fringe (harmonics); N steps are blind to harmonics up to N - 2, so
    8 steps decode it at least 10 times better than 4 steps."""
    display = FringeDisplay(gamma_correction=1.0, bit_depth=16, blur_px=0.0, pixel_pitch_mm=0.01)
    u = np.arange(-400, 400) * 0.01 + 0.005  # display pixel centres: no staircase
    errors = []
    for steps in (4, 8):
        seq = FringeSequence((64.0, 8.0), steps)
        frames = [seq.frames()[seq.index("x", 1, k)] for k in range(steps)]
        phase = decode(np.stack([display.radiance(u, 0.0, f) for f in frames]), seq.shifts())
        errors.append(float(np.abs(wrap(phase - 2 * np.pi * u / 8.0)).max()))
    print(f"uncorrected gamma: max phase error 4 steps {errors[0]:.4f}, 8 steps {errors[1]:.5f} rad")
    assert errors[0] > 0.005 and errors[1] < errors[0] / 10


def test_fringe_preset_loads_and_marker_setups_are_unchanged():
    setup = load_setup("thesis-1.10-fringes")
    assert setup.fringe_display == FringeDisplay() and setup.fringe_sequence == FringeSequence()
    assert setup.pattern == load_setup("thesis-1.10-deflectometry").pattern
    marker = load_setup("thesis-1.10-deflectometry")
    assert marker.fringes is None and marker.fringe_display is None and '"fringes"' not in marker.to_json()
    assert FringeDisplay.from_dict(setup.fringe_display.to_dict()) == setup.fringe_display


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: FringeSequence((64.0, 8.0), 3), "steps must be an integer >= 4"),
        (lambda: FringeSequence((8.0, 64.0), 4), "strictly decreasing"),
        (lambda: FringeSequence((64.0, 1.0), 4), "ratio 64 exceeds"),
        (lambda: FringeSequence((), 4), "at least one period"),
        (lambda: FringeFrame("z", 1.0, 0.0), "direction must be"),
        (lambda: FringeFrame("x", float("nan"), 0.0), "period_mm must be a finite number"),
        (lambda: FringeDisplay(0.05, (50.01, 50.0)), "not a whole number"),
        (lambda: FringeDisplay(black_level=1.0), "black_level"),
        (lambda: FringeDisplay(bit_depth=0), "bit_depth"),
        (lambda: FringeSequence((40.0, 8.0), 4).check_display(FringeDisplay()), "does not cover the display"),
        (lambda: FringeSequence((64.0, 8.0, 1.0, 0.15), 4).check_display(FringeDisplay()), "fewer than 4 display"),
        (lambda: FringeDisplay.from_dict({"gamma": 2.2}), "keys"),
    ],
)
def test_bad_fringe_parameters_are_one_clear_error(make, match):
    with pytest.raises(SetupError, match=match):
        make()


@pytest.mark.parametrize(
    ("overrides", "match"),
    [
        ({"fringes": {"sequence": {"periods": [40.0, 8.0]}}}, "field fringes: the coarsest fringe period 40 mm"),
        ({"fringes": {"display": {"gamma": -1.0}}}, "fringes.display.gamma"),
        ({"fringes": {"sequence": {"steps": 3}}}, "fringes.sequence.steps"),
        ({"fringes": {"display": {"colour": 1}}}, "fringes.display.colour"),
    ],
)
def test_bad_fringes_table_names_the_field(overrides, match):
    with pytest.raises(SetupError, match=match):
        load_setup("thesis-1.10-fringes", overrides)


def test_fringes_need_a_deflectometry_or_mirror_scene():
    with pytest.raises(SetupError, match="needs a deflectometry or mirror setup"):
        load_setup("thesis-2.8.1-perpendicular", {"fringes": {}})
    assert load_setup("thesis-2.8.3-mirror", {"fringes": {}}).fringe_sequence == FringeSequence()
