"""benchmarks/speed_table.py: its table holds every row with a speed goal, the reference is deterministic, the
quiet-machine estimate is seconds x quiet reference / reference now, and --calibrate writes the record it reads."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def st() -> ModuleType:
    spec = importlib.util.spec_from_file_location("speed_table", ROOT / "benchmarks" / "speed_table.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["speed_table"] = mod
    spec.loader.exec_module(mod)
    return mod


def test_every_goal_has_a_measurement(st: ModuleType) -> None:
    assert list(st.TABLE) == [str(k) for k in range(1, 13)]
    assert set(st.ROWS) == set(st.TABLE)
    assert {k for k, g in st.TABLE.items() if g.full_only} == {"7", "8", "11"}
    # the rows' goals, seconds
    goals = {k: g.goal_s for k, g in st.TABLE.items()}
    assert goals == {
        "1": 0.150,
        "2": 0.300,
        "3": 0.033,
        "4": 0.5,
        "5": 1.0,
        "6": 8.0,
        "7": 60.0,
        "8": 20.0,
        "9": 0.15,
        "10": 5.0,
        "11": None,
        "12": 2.0,
    }
    assert st.TABLE["2"].first_round_s == (0.9, 1.15)


def test_glass_surface_is_a_valid_setup_like_float_glass(st: ModuleType) -> None:
    from scopetwin.scenes.setup import load_setup

    # the spec only: drawing it pads the grid by 4 x 40 mm (seconds); rendered once and cached by the benchmark
    setup = load_setup(st.PRESET, {"substrate": {"surface": {**st.GLASS, "seed": st.GLASS_SEEDS[0]}}})
    assert setup.substrate is not None
    spec = setup.substrate.surface
    assert (spec.kind, spec.spectrum) == ("psd", "power")
    assert 14.0 <= spec.range_um <= 60.0  # PV of float glass, µm
    assert 20.0 <= spec.broadband_rms_nm <= 100.0  # micro-waviness
    assert (spec.broadband_min_wavelength_mm, spec.broadband_wavelength_mm) == (1.0, 8.0)


def test_quiet_estimate_scales_by_the_reference(st: ModuleType) -> None:
    text = st.line("1", "path", 2.0, 0.5, 0.25, 1.5, "1.2")
    fields = text.split()
    # seconds 2 as measured, beside it the quiet estimate 1 s (reference 0.5 now, 0.25 quiet), ratio 4; the goal
    # 1.5 s is met by the estimate, not by the seconds as measured, and the status says both
    assert fields[2:6] == ["2", "1", "0.500", "4"]
    assert text.endswith("met (as measured: NOT met)")
    assert st.line("1", "path", 1.0, 0.5, 0.25, 1.5, "1.2").endswith(" met")  # both meet it: one word
    assert st.line("1", "path", 2.0, 0.5, None, 1.5, "1.2").endswith("NOT met")  # no quiet record: the seconds
    assert "—" in st.line("1", "path", float("nan"), 0.5, 0.25, 1.5, "1.2")


def test_calibrate_writes_the_record_the_table_reads(st: ModuleType, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr(st, "REFERENCE_ROUNDS", 1)
    path = tmp_path / "ref.json"
    rec = st.calibrate(3, path)
    stored = st.load_quiet_reference(path)
    assert stored == json.loads(path.read_text()) == rec
    assert 0 < stored["cpu_min_s"] and 0 < stored["wall_min_s"] <= stored["wall_median_s"]
    assert stored["reference_s"] in (stored["wall_min_s"], stored["cpu_min_s"])
    assert st.load_quiet_reference(tmp_path / "absent.json") is None


def test_reference_workload_is_deterministic(st: ModuleType) -> None:
    a = st._spd().copy()
    st._SPD.clear()
    assert np.array_equal(st._spd(), a)  # the same matrix from the thesis, run after run
    assert a.shape == (600, 600) and np.array_equal(a, a.T)
    np.linalg.cholesky(a)  # SPD: the factorisation the reference times exists
    wall, cpu = st.reference()
    assert wall > 0 and cpu > 0
    work, prod = st._buffers()  # the factor computed in place in its buffer (nothing allocated while timed)
    low = np.tril(work)
    assert np.allclose(low @ low.T, a) and np.allclose(prod, a)


def test_a_stored_row_prints_again_with_the_quiet_reference(st: ModuleType, capsys: pytest.CaptureFixture[str]) -> None:
    row = {
        "row": "6",
        "path": "scopetwin run (wall)",
        "seconds": 30.0,
        "reference_s": 0.6,
        "first_round_s": [12.0, 12.0],
        "goal_s": 12.0,
        "extras": [{"label": "step: detect + reconstruct", "seconds": 6.0, "goal_s": None}],
        "note": "",
    }
    st.print_row(row, 0.2)
    first, extra = capsys.readouterr().out.splitlines()
    # seconds, quiet estimate 30 x 0.2 / 0.6 = 10 s, reference, ratio, goal, first round, status
    assert first.split()[-12:] == [
        "30",
        "10",
        "0.600",
        "50",
        "<=",
        "12",
        "12",
        "met",
        "(as",
        "measured:",
        "NOT",
        "met)",
    ]
    assert extra.split()[-5:] == ["6", "2", "0.600", "10", "—"]  # the sub-row: 6 x 0.2 / 0.6 = 2 s, no goal
    row["reference_cpu_s"] = 0.2
    st.print_row(row, 0.2)
    assert capsys.readouterr().out.split()[6:8] == ["0.600", "3.00"]  # reference wall / CPU: a busy machine


def test_modules_without_up_to_date_bytecode_are_found(st: ModuleType, tmp_path: Path, monkeypatch) -> None:
    """A module whose bytecode is missing or older than its source is listed; one compiled after its last edit is
    not (the note the table prints where the environment writes no bytecode)."""
    import os
    import py_compile

    pkg = tmp_path / "recon"
    pkg.mkdir()
    fresh, edited, bare = (pkg / f"{n}.py" for n in ("fresh", "edited", "bare"))
    for src in (fresh, edited, bare):
        src.write_text("X = 1\n")
    for src in (fresh, edited):
        py_compile.compile(str(src), doraise=True)
    later = os.stat(edited).st_mtime + 10
    os.utime(edited, (later, later))
    monkeypatch.setattr(st, "ROOT", tmp_path)
    monkeypatch.setattr(st, "PACKAGE_FOLDERS", ("recon",))
    assert st.uncompiled_modules() == ["recon/bare.py", "recon/edited.py"]
