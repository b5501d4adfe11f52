"""Property test: the command line and the TOML loaders under generated arguments and files.

Whatever the arguments — numbers that are zero, negative, huge, ``inf``, ``nan`` or not numbers at all; paths that do
not exist, are folders, hold garbage or hold a tiny valid image; TOML files with keys replaced by such values — a
command ends with exit code 0 or 2 and at most one ``error:`` line, never a traceback, and a loader returns or raises
a :class:`~scopetwin.scenes.errors.ScopetwinError`. Renders are replaced by stubs (the checks before them stay real),
so the
test is fast: few examples per command, tiny images.
"""

from __future__ import annotations

import contextlib
import io
import os
import tempfile
import traceback
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from scopetwin.cli import main
from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.io import write_image

#: Examples per test; SCOPETWIN_PROPERTY_EXAMPLES=500 (with SCOPETWIN_PROPERTY_RANDOM=1: fresh draws) digs deeper.
EXAMPLES = int(os.environ.get("SCOPETWIN_PROPERTY_EXAMPLES", "20"))
SETTINGS = settings(
    max_examples=EXAMPLES,
    deadline=None,
    derandomize=not os.environ.get("SCOPETWIN_PROPERTY_RANDOM"),  # by default the same examples every run
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)

SMALL = """
base = "thesis-2.8.1-angular"
[camera]
pixels = [136, 102]
pixel_pitch = 0.0465
[render]
spp = 4
"""

#: Texts a number option may get: valid, edge, out of range, non-finite, not numbers.
NUMBERS = st.sampled_from(
    ["1", "4", "16", "0", "-3", "-0", "2.5", "1e9", "1e400", "inf", "-inf", "nan", "abc", "", "0x10", "99999999999"]
)
#: TOML values a key may get.
TOML_VALUES = st.sampled_from(
    [
        "0",
        "-1",
        "3",
        "2.5",
        "1e11",
        "1e308",
        "-1e308",
        "inf",
        "-inf",
        "nan",
        '"abc"',
        "true",
        "[]",
        "[1, 2]",
        "[0, 0, 0]",
        "[-inf, inf]",
        "[1e308, 1e308]",
        "[100000, 100000]",
        "{ uniform = [-inf, inf] }",
        "{ normal = [0, nan] }",
        "{ fixed = 1e308 }",
    ]
)


@contextlib.contextmanager
def _folder() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="st-prop-") as d:
        yield Path(d)


def _paths(d: Path) -> dict[str, str]:
    """Files of every kind a path argument may name."""
    (d / "garbage.exr").write_bytes(b"not an exr\x00\xff" * 10)
    (d / "small.toml").write_text(SMALL)
    (d / "bad.toml").write_text("this is = = not toml\n[")
    (d / "folder").mkdir(exist_ok=True)
    write_image(d / "tiny.exr", np.full((6, 8), 0.5, np.float32))
    write_image(d / "nan.exr", np.full((102, 136), np.nan, np.float32))
    return {
        "missing": str(d / "missing.exr"),
        "garbage": str(d / "garbage.exr"),
        "folder": str(d / "folder"),
        "tiny": str(d / "tiny.exr"),
        "nan": str(d / "nan.exr"),
        "small": str(d / "small.toml"),
        "badtoml": str(d / "bad.toml"),
        "preset": "thesis-2.9.1-target-6x4",
        "grin": "thesis-7.5.2-grin-egfp",
        "unknown": "no-such-preset",
        "out": str(d / "out"),
        "outexr": str(d / "out.exr"),
        "json": str(d / "r.json"),
    }


def _check(argv: list[str]) -> None:
    """main(argv) ends with 0 or 2 and at most one error line; anything else fails with the traceback."""
    out, err = io.StringIO(), io.StringIO()
    code: int | None
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)  # "overflow encountered" is a silent wrong result
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse
            code = int(exc.code) if isinstance(exc.code, int) else 2
        except BaseException:
            pytest.fail(f"scopetwin {' '.join(argv)} raised:\n{traceback.format_exc()}")
    text = err.getvalue()
    errors = [line for line in text.splitlines() if "error:" in line]
    assert code in (0, 2), (argv, code, text)
    assert "Traceback" not in text, (argv, text)
    assert len(errors) <= 1, (argv, text)
    if code == 2:
        assert len(errors) == 1, (argv, text)


