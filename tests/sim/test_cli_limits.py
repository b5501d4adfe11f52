"""Limits from estimates and validated numbers: refused before any work, one line naming the
option or key and the estimate, exit 2, nothing written; GRIN windows between the lenses; previews; overlays."""

from __future__ import annotations

import types

import numpy as np
import pytest

from scopetwin.cli import main
from scopetwin.scenes import limits
from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.grin import load_grin_setup
from scopetwin.scenes.grin.setup import check_image_window
from scopetwin.scenes.io import read_image, write_image
from scopetwin.scenes.limits import LimitError, check_image_size, check_render

GRIN = "thesis-8.3.2-grin-realized"


def _run(capsys, *argv):
    """main() with argparse errors as exit codes: (code, stdout, stderr)."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse
        code = int(exc.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def _error_lines(err: str) -> list[str]:
    return [line for line in err.splitlines() if "error:" in line]


def _refused(capsys, *argv, names: tuple[str, ...] = ()) -> str:
    code, _, err = _run(capsys, *argv)
    assert code == 2, err
    lines = _error_lines(err)
    assert len(lines) == 1 and "Traceback" not in err, err
    for n in names:
        assert n in lines[0], (n, lines[0])
    return lines[0]


# -- numeric options -------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("argv", "option"),
    [
        (["optics", "grin", GRIN, "--image", "dots-25", "--out", "{tmp}/a.exr", "--spp", "0"], "--spp"),
        (["optics", "grin", GRIN, "--image", "dots-25", "--out", "{tmp}/a.exr", "--spp", "-3"], "--spp"),
        (["optics", "grin", GRIN, "--image", "dots-25", "--out", "{tmp}/a.exr", "--width", "-5"], "--width"),
        (["optics", "grin", GRIN, "--image", "dots-25", "--out", "{tmp}/a.exr", "--height", "1.5"], "--height"),
        (["optics", "grin", GRIN, "--target-offset", "nan", "0"], "--target-offset"),
        (["optics", "grin", GRIN, "--seed", "-1"], "--seed"),
        (["optics", "cmu", "--out", "{tmp}/c", "--spp", "0"], "--spp"),
        (["optics", "scan", "--width", "inf"], "--width"),
        (["optics", "scan", "--n", "0"], "--n"),
        (["optics", "scan", "--exposure-s", "-0.1"], "--exposure-s"),
        (["render", "thesis-2.9.1-target-6x4", "--out", "{tmp}/r", "--spp", "0"], "--spp"),
        (["render", "thesis-2.9.1-target-6x4", "--out", "{tmp}/r", "--seed", "-2"], "--seed"),
        (["calibrate", "{tmp}/x.exr", "--focal-length", "-25"], "--focal-length"),
        (["calibrate", "{tmp}/x.exr", "--pixel-pitch", "0"], "--pixel-pitch"),
        (["calibrate", "{tmp}/x.exr", "--image-distance", "inf"], "--image-distance"),
    ],
)
def test_numeric_options_refused_with_the_option_named(argv, option, tmp_path, capsys):
    _refused(capsys, *[a.format(tmp=tmp_path) for a in argv], names=(f"argument {option}",))
    assert list(tmp_path.iterdir()) == []


def test_nz_estimate_must_be_finite(tmp_path, capsys):
    write_image(tmp_path / "x.exr", np.zeros((4, 4), np.float32))
    _refused(capsys, "calibrate", tmp_path / "x.exr", "--nz-estimate", "nan,0,1", names=("--nz-estimate",))


# -- setup numbers: finite, and one image must fit ----------------------------------------------------------------
@pytest.mark.parametrize(
    ("toml", "key"),
    [
        ('base = "thesis-1.10-deflectometry"\n[substrate.surface]\nrange_um = inf\n', "range_um"),
        ('base = "thesis-2.9.1-target-6x4"\n[camera]\npixel_pitch = nan\n', "pixel_pitch"),
        ('base = "thesis-2.9.1-target-6x4"\n[camera]\npixels = [100000, 100000]\n', "pixels"),
        ('base = "thesis-1.10-deflectometry"\n[substrate.surface]\ngrid = [200000, 200000]\n', "surface.grid"),
        ('base = "thesis-2.9.1-target-6x4"\n[render]\nseed = 5000000000\n', "render.seed"),
    ],
)
def test_setup_numbers_refused_naming_the_key(toml, key, tmp_path, capsys):
    setup = tmp_path / "s.toml"
    setup.write_text(toml)
    line = _refused(capsys, "render", setup, "--out", tmp_path / "out", names=(key,))
    assert "pixels" not in key or ("GiB" in line and "memory" in line)  # the estimate and the limit
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("old", "new", "key"),
    [
        ("count = 8", "count = 1e11", "dataset.count"),
        ("count = 8", "count = 100000000000", "dataset.count"),
        ("uniform = [0.4, 0.9]", "uniform = [-inf, inf]", "vary.exposure_fill.uniform"),
        ("normal = [0.0, 0.2]", "normal = [0.0, nan]", "vary.camera_shift.normal"),
        ("pixel_pitch = 0.0093", "pixel_pitch = inf", "pixel_pitch"),
        ("pixels = [680, 512]", "pixels = [200000, 200000]", "pixels"),
    ],
)
def test_dataset_config_numbers_refused_naming_the_key(old, new, key, tmp_path, capsys):
    from pathlib import Path

    text = (Path(__file__).parents[2] / "examples/datasets/01-deflectometry-small.toml").read_text()
    assert old in text
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(text.replace(old, new))
    _refused(capsys, "dataset", "generate", cfg, "--out", tmp_path / "ds", "--workers", "0", names=(key,))
    assert not (tmp_path / "ds").exists()


def test_dataset_sample_render_time_is_checked_before_the_folder_exists(tmp_path, capsys):
    """Each Part I sample's render (pixels x spp) is estimated while the plan is built, before any folder exists."""
    from pathlib import Path

    text = (Path(__file__).parents[2] / "examples/datasets/01-deflectometry-small.toml").read_text()
    cfg = tmp_path / "cfg.toml"
    cfg.write_text(text.replace("spp = 16", "spp = 2000000000"))
    _refused(capsys, "dataset", "generate", cfg, "--out", tmp_path / "ds", "--workers", "0", names=("rays", "limit"))
    assert not (tmp_path / "ds").exists()


