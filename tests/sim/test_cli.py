"""The command line: contract outputs, and bad input -> one error line, exit 2, nothing written."""

import json

import numpy as np
import pytest

from scopetwin.cli import main
from scopetwin.scenes.io import read_heightmap, read_image, write_image

SMALL = """
base = "thesis-2.8.1-angular"
[camera]
pixels = [136, 102]
pixel_pitch = 0.0465
[render]
spp = 4
"""


def _run(capsys, *argv):
    code = main([str(a) for a in argv])
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_render_writes_contract_files(tmp_path, capsys):
    setup = tmp_path / "small.toml"
    setup.write_text(SMALL)
    out = tmp_path / "out"
    code, _, err = _run(capsys, "render", setup, "--out", out, "--renderer", "analytic", "--json", tmp_path / "r.json")
    assert code == 0, err
    result = json.loads((tmp_path / "r.json").read_text())
    assert set(result) == {"image", "truth", "spp", "seconds"} and result["spp"] == 4
    image, attrs = read_image(result["image"])
    assert image.shape == (102, 136) and image.dtype == np.float32 and image.max() > 0.5
    assert json.loads(attrs["scopetwin_setup"])["camera"]["pixels"] == [136, 102]
    assert json.loads(attrs["scopetwin_provenance"])["spp"] == 4
    truth = json.loads((out / "truth.json").read_text())
    assert {"i", "j", "center_col", "center_row", "visible"} <= set(truth["markers"][0])
    assert sorted(p.name for p in out.iterdir()) == ["image.exr", "preview.png", "truth.json"]
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_render_deflectometry_with_user_surface(tmp_path, capsys):
    from scopetwin.scenes.io import write_heightmap
    from scopetwin.scenes.surface import HeightMap

    hm = HeightMap.from_function(lambda x, y: -1e-5 * y**2 + 0.0081225, -12.6, 12.6, -28.5, 28.5, 32, 64)
    write_heightmap(tmp_path / "z.exr", hm)
    setup = tmp_path / "d.toml"
    setup.write_text(
        'base = "thesis-1.10-deflectometry"\n[camera]\npixels = [68, 51]\npixel_pitch = 0.093\n[render]\nspp = 1\n'
    )
    code, _, err = _run(
        capsys, "render", setup, "--out", tmp_path / "o", "--surface", tmp_path / "z.exr", "--renderer", "analytic"
    )
    assert code == 0, err
    back = read_heightmap(tmp_path / "o" / "surface.exr")
    np.testing.assert_allclose(back.z, hm.z, atol=1e-9)


def test_presets_lists_the_contract_names(capsys):
    code, out, _ = _run(capsys, "presets")
    assert code == 0
    for name in ("thesis-1.10-deflectometry", "thesis-2.8.3-mirror", "thesis-2.9.1-target-4x4"):
        assert name in out


BAD_TOMLS = {
    "non-orthonormal": ('base = "thesis-2.8.1-angular"\n[camera]\nt_y = [0.0, 0.6, 0.8575]\n', "not a unit vector"),
    "negative-pitch": ('base = "thesis-2.8.1-angular"\n[pattern]\npitch = [-4.0, 4.0]\n', "pitch must be > 0"),
}


@pytest.mark.parametrize("case", sorted(BAD_TOMLS))
def test_bad_setup_files(tmp_path, capsys, case):
    toml, message = BAD_TOMLS[case]
    (tmp_path / "bad.toml").write_text(toml)
    out = tmp_path / "out"
    code, stdout, err = _run(capsys, "render", tmp_path / "bad.toml", "--out", out, "--json", tmp_path / "r.json")
    assert code == 2
    assert err.startswith("scopetwin: error: ") and message in err and err.count("\n") == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["bad.toml"]


def test_unknown_preset(tmp_path, capsys):
    code, _, err = _run(capsys, "render", "thesis-0.0-nothing", "--out", tmp_path / "out")
    assert code == 2 and "unknown preset 'thesis-0.0-nothing'" in err
    assert list(tmp_path.iterdir()) == []


def test_unreadable_and_wrong_channel_surface(tmp_path, capsys):
    (tmp_path / "junk.exr").write_text("junk")
    write_image(tmp_path / "image.exr", np.zeros((8, 8)))
    for name, message in (
        ("junk.exr", "not a readable OpenEXR"),
        ("image.exr", "no channel 'Z'"),
        ("missing.exr", "does not exist"),
    ):
        code, _, err = _run(
            capsys, "render", "thesis-1.10-deflectometry", "--out", tmp_path / "out", "--surface", tmp_path / name
        )
        assert code == 2 and message in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["image.exr", "junk.exr"]