@pytest.fixture
def no_renders(monkeypatch: pytest.MonkeyPatch) -> None:
    """Renders replaced by black images of the requested size (every check before them stays real)."""
    import scopetwin.scenes.mitsuba.grin as grin
    import scopetwin.sim.measurement as measurement

    def fake_measurement(setup: Any, heights: Any, spp: int, seed: int, noise: bool, renderer: str = "") -> Any:
        cam = setup.camera_model
        return np.zeros((cam.ny, cam.nx), np.float32), 0.0

    def fake_grin(setup: Any, stack: Any, target: Any, spp: int = 16, width: Any = None, height: Any = None, **kw: Any):
        return np.zeros((height or setup.camera.height_px, width or setup.camera.width_px), np.float32)

    def fake_generate(plan: Any, out: Any, *args: Any, **kw: Any) -> dict[str, Any]:
        raise ScopetwinError("(test stub) the plan passed every check; not rendering")

    monkeypatch.setattr(measurement, "render_measurement", fake_measurement)  # the commands import them when run
    monkeypatch.setattr(grin, "render_image", fake_grin)
    import scopetwin.sim.datasets.store as store

    monkeypatch.setattr(store, "generate", fake_generate)


def _opt(name: str, values: st.SearchStrategy[str]) -> st.SearchStrategy[list[str]]:
    """An option with a value, or nothing."""
    return st.one_of(st.just([]), values.map(lambda v: [name, v]))


PATH_KEYS = st.sampled_from(["missing", "garbage", "folder", "tiny", "nan", "small", "badtoml", "preset", "unknown"])


@SETTINGS
@given(
    setup=PATH_KEYS,
    spp=_opt("--spp", NUMBERS),
    seed=_opt("--seed", NUMBERS),
    surface=st.one_of(st.just([]), PATH_KEYS.map(lambda k: ["--surface", k])),
)
@example(setup="small", spp=["--spp", "4"], seed=["--seed", "1"], surface=[])  # valid: reaches the (stub) render
def test_render(no_renders: None, setup: str, spp: list[str], seed: list[str], surface: list[str]) -> None:
    with _folder() as d:
        p = _paths(d)
        argv = ["render", p[setup], "--out", p["out"], "--renderer", "analytic", *spp, *seed]
        _check(argv + [p.get(v, v) for v in surface])


@SETTINGS
@given(image=PATH_KEYS, pattern=PATH_KEYS, overlay=st.booleans())
def test_markers(image: str, pattern: str, overlay: bool) -> None:
    with _folder() as d:
        p = _paths(d)
        extra = ["--overlay", str(d / "o.png")] if overlay else []
        _check(["markers", p[image], "--pattern", p[pattern], "--json", p["json"], *extra])


@SETTINGS
@given(image=PATH_KEYS, setup=PATH_KEYS, sigma=_opt("--sigma", NUMBERS))
def test_reconstruct(image: str, setup: str, sigma: list[str]) -> None:
    with _folder() as d:
        p = _paths(d)
        _check(["reconstruct", p[image], "--setup", p[setup], "--out", p["outexr"], *sigma])


@SETTINGS
@given(
    image=PATH_KEYS,
    target=st.one_of(st.just([]), PATH_KEYS.map(lambda k: ["--target", k])),
    focal=_opt("--focal-length", NUMBERS),
    pitch=_opt("--pixel-pitch", NUMBERS),
    nz=_opt("--nz-estimate", st.sampled_from(["0,0,1", "0,0,0", "nan,0,1", "1,2", "a,b,c", "inf,0,1"])),
)
def test_calibrate(image: str, target: list[str], focal: list[str], pitch: list[str], nz: list[str]) -> None:
    with _folder() as d:
        p = _paths(d)
        _check(["calibrate", p[image], *[p.get(v, v) for v in target], *focal, *pitch, *nz])


