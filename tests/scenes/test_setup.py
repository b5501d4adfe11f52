"""Setup models, presets and TOML loading: every preset loads; bad input names the field."""

import pytest

from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.setup import load_setup, preset_info, preset_names

PART_ONE = [
    "thesis-1.10-deflectometry",
    "thesis-2.8.1-perpendicular",
    "thesis-2.8.1-angular",
    "thesis-2.8.3-substrate",
    "thesis-2.8.3-mirror",
    "thesis-2.8.5-distortion",
    "thesis-2.9.1-target-6x4",
    "thesis-2.9.1-target-4x4",
]


def test_all_part_one_presets_exist_and_cite_a_section():
    names = preset_names()
    for name in PART_ONE:
        assert name in names
    info = {p["name"]: p for p in preset_info()}
    for name in PART_ONE:
        assert info[name]["section"].startswith("§")
        setup = load_setup(name)
        assert setup.name == name
        assert setup.camera_model.nx == 1360


def test_thesis_numbers_are_kept():
    s = load_setup("thesis-1.10-deflectometry")
    assert s.camera.origin == (0.0, -200.0, 120.0) and s.camera.image_distance == 28.0
    assert s.pattern.markers == (33, 33) and s.pattern.pitch == (1.5, 1.5)
    assert s.substrate.size == (25.2, 57.0) and s.substrate.roi_length == 48.0
    assert s.substrate.surface.range_um == 40.0
    d = load_setup("thesis-2.8.5-distortion")
    assert d.camera.r_cs == (0.0465, 0.0465) and d.camera.c2 == 0.00123


def test_toml_with_base_and_overrides(tmp_path):
    f = tmp_path / "mine.toml"
    f.write_text('base = "thesis-1.10-deflectometry"\n[substrate.surface]\nrange_um = 80.0\n')
    s = load_setup(f)
    assert s.substrate.surface.range_um == 80.0 and s.pattern.markers == (33, 33)
    assert s.name == "mine"


@pytest.mark.parametrize(
    ("toml", "message"),
    [
        ('base = "thesis-1.10-deflectometry"\n[camera]\nt_x = [1.0, 0.2, 0.0]\n', "camera.*T_x is not a unit"),
        ('base = "thesis-1.10-deflectometry"\n[pattern]\npitch = [-1.5, 1.5]\n', "pattern.*pitch must be > 0"),
        ('base = "thesis-1.10-deflectometry"\n[render]\nspp = 0\n', "render.spp"),
        ('base = "thesis-1.10-deflectometry"\n[camera]\nbogus = 1\n', "camera.bogus"),
        ('base = "no-such-preset"\n', "unknown preset 'no-such-preset'"),
        ("this is = not toml [", "not valid TOML"),
    ],
)
def test_bad_setups_give_one_clear_error(tmp_path, toml, message):
    f = tmp_path / "bad.toml"
    f.write_text(toml)
    with pytest.raises(SetupError, match=message):
        load_setup(f)


def test_unknown_preset_lists_known_ones():
    with pytest.raises(SetupError, match="known presets: .*thesis-1.10-deflectometry"):
        load_setup("thesis-9.9-nothing")