def test_grin_and_cmu_numbers_are_finite():
    with pytest.raises(SetupError, match="rod1.length"):
        load_grin_setup(GRIN, {"rod1": {"length": float("inf")}})
    with pytest.raises(SetupError, match="width_px x height_px"):
        load_grin_setup(GRIN, {"camera": {"width_px": 200000, "height_px": 200000}})
    from scopetwin.scenes.cmu.layout import load_cmu_setup

    with pytest.raises(SetupError, match="nan|finite"):
        load_cmu_setup("thesis-cmu", {"camera": {"pixel_um": float("nan")}})


def test_render_spp_beyond_the_time_limit_is_refused_before_the_output_exists(tmp_path, capsys):
    setup = tmp_path / "s.toml"
    setup.write_text('base = "thesis-2.9.1-target-6x4"\n[render]\nspp = 1000000000\n')
    line = _refused(capsys, "render", setup, "--out", tmp_path / "out", names=("rays", "limit", "1000000000 spp"))
    assert "SCOPETWIN_RENDER_LIMIT_S" in line
    assert not (tmp_path / "out").exists()


def test_grin_spp_beyond_the_time_limit(tmp_path, capsys):
    _refused(
        capsys,
        *("optics", "grin", GRIN, "--image", "dots-25", "--out", tmp_path / "a.exr", "--spp", "1000000000"),
        names=("rays", "limit"),
    )
    assert list(tmp_path.iterdir()) == []


def test_cmu_render_beyond_the_time_limit_makes_no_folder(tmp_path, capsys):
    _refused(capsys, "optics", "cmu", "--out", tmp_path / "c", "--spp", "100000000", names=("rays", "limit"))
    assert not (tmp_path / "c").exists()


# -- the estimates themselves ---------------------------------------------------------------------------------------
def test_check_image_size_gives_estimate_and_limit():
    check_image_size(1000, 1000, "pixels", memory=1 << 30)  # 48 MB of 1 GiB: fine
    with pytest.raises(LimitError, match=r"pixels: a 10000 x 10000 px image needs about 4\.5 GiB .* 1\.0 GiB"):
        check_image_size(10000, 10000, "pixels", memory=1 << 30)