@SETTINGS
@given(
    preset=st.sampled_from(["grin", "preset", "unknown", "badtoml", "missing"]),
    image=_opt("--image", st.sampled_from(["dots-25", "lines-8", "nope"])),
    spp=_opt("--spp", NUMBERS),
    size=st.sampled_from([[], ["--width", "8", "--height", "6"], ["--width", "0"], ["--height", "-5"]]),
    offset=_opt("--target-offset", st.sampled_from(["0", "nan", "inf", "0.5"])),
)
@example(
    preset="grin", image=["--image", "dots-25"], spp=["--spp", "1"], size=["--width", "8", "--height", "6"], offset=[]
)
def test_optics_grin(
    no_renders: None, preset: str, image: list[str], spp: list[str], size: list[str], offset: list[str]
) -> None:
    with _folder() as d:
        p = _paths(d)
        offset_args = offset + ["0"] if offset else []
        _check(["optics", "grin", p[preset], *image, "--out", p["outexr"], *spp, *size, *offset_args])


# -- generated TOML files ------------------------------------------------------------------------------------------
SETUP_KEYS = [
    ("camera", "pixels"),
    ("camera", "pixel_pitch"),
    ("camera", "focal_length"),
    ("camera", "origin"),
    ("camera", "c2"),
    ("pattern", "pitch"),
    ("pattern", "markers"),
    ("pattern", "radius"),
    ("render", "spp"),
    ("render", "seed"),
    ("sensor", "bit_depth"),
    ("sensor", "exposure_s"),
    ("substrate", "size"),
    ("substrate.surface", "range_um"),
    ("substrate.surface", "grid"),
    ("substrate.surface", "correlation_length"),
    ("nonsense", "key"),
]


def _toml(base: str, changes: list[tuple[tuple[str, str], str]]) -> str:
    """A TOML file: ``base = ...`` plus one table per changed key (the last value of a key wins)."""
    tables: dict[str, dict[str, str]] = {}
    for (table, key), value in changes:
        tables.setdefault(table, {})[key] = value
    lines = [f'base = "{base}"'] if base else []
    for table, kv in tables.items():
        lines.append(f"[{table}]")
        lines += [f"{k} = {v}" for k, v in kv.items()]
    return "\n".join(lines) + "\n"


def _load(loader: Any, path: Path) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        try:
            loader(path)
        except ScopetwinError as exc:
            assert "\n" not in str(exc).strip(), str(exc)
        except BaseException:
            pytest.fail(f"{loader.__name__}({path.read_text()!r}) raised:\n{traceback.format_exc()}")


@SETTINGS
@given(
    base=st.sampled_from(["thesis-1.10-deflectometry", "thesis-2.9.1-target-6x4", "thesis-2.8.3-mirror"]),
    changes=st.lists(st.tuples(st.sampled_from(SETUP_KEYS), TOML_VALUES), min_size=1, max_size=3),
)
def test_setup_loader(base: str, changes: list[tuple[tuple[str, str], str]]) -> None:
    from scopetwin.scenes.setup import load_setup

    with _folder() as d:
        path = d / "s.toml"
        path.write_text(_toml(base, changes))
        _load(load_setup, path)


GRIN_KEYS = [
    ("rod1", "length"),
    ("rod1", "step_mm"),
    ("rod1", "radius"),
    ("rod2.profile", "nr2"),
    ("object", "distance"),
    ("object", "field_radius"),
    ("array", "nx"),
    ("array", "pitch"),
    ("camera", "width_px"),
    ("camera", "pixel_um"),
    ("aperture", "na_object"),
    ("top", "wavelength_nm"),
]


@SETTINGS
@given(
    base=st.sampled_from(["thesis-8.3.2-grin-realized", "thesis-7.5.2-grin-egfp"]),
    changes=st.lists(st.tuples(st.sampled_from(GRIN_KEYS), TOML_VALUES), min_size=1, max_size=3),
)
def test_grin_setup_loader(base: str, changes: list[tuple[tuple[str, str], str]]) -> None:
    from scopetwin.scenes.grin import load_grin_setup

    top = [f"{k} = {v}" for (t, k), v in changes if t == "top"]
    text = _toml(base, [c for c in changes if c[0][0] != "top"]).replace(
        f'base = "{base}"', f'base = "{base}"\n' + "\n".join(top)
    )
    with _folder() as d:
        path = d / "g.toml"
        path.write_text(text)
        _load(load_grin_setup, path)


