"""GRIN presets, overrides and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from scopetwin.scenes.errors import ScopetwinError, SetupError
from scopetwin.scenes.grin import load_grin_setup, profile_override
from scopetwin.scenes.grin.analysis import analyse
from scopetwin.scenes.grin.glass import glass
from scopetwin.scenes.grin.targets import TargetError, target

PRESETS = ["thesis-7.5.2-grin-egfp", "thesis-8.3.1-grin-optimized", "thesis-8.3.2-grin-realized"]


@pytest.mark.parametrize("name", PRESETS)
def test_presets_load_with_their_section(name):
    s = load_grin_setup(name)
    assert s.section == "§" + name.split("-")[1]
    st = s.stack()
    assert [layer.name for layer in st.layers][:3] == ["cover", "object_gap", "rod1"]
    assert st.layers[0].z0 == 0.0


def test_toml_base_override_and_sech_profile(tmp_path):
    p = tmp_path / "mine.toml"
    p.write_text('kind = "grin"\nbase = "thesis-8.3.2-grin-realized"\n[rod2]\nlength = 0.9\n')
    s = load_grin_setup(p)
    assert s.rod2.length == 0.9 and s.rod1.length == 3.58
    prof = tmp_path / "sech.toml"
    prof.write_text('[rod1.profile]\nkind = "sech"\nn0 = 1.62893\ng = 0.3074745\n')
    s2 = profile_override(s, prof)
    assert s2.rod1.profile.kind == "sech"
    # the sech profile has the same paraxial g as the GrinTech nr2: same paraxial EFL
    rep1, rep2 = analyse(s, samples=8), analyse(s2, samples=8)
    assert rep2.efl_mm == pytest.approx(rep1.efl_mm, rel=1e-5)


def test_profile_with_index_below_one_is_rejected(tmp_path):
    p = tmp_path / "bad.toml"
    p.write_text('kind = "grin"\nbase = "thesis-8.3.2-grin-realized"\n[rod1.profile]\nn0 = 1.2\nnr2 = -0.5\n')
    with pytest.raises(SetupError, match=r"rod1\.profile.*n = 0\.\d+ < 1 at r ="):
        load_grin_setup(p)


def test_rod_longer_than_scene_is_rejected(tmp_path):
    p = tmp_path / "long.toml"
    p.write_text('kind = "grin"\nbase = "thesis-8.3.2-grin-realized"\n[rod1]\nlength = 80.0\n')
    with pytest.raises(SetupError, match=r"rod1\.length.*longer than the scene"):
        load_grin_setup(p)


def test_other_bad_inputs():
    with pytest.raises(SetupError, match="unknown preset"):
        load_grin_setup("thesis-9.9-nothing")
    with pytest.raises(SetupError, match="not a GRIN objective"):
        load_grin_setup("thesis-1.10-deflectometry")
    with pytest.raises(SetupError, match=r"substrate\.glass.*unknown glass"):
        load_grin_setup("thesis-8.3.2-grin-realized", {"substrate": {"glass": "UNOBTAINIUM"}})
    with pytest.raises(SetupError, match="overlap"):
        load_grin_setup("thesis-8.3.2-grin-realized", {"array": {"pitch": 1.5}})
    with pytest.raises(ScopetwinError):
        glass("nope")


def test_target_outside_field_is_rejected():
    target("grid-25").check_field(0.2)
    with pytest.raises(TargetError, match="outside the field of view"):
        target("grid-25", offset=(0.05, 0.0)).check_field(0.2)
    with pytest.raises(TargetError, match="unknown target"):
        target("siemens-star")


def test_targets_have_their_periods():
    x = np.linspace(-0.1, 0.1, 20001)
    for name, period, duty in (("lines-8", 0.008, 0.5), ("grid-25", 0.025, 1 - 0.002 / 0.025)):
        t = target(name).transmission(x, np.full_like(x, 0.0101 if name == "grid-25" else 0.0))
        assert t.mean() == pytest.approx(duty, abs=0.01)
        edges = np.flatnonzero(np.diff(t) > 0)
        assert np.median(np.diff(edges)) * (x[1] - x[0]) == pytest.approx(period, rel=1e-3)


def test_glass_dispersion_follows_abbe_number():
    g = glass("B270")
    nf, nc, nd = g.index(486.13), g.index(656.27), g.index(587.56)
    assert nd == pytest.approx(1.5230, abs=1e-12)
    assert (nd - 1) / (nf - nc) == pytest.approx(58.5, rel=1e-9)
