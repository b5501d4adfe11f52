"""A property-based run over setups (TOML fragments), rigs, MDA sequences and dataset configs.

Hypothesis writes input files from the keys the loaders know and from values of every kind — numbers that are zero,
negative, tiny (1e-300), huge (1e300), ``inf``, ``nan``; strings; arrays and tables nested up to 4000 levels deep;
text that is not the format at all — and for rigs, devices on in-process emulators that stop answering after a few
requests. Whatever the input:

* the loader returns, or raises one :class:`~scopetwin.scenes.errors.ScopetwinError` — **no traceback** (no other
  exception, ``RecursionError`` included);
* it ends within a **bounded time** (a deadline per example; the rigs' device timeouts are 0.05 s);
* it leaves **nothing behind**: no file beside the inputs, no emulator thread still running;
* what it returns holds **finite numbers** only (a setup that loads has no ``inf``, ``nan``, or a number of 1e300).

The example counts keep the file under a minute on two cores (the rigs' device timeouts are 0.05 s);
``SCOPETWIN_PROPERTY_EXAMPLES=200`` digs deeper, ``SCOPETWIN_PROPERTY_RANDOM=1`` draws fresh examples.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from datetime import timedelta
from pathlib import Path
from typing import Any

import yaml
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from scopetwin.scenes.errors import ScopetwinError

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = int(os.environ.get("SCOPETWIN_PROPERTY_EXAMPLES", "25"))
SETTINGS = settings(
    max_examples=EXAMPLES,
    deadline=timedelta(seconds=10),  # no hang: every example ends within 10 s
    derandomize=not os.environ.get("SCOPETWIN_PROPERTY_RANDOM"),
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
#: Most seconds one load may take (far above a normal load; a hang or an unbounded read is far beyond it).
BUDGET_S = 8.0

# -- values ---------------------------------------------------------------------------------------------------------
NUMBERS = st.one_of(
    st.sampled_from([0, -1, 1, 2, 3, 4, 16, 2**31, 2**63 - 1, -(2**63)]),
    st.sampled_from([0.0, -0.0, 1e-300, -1e-300, 1e300, -1e300, math.inf, -math.inf, math.nan, 0.5, 2.5, 40.0]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
)
SCALARS = st.one_of(NUMBERS, st.booleans(), st.text(max_size=12), st.sampled_from(["emu://pi-gcs", "/dev/zero", ""]))
VALUES = st.recursive(
    SCALARS,
    lambda inner: st.one_of(
        st.lists(inner, max_size=4),
        st.dictionaries(st.sampled_from(["a", "b", "x", "kind", "range"]), inner, max_size=3),
    ),
    max_leaves=12,
)
#: Raw TOML text for a value: nesting deep enough to break a recursive parser, and things that are not TOML.
DEEP = st.sampled_from([1, 2, 63, 64, 65, 200, 1500, 4000])
RAW = st.one_of(
    DEEP.map(lambda n: "[" * n + "1" + "]" * n),
    DEEP.map(lambda n: "{a = " * n + "1" + "}" * n),
    st.sampled_from(["nan", "inf", "-inf", "1e999", "[1, 2", "{", '"\\ud800"', "0x", "'''", "= =", "[[]]"]),
)


def toml_value(value: Any) -> str:
    """``value`` as TOML text (inline arrays and tables; non-finite floats as ``nan``, ``inf``, ``-inf``)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    return "{" + ", ".join(f"{json.dumps(str(k))} = {toml_value(v)}" for k, v in value.items()) + "}"


def _entry(keys: list[str]) -> st.SearchStrategy[tuple[str, str]]:
    """A ``dotted.key = value`` line: a key the loader knows (or a new one), a value of any kind or raw text."""
    key = st.one_of(st.sampled_from(keys), st.from_regex(r"[a-z_]{1,8}(\.[a-z_]{1,8}){0,2}", fullmatch=True))
    return st.tuples(key, st.one_of(VALUES.map(toml_value), RAW))


def _lines(entries: list[tuple[str, str]]) -> str:
    return "".join(f"{key} = {value}\n" for key, value in entries)


