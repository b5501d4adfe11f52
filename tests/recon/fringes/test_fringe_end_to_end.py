"""Fringes end to end: ``scopetwin render`` of a fringe setup with a pattern stage (Mitsuba, 16 spp, EMVA 1288 noise),
then ``scopetwin reconstruct fringes.json`` (and ``--second shifted_fringes.json``) and the front door on the same
frames; errors against the true surface over the ROI (sim.pipeline.roi_errors).

Measured on the 4x binned camera (340 x 256 px, 26,000 decoded pixels): frame criterion absolute -0.53 µm at
u = 0.33 µm, shape 0.065 µm at u = 0.043 µm; two display positions (+10 mm) absolute +0.018 µm at u = 0.084 µm,
shape 0.004 µm at u = 0.011 µm. Acceptance: the shape within 0.15 µm (frame criterion) and 0.03 µm (two positions),
the absolute height within 3 of its reported uncertainty (and within 0.3 µm with two positions). Bad input (a
fringe list of the wrong length, a setup of another camera size, a marker setup, a marker method) is refused with one
line, exit 2, and no height map. The full-size preset (1360 x 1024, 24 frames) runs in the slow test.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import scopetwin
from scopetwin.cli import main
from scopetwin.recon.substrate import Substrate2D
from scopetwin.scenes.io import read_heightmap
from scopetwin.sim.fringes import read_fringes
from scopetwin.sim.pipeline import roi_errors

pytestmark = pytest.mark.mitsuba
SHIFT_MM = 10.0
SMALL_TOML = f"""base = "thesis-1.10-fringes"
[camera]
pixels = [340, 256]
pixel_pitch = 0.0186
[pattern_stage]
shift_mm = {SHIFT_MM}
[render]
spp = 16
noise = true
"""


@pytest.fixture(scope="module")
def rendered(tmp_path_factory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp("fringes")
    (root / "small.toml").write_text(SMALL_TOML)
    assert (
        main(["render", str(root / "small.toml"), "--out", str(root / "f"), "-q", "--json", str(root / "r.json")]) == 0
    )
    return root, json.loads((root / "r.json").read_text())


def _errors(heights: Path, root: Path) -> dict[str, float]:
    setup = scopetwin.load_setup(root / "small.toml")
    return roi_errors(
        read_heightmap(heights).height, read_heightmap(root / "f" / "surface.exr"), Substrate2D.from_setup(setup)
    )


def test_render_writes_both_display_positions(rendered):
    root, r = rendered
    assert len(r["images"]) == 24 and len(r["shifted_images"]) == 24 and r["pattern_shift_mm"] == SHIFT_MM
    assert Path(r["fringes"]).name == "fringes.json" and Path(r["shifted_fringes"]).name == "shifted_fringes.json"
    second = read_fringes(r["shifted_fringes"])
    assert second.images.shape == (24, 256, 340) and second.seed == read_fringes(r["fringes"]).seed + 1
    moved = np.subtract(second.setup.pattern.origin, scopetwin.load_setup(root / "small.toml").pattern.origin)
    np.testing.assert_allclose(moved, SHIFT_MM * np.asarray(second.setup.pattern.n_z), atol=1e-9)


def test_cli_reconstructs_a_fringe_measurement(rendered, capsys):
    root, r = rendered
    out, js = root / "h.exr", root / "h.json"
    assert main(["reconstruct", r["fringes"], "--out", str(out), "--json", str(js)]) == 0
    assert "fringe frames (frame criterion)" in capsys.readouterr().out
    res = json.loads(js.read_text())
    for key in ("uncertainty", "strategy", "seconds", "start_height_um", "roi_coverage", "outer_iterations"):
        assert key in res, key
    assert res["method"] == "fringes" and res["absolute_from"] == "frame-criterion" and res["roi_coverage"] > 0.95
    assert res["strategy"][0].startswith("decode: ") and res["observations"] > 20_000
    err, u = _errors(out, root), res["uncertainty"]
    assert abs(err["roi_shape_um"]) < 0.15 and err["roi_shape_um"] < 3 * u["shape_um"], (err, u)
    assert abs(err["roi_absolute_um"]) < 3 * u["absolute_um"], (err, u)
    m = read_heightmap(out)
    assert m.z.shape == (288, 128)


def test_cli_two_display_positions(rendered):
    root, r = rendered
    out, js = root / "h2.exr", root / "h2.json"
    assert (
        main(
            ["reconstruct", r["fringes"], "--second", r["shifted_fringes"], "--out", str(out), "--json", str(js), "-q"]
        )
        == 0
    )
    res = json.loads(js.read_text())
    assert res["absolute_from"] == "two-positions" and res["pattern_shift_mm"] == SHIFT_MM
    err, u = _errors(out, root), res["uncertainty"]
    assert err["roi_shape_um"] < 0.03 and err["roi_shape_um"] < 3 * u["shape_um"], (err, u)
    assert abs(err["roi_absolute_um"]) < min(0.3, 3 * u["absolute_um"]), (err, u)


def test_front_door_on_the_rendered_frames(rendered):
    root, r = rendered
    first, second = read_fringes(r["fringes"]), read_fringes(r["shifted_fringes"])
    setup = scopetwin.load_setup(root / "small.toml")
    done = scopetwin.reconstruct(first.images, setup, second=second.images)  # the shift: the setup's [pattern_stage]
    err = roi_errors(done.height_at, first.heights, done.result.substrate)
    assert done.method == "fringes" and done.result.method == "two-positions"
    assert abs(err["roi_absolute_um"]) < min(0.3, 3 * done.uncertainty.absolute_um), (err, done.uncertainty)


def _edit(path: Path, change) -> None:
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


@pytest.mark.parametrize(
    ("case", "match"),
    [
        ("short", "its 23 frames are not the 24 frames"),
        ("size", "images of 340 x 256 px, but the camera .* has 680 x 512"),
        ("markers", r"has no \[fringes\] table"),
        ("method", "takes the fringe method, not --method centroid"),
    ],
)
def test_bad_input_is_refused_with_exit_2(rendered, tmp_path, capsys, case, match):
    import re
    import shutil

    root, r = rendered
    folder = tmp_path / "f"
    shutil.copytree(root / "f", folder)
    argv = ["reconstruct", str(folder / "fringes.json"), "--out", str(tmp_path / "h.exr"), "-q"]
    if case == "short":
        _edit(folder / "fringes.json", lambda d: d["frames"].pop())
    elif case == "size":
        (tmp_path / "big.toml").write_text(SMALL_TOML.replace("[340, 256]", "[680, 512]").replace("0.0186", "0.0093"))
        argv += ["--setup", str(tmp_path / "big.toml")]
    elif case == "markers":
        argv += ["--setup", "thesis-1.10-deflectometry"]
    else:
        argv += ["--method", "centroid"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and re.search(match, err[0]), err
    assert not (tmp_path / "h.exr").exists()


@pytest.mark.slow
def test_the_full_preset_end_to_end(tmp_path):
    """The thesis-1.10-fringes preset at 1360 x 1024 (24 frames, 16 spp, noise) through the front door."""
    m = scopetwin.render("thesis-1.10-fringes", spp=16, seed=3)
    assert m.images.shape == (24, 1024, 1360)
    done = scopetwin.reconstruct(m.images, m.setup)
    err = roi_errors(done.height_at, m.heights, done.result.substrate)
    u = done.uncertainty
    print(err, u, done.strategy, done.result.seconds)
    s = done.summary()
    assert done.result.converged and s["observations"] * s["block_px"] ** 2 > 300_000
    assert err["roi_shape_um"] < 0.1 and err["roi_shape_um"] < 3 * u.shape_um, (err, u)
    assert abs(err["roi_absolute_um"]) < 3 * u.absolute_um, (err, u)
