"""``optics cmu --budget`` (sim.cmu_budget): the tables, the JSON and the plot, the option checks, and cell
images rendered at the budget's photon counts whose mean electrons are the budget's."""

from __future__ import annotations

import json

import numpy as np
import pytest

from scopetwin.cli import main
from scopetwin.scenes.cmu import photon_budget as pb
from scopetwin.scenes.cmu.layout import load_cmu_setup
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.sim import cmu_budget


def test_report_tables() -> None:
    r = cmu_budget.report()
    assert set(r["seed"]) == set(r["lasers"]) == {"blue", "green", "red", "nir"}
    assert r["seed"]["blue"]["predicted_ms"] == pytest.approx(80.0)
    for row in r["seed"].values():
        assert row["density_per_um2"] == pytest.approx(r["seed"]["blue"]["implied_density_per_um2"])
    t = r["timing"]
    assert t["fields"] == 2000
    thesis = t["scenarios"]["thesis sources"]
    assert thesis["cmu_s"]["exposure"] == pytest.approx(9.8)
    assert thesis["speedup"] > thesis["speedup_map"] > 1.0
    # the lasers' exposures are the laser table's
    assert t["exposures_ms"]["lasers"]["green"] == pytest.approx(r["lasers"]["green"]["exposure_ms"])
    text = "\n".join(cmu_budget.format_report(r))
    for needle in ("Hoechst 33258", "DRAQ5", "488 nm", "seq.+map", "slide (h)", "the thesis, §4.2.2"):
        assert needle in text


def test_cli_budget_json_and_plot(tmp_path, capsys) -> None:
    out, plot = tmp_path / "budget.json", tmp_path / "budget.png"
    assert main(["optics", "cmu", "--budget", "--json", str(out), "--plot", str(plot), "--raster", "10", "20"]) == 0
    data = json.loads(out.read_text())
    assert {"seed", "lasers", "timing", "fluorophores", "plot"} <= set(data)
    assert data["timing"]["fields"] == 200
    assert plot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    printed = capsys.readouterr().out
    assert "one labelling density for all four stains" in printed and "time per field" in printed


@pytest.mark.parametrize(
    "argv",
    [
        ["--plot", "x.png"],  # a budget option without --budget
        ["--snr", "5"],
        ["--budget", "--stop"],  # a ray-analysis option with --budget
        ["--budget", "--splitter-maps", "770DCXR=x.exr"],
    ],
)
def test_budget_options_are_checked(argv, tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    assert main(["optics", "cmu", *argv]) == 2


def test_window_texture_mean_is_the_cells_fraction() -> None:
    setup = load_cmu_setup()
    whole = cmu_budget.window_texture_mean(setup, 10_000, 10.0)  # the whole field
    assert 0.3 < whole < 0.8  # 500 cells of 50 x 25 µm, nuclei 1, cytoplasm 0.4, over 0.9 x 0.67 mm
    with pytest.raises(ScopetwinError):
        pb.channel_budget("red", -1.0)


@pytest.mark.mitsuba
@pytest.mark.parametrize("channel", ["nir", "green"])
def test_rendered_cells_carry_the_budgets_electrons(channel) -> None:
    """The cells through the NIR channel (sharp: its splitters only transmit) and the green one (two reflections and
    the folding mirror), a 48 px window, 8 spp, at the thesis's exposure and the density it implies (SNR 10, 162 e-
    on a nucleus): the mean electrons of the captured image equal the budget's rate x exposure x the texture's mean
    over the window.

    Stated tolerance 5 %: the render's Monte Carlo noise (0.5-2 % at 8 spp over 2304 px, four or five seeds), its
    difference from the on-axis radiometry of :func:`~scopetwin.scenes.mitsuba.cmu.unit_texel_irradiance` (< 2 % on
    uniform renders) and the light the blur moves across the window's edge (green: -1 to -2.5 %); shot and dark noise
    of the mean: 0.3 %. (A mirror counted twice, as the renderer once did, gives -5 % in green.)
    """
    setup = load_cmu_setup()
    t = pb.SEED_EXPOSURE_MS[channel]
    b = pb.channel_budget(channel, pb.implied_density(channel, t))
    r = cmu_budget.render_channel_electrons(setup, channel, b, t, spp=8, window_px=48, seed=1)
    assert r["nucleus_e"] == pytest.approx(161.8, rel=1e-3) and r["nucleus_snr"] == pytest.approx(10.0, rel=1e-3)
    assert r["measured_mean_e"] == pytest.approx(r["predicted_mean_e"], rel=0.05)
    assert r["saturated_fraction"] == 0.0


@pytest.mark.mitsuba
@pytest.mark.slow
def test_cli_renders_the_cells_at_the_thesis_exposures(tmp_path) -> None:
    """``--budget --out``: four DN images with previews; each channel's window mean within 5 % of the budget (blue,
    green, red bright enough; the NIR at 6000 ms and the Hoechst density has ~3 e- a nucleus: only its files are
    checked), and the red at the thesis's 9800 ms far from the full well (about a tenth of the ADC's range)."""
    out = tmp_path / "cells"
    js = tmp_path / "cells.json"
    argv = ["optics", "cmu", "--budget", "--out", str(out), "--spp", "4", "--window", "64", "--json", str(js)]
    assert main(argv) == 0
    cells = json.loads(js.read_text())["cells"]
    for ch in ("blue", "green", "red"):
        assert cells[ch]["measured_mean_e"] == pytest.approx(cells[ch]["predicted_mean_e"], rel=0.05)
    assert cells["red"]["nucleus_adc_fraction"] < 0.2
    for ch, row in cells.items():
        for path in row["files"].values():
            assert (out / path.split("/")[-1]).exists(), (ch, path)
    assert np.isfinite(cells["nir"]["nucleus_snr"]) and cells["nir"]["nucleus_snr"] < 1.0