# -- the checks -----------------------------------------------------------------------------------------------------
@contextmanager
def _folder() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="st-inputs-") as d:
        yield Path(d)


def _non_finite(data: Any) -> list[Any]:
    """Numbers in ``data`` (a model dump) that are not finite or are beyond 1e15 in size."""
    bad, stack = [], [data]
    while stack:
        item = stack.pop()
        if isinstance(item, dict):
            stack.extend(item.values())
        elif isinstance(item, list | tuple):
            stack.extend(item)
        elif isinstance(item, float) and not (math.isfinite(item) and abs(item) <= 1e15):
            bad.append(item)
    return bad


def _holds(load: Callable[[], Any], folder: Path, inputs: set[str]) -> Any:
    """``load()`` returns or raises a ScopetwinError, in bounded time, leaving only ``inputs`` and no new thread."""
    threads = threading.active_count()
    t0 = time.monotonic()
    try:
        result = load()
        event("loaded")
    except ScopetwinError as exc:
        text = str(exc)
        assert text and "\n" not in text, f"the error is not one line: {text!r}"
        event(f"refused: {type(exc).__name__}")
        result = None
    seconds = time.monotonic() - t0
    assert seconds < BUDGET_S, f"took {seconds:.1f} s"
    left = {p.name for p in folder.iterdir()} - inputs
    assert not left, f"left behind: {sorted(left)}"
    deadline = time.monotonic() + 3.0  # an emulator's thread ends within its stop() (2 s join at most)
    while threading.active_count() > threads and time.monotonic() < deadline:
        time.sleep(0.02)
    assert threading.active_count() <= threads, [t.name for t in threading.enumerate()]
    return result


# -- setups ---------------------------------------------------------------------------------------------------------
SETUP_KEYS = [
    "camera.pixel_pitch",
    "camera.focal_length",
    "camera.pixels",
    "camera.origin",
    "camera.phi",
    "camera.r_0",
    "camera.c2",
    "camera.f_number",
    "camera.image_distance",
    "pattern.pitch",
    "pattern.radius",
    "pattern.markers",
    "substrate.size",
    "substrate.roi_length",
    "substrate.surface.range_um",
    "substrate.surface.grid",
    "substrate.surface.correlation_length",
    "sensor.exposure_s",
    "sensor.full_well_e",
    "sensor.photons_per_unit_s",
    "render.spp",
    "mirror.size",
    "calibration.camera.shift_mm",
]
PRESETS = st.sampled_from(
    ["thesis-1.10-deflectometry", "thesis-2.8.1-angular", "thesis-2.8.3-mirror", "/dev/zero", "missing.toml", "x"]
)


@SETTINGS
@given(
    base=PRESETS, entries=st.lists(_entry(SETUP_KEYS), max_size=4), tail=st.one_of(st.just(""), st.text(max_size=30))
)
def test_setups(base: str, entries: list[tuple[str, str]], tail: str) -> None:
    from scopetwin.scenes.setup import load_setup

    with _folder() as d:
        path = d / "setup.toml"
        path.write_text(f'base = "{base}"\n' + _lines(entries) + tail, encoding="utf-8")
        setup = _holds(lambda: load_setup(path), d, {"setup.toml"})
    if setup is not None:
        assert not _non_finite(setup.model_dump()), _non_finite(setup.model_dump())
        assert 1e-4 <= setup.camera.pixel_pitch <= 1.0


# -- dataset configs ------------------------------------------------------------------------------------------------
DATASET_KEYS = [
    "dataset.count",
    "dataset.spp",
    "dataset.master_seed",
    "dataset.kind",
    "dataset.setup",
    "vary.surface_range_um",
    "vary.camera_shift",
    "vary.exposure_fill",
    "setup.camera.pixels",
    "setup.camera.pixel_pitch",
]
DATASET = (
    '[dataset]\nkind = "deflectometry"\nsetup = "thesis-1.10-deflectometry"\ncount = 2\nmaster_seed = 1\nspp = 1\n'
    "[setup.camera]\npixels = [68, 51]\npixel_pitch = 0.093\n[vary]\nsurface_range_um = { uniform = [20.0, 60.0] }\n"
)


