"""Fringe measurements (sim/fringes.py): the sensor noise of a rendered sequence against its EMVA 1288 prediction,
the folder's write/read round trip, bad folders refused before decoding, and ``scopetwin render`` on a fringe setup."""

from __future__ import annotations

import json
import os
import shutil

import numpy as np
import pytest

from scopetwin.scenes.errors import FileFormatError
from scopetwin.scenes.fringes import FringeSequence
from scopetwin.scenes.inputs import InputError
from scopetwin.scenes.io import write_image
from scopetwin.scenes.safe_read import UnsafeInput
from scopetwin.scenes.setup import load_setup
from scopetwin.sim.fringes import FringeMeasurement, read_fringes, render_fringes, save_fringes

#: The §1.10 fringe preset seen by a quarter of the pixels (same field of view), two periods: 16 frames.
SMALL = {
    "camera": {"pixels": [680, 512], "pixel_pitch": 0.0093},
    "fringes": {"sequence": {"periods": [64.0, 8.0], "steps": 4}},
}


def decode(stack: np.ndarray, shifts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """N-step phase, offset A and modulation B of I_k = A + B cos(phi + delta_k)."""
    s, c = np.tensordot(np.sin(shifts), stack, 1), np.tensordot(np.cos(shifts), stack, 1)
    return np.arctan2(-s, c), stack.mean(axis=0), 2.0 / len(shifts) * np.hypot(s, c)


@pytest.mark.mitsuba
def test_sensor_noise_of_the_sequence_matches_the_emva_prediction(mono_variant):
    """The same seed with and without noise renders the same irradiance, so the phase difference is the sensor's
    alone; its per-pixel standard deviation, predicted from the EMVA 1288 model as sqrt(2 / N) sigma_I / B with
    sigma_I^2 = K (A - black) + K^2 sigma_d^2 + 1/12 DN^2, matches the observed one within 5 % (1.00 measured).
    One exposure serves every frame; each frame has its own noise seed."""
    from scipy import ndimage

    from scopetwin.sim.surfaces import surface_for

    setup = load_setup("thesis-1.10-fringes", SMALL)
    heights = surface_for(setup)
    clean = render_fringes(setup, heights, spp=4, seed=5, noise=False, variant=mono_variant)
    noisy = render_fringes(setup, heights, spp=4, seed=5, noise=True, variant=mono_variant)
    assert noisy.images.shape == (16, 512, 680) and noisy.images.dtype == np.float32
    assert clean.exposure_s is None and noisy.exposure_s is not None and noisy.exposure_s > 0
    assert len(set(noisy.noise_seeds)) == 16 and len(noisy.seconds_per_frame) == 16
    sensor = setup.sensor
    lit = ndimage.binary_erosion(clean.images[0] > 0.05, np.ones((5, 5)))
    shifts = setup.fringe_sequence.shifts()
    ratios = []
    for direction in "xy":
        for p in range(2):
            idx = [setup.fringe_sequence.index(direction, p, k) for k in range(4)]
            phi0, _, _ = decode(clean.images[idx].astype(np.float64), shifts)
            phi, a, b = decode(noisy.images[idx].astype(np.float64), shifts)
            err = np.angle(np.exp(1j * (phi - phi0)))[lit]
            k = sensor.gain_dn_per_e
            sigma_i = np.sqrt(k * (a - sensor.black_level_dn) + k**2 * sensor.dark_noise_e**2 + 1 / 12)[lit]
            predicted = np.sqrt(2 / 4) * sigma_i / b[lit]
            ratio = float(np.sqrt(np.mean((err / predicted) ** 2)))
            print(f"{direction} period {p}: phase noise RMS {err.std():.4f} rad, observed / predicted {ratio:.3f}")
            ratios.append(ratio)
    assert all(0.95 < r < 1.05 for r in ratios)


def _synthetic(tmp_path, rng) -> FringeMeasurement:
    """A measurement of a 64 x 48 px camera with random images (no render), written to ``tmp_path / "m"``."""
    from scopetwin.sim.surfaces import surface_for

    setup = load_setup(
        "thesis-1.10-fringes",
        {"camera": {"pixels": [64, 48], "pixel_pitch": 0.0988}, "fringes": {"sequence": {"periods": [64.0]}}},
    )
    seq = setup.fringe_sequence
    images = rng.uniform(0, 4000, (len(seq), 48, 64)).astype(np.float32)
    m = FringeMeasurement(
        images, seq.frames(), setup.fringe_display, seq, setup, surface_for(setup), 16, 3, True, 0.021,
        tuple(range(len(seq))), (0.1,) * len(seq), {"seed": 3, "spp": 16},
    )  # fmt: skip
    save_fringes(m, tmp_path / "m")
    return m


def test_write_read_round_trip(tmp_path, rng):
    m = _synthetic(tmp_path, rng)
    names = sorted(p.name for p in (tmp_path / "m").iterdir())
    assert names == [f"fringe_{k:04d}.exr" for k in range(8)] + ["fringes.json", "surface.exr"]
    back = read_fringes(tmp_path / "m")
    np.testing.assert_array_equal(back.images, m.images)
    assert back.frames == m.frames and back.display == m.display and back.sequence == m.sequence
    assert back.setup == m.setup and back.setup.fringe_sequence == FringeSequence((64.0,), 4)
    np.testing.assert_array_equal(back.heights.z, m.heights.z.astype(np.float32))  # the EXR holds float32
    assert (back.spp, back.seed, back.noise, back.exposure_s) == (16, 3, True, 0.021)
    assert back.noise_seeds == m.noise_seeds and back.frame_index("y", 0, 2) == 6
    data = json.loads((tmp_path / "m" / "fringes.json").read_text())
    assert data["format"] == 1 and data["frames"][5] == {"file": "fringe_0005.exr", **m.frames[5].to_dict()}
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []  # no stage left


def _edit(folder, change) -> None:
    path = folder / "fringes.json"
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


@pytest.mark.parametrize(
    ("change", "error", "match"),
    [
        (lambda d: d.update(format=99), UnsafeInput, "newer than this scopetwin reads"),
        (lambda d: d.update(kind="markers"), FileFormatError, "kind must be 'fringes'"),
        (lambda d: d["frames"][1].update(file="../outside.exr"), UnsafeInput, "leaves"),
        (lambda d: d["frames"][1].update(file="/etc/passwd"), UnsafeInput, "absolute path"),
        (lambda d: d["frames"][1].update(file="fringe_0000.exr"), FileFormatError, "two frames name the same file"),
        (lambda d: d["frames"][1].update(direction="z"), FileFormatError, "direction must be"),
        (lambda d: d["display"].update(bit_depth=99), FileFormatError, "bit_depth"),
        (lambda d: d["setup"]["camera"].update(pixels=[65, 48]), FileFormatError, "shape"),
        (lambda d: d.update(frames=[]), FileFormatError, "frames must be a list of 1 to"),
        (lambda d: d.update(spp="many"), FileFormatError, "'spp' must be int"),
    ],
)
def test_bad_fringes_json_is_refused(tmp_path, rng, change, error, match):
    _synthetic(tmp_path, rng)
    _edit(tmp_path / "m", change)
    with pytest.raises(error, match=match):
        read_fringes(tmp_path / "m")


def test_bad_frame_files_are_refused_before_decoding(tmp_path, rng):
    _synthetic(tmp_path, rng)
    folder = tmp_path / "m"
    write_image(folder / "fringe_0003.exr", np.zeros((480, 640), np.float32))  # another camera's size
    with pytest.raises(UnsafeInput, match="declares 640 x 480 px, but 64 x 48 px are expected"):
        read_fringes(folder)
    outside = tmp_path / "outside.exr"
    write_image(outside, np.zeros((48, 64), np.float32))
    (folder / "fringe_0003.exr").unlink()
    (folder / "fringe_0003.exr").symlink_to(outside)
    with pytest.raises(UnsafeInput, match="outside"):
        read_fringes(folder)
    (folder / "fringe_0003.exr").unlink()
    os.mkfifo(folder / "fringe_0003.exr")
    with pytest.raises(InputError, match="not a regular file"):
        read_fringes(folder)
    shutil.rmtree(folder)
    folder.mkdir()
    with pytest.raises(UnsafeInput, match="does not exist"):
        read_fringes(folder)


@pytest.mark.mitsuba
def test_render_command_writes_every_frame_of_a_fringe_setup(tmp_path, capsys):
    """``scopetwin render`` on a [fringes] setup writes one EXR per frame and fringes.json; --json lists them."""
    from scopetwin.cli import main

    toml = tmp_path / "f.toml"
    toml.write_text(
        'base = "thesis-1.10-fringes"\n[camera]\npixels = [340, 256]\npixel_pitch = 0.0186\n'
        "[fringes.sequence]\nperiods = [64.0]\nsteps = 4\n"
    )
    code = main(["render", str(toml), "--out", str(tmp_path / "out"), "--spp", "2", "--json", str(tmp_path / "r.json")])
    assert code == 0, capsys.readouterr().err
    result = json.loads((tmp_path / "r.json").read_text())
    assert set(result) == {"images", "fringes", "surface", "frames", "spp", "seconds", "seconds_per_frame"}
    assert len(result["images"]) == len(result["frames"]) == 8 and result["spp"] == 2
    back = read_fringes(tmp_path / "out")
    assert back.images.shape == (8, 256, 340) and back.images.max() > 0.5 and not back.noise
    assert [f.to_dict() for f in back.frames] == result["frames"]
    code = main(["render", str(toml), "--out", str(tmp_path / "o2"), "--renderer", "analytic"])
    assert code == 2 and "only the Mitsuba renderer" in capsys.readouterr().err
    assert not (tmp_path / "o2").exists()