RIG_KEYS = [
    ("devices.x", "travel_mm"),
    ("devices.x", "max_velocity_mm_s"),
    ("devices.x", "position_mm"),
    ("devices.focus", "range_um"),
    ("devices.focus", "position_um"),
    ("devices.uv", "max_current_ma"),
    ("devices.uv", "kind"),
    ("devices.x", "driver"),
]


@SETTINGS
@given(changes=st.lists(st.tuples(st.sampled_from(RIG_KEYS), TOML_VALUES), min_size=1, max_size=3))
def test_rig_loader(changes: list[tuple[tuple[str, str], str]]) -> None:
    from scopetwin.instrument.rig import load_rig

    base = {
        "devices.x": {
            "kind": '"stage"',
            "driver": '"sim"',
            "travel_mm": "[0.0, 150.0]",
            "max_velocity_mm_s": "50.0",
        },
        "devices.focus": {"kind": '"focus"', "driver": '"sim"', "range_um": "[0.0, 400.0]"},
        "devices.uv": {"kind": '"light"', "driver": '"sim"', "max_current_ma": "500.0"},
    }
    for (table, key), value in changes:
        base[table][key] = value
    text = "\n".join(f"[{t}]\n" + "\n".join(f"{k} = {v}" for k, v in kv.items()) for t, kv in base.items()) + "\n"

    def load_and_close(path: Path) -> None:
        load_rig(path).close()

    load_and_close.__name__ = "load_rig"
    with _folder() as d:
        path = d / "rig.toml"
        path.write_text(text)
        _load(load_and_close, path)


DATASET_KEYS = [
    ("dataset", "count"),
    ("dataset", "spp"),
    ("dataset", "master_seed"),
    ("dataset", "kind"),
    ("vary", "surface_range_um"),
    ("vary", "camera_shift"),
    ("vary", "exposure_fill"),
    ("setup.camera", "pixels"),
    ("setup.camera", "pixel_pitch"),
]


def _dataset_toml(changes: list[tuple[tuple[str, str], str]]) -> str:
    tables: dict[str, dict[str, str]] = {
        "dataset": {
            "kind": '"deflectometry"',
            "setup": '"thesis-1.10-deflectometry"',
            "count": "2",
            "master_seed": "1",
            "spp": "1",
        },
        "setup.camera": {"pixels": "[68, 51]", "pixel_pitch": "0.093"},
        "vary": {"surface_range_um": "{ uniform = [20.0, 60.0] }"},
    }
    for (table, key), value in changes:
        tables[table][key] = value
    return "\n".join(f"[{t}]\n" + "\n".join(f"{k} = {v}" for k, v in kv.items()) for t, kv in tables.items()) + "\n"


@SETTINGS
@given(changes=st.lists(st.tuples(st.sampled_from(DATASET_KEYS), TOML_VALUES), min_size=1, max_size=3))
def test_dataset_config_loader(changes: list[tuple[tuple[str, str], str]]) -> None:
    from scopetwin.sim.datasets.config import load_config

    with _folder() as d:
        path = d / "cfg.toml"
        path.write_text(_dataset_toml(changes))
        _load(load_config, path)


@settings(SETTINGS, max_examples=max(1, EXAMPLES // 2))
@given(
    changes=st.lists(st.tuples(st.sampled_from(DATASET_KEYS), TOML_VALUES), min_size=0, max_size=2),
    count=_opt("--count", NUMBERS),
    indices=_opt("--indices", st.sampled_from(["0:1", "1:0", "a:b", "0:99999999999", "-1:2"])),
)
def test_dataset_generate(no_renders: None, changes: list[Any], count: list[str], indices: list[str]) -> None:
    """The whole config check and the plan (every sample's setup) are real; only the rendering is a stub."""
    with _folder() as d:
        path = d / "cfg.toml"
        path.write_text(_dataset_toml(changes))
        _check(
            ["dataset", "generate", str(path), "--out", str(d / "ds"), "--workers", "0", "--quiet", *count, *indices]
        )