@SETTINGS
@given(
    entries=st.lists(_entry(DATASET_KEYS), max_size=3),
    sets=st.lists(st.tuples(st.sampled_from(DATASET_KEYS), st.one_of(VALUES.map(toml_value), RAW)), max_size=2),
)
def test_dataset_configs(entries: list[tuple[str, str]], sets: list[tuple[str, str]]) -> None:
    from scopetwin.sim.datasets.config import load_config

    with _folder() as d:
        path = d / "dataset.toml"
        # the generated keys go first, as top-level dotted keys (a table they name again is a TOML error, fine)
        path.write_text(_lines(entries) + DATASET)
        overrides = [f"{k}={v}" for k, v in sets]
        config = _holds(lambda: load_config(path, overrides=overrides), d, {"dataset.toml"})
    if config is not None:  # its own numbers are finite (the setup overrides are checked as each sample's setup)
        typed = {k: v for k, v in config.model_dump().items() if k != "setup"}
        assert not _non_finite(typed), _non_finite(typed)


# -- MDA sequences --------------------------------------------------------------------------------------------------
MDA_VALUES = st.one_of(NUMBERS, st.text(max_size=6))
CHANNEL = st.fixed_dictionaries(
    {"config": st.sampled_from(["uv", "deep_red", "nope", ""]), "group": st.just("Channel")},
    optional={"exposure": MDA_VALUES, "z_offset": MDA_VALUES, "acquire_every": MDA_VALUES},
)
SEQUENCES = st.fixed_dictionaries(
    {},
    optional={
        "channels": st.lists(CHANNEL, max_size=3),
        "z_plan": st.one_of(
            st.fixed_dictionaries({"range": MDA_VALUES, "step": MDA_VALUES}),
            st.fixed_dictionaries({"top": MDA_VALUES, "bottom": MDA_VALUES, "step": MDA_VALUES}),
            st.fixed_dictionaries({"absolute": st.lists(MDA_VALUES, max_size=4)}),
        ),
        "time_plan": st.fixed_dictionaries({"interval": MDA_VALUES, "loops": MDA_VALUES}),
        "stage_positions": st.lists(
            st.fixed_dictionaries({"x": MDA_VALUES, "y": MDA_VALUES, "z": MDA_VALUES}), max_size=3
        ),
        "grid_plan": st.fixed_dictionaries({"rows": MDA_VALUES, "columns": MDA_VALUES}),
        "axis_order": st.sampled_from(["tpgcz", "pcz", "x", ""]),
        "metadata": VALUES,
    },
)


def _json_text(data: Any) -> str:
    return json.dumps(data, allow_nan=True)