def test_check_render_time_and_limit(monkeypatch):
    seconds = check_render(1000, 1000, 80, "x", "setup", memory=1 << 34, limit_s=10.0)
    assert seconds == pytest.approx(1.0)  # 8e7 rays at 8e7 rays/s
    with pytest.raises(LimitError, match="over the render limit of 5 s"):
        check_render(1000, 1000, 800, "x", "setup", memory=1 << 34, limit_s=5.0)
    with pytest.raises(LimitError, match="spp must be >= 1"):
        check_render(10, 10, 0, "x", memory=1 << 34)
    monkeypatch.setenv("SCOPETWIN_RENDER_LIMIT_S", "2")
    assert limits.render_time_limit_s() == 2.0
    with pytest.raises(LimitError, match="limit of 2 s"):
        check_render(1000, 1000, 800, "x", memory=1 << 34)
    monkeypatch.setenv("SCOPETWIN_RENDER_LIMIT_S", "inf")
    with pytest.raises(LimitError, match="SCOPETWIN_RENDER_LIMIT_S"):
        limits.render_time_limit_s()


def test_available_memory_is_positive():
    assert 0 < limits.available_memory() <= limits.physical_memory() * 1.01


# -- GRIN windows between the lenses --------------------------------------------------------------------------------
def test_grin_window_between_the_lenses_is_refused_naming_the_centres(tmp_path, capsys):
    out = tmp_path / "a.exr"
    line = _refused(
        capsys,
        *("optics", "grin", GRIN, "--image", "dots-25", "--out", out, "--width", "256", "--height", "256"),
        names=("(-1.125, -1.125)", "(1.125, 1.125)", "256 x 256 px", "--width"),
    )
    assert "black" in line
    assert list(tmp_path.iterdir()) == []


def test_check_image_window_accepts_windows_that_reach_a_lens():
    setup = load_grin_setup(GRIN)
    m = 5.0  # this preset's paraxial magnification is 5.02
    check_image_window(setup, 2592, 1944, (0.0, 0.0), m, 0.2)  # the whole camera
    check_image_window(setup, 256, 256, (1.125, 1.125), m, 0.2)  # on an axis
    with pytest.raises(SetupError, match="at least --width 3"):
        check_image_window(setup, 256, 256, (0.0, 0.0), m, 0.2)


@pytest.mark.mitsuba
def test_grin_image_just_past_the_bound_sees_light_and_has_a_preview(tmp_path, capsys):
    """The smallest window the check suggests is lit (the bound is not too tight to be useful)."""
    setup = load_grin_setup(GRIN)
    with pytest.raises(SetupError) as exc:
        check_image_window(setup, 256, 256, (0.0, 0.0), 5.0152, 0.2)
    side = int(str(exc.value).rsplit("--width ", 1)[1].split()[0])
    big = side + 120  # the bound includes a 5 % margin: go a little beyond it
    out = tmp_path / "g.exr"
    code, _, err = _run(
        capsys,
        *("optics", "grin", GRIN, "--image", "dots-25", "--out", out, "--width", big, "--height", big, "--spp", "1"),
    )
    assert code == 0, err
    image, _ = read_image(out)
    assert image.max() > 0
    assert (tmp_path / "g.png").stat().st_size > 0


# -- previews of optics cmu --out -------------------------------------------------------------------------------------
@pytest.mark.slow
def test_cmu_out_writes_a_png_preview_per_image(tmp_path, capsys, monkeypatch):
    import scopetwin.sim.cmu_unit as cmu_unit

    def fake_render(setup, maps, table, out, spp, stop, cells):  # the analyses stay real, the renders do not
        files = {}
        for ch in table:
            path = out / f"star_{ch}.exr"
            write_image(path, np.linspace(0, 1, 64, dtype=np.float32).reshape(8, 8))
            files[f"star_{ch}"] = str(path)
        measured = {ch: {"magnification": 1.0, "delta_x_um": 0.0} for ch in table}
        return {"measured": measured, "files": files}

    monkeypatch.setattr(cmu_unit, "render_and_measure", fake_render)
    code, out, err = _run(capsys, "optics", "cmu", "--out", tmp_path / "c", "--json", tmp_path / "c.json")
    assert code == 0, err
    pngs = sorted(p.name for p in (tmp_path / "c").glob("*.png"))
    assert pngs == ["star_blue.png", "star_green.png", "star_nir.png", "star_red.png"]
    assert "PNG previews" in out


