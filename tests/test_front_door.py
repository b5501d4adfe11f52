"""The Python front door: the README's example as written, and one image giving the same heights through
``scopetwin reconstruct``, ``scopetwin run``'s reconstruction step and ``scopetwin.reconstruct`` — also where the
reference marker is tied and the strategy decides it."""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import numpy as np
import OpenEXR
import pytest

import scopetwin
from scopetwin.scenes.io import write_image

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.mitsuba


def _readme_example() -> str:
    text = (ROOT / "README.md").read_text()
    section = text.split("## From Python", 1)[1]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


def test_the_readme_example_runs_and_recovers_the_surface():
    out = io.StringIO()
    scope: dict[str, object] = {}
    with contextlib.redirect_stdout(out):
        exec(compile(_readme_example(), "README.md", "exec"), scope)  # noqa: S102 - the README's own code
    r, m = scope["r"], scope["m"]
    err = scope["error_um"]
    assert abs(float(np.mean(err))) <= 3 * r.uncertainty.absolute_um + 0.05  # µm: within 3 u (+ ROI vs grid)
    assert float(np.std(err)) < 0.5  # µm: the shape of a 40 µm bow, from one noisy 4 spp frame
    assert "start-height search" in out.getvalue() and "absolute" in out.getvalue()
    assert m.image.shape == (m.setup.camera_model.ny, m.setup.camera_model.nx)


PRESET = "thesis-1.10-deflectometry"


def _three_ways(m: scopetwin.Measurement, tmp_path: Path, with_run: bool = True) -> list[np.ndarray]:
    """Heights on the contract's node grid from ``scopetwin reconstruct``, ``scopetwin.reconstruct`` and the
    reconstruction step of ``scopetwin run`` (that one only ``with_run``; the surface fields of the setup do not enter
    a reconstruction, so the CLI gets the preset by name)."""
    from scopetwin.cli import main
    from scopetwin.recon.substrate import Substrate2D
    from scopetwin.sim.pipeline import _detect_and_reconstruct

    exr = tmp_path / "image.exr"
    write_image(exr, m.image, m.setup.to_json())
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["reconstruct", str(exr), "--setup", PRESET, "--out", str(tmp_path / "z.exr")]) == 0
    with OpenEXR.File(str(tmp_path / "z.exr")) as f:  # NaN where no marker measures (channel Z_measured)
        cli = np.asarray(f.channels()["Z"].pixels)
    done = scopetwin.reconstruct(m.image, m.setup)
    front = _masked(done.heightmap().z, done.measured_mask())
    if not with_run:
        return [cli, front]
    sub = Substrate2D.from_setup(m.setup)
    _, _, results = _detect_and_reconstruct(m.image, {"ideal": m.setup}, tmp_path, m.heights, sub)
    res = results["ideal"]["result"]
    return [cli, front, _masked(res.heightmap().z, res.measured_mask())]


def _masked(z: np.ndarray, measured: np.ndarray | None) -> np.ndarray:
    """Heights as a reconstruction's height-map file holds them: float32, NaN at the nodes no marker measures."""
    z = z.astype(np.float32)
    return z if measured is None else np.where(measured, z, np.float32(np.nan))


@pytest.mark.slow
def test_run_reconstruct_and_the_front_door_agree(tmp_path):
    m = scopetwin.render(PRESET, spp=4, seed=3)
    cli, front, run = _three_ways(m, tmp_path)
    assert np.array_equal(cli, front, equal_nan=True) and np.array_equal(cli, run, equal_nan=True)


@pytest.mark.slow
def test_they_agree_where_the_reference_marker_is_tied(tmp_path):
    """3 mm / 60 µm surface seed 7: four spots as large as the reference marker; the strategy decides the tie the
    same way through the command line (the image and its setup through an EXR file) and the front door. (``run``'s
    step calls the strategy as the front door does, with the same arguments: the test above; its tied case would
    add a third reconstruction of 30 s and nothing else.)"""
    from scopetwin.recon.markers import ReferenceTieError, find_markers_for

    over = {"substrate": {"surface": {"correlation_length": 3.0, "range_um": 60.0, "seed": 7}}}
    m = scopetwin.render(scopetwin.load_setup(PRESET, over), spp=4, seed=1, noise=False)
    with pytest.raises(ReferenceTieError):
        find_markers_for(m.image, m.setup)
    cli, front = _three_ways(m, tmp_path, with_run=False)
    assert np.array_equal(cli, front, equal_nan=True)
    assert 0 < np.isnan(cli).mean() < 0.1  # the few ROI nodes beyond two marker spacings of every marker


@pytest.mark.slow
def test_the_next_frame_of_a_live_loop_starts_from_the_previous_prior():
    """``previous=``: the next frame's search starts on the basis scale the earlier frame ended on and its posterior
    from the earlier frame's prior (one evidence start instead of two); it gives the surface and uncertainty the cold
    start gives, within a fifth of that uncertainty."""
    first, second = (scopetwin.render(PRESET, spp=4, seed=s) for s in (1, 2))
    r1 = scopetwin.reconstruct(first.image, first.setup)
    assert r1.prior is not None and r1.prior.as_dict()["kind"] == "basis"  # the preset's kind: the finite basis
    cold = scopetwin.reconstruct(second.image, second.setup)
    warm = scopetwin.reconstruct(second.image, second.setup, previous=r1)
    assert r1.scale is not None and f"basis scale {r1.scale:g} mm" in warm.strategy[0]  # its search starts there
    u = cold.uncertainty.absolute_um
    assert abs(warm.uncertainty.absolute_um - u) <= 0.1 * u
    x, y = np.meshgrid(np.linspace(-10, 10, 21), np.linspace(-15, 15, 31))
    assert float(np.max(np.abs(warm.height_at(x, y) - cold.height_at(x, y)))) * 1e3 <= 0.2 * u + 0.01