@SETTINGS
@given(
    data=SEQUENCES,
    form=st.sampled_from(["json", "yaml", "deep-json", "deep-yaml", "garbage"]),
    depth=DEEP,
)
def test_mda_sequences(data: dict[str, Any], form: str, depth: int) -> None:
    from scopetwin.cli.rig import mda_size
    from scopetwin.instrument.mdaplan import load_sequence

    deep = "[" * depth + "]" * depth
    texts = {
        "json": ("seq.json", _json_text(data)),
        "yaml": ("seq.yaml", yaml.safe_dump(data)),
        "deep-json": ("seq.json", '{"metadata": ' + deep + "}"),
        "deep-yaml": ("seq.yaml", "metadata: " + deep + "\n"),
        "garbage": ("seq.json", _json_text(data)[: max(1, len(_json_text(data)) // 2)]),
    }
    name, text = texts[form]
    with _folder() as d:
        path = d / name
        path.write_text(text)

        def load() -> Any:
            sequence = load_sequence(path)
            return mda_size(str(ROOT / "rigs" / "sim-cmu.toml"), None, sequence)  # sized in closed form: no hang

        _holds(load, d, {name})


# -- rigs -----------------------------------------------------------------------------------------------------------
RIG_FIELDS = {
    "stage": ["travel_mm", "max_velocity_mm_s", "position_mm", "velocity_mm_s", "axis"],
    "focus": ["range_um", "position_um", "voltage_range_v", "channel", "model"],
    "light": ["max_current_ma", "channel", "current_step_ma", "wavelength_nm"],
    "camera": ["sensor_shape", "exposure_range_s", "pixel_size_um", "magnification", "seed"],
}
SAFE = {
    ("stage", "sim"): "travel_mm = [0.0, 150.0]\nmax_velocity_mm_s = 50.0\n",
    ("stage", "pi-gcs"): 'port = "{port}"\ntravel_mm = [0.0, 150.0]\n',
    ("focus", "sim"): "range_um = [0.0, 400.0]\n",
    ("focus", "jena-piezo"): 'port = "{port}"\n',
    ("light", "sim"): "max_current_ma = 500.0\n",
    ("light", "fpga-board"): 'port = "{port}"\nchannel = 0\nmax_current_ma = 500.0\n',
    ("camera", "sim"): "sensor_shape = [16, 16]\n",
}
EMULATOR_OF = {"pi-gcs": "pi-gcs", "jena-piezo": "jena-piezo", "fpga-board": "fpga-board"}
DEVICE = st.tuples(
    st.sampled_from(sorted(SAFE)),
    st.sampled_from(["none", "silent", "garbage", "flood", "drop"]),
    st.integers(0, 12),
    st.lists(
        st.tuples(st.sampled_from(sorted({f for v in RIG_FIELDS.values() for f in v})), VALUES.map(toml_value)),
        max_size=2,
    ),
)


def _rig_text(devices: list[tuple[tuple[str, str], str, int, list[tuple[str, str]]]]) -> str:
    parts = []
    for i, ((kind, driver), fault, after, changes) in enumerate(devices):
        port = f"emu://{EMULATOR_OF.get(driver, 'none')}?fault={fault}&fault_after={after}"
        body = SAFE[(kind, driver)].format(port=port)
        fields = dict(line.split(" = ", 1) for line in body.splitlines())
        fields.update(dict(changes))
        lines = "".join(f"{k} = {v}\n" for k, v in fields.items())
        parts.append(f'[devices.d{i}]\nkind = "{kind}"\ndriver = "{driver}"\ntimeout_s = 0.05\n{lines}')
    return "".join(parts)


def _open_and_close(path: Path) -> Any:
    from scopetwin.instrument.rig import open_rig

    with open_rig(path) as rig:
        return rig.describe()


#: A device on an emulator that may stop answering, with its fields as shipped (the fields vary in test_sim_rigs).
FAULTY = st.tuples(DEVICE.map(lambda t: t[0]), DEVICE.map(lambda t: t[1]), st.integers(0, 12), st.just([]))


@SETTINGS
@given(devices=st.lists(st.one_of(FAULTY, DEVICE), min_size=1, max_size=3), tail=st.sampled_from(["", "x = [[1]]\n"]))
def test_rigs(devices: list[Any], tail: str) -> None:
    """Rigs opened and closed: sim devices and drivers on emulators that may stop answering after a few requests."""
    with _folder() as d:
        path = d / "rig.toml"
        path.write_text(tail + _rig_text(devices))
        info = _holds(lambda: _open_and_close(path), d, {"rig.toml"})
    if info is not None:
        assert not _non_finite(info), _non_finite(info)


@settings(SETTINGS, max_examples=EXAMPLES)
@given(
    devices=st.lists(
        st.tuples(
            st.sampled_from([k for k in SAFE if k[1] == "sim"]), st.just("none"), st.just(0), DEVICE.map(lambda t: t[3])
        ),
        min_size=1,
        max_size=3,
    ),
    tail=st.one_of(st.just(""), RAW.map(lambda r: f"x = {r}\n")),
)
def test_sim_rigs(devices: list[Any], tail: str) -> None:
    """Rigs of simulated devices only (fast): every field of every kind with a value of any kind."""
    with _folder() as d:
        path = d / "rig.toml"
        path.write_text(tail + _rig_text(devices))
        info = _holds(lambda: _open_and_close(path), d, {"rig.toml"})
    if info is not None:
        assert not _non_finite(info), _non_finite(info)