# -- legible overlays and the N_z note ------------------------------------------------------------------------------
def test_label_step_keeps_labels_apart():
    from scopetwin.sim.figures import label_step

    cols, rows = np.meshgrid(np.arange(20) * 27.0, np.arange(20) * 27.0)
    pts = np.stack([cols.ravel(), rows.ravel()], axis=1)
    assert label_step(pts, 40.0) == 2  # 2 x 27 px >= 1.3 x 40 px
    assert label_step(pts, 10.0) == 1
    assert label_step(pts[:1], 40.0) == 1


def test_overlay_draws_the_reference_label_with_a_halo():
    from scopetwin.sim.figures import overlay_image

    ij = np.array([(i, j) for j in range(-6, 7) for i in range(-6, 7)])

    class FakeMarkers(types.SimpleNamespace):
        def __len__(self) -> int:
            return len(ij)

    m = FakeMarkers(
        spots=types.SimpleNamespace(background=0.0, centroids=np.zeros((0, 2))),
        peak=np.ones(len(ij)),
        centroids=ij * 14.0 + 100.0,
        ij=ij,
    )
    img = overlay_image(np.full((200, 200), 0.5, np.float32), m)  # type: ignore[arg-type]
    yellow = (img[..., 0] < 60) & (img[..., 1] > 200) & (img[..., 2] > 200)
    black = img.sum(axis=2) == 0
    assert img.shape == (200, 200, 3) and yellow.sum() > 20 and black.sum() > 20  # label (0,0) and its halo


def test_nz_note_is_said_plainly():
    from scopetwin.cli.calibrate import _warnings

    cal = types.SimpleNamespace(
        warnings=(
            "the N_z estimate (0, -2.311e-17, 1) does not tell the two mirror-ambiguous poses apart; "
            "the better-fitting one is used",
            "something else",
        ),
        residual_rms_px=0.0018,
    )
    lines = _warnings(cal, "mirror view", (0.0, -2.311e-17, 1.0), "do this.")  # type: ignore[arg-type]
    assert lines[0].startswith("warning: mirror view: the a-priori sensor normal (0, 0, 1) lies midway")
    assert "0.0018 px rms" in lines[0] and "No action is needed" in lines[0] and lines[0].endswith("do this.")
    assert lines[1] == "warning: mirror view: something else"


# -- plain help texts ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "command",
    [
        ["render"],
        ["presets"],
        ["markers"],
        ["calibrate"],
        ["calibrate-setup"],
        ["optics"],
        ["optics", "grin"],
        ["optics", "cmu"],
        ["optics", "scan"],
    ],
)
def test_help_is_plain_text(command, capsys):
    code, out, _ = _run(capsys, *command, "--help")
    assert code == 0 and out.strip()
    for markup in ("``", ":mod:", ":func:", ":class:", "`"):
        assert markup not in out, (command, markup)


def test_the_reworded_note_still_matches_the_calibration():
    """The CLI recognises the calibration's mirror-ambiguity note by its wording: the two must not drift apart."""
    import inspect

    import scopetwin.calib.oneshot.calibration as calibration
    from scopetwin.cli.calibrate import _AMBIGUOUS

    assert _AMBIGUOUS in inspect.getsource(calibration)


@pytest.mark.parametrize("second", [False, True])
def test_reconstruct_checks_an_exr_header_before_decoding(tmp_path, capsys, second):
    """An image whose EXR header declares 20000 x 20000 px (a few hundred bytes on disk) is refused from the header:
    one line, exit 2, before a pixel is decoded; as the first image and as the second."""
    import struct

    from scopetwin.scenes.setup import load_setup

    big = tmp_path / "big.exr"
    write_image(big, np.ones((4, 6), np.float32))
    data = bytearray(big.read_bytes())
    at = data.index(b"dataWindow\x00box2i\x00") + len(b"dataWindow\x00box2i\x00") + 4
    data[at : at + 16] = struct.pack("<4i", 0, 0, 19999, 19999)
    big.write_bytes(bytes(data))
    nx, ny = load_setup("thesis-1.10-deflectometry").camera.pixels
    first = big
    extra: list[object] = []
    if second:
        first = tmp_path / "first.exr"
        write_image(first, np.ones((ny, nx), np.float32))
        extra = ["--second", big, "--pattern-shift", "1.0"]
    code, _, err = _run(
        capsys, "reconstruct", first, "--setup", "thesis-1.10-deflectometry", "--out", tmp_path / "h.exr", *extra
    )
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert f"declares 20000 x 20000 px, but {nx} x {ny} px are expected; nothing was decoded" in err
    assert not (tmp_path / "h.exr").exists()
