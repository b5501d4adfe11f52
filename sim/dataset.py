"""Synthetic datasets at scale: many rendered measurements with exact truth, on Dask or in-process.

A dataset is described by a TOML config (``examples/datasets/*.toml``)::

    [dataset]
    kind = "deflectometry"          # deflectometry | calibration | grin | cmu
    setup = "thesis-1.10-deflectometry"   # preset name or setup TOML (relative to the config)
    count = 8
    master_seed = 1
    spp = 16
    noise = true                    # EMVA 1288 sensor model (seed §1.11 camera class)

    [setup]                         # fixed overrides merged into the setup (any setup field)
    camera.pixels = [680, 512]

    [vary]                          # what varies from sample to sample, and how
    surface_range_um = { uniform = [20.0, 60.0] }
    camera_shift = { normal = [0.0, 0.2] }

A ``cmu`` sample (seed Part II, §5.1-§5.2) is one image per channel of the four-channel unit
(``scenes.mitsuba.cmu``), each camera at its own refocused image distance (plus ``channel_defocus``),
offset and tilt; the splitters' modelled bows and residual seeds vary per sample; ``[cmu]`` picks the
channels, a sensor window and the tube-lens stop (:class:`CmuSection`). Keys with a ``per`` group
(``bow_*``/``residual_rms_um``: each splitter, ``channel_*``: each channel) are drawn independently
for every member, so one distribution describes e.g. all four camera offsets.

Every distribution is one of ``fixed``, ``uniform = [lo, hi]``, ``normal = [mean, std]``,
``loguniform = [lo, hi]``, ``choice = [...]`` or ``sweep = [...]``; all ``sweep`` keys form a
cartesian grid that sample i walks through (i modulo the grid size), repeated with fresh seeds.
The config is checked completely before any work starts: unknown keys, a distribution whose
support leaves the key's domain (a negative range, a viewing angle above 90 degrees) and any
sample whose setup would be invalid are rejected with a message naming the key.

Determinism: every random quantity of sample i comes from ``SeedSequence([master_seed, i,
crc32(name)])``, so sample i is the same bytes whatever worker renders it, in whatever order,
alone or with others (seed-independent of the count and of the other samples).

Layout of a dataset folder::

    DIR/dataset.json          the normalised config (what ``resume`` reads)
    DIR/manifest.jsonl        one JSON line per finished sample (hashes + host, worker, time)
    DIR/samples/000000/       one folder per sample: image.exr, truth.json, surface.exr,
                              normals.exr (deflectometry), preview.png, sample.json (hashes);
                              'cmu': image_<channel>.exr per channel, height_<element>.exr

A sample folder is written under a temporary name in ``DIR/samples`` and renamed into place
when complete (atomic on POSIX file systems); sample files hold no timestamps or host names
(those are in the manifest). ``resume`` removes temporary folders, re-lists finished samples
the manifest lost (a killed client), and renders only what is missing; ``verify`` checks every
sample against the manifest and its own hashes.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import math
import os
import shutil
import socket
import tempfile
import time
import tomllib
import zlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from scenes.errors import ScopetwinError, SetupError

FORMAT_VERSION = 1
CONFIG_FILE = "dataset.json"
MANIFEST = "manifest.jsonl"
SAMPLES = "samples"
TMP_PREFIX = ".tmp-"
SAMPLE_FILE = "sample.json"
KINDS = ("deflectometry", "calibration", "grin", "cmu")


class DatasetError(ScopetwinError, ValueError):
    """A dataset config, folder or request that cannot be used; the message names the key or file."""


# -- distributions --------------------------------------------------------------------------------
class _Model(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


Scalar = float | int | str | bool
Value = Scalar | list[float]


class Dist(_Model):
    """One distribution: exactly one of the fields is given."""

    fixed: Value | None = None
    uniform: tuple[float, float] | None = None
    normal: tuple[float, float] | None = None
    loguniform: tuple[float, float] | None = None
    choice: list[Value] | None = None
    sweep: list[Value] | None = None

    @model_validator(mode="after")
    def _check(self) -> Dist:
        given = [k for k in type(self).model_fields if getattr(self, k) is not None]
        if len(given) != 1:
            raise ValueError(
                f"give exactly one of fixed, uniform, normal, loguniform, choice, sweep (got "
                f"{', '.join(given) or 'none'})"
            )
        if self.uniform is not None and not self.uniform[0] <= self.uniform[1]:
            raise ValueError(f"uniform needs lo <= hi, got {list(self.uniform)}")
        if self.normal is not None and not self.normal[1] >= 0:
            raise ValueError(f"normal needs a standard deviation >= 0, got {self.normal[1]}")
        if self.loguniform is not None and not 0 < self.loguniform[0] <= self.loguniform[1]:
            raise ValueError(f"loguniform needs 0 < lo <= hi, got {list(self.loguniform)}")
        for name in ("choice", "sweep"):
            v = getattr(self, name)
            if v is not None and len(v) == 0:
                raise ValueError(f"{name} needs at least one value")
        return self

    @property
    def kind(self) -> str:
        return next(k for k in type(self).model_fields if getattr(self, k) is not None)

    def values(self) -> list[Value] | None:
        """The finite set of values (fixed, choice, sweep) or None for a continuous distribution."""
        if self.fixed is not None:
            return [self.fixed]
        return self.choice if self.choice is not None else self.sweep

    def support(self) -> tuple[float, float] | None:
        """Numeric bounds of a continuous distribution (normal: unbounded)."""
        if self.uniform is not None:
            return self.uniform
        if self.loguniform is not None:
            return self.loguniform
        if self.normal is not None:
            return (self.normal[0], self.normal[0]) if self.normal[1] == 0 else (-math.inf, math.inf)
        return None

    def draw(self, rng: np.random.Generator, size: int) -> list[Any]:
        """``size`` independent draws (a sweep value is chosen by the caller, not here)."""
        if self.uniform is not None:
            return rng.uniform(*self.uniform, size).tolist()
        if self.normal is not None:
            return rng.normal(*self.normal, size).tolist()
        if self.loguniform is not None:
            lo, hi = np.log(self.loguniform)
            return np.exp(rng.uniform(lo, hi, size)).tolist()
        if self.choice is not None:
            return [self.choice[int(k)] for k in rng.integers(0, len(self.choice), size)]
        raise AssertionError("fixed and sweep values are not drawn")


@dataclass(frozen=True)
class Domain:
    """Where a varied quantity may lie, which kinds use it, and how many components it has."""

    lo: float
    hi: float
    lo_open: bool
    hi_open: bool
    kinds: tuple[str, ...]
    dims: int
    unit: str
    text: str
    strings: tuple[str, ...] | dict[str, tuple[str, ...]] = ()
    per: Literal["", "splitter", "channel"] = ""

    def names(self, kind: str) -> tuple[str, ...]:
        """The allowed names of a string-valued quantity for samples of ``kind`` (empty: numeric)."""
        return self.strings.get(kind, ()) if isinstance(self.strings, dict) else self.strings

    def contains(self, v: float) -> bool:
        if math.isinf(v) and v in (self.lo, self.hi):  # an unbounded distribution on an unbounded domain
            return True
        above = v > self.lo if self.lo_open else v >= self.lo
        below = v < self.hi if self.hi_open else v <= self.hi
        return bool(above and below)

    def describe(self) -> str:
        return f"{'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"


_INF = math.inf
_PART1 = ("deflectometry", "calibration")
_SURFACE_KINDS = ("random", "plane", "sphere", "saddle", "cylinder")
DOMAINS: dict[str, Domain] = {
    "surface_range_um": Domain(0, _INF, False, True, ("deflectometry",), 1, "µm", "peak-to-valley range (§1.9)"),
    "surface_correlation_length": Domain(
        0, _INF, True, True, ("deflectometry",), 1, "mm", "low-pass correlation length (§1.9)"
    ),
    "surface_kind": Domain(0, 0, False, False, ("deflectometry",), 1, "", "surface generator", strings=_SURFACE_KINDS),
    "view_angle_deg": Domain(
        0, 90, True, False, ("calibration",), 1, "deg", "camera elevation over the target (§2.8.2 angle scan)"
    ),
    "view_distance": Domain(0, _INF, True, True, ("calibration",), 1, "mm", "camera distance from the target centre"),
    "camera_shift": Domain(-_INF, _INF, True, True, _PART1, 3, "mm", "camera centre jitter, per axis"),
    "camera_rotation": Domain(-_INF, _INF, True, True, _PART1, 3, "rad", "camera rotation vector, per axis"),
    "f_number": Domain(0, _INF, True, True, _PART1, 1, "", "thin-lens f-number"),
    "defocus": Domain(-_INF, _INF, True, True, _PART1, 1, "mm", "plane in focus minus the nominal one"),
    "distortion_c2": Domain(-_INF, _INF, True, True, _PART1, 1, "1/mm", "radial distortion c2 (§2.5.1)"),
    "principal_offset": Domain(-_INF, _INF, True, True, _PART1, 2, "mm", "r_cs, per axis (§2.8.5)"),
    "exposure_fill": Domain(0, 1, True, False, (*_PART1, "cmu"), 1, "", "fraction of the full well at the image peak"),
    "exposure_s": Domain(0, _INF, True, True, _PART1, 1, "s", "exposure time"),
    "target": Domain(
        0,
        0,
        False,
        False,
        ("grin", "cmu"),
        1,
        "",
        "test object (grin: §8.5 target; cmu: §5.2.2 Siemens star or §5.1.2 dummy cells)",
        strings={"grin": ("dots-25", "grid-25", "grid-12.5", "lines-8"), "cmu": ("star", "cells")},
    ),
    "target_offset": Domain(-_INF, _INF, True, True, ("grin",), 2, "mm", "target offset from the axis, per axis"),
    "bow_range_um": Domain(
        0, _INF, False, True, ("cmu",), 1, "µm", "bow range of each beam splitter (§5.1.1)", per="splitter"
    ),
    "bow_scale": Domain(
        0, _INF, False, True, ("cmu",), 1, "", "factor on each splitter's bow range of the setup", per="splitter"
    ),
    "residual_rms_um": Domain(
        0, _INF, False, True, ("cmu",), 1, "µm", "RMS of each splitter's smooth residual", per="splitter"
    ),
    "channel_defocus": Domain(
        -_INF,
        _INF,
        True,
        True,
        ("cmu",),
        1,
        "mm",
        "camera distance minus the refocused image distance, per channel",
        per="channel",
    ),
    "channel_offset_px": Domain(
        -_INF,
        _INF,
        True,
        True,
        ("cmu",),
        2,
        "px",
        "camera offset (col, row) of each channel (Table 5.3)",
        per="channel",
    ),
    "channel_tilt_deg": Domain(
        -45, 45, False, False, ("cmu",), 1, "deg", "in-plane camera tilt of each channel (Table 5.4)", per="channel"
    ),
}


class VarySpec(_Model):
    """The varied quantities (see :data:`DOMAINS`); field order fixes the sweep order."""

    surface_range_um: Dist | None = None
    surface_correlation_length: Dist | None = None
    surface_kind: Dist | None = None
    view_angle_deg: Dist | None = None
    view_distance: Dist | None = None
    camera_shift: Dist | None = None
    camera_rotation: Dist | None = None
    f_number: Dist | None = None
    defocus: Dist | None = None
    distortion_c2: Dist | None = None
    principal_offset: Dist | None = None
    exposure_fill: Dist | None = None
    exposure_s: Dist | None = None
    target: Dist | None = None
    target_offset: Dist | None = None
    bow_range_um: Dist | None = None
    bow_scale: Dist | None = None
    residual_rms_um: Dist | None = None
    channel_defocus: Dist | None = None
    channel_offset_px: Dist | None = None
    channel_tilt_deg: Dist | None = None

    def items(self) -> list[tuple[str, Dist]]:
        return [(k, getattr(self, k)) for k in type(self).model_fields if getattr(self, k) is not None]


class DatasetSection(_Model):
    """The ``[dataset]`` table."""

    kind: Literal["deflectometry", "calibration", "grin", "cmu"]
    setup: str = Field(description="preset name or setup TOML path")
    count: int = Field(gt=0)
    master_seed: int = Field(ge=0)
    spp: int = Field(16, gt=0)
    noise: bool = False
    description: str = ""
    preview: bool = Field(True, description="write preview.png beside each image")


class GrinSection(_Model):
    """The ``[grin]`` table: image size of GRIN target images."""

    width: int | None = Field(None, gt=0)
    height: int | None = Field(None, gt=0)
    step_mm: float = Field(0.3, gt=0)


class CmuSection(_Model):
    """The ``[cmu]`` table: which channels, which part of the sensor, the tube-lens stop (seed §5.1.2)."""

    channels: list[str] | None = Field(None, min_length=1, description="default: every channel of the setup")
    window: tuple[int, int, int, int] | None = Field(None, description="(row0, col0, height, width) of the sensor")
    stop: bool = Field(False, description="the 4 mm aperture in front of every tube lens")
    n_pupil: int = Field(21, ge=5, le=101, description="pupil grid of the numpy tracer (refocus and truth)")


class DatasetConfig(_Model):
    """A whole dataset config (module docstring)."""

    dataset: DatasetSection
    setup: dict[str, Any] = Field(default_factory=dict)
    vary: VarySpec = VarySpec()
    grin: GrinSection = GrinSection()
    cmu: CmuSection = CmuSection()


# -- loading and validation -------------------------------------------------------------------------
def _loc(err: dict[str, Any]) -> str:
    return ".".join(str(p) for p in err["loc"] if not (isinstance(p, str) and "[" in p))


def _format(exc: ValidationError, label: str) -> str:
    err = exc.errors()[0]
    msg = err["msg"].removeprefix("Value error, ")
    if err["type"] == "extra_forbidden":
        msg = "unknown key"
    more = f" (and {len(exc.errors()) - 1} more problems)" if len(exc.errors()) > 1 else ""
    return f"dataset config {label}: key {_loc(err) or '(top level)'}: {msg}{more}"


def config_from_dict(
    data: dict[str, Any], label: str = "<dict>", base_dir: Path | None = None, count: int | None = None
) -> DatasetConfig:
    """Validate a config dictionary (schema, domains, kinds) and resolve a relative setup path.

    Raises
    ------
    DatasetError
        Unknown key, wrong type, impossible distribution, a key that does not apply to the kind.
    """
    data = json.loads(json.dumps(data))
    if count is not None:
        if count <= 0:
            raise DatasetError(f"--count must be > 0, got {count}")
        data.setdefault("dataset", {})["count"] = int(count)
    try:
        cfg = DatasetConfig.model_validate(data)
    except ValidationError as exc:
        raise DatasetError(_format(exc, label)) from None
    setup = cfg.dataset.setup
    if base_dir is not None and setup.endswith(".toml") and not Path(setup).is_absolute():
        cfg = cfg.model_copy(update={"dataset": cfg.dataset.model_copy(update={"setup": str(base_dir / setup)})})
    _check_domains(cfg, label)
    return cfg


def _check_domains(cfg: DatasetConfig, label: str) -> None:
    kind = cfg.dataset.kind
    for name, dist in cfg.vary.items():
        dom = DOMAINS[name]
        where = f"dataset config {label}: key vary.{name}"
        if kind not in dom.kinds:
            raise DatasetError(f"{where}: does not apply to {kind!r} samples (only to {', '.join(dom.kinds)})")
        values = dist.values()
        names = dom.names(kind)
        if names:
            if values is None:
                raise DatasetError(f"{where}: {dom.text} takes fixed, choice or sweep of names, not {dist.kind}")
            bad = [v for v in values if v not in names]
            if bad:
                raise DatasetError(f"{where}: impossible value {bad[0]!r} (known: {', '.join(names)})")
            continue
        if values is not None:
            flat = []
            for v in values:
                comps = v if isinstance(v, list) else [v]
                if isinstance(v, list) and len(v) != dom.dims:
                    raise DatasetError(f"{where}: a value needs {dom.dims} components, got {v}")
                if any(isinstance(c, bool | str) for c in comps):
                    raise DatasetError(f"{where}: values must be numbers, got {v!r}")
                flat += comps
            bad = [v for v in flat if not (math.isfinite(v) and dom.contains(v))]
            if bad:
                raise DatasetError(
                    f"{where}: impossible value {bad[0]} {dom.unit} (the {dom.text} must lie in {dom.describe()})"
                )
            continue
        lo, hi = dist.support()  # type: ignore[misc]
        if not (dom.contains(lo) and dom.contains(hi)):
            raise DatasetError(
                f"{where}: impossible distribution {dist.kind} {list(getattr(dist, dist.kind))}: it "
                f"can give values outside {dom.describe()} {dom.unit} (the {dom.text})"
            )
    if cfg.vary.exposure_fill is not None and cfg.vary.exposure_s is not None:
        raise DatasetError(f"dataset config {label}: key vary.exposure_s: give exposure_fill or exposure_s, not both")
    if cfg.vary.bow_range_um is not None and cfg.vary.bow_scale is not None:
        raise DatasetError(f"dataset config {label}: key vary.bow_scale: give bow_range_um or bow_scale, not both")
    for table, default in (("grin", GrinSection()), ("cmu", CmuSection())):
        if getattr(cfg, table) != default and kind != table:
            raise DatasetError(
                f"dataset config {label}: key {table}: the [{table}] table applies only to {table!r} "
                f"samples, not {kind!r}"
            )


def load_config(path: str | Path, count: int | None = None) -> DatasetConfig:
    """Read and validate a dataset config TOML (``count`` overrides ``[dataset] count``)."""
    p = Path(path)
    try:
        with open(p, "rb") as fh:
            data = tomllib.load(fh)
    except OSError as exc:
        raise DatasetError(f"cannot read dataset config {p}: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise DatasetError(f"dataset config {p} is not valid TOML: {exc}") from None
    return config_from_dict(data, str(p), p.resolve().parent, count)


# -- per-sample randomness --------------------------------------------------------------------------
def _sequence(master_seed: int, index: int, name: str) -> np.random.SeedSequence:
    return np.random.SeedSequence([int(master_seed), int(index), zlib.crc32(name.encode())])


def sample_rng(master_seed: int, index: int, name: str) -> np.random.Generator:
    """The generator of quantity ``name`` of sample ``index`` (independent of every other sample and name)."""
    return np.random.default_rng(_sequence(master_seed, index, name))


def sample_seed(master_seed: int, index: int, name: str) -> int:
    """A 31-bit seed for quantity ``name`` of sample ``index`` (surface, render, ...)."""
    return int(_sequence(master_seed, index, name).generate_state(1, dtype=np.uint32)[0] & 0x7FFFFFFF)


def _sweep_cell(cfg: DatasetConfig, index: int) -> dict[str, Value]:
    sweeps = [(k, d.sweep) for k, d in cfg.vary.items() if d.sweep is not None]
    if not sweeps:
        return {}
    sizes = [len(v) for _, v in sweeps]
    cell = np.unravel_index(index % int(np.prod(sizes)), sizes)
    return {k: v[int(c)] for (k, v), c in zip(sweeps, cell, strict=True)}


def draw_parameters(cfg: DatasetConfig, index: int, groups: dict[str, Sequence[str]] | None = None) -> dict[str, Any]:
    """The varied quantities of sample ``index`` (JSON-ready; vectors as lists).

    A quantity with a ``per`` group (:class:`Domain`) becomes ``{member: value}`` over ``groups[per]``
    (channels default to the unit's four); each member has its own generator (``name:member``), so a
    member's value does not depend on which other members the setup has.
    """
    cell = _sweep_cell(cfg, index)
    out: dict[str, Any] = {}
    for name, dist in cfg.vary.items():
        dom = DOMAINS[name]
        dims = dom.dims
        members = _members(dom, groups, name)
        if name in cell or dist.fixed is not None:
            v = cell.get(name, dist.fixed)
            v = v if (dims == 1 or isinstance(v, list)) else [v] * dims
            out[name] = v if members is None else {m: v for m in members}
            continue
        if members is None:
            vals = dist.draw(sample_rng(cfg.dataset.master_seed, index, name), dims)
            out[name] = vals[0] if dims == 1 else vals
            continue
        drawn = {m: dist.draw(sample_rng(cfg.dataset.master_seed, index, f"{name}:{m}"), dims) for m in members}
        out[name] = {m: (v[0] if dims == 1 else v) for m, v in drawn.items()}
    return out


def _members(dom: Domain, groups: dict[str, Sequence[str]] | None, name: str) -> list[str] | None:
    """The members a ``per`` quantity is drawn for (None: one value per sample)."""
    if not dom.per:
        return None
    given = (groups or {}).get(dom.per)
    if given is None and dom.per == "channel":
        from scenes.cmu.layout import CHANNEL_NAMES

        given = CHANNEL_NAMES
    if given is None:
        raise DatasetError(
            f"key vary.{name}: drawn per {dom.per}; the {dom.per} names come from the setup (use Plan.parameters)"
        )
    return list(given)


def sweep_size(cfg: DatasetConfig) -> int:
    """Number of cells of the sweep grid (1 without sweeps)."""
    return int(np.prod([len(d.sweep) for _, d in cfg.vary.items() if d.sweep is not None] or [1]))


# -- building a sample's setup ----------------------------------------------------------------------
def _merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out


def base_setup_dict(cfg: DatasetConfig) -> dict[str, Any]:
    """The setup (Part I) dictionary every sample starts from: the preset/TOML chain plus ``[setup]``."""
    from scenes.setup import resolve_toml

    try:
        data, _ = resolve_toml(cfg.dataset.setup)
    except SetupError as exc:
        raise DatasetError(f"dataset config: key dataset.setup: {exc}") from None
    kind = data.pop("kind", None)
    if kind not in (None, "setup"):
        raise DatasetError(
            f"dataset config: key dataset.setup: {cfg.dataset.setup!r} is a {kind!r} preset, not a "
            f"Part I setup (kind {cfg.dataset.kind!r})"
        )
    return _merge(data, cfg.setup)


def _rotation(rotvec: Sequence[float]) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.asarray(rotvec, dtype=np.float64)).as_matrix()


def part1_setup(cfg: DatasetConfig, base: dict[str, Any], index: int, params: dict[str, Any]):
    """The validated :class:`scenes.setup.Setup` of sample ``index`` (varied quantities applied)."""
    from scenes.setup import setup_from_dict

    d = json.loads(json.dumps(base))
    cam = d.setdefault("camera", {})
    master = cfg.dataset.master_seed
    if cfg.dataset.kind == "deflectometry":
        surf = d.setdefault("substrate", {}).setdefault("surface", {})
        surf["seed"] = sample_seed(master, index, "surface")
        for key, field in (
            ("surface_range_um", "range_um"),
            ("surface_correlation_length", "correlation_length"),
            ("surface_kind", "kind"),
        ):
            if key in params:
                surf[field] = params[key]
    if "view_angle_deg" in params or "view_distance" in params:
        if d.get("scene") != "target":
            raise DatasetError("dataset config: key vary.view_angle_deg: the viewing-angle scan needs a target scene")
        a = math.radians(float(params.get("view_angle_deg", 90.0)))
        dist = float(params.get("view_distance", math.dist(cam.get("origin", (0, 0, 0)), (0, 0, 0))))
        s, c = math.sin(a), math.cos(a)
        centre = np.asarray(d.get("pattern", {}).get("origin", (0.0, 0.0, 0.0)), dtype=np.float64)
        for k in ("r_0", "phi"):
            cam.pop(k, None)
        cam.update(
            origin=(centre + [0.0, -dist * c, dist * s]).tolist(),
            t_x=[1.0, 0.0, 0.0],
            t_y=[0.0, s, c],
            n_z=[0.0, -c, s],
        )
        cam.setdefault("image_distance", 28.0)
    if "camera_shift" in params:
        cam["origin"] = (np.asarray(cam["origin"], dtype=np.float64) + params["camera_shift"]).tolist()
    if "camera_rotation" in params:
        if cam.get("t_x") is None:
            raise DatasetError(
                "dataset config: key vary.camera_rotation: needs a camera given by its axes "
                "(t_x, t_y, n_z), not by r_0/phi"
            )
        rot = _rotation(params["camera_rotation"])
        for k in ("t_x", "t_y", "n_z"):
            cam[k] = (rot @ np.asarray(cam[k], dtype=np.float64)).tolist()
    if "f_number" in params:
        cam["f_number"] = params["f_number"]
    if "distortion_c2" in params:
        cam["c2"] = params["distortion_c2"]
    if "principal_offset" in params:
        cam["r_cs"] = list(params["principal_offset"])
    if "exposure_fill" in params:
        d.setdefault("sensor", {})["fill_fraction"] = params["exposure_fill"]
    if "exposure_s" in params:
        d.setdefault("sensor", {})["exposure_s"] = params["exposure_s"]
    d.setdefault("render", {}).update(
        spp=cfg.dataset.spp,
        seed=sample_seed(master, index, "render"),
        noise=bool(cfg.dataset.noise or "exposure_fill" in params or "exposure_s" in params),
    )
    d["name"] = f"{d.get('name', 'setup')}-sample-{index:06d}"
    try:
        setup = setup_from_dict(d, f"sample {index}")
        if "defocus" in params:
            g0 = setup.camera_model.focus_distance()
            if g0 is None:
                raise DatasetError(
                    "dataset config: key vary.defocus: needs a thin lens: set camera.f_number in "
                    "[setup] or vary f_number"
                )
            cam["focus_distance"] = g0 + float(params["defocus"])
            setup = setup_from_dict(d, f"sample {index}")
    except SetupError as exc:
        raise DatasetError(f"sample {index} (parameters {params}): {exc}") from None
    return setup


# -- the plan: everything the workers need, checked before any work ---------------------------------
def _capability(kind: str) -> None:
    """Raise when the renderer of a sample kind is not part of this installation."""
    if kind == "cmu":
        import importlib.util

        if importlib.util.find_spec("scenes.mitsuba.cmu") is None:
            raise DatasetError(
                "sample kind 'cmu' needs the four-channel microscope renderer "
                "(scenes.mitsuba.cmu, issue 8), which this installation does not have"
            )


@dataclass(frozen=True)
class Plan:
    """A validated config with its resolved base setup: what is sent to every worker."""

    config: DatasetConfig
    base: dict[str, Any]

    @classmethod
    def build(cls, cfg: DatasetConfig, indices: Iterable[int] | None = None, check: bool = True) -> Plan:
        """Resolve the base setup and (``check``) build every requested sample's setup to validate it."""
        _capability(cfg.dataset.kind)
        if cfg.dataset.kind == "grin":
            base = _grin_base(cfg)
        elif cfg.dataset.kind == "cmu":
            base = _cmu_base(cfg)
        else:
            base = base_setup_dict(cfg)
            scene = base.get("scene")
            want = {"deflectometry": ("deflectometry",), "calibration": ("target", "mirror")}[cfg.dataset.kind]
            if scene not in want:
                raise DatasetError(
                    f"dataset config: key dataset.setup: {cfg.dataset.setup!r} is a {scene!r} scene; "
                    f"{cfg.dataset.kind!r} samples need {' or '.join(want)}"
                )
        plan = cls(cfg, base)
        if check:
            for i in range(cfg.dataset.count) if indices is None else indices:
                plan.setup_of(i)
        return plan

    def to_json(self) -> dict[str, Any]:
        return {
            "format": FORMAT_VERSION,
            "config": self.config.model_dump(mode="json", exclude_none=True),
            "base_setup": self.base,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Plan:
        if data.get("format") != FORMAT_VERSION:
            raise DatasetError(f"dataset format {data.get('format')!r} is not supported (expected {FORMAT_VERSION})")
        return cls(config_from_dict(data["config"], CONFIG_FILE), data["base_setup"])

    def parameters(self, index: int) -> dict[str, Any]:
        groups = None
        if self.config.dataset.kind == "cmu":
            groups = {"splitter": list(self.base["splitters"]), "channel": _cmu_channels(self.config, self.base)}
        return draw_parameters(self.config, index, groups)

    def setup_of(self, index: int) -> Any:
        params = self.parameters(index)
        if self.config.dataset.kind == "grin":
            return _grin_setup(self, index, params)
        if self.config.dataset.kind == "cmu":
            return _cmu_sample(self, index, params)
        return part1_setup(self.config, self.base, index, params)


def _grin_base(cfg: DatasetConfig) -> dict[str, Any]:
    from scenes.grin.setup import load_grin_setup

    try:
        setup = load_grin_setup(cfg.dataset.setup, cfg.setup or None)
    except ScopetwinError as exc:
        raise DatasetError(f"dataset config: key dataset.setup / [setup]: {exc}") from None
    return json.loads(setup.to_json())


def _grin_setup(plan: Plan, index: int, params: dict[str, Any]) -> Any:
    from scenes.grin.setup import grin_setup_from_dict
    from scenes.grin.targets import target

    setup = grin_setup_from_dict(plan.base, f"sample {index}")
    tgt = target(str(params.get("target", "grid-25")), tuple(params.get("target_offset", (0.0, 0.0))))
    try:
        tgt.check_field(setup.object.field_radius)
    except ScopetwinError as exc:
        raise DatasetError(f"sample {index}: key vary.target_offset: {exc}") from None
    return setup, tgt


def _cmu_channels(cfg: DatasetConfig, base: dict[str, Any]) -> list[str]:
    """The channels a cmu sample renders, in the setup's order."""
    wanted = cfg.cmu.channels
    return [c for c in base["channels"] if wanted is None or c in wanted]


def _cmu_base(cfg: DatasetConfig) -> dict[str, Any]:
    """The unit every cmu sample starts from (preset/TOML plus ``[setup]``), with ``[cmu]`` checked against it."""
    from scenes.cmu.layout import load_cmu_setup

    try:
        setup = load_cmu_setup(cfg.dataset.setup, cfg.setup or None)
    except ScopetwinError as exc:
        raise DatasetError(f"dataset config: key dataset.setup / [setup]: {exc}") from None
    c = cfg.cmu
    if c.channels is not None:
        bad = [ch for ch in c.channels if ch not in setup.channels]
        if bad or len(set(c.channels)) != len(c.channels):
            what = f"unknown channel {bad[0]!r}" if bad else "a channel is named twice"
            raise DatasetError(f"dataset config: key cmu.channels: {what} (the setup has {', '.join(setup.channels)})")
    if c.window is not None:
        r0, c0, h, w = c.window
        cam = setup.camera
        if min(r0, c0) < 0 or min(h, w) < 1 or r0 + h > cam.height_px or c0 + w > cam.width_px:
            raise DatasetError(
                f"dataset config: key cmu.window: {list(c.window)} (row0, col0, height, width) must lie "
                f"inside the {cam.width_px} x {cam.height_px} px sensor"
            )
    return json.loads(setup.to_json())


@dataclass(frozen=True)
class CmuSample:
    """One cmu sample's unit and cameras: per channel the defocus (mm), tilt (deg) and offset (px, (col, row))."""

    setup: Any
    target: str
    channels: tuple[str, ...]
    defocus: dict[str, float]
    tilt_deg: dict[str, float]
    offset_px: dict[str, tuple[float, float]]
    exposure_fill: float | None


def _cmu_sample(plan: Plan, index: int, params: dict[str, Any]) -> CmuSample:
    """The unit of sample ``index``: the splitters' bows and residual seeds, the cells' seed, the camera poses.

    With the Siemens star, every channel's frame must lie inside the image at the nominal magnification
    f_tube / f_objective (the bows change it by < 2 %): checked here, before any work.
    """
    from scenes.cmu.layout import cmu_setup_from_dict

    cfg = plan.config
    master = cfg.dataset.master_seed
    d = json.loads(json.dumps(plan.base))
    for name, el in d["splitters"].items():
        if "bow_range_um" in params:
            el["bow_range_um"] = params["bow_range_um"][name]
        if "bow_scale" in params:
            el["bow_range_um"] = float(el.get("bow_range_um", 0.0)) * params["bow_scale"][name]
        if "residual_rms_um" in params:
            el["residual_rms_um"] = params["residual_rms_um"][name]
        el["residual_seed"] = sample_seed(master, index, f"residual:{name}")
    d.setdefault("cells", {})["seed"] = sample_seed(master, index, "cells")
    d["name"] = f"{d.get('name') or 'cmu'}-sample-{index:06d}"
    try:
        setup = cmu_setup_from_dict(d, f"sample {index}")
    except SetupError as exc:
        raise DatasetError(f"sample {index} (parameters {params}): {exc}") from None
    channels = tuple(_cmu_channels(cfg, plan.base))
    per = {k: params.get(k, {}) for k in ("channel_defocus", "channel_tilt_deg", "channel_offset_px")}
    sample = CmuSample(
        setup,
        str(params.get("target", "star")),
        channels,
        {c: float(per["channel_defocus"].get(c, 0.0)) for c in channels},
        {c: float(per["channel_tilt_deg"].get(c, 0.0)) for c in channels},
        {c: tuple(float(v) for v in per["channel_offset_px"].get(c, (0.0, 0.0))) for c in channels},
        params.get("exposure_fill"),
    )
    if sample.target == "star":
        _check_star_in_image(cfg, sample, index, params)
    return sample


def _image_box(cfg: DatasetConfig, setup: Any) -> tuple[int, int, int, int]:
    """(row0, col0, height, width) of the rendered part of the sensor."""
    return cfg.cmu.window or (0, 0, setup.camera.height_px, setup.camera.width_px)


def _check_star_in_image(cfg: DatasetConfig, sample: CmuSample, index: int, params: dict[str, Any]) -> None:
    setup = sample.setup
    r0, c0, h, w = _image_box(cfg, setup)
    m0 = setup.tube.focal_length / setup.objective.focal_length
    half = 1.02 * m0 * (0.5 * setup.target.frame_side + setup.target.frame_line) / (setup.camera.pixel_um * 1e-3)
    for ch in sample.channels:
        t = math.radians(sample.tilt_deg[ch])
        rot = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
        corners = (rot @ (half * np.array([[-1, -1, 1, 1], [-1, 1, -1, 1]]))).T
        centre = np.array(
            [
                0.5 * setup.camera.width_px + sample.offset_px[ch][0] - c0,
                0.5 * setup.camera.height_px + sample.offset_px[ch][1] - r0,
            ]
        )
        pts = corners + centre
        if pts.min() < 0 or pts[:, 0].max() > w or pts[:, 1].max() > h:
            key = next((k for k in ("channel_offset_px", "channel_tilt_deg") if k in params), "cmu.window")
            key = key if key == "cmu.window" else f"vary.{key}"
            raise DatasetError(
                f"sample {index}: key {key}: the Siemens-star frame ({2 * half:.0f} px wide) of channel "
                f"{ch} leaves the {w} x {h} px image (offset {list(sample.offset_px[ch])} px, tilt "
                f"{sample.tilt_deg[ch]:g} deg); use smaller offsets or a larger window"
            )


# -- writing one sample (runs on a worker) ----------------------------------------------------------
_WORKER_STATE: dict[str, Any] = {}


def _init_process(threads: int | None) -> None:
    """Once per worker process: Dr.Jit's thread count (one per worker on a local cluster)."""
    if threads and _WORKER_STATE.get("threads") != threads:
        from scenes.mitsuba.variant import set_thread_count

        set_thread_count(int(threads))
        _WORKER_STATE["threads"] = threads


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def sample_name(index: int) -> str:
    return f"{index:06d}"


def versions() -> dict[str, str]:
    import importlib.metadata as md

    out = {}
    for pkg in ("scopetwin", "mitsuba", "drjit", "numpy", "OpenEXR"):
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            out[pkg] = "unknown"
    return out


class _Stage:
    """The ``path(name)`` interface of :class:`sim.cli.StagedOutput` over a plain folder."""

    def __init__(self, folder: Path) -> None:
        self.stage = folder

    def path(self, name: str) -> Path:
        return self.stage / name


def _write_normals(path: Path, heights) -> None:
    """Unit surface normals at the height-map nodes: channels NX, NY, NZ (plus Z), extents as in the contract."""
    import OpenEXR

    from scenes.io import EXTENT_KEYS, atomic_path

    xx, yy = np.meshgrid(heights.x_nodes, heights.y_nodes)
    n = heights.normals(xx, yy)
    chans = {"NX": n[..., 0], "NY": n[..., 1], "NZ": n[..., 2], "Z": heights.z}
    chans = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in chans.items()}
    header: dict[str, Any] = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update(zip(EXTENT_KEYS, (heights.x_min, heights.x_max, heights.y_min, heights.y_max), strict=True))
    with atomic_path(path) as tmp:
        OpenEXR.File(header, chans).write(str(tmp))


def _write_part1(plan: Plan, index: int, stage: _Stage) -> dict[str, Any]:
    from sim.cli import render_measurement, write_measurement
    from sim.surfaces import surface_for

    setup = plan.setup_of(index)
    heights = surface_for(setup)
    spp, seed = setup.render.spp, setup.render.seed
    image, _ = render_measurement(setup, heights, spp, seed, setup.render.noise)
    names = write_measurement(stage, "", setup, heights, image, spp, seed, "mitsuba")
    if not plan.config.dataset.preview:
        stage.path(names.pop("preview")).unlink()
    if heights is not None:
        _write_normals(stage.path("normals.exr"), heights)
        names["normals"] = "normals.exr"
    truth = json.loads(stage.path(names["truth"]).read_text())
    cam = setup.camera_model
    truth.update(
        camera={
            "r_c": cam.frame.origin.tolist(),
            "t_x": cam.frame.tx.tolist(),
            "t_y": cam.frame.ty.tolist(),
            "n_z": cam.frame.nz.tolist(),
            "b": cam.b,
            "r_cs": list(cam.r_cs),
            "c0": cam.c0,
            "c2": cam.c2,
            "focus_distance": cam.focus_distance(),
        },
        setup_json=json.loads(setup.to_json()),
        seeds={
            "surface": setup.substrate.surface.seed if setup.substrate else None,
            "render": seed,
            "noise": seed if setup.render.noise else None,
        },
    )
    return {"files": names, "truth": truth}


def _write_grin(plan: Plan, index: int, stage: _Stage) -> dict[str, Any]:
    from scenes.grin.analysis import analyse
    from scenes.io import write_image
    from scenes.mitsuba.grin import render_image

    setup, tgt = plan.setup_of(index)
    rep = analyse(setup, samples=16)
    stack = setup.stack(image_distance=rep.image_distance_mm)
    if rep.stop_radius_mm is not None:
        stack = stack.with_stop_radius(rep.stop_radius_mm)
    seed = sample_seed(plan.config.dataset.master_seed, index, "render")
    g = plan.config.grin
    whole = setup.array.nx * setup.array.ny > 1 and g.width is None and g.height is None
    centre = (0.0, 0.0) if whole else tuple(float(v) for v in setup.array.axes()[0])  # a window: objective 0
    img = render_image(
        setup,
        stack,
        tgt,
        spp=plan.config.dataset.spp,
        width=g.width,
        height=g.height,
        step_mm=g.step_mm,
        center=centre,
        seed=seed,
    )
    prov = {"seed": seed, "spp": plan.config.dataset.spp, "renderer": "mitsuba-grin", "versions": versions()}
    write_image(stage.path("image.exr"), img, setup.to_json(), prov)
    truth = {
        "setup": setup.name,
        "scene": "grin",
        "target": {"name": tgt.name, "offset": list(tgt.offset), "period": tgt.period, "feature": tgt.feature},
        "image_distance_mm": rep.image_distance_mm,
        "magnification": rep.magnification,
        "na_object": rep.na_object,
        "centre_mm": list(centre),
        "seeds": {"render": seed},
        "setup_json": json.loads(setup.to_json()),
    }
    return {"files": {"image": "image.exr"}, "truth": truth}


#: The CMU cameras' sensor (Basler scA1400-30gm, Sony ICX285, §4.1.4): the EMVA model's defaults (full well
#: 18 ke-, 10 e- dark noise); the quantum efficiency is 1 because the rendered image already counts electrons
#: (the detection response includes the camera's QE), and the gain fills the ADC as the Part I default does.
CMU_FILL_DEFAULT = 0.7


def _cmu_sensor(bit_depth: int) -> Any:
    from scenes.sensor import EmvaSensor

    full_well = 18000.0
    return EmvaSensor(
        quantum_efficiency=1.0,
        full_well_e=full_well,
        gain_dn_per_e=(2**bit_depth - 96) / full_well,
        bit_depth=bit_depth,
    )


def _object_to_pixel(
    setup: Any, opt: Any, channel: str, pose: Any, box: tuple[int, int, int, int], half: float, n_pupil: int = 15
) -> np.ndarray:
    """Affine map (2 x 3) from object (x, y, 1) in mm to (col, row) in the written image's pixel coordinates.

    Fitted to the traced spot centroids (numpy tracer, the channel's real plates) of a 3 x 3 object grid of
    +-``half`` mm on the camera plane at ``pose.image_distance``, mapped to pixels with the camera's axes, tilt
    and offset exactly as :func:`scenes.mitsuba.cmu.render_channel` maps pixels to the plane (its inverse).
    Pixel (r, c) covers [c, c+1) x [r, r+1) (DESIGN.md), so the star's centre is at ``A[:, 2]``.
    """
    from scenes.cmu.analysis import image_rays, pupil_grid
    from scenes.mitsuba.cmu import sensor_axes

    ex, ey = sensor_axes(setup, channel)
    to_ab = np.linalg.inv(np.column_stack([ex, ey]))
    t = math.radians(pose.tilt_deg)
    rot = np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    p_mm = setup.camera.pixel_um * 1e-3
    r0, c0, _, _ = box
    px, py = pupil_grid(n_pupil)
    obj, img = [], []
    for x0 in (-half, 0.0, half):
        for y0 in (-half, 0.0, half):
            u, v = image_rays(opt, x0, y0, px, py).at(pose.image_distance)
            a, b = rot @ (to_ab @ np.array([u.mean(), v.mean()]))
            img.append(
                (
                    0.5 * setup.camera.width_px + pose.offset_px[0] + a / p_mm - c0,
                    0.5 * setup.camera.height_px + pose.offset_px[1] - b / p_mm - r0,
                )
            )
            obj.append((x0, y0, 1.0))
    coef, *_ = np.linalg.lstsq(np.asarray(obj), np.asarray(img), rcond=None)
    return coef.T


def _affine_truth(a: np.ndarray, pixel_um: float) -> dict[str, Any]:
    """Magnification (sqrt |det|, and the singular values), centre and displayed tilt of an object->pixel map.

    The tilt is the rotation of the displayed image (rows up), counter-clockwise positive, as
    :mod:`calib.channels` measures it.
    """
    lin = a[:, :2]
    p_mm = pixel_um * 1e-3
    sv = np.linalg.svd(lin, compute_uv=False) * p_mm
    return {
        "magnification": float(math.sqrt(abs(np.linalg.det(lin))) * p_mm),
        "magnification_xy": [float(sv[0]), float(sv[1])],
        "frame_center_px": [float(a[0, 2]), float(a[1, 2])],
        "image_tilt_deg": float(math.degrees(math.atan2(-lin[1, 0] - lin[0, 1], lin[0, 0] - lin[1, 1]))),
        "object_to_pixel": a.tolist(),
    }


def _write_cmu(plan: Plan, index: int, stage: _Stage) -> dict[str, Any]:
    """One channel set of the four-channel unit (seed §5.1.2, §5.2.2): an image per channel, the plates' maps, truth.

    Each camera sits at its channel's refocused image distance (the numpy tracer's RMS-spot focus, §5.1.2) plus
    the drawn defocus, with the drawn tilt and offset; the truth is the tracer's object->pixel map of that camera.
    """
    from scenes.cmu.analysis import analyse, channel_optics
    from scenes.cmu.plates import plate_heightmap
    from scenes.io import write_heightmap, write_image
    from scenes.mitsuba.cmu import CameraPose, render_channel, unit_scene

    cfg = plan.config
    sample: CmuSample = plan.setup_of(index)
    setup = sample.setup
    master, spp = cfg.dataset.master_seed, cfg.dataset.spp
    files: dict[str, str] = {}
    elements = {**setup.splitters, **setup.mirrors}
    maps = {name: plate_heightmap(spec, setup.plate) for name, spec in elements.items()}
    plates = {}
    for name, spec in elements.items():
        role = "splitter" if name in setup.splitters else "mirror"
        if role == "mirror" and not np.any(maps[name].z):
            continue
        fname = f"height_{name}.exr"
        write_heightmap(stage.path(fname), maps[name], scopetwin_element=name)
        files[f"height_{name}"] = fname
        plates[name] = {
            "file": fname,
            "role": role,
            "bow_range_um": spec.bow_range_um,
            "residual_rms_um": spec.residual_rms_um,
            "residual_seed": spec.residual_seed,
            "concave": spec.concave,
            "height_map": spec.height_map,
            "range_um": float(np.ptp(maps[name].z) * 1e3),
        }
    scene = unit_scene(setup, maps)
    box = _image_box(cfg, setup)
    noise = bool(cfg.dataset.noise or sample.exposure_fill is not None)
    fill = CMU_FILL_DEFAULT if sample.exposure_fill is None else float(sample.exposure_fill)
    sensor = _cmu_sensor(setup.camera.bit_depth) if noise else None
    half = 0.5 * setup.target.frame_side if sample.target == "star" else 0.25 * min(setup.field_mm)
    channels, images = {}, []
    for ch in sample.channels:
        opt = channel_optics(setup, ch, maps, stop=cfg.cmu.stop)
        focus = analyse(setup, opt, n_pupil=cfg.cmu.n_pupil)
        b = focus.image_distance_mm + sample.defocus[ch]
        res = focus if sample.defocus[ch] == 0 else analyse(setup, opt, n_pupil=cfg.cmu.n_pupil, image_distance=b)
        pose = CameraPose(b, sample.tilt_deg[ch], sample.offset_px[ch])
        rseed = sample_seed(master, index, f"render:{ch}")
        img = render_channel(
            setup, ch, pose, sample.target, spp=spp, window=box, stop=cfg.cmu.stop, seed=rseed, scene=scene
        )
        exposure, nseed = None, None
        if sensor is not None:
            peak = float(np.percentile(img, 99.9))  # Monte-Carlo outliers above it saturate, as hot spots would
            if not peak > 0:
                raise ScopetwinError(
                    f"sample {index}, channel {ch}: the rendered image is black: cannot choose an "
                    "exposure for the noise model"
                )
            exposure = sensor.exposure_for(peak, 1.0, fill)
            nseed = sample_seed(master, index, f"noise:{ch}")
            img = sensor.capture(img, 1.0, exposure, rng=nseed)
        fname = f"image_{ch}.exr"
        prov = {
            "seed": rseed,
            "spp": spp,
            "renderer": "mitsuba-cmu",
            "channel": ch,
            "target": sample.target,
            "noise_seed": nseed,
            "versions": versions(),
        }
        write_image(stage.path(fname), img, setup.to_json(), prov, image_distance_mm=float(b), scopetwin_channel=ch)
        files[f"image_{ch}"] = fname
        images.append(img)
        spec = setup.channels[ch]
        channels[ch] = {
            "image": fname,
            "path": list(spec.path),
            "filter": spec.filter,
            "image_distance_mm": float(b),
            "refocused_image_distance_mm": focus.image_distance_mm,
            "defocus_mm": sample.defocus[ch],
            "camera": {"tilt_deg": pose.tilt_deg, "offset_px": list(pose.offset_px)},
            **_affine_truth(_object_to_pixel(setup, opt, ch, pose, box, half), setup.camera.pixel_um),
            "rms_spot_um": res.rms_spot_um,
            "astigmatism_mm": res.astigmatism_mm,
            "transmitted_fraction": res.transmitted_fraction,
            "exposure_e_per_unit": exposure,
            "seeds": {"render": rseed, "noise": nseed},
        }
    if cfg.dataset.preview:
        from sim.cli import _preview

        tiles = [im / (float(np.percentile(im, 99.9)) or 1.0) for im in images]
        _preview(stage.path("preview.png"), np.hstack(tiles))
        files["preview"] = "preview.png"
    target = setup.target if sample.target == "star" else setup.cells
    truth = {
        "setup": setup.name,
        "scene": "cmu",
        "target": {"name": sample.target, **target.model_dump()},
        "window": list(box),
        "stop": cfg.cmu.stop,
        "spp": spp,
        "sensor": None if sensor is None else {**dataclasses.asdict(sensor), "fill_fraction": fill},
        "channels": channels,
        "plates": plates,
        "seeds": {
            "residual": {n: s.residual_seed for n, s in setup.splitters.items()},
            "cells": setup.cells.seed,
            "render": {c: v["seeds"]["render"] for c, v in channels.items()},
            "noise": {c: v["seeds"]["noise"] for c, v in channels.items()},
        },
        "setup_json": json.loads(setup.to_json()),
    }
    return {"files": files, "truth": truth}


def _sample_record(folder: Path) -> dict[str, Any]:
    files = {}
    for f in sorted(folder.iterdir()):
        if f.name != SAMPLE_FILE and f.is_file():
            files[f.name] = {"sha256": sha256_file(f), "bytes": f.stat().st_size}
    return files


def generate_sample(plan_json: dict[str, Any], index: int, root: str, threads: int | None = None) -> dict[str, Any]:
    """Render sample ``index`` into ``root/samples/NNNNNN`` atomically; return its manifest record.

    Runs on a worker (any worker: the result depends only on the plan and ``index``). A sample
    folder that already exists is not redone (``status: "exists"``).
    """
    _init_process(threads)
    t0 = time.perf_counter()
    samples = Path(root) / SAMPLES
    final = samples / sample_name(index)
    record = {"index": index, "name": sample_name(index)}
    if not (final / SAMPLE_FILE).is_file():
        plan = Plan.from_json(plan_json)
        samples.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(prefix=f"{TMP_PREFIX}{sample_name(index)}-", dir=samples))
        umask = os.umask(0)
        os.umask(umask)
        stage.chmod(0o777 & ~umask)
        try:
            writer = {"grin": _write_grin, "cmu": _write_cmu}.get(plan.config.dataset.kind, _write_part1)
            out = writer(plan, index, _Stage(stage))
            from scenes.io import write_json_atomic

            truth = out["truth"]
            truth.update(
                sample=index,
                master_seed=plan.config.dataset.master_seed,
                kind=plan.config.dataset.kind,
                parameters=plan.parameters(index),
                versions=versions(),
            )
            write_json_atomic(stage / "truth.json", truth)
            body = {**record, "kind": plan.config.dataset.kind, "files": _sample_record(stage)}
            write_json_atomic(stage / SAMPLE_FILE, body)
            try:
                os.rename(stage, final)
                status = "written"
            except OSError:  # another run finished the same sample first: identical bytes, keep theirs
                status = "exists"
        finally:
            if stage.exists():
                shutil.rmtree(stage, ignore_errors=True)
    else:
        status = "exists"
    body = json.loads((final / SAMPLE_FILE).read_text())
    return {**body, "status": status, "seconds": time.perf_counter() - t0}


# -- executors: in-process or Dask ------------------------------------------------------------------
def default_workers() -> int:
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


@contextlib.contextmanager
def dask_client(scheduler: str | None = None, workers: int | None = None) -> Iterator[Any]:
    """A Dask client: on ``scheduler`` (an existing cluster, unchanged) or on an embedded LocalCluster.

    The local cluster has ``workers`` worker processes (default: one per core) with one thread each,
    started with ``spawn`` (Mitsuba's plugin registry is per thread and does not survive ``fork``),
    and listens on 127.0.0.1 only, without a dashboard.
    """
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError as exc:
        raise DatasetError(
            f"Dask distributed is not installed ({exc}); install dask[distributed] or use "
            "--workers 0 to work in this process"
        ) from None
    if scheduler:
        try:
            client = Client(scheduler, timeout="30s")
        except (OSError, TimeoutError) as exc:
            raise DatasetError(f"cannot connect to the Dask scheduler {scheduler}: {exc}") from None
        try:
            yield client
        finally:
            client.close()
        return
    with dask.config.set(
        {
            "distributed.worker.multiprocessing-method": "spawn",
            "distributed.scheduler.allowed-failures": 5,
            "distributed.worker.memory.terminate": False,
        }
    ):
        cluster = LocalCluster(
            n_workers=workers or default_workers(),
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
            silence_logs=logging.ERROR,
        )
        client = Client(cluster)
        try:
            yield client
        finally:
            client.close()
            cluster.close()


class TaskFailure(ScopetwinError):
    """A task raised on a worker; the message is the original exception's type and message."""


def _guarded(func: Callable[..., Any], *args: Any) -> tuple[bool, Any]:
    """Run a task and hand its exception back as a value (no worker-log traceback, always unpicklable-safe)."""
    try:
        return True, func(*args)
    except Exception as exc:  # noqa: BLE001 - handed to the client
        return False, f"{type(exc).__name__}: {exc}"


def failure_text(err: BaseException) -> str:
    """'Type: message' of a task's error."""
    return str(err) if isinstance(err, TaskFailure) else f"{type(err).__name__}: {err}"


def run_tasks(
    func: Callable[..., Any], args: Sequence[tuple], client: Any | None, keys: Sequence[str] | None = None
) -> Iterator[tuple[int, Any, BaseException | None]]:
    """Run ``func(*a)`` for every ``a`` in ``args``; yield (position, result, error) as each finishes.

    ``client`` None runs in this process, in order. Errors are yielded, not raised, so one bad
    task does not lose the others' results.
    """
    if client is None:
        for k, a in enumerate(args):
            try:
                yield k, func(*a), None
            except Exception as exc:  # noqa: BLE001 - handed to the caller
                yield k, None, exc
        return
    from distributed import as_completed

    futures = [
        client.submit(_guarded, func, *a, key=None if keys is None else keys[k], pure=False) for k, a in enumerate(args)
    ]
    position = {f.key: k for k, f in enumerate(futures)}
    try:
        for fut in as_completed(futures):
            k = position[fut.key]
            try:
                ok, value = fut.result()
            except Exception as exc:  # noqa: BLE001 - e.g. KilledWorker after repeated worker deaths
                yield k, None, exc
                continue
            yield (k, value, None) if ok else (k, None, TaskFailure(value))
            fut.release()
    finally:
        for f in futures:
            f.cancel()


# -- the dataset folder: manifest, recovery, generation, verification -------------------------------
def _read_manifest(root: Path) -> tuple[list[dict[str, Any]], int]:
    """Parsed manifest lines and the number of unreadable ones (a line cut by a kill)."""
    path = root / MANIFEST
    if not path.exists():
        return [], 0
    rows, bad = [], 0
    for line in path.read_text().splitlines():
        if not line.strip():
            continue
        try:
            row = json.loads(line)
            int(row["index"])
            rows.append(row)
        except (json.JSONDecodeError, KeyError, TypeError, ValueError):
            bad += 1
    return rows, bad


def _check_sample(folder: Path, expected: dict[str, Any] | None = None) -> str | None:
    """None if the folder's files match its sample.json (and ``expected`` hashes); else the reason."""
    try:
        body = json.loads((folder / SAMPLE_FILE).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        return f"{SAMPLE_FILE} unreadable ({exc.__class__.__name__})"
    files = body.get("files", {})
    if expected is not None and expected != files:
        return "hashes differ from the manifest"
    present = {f.name for f in folder.iterdir() if f.name != SAMPLE_FILE}
    if present != set(files):
        return f"files differ from {SAMPLE_FILE}: {sorted(present ^ set(files))}"
    for name, meta in files.items():
        p = folder / name
        if p.stat().st_size != meta["bytes"] or sha256_file(p) != meta["sha256"]:
            return f"{name} does not match its hash"
    return None


def _manifest_line(rec: dict[str, Any], worker: str) -> dict[str, Any]:
    keep = {k: rec[k] for k in ("index", "name", "kind", "files") if k in rec}
    return {
        **keep,
        "status": rec.get("status", "written"),
        "seconds": round(float(rec.get("seconds", 0.0)), 3),
        "worker": worker,
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "finished_utc": datetime.now(UTC).isoformat(timespec="seconds"),
    }


def _append(fh, row: dict[str, Any]) -> None:
    fh.write(json.dumps(row, separators=(",", ":")) + "\n")
    fh.flush()
    os.fsync(fh.fileno())


def recover(root: Path) -> dict[str, Any]:
    """Tidy a dataset folder after an interruption; return what was done.

    Removes temporary sample folders, drops unreadable/duplicate manifest lines and lines of
    samples that are gone or corrupt, deletes corrupt sample folders (they are redone), and lists
    finished samples the manifest does not know (the client died between rename and manifest).
    """
    from scenes.io import write_text_atomic

    samples = root / SAMPLES
    samples.mkdir(parents=True, exist_ok=True)
    removed_tmp = []
    for p in samples.iterdir():
        if p.name.startswith(".") and p.is_dir():
            shutil.rmtree(p, ignore_errors=True)
            removed_tmp.append(p.name)
    rows, bad_lines = _read_manifest(root)
    listed: dict[int, dict[str, Any]] = {}
    for row in rows:
        listed.setdefault(int(row["index"]), row)
    kept, corrupt, relisted = [], [], []
    folders = {int(p.name): p for p in samples.iterdir() if p.is_dir() and p.name.isdigit()}
    for idx, folder in sorted(folders.items()):
        reason = _check_sample(folder)
        if reason is not None:
            shutil.rmtree(folder, ignore_errors=True)
            corrupt.append(idx)
            continue
        row = listed.get(idx)
        body = json.loads((folder / SAMPLE_FILE).read_text())
        if row is None or row.get("files") != body["files"]:
            row = _manifest_line({**body, "status": "recovered"}, "recovered")
            relisted.append(idx)
        kept.append(row)
    write_text_atomic(root / MANIFEST, "".join(json.dumps(r, separators=(",", ":")) + "\n" for r in kept))
    return {
        "removed_temporary": sorted(removed_tmp),
        "dropped_manifest_lines": bad_lines + len(rows) - len(kept) + len(relisted),
        "corrupt_removed": corrupt,
        "relisted": relisted,
        "done": sorted(folders.keys() - set(corrupt)),
    }


def _write_plan(root: Path, plan: Plan) -> None:
    from scenes.io import write_json_atomic

    path = root / CONFIG_FILE
    new = plan.to_json()
    if path.exists():
        old = json.loads(path.read_text())
        if old != json.loads(json.dumps(new)):
            raise DatasetError(
                f"{root} already holds a different dataset ({CONFIG_FILE} differs); choose another "
                "--out or `scopetwin dataset resume` it"
            )
        return
    write_json_atomic(path, new)


def parse_indices(text: str | None, count: int) -> list[int]:
    """``"A:B"`` -> [A, B) within [0, count); None -> all."""
    if text is None:
        return list(range(count))
    try:
        a, b = (int(t) if t else d for t, d in zip(text.split(":"), (0, count), strict=True))
    except ValueError:
        raise DatasetError(f"--indices must look like A:B (half-open), got {text!r}") from None
    if not 0 <= a < b <= count:
        raise DatasetError(f"--indices {text} must satisfy 0 <= A < B <= count ({count})")
    return list(range(a, b))


def generate(
    plan: Plan,
    out: str | Path,
    scheduler: str | None = None,
    workers: int | None = None,
    threads: int | None = None,
    indices: Sequence[int] | None = None,
    progress: bool = True,
    client: Any | None = None,
) -> dict[str, Any]:
    """Generate (or finish) the samples ``indices`` of a dataset in ``out``.

    Parameters
    ----------
    plan : Plan
        Validated config (:meth:`Plan.build` checks every sample's setup before this is called).
    out : path
        Dataset folder (created; a folder holding another dataset is refused).
    scheduler : str, optional
        Address of an existing Dask scheduler (``tcp://host:8786``), used unchanged.
    workers : int, optional
        Local worker processes (default one per core); 0 works in this process without Dask.
    threads : int, optional
        Dr.Jit threads per worker (default: 1 on the local cluster, the library default elsewhere).
    indices : sequence of int, optional
        Which samples (default all ``count``).
    progress : bool
        Show a progress bar (rate and ETA).
    client : distributed.Client, optional
        Use this client (and its cluster) instead of opening one.
    """
    from tqdm import tqdm

    root = Path(out)
    root.mkdir(parents=True, exist_ok=True)
    _write_plan(root, plan)
    state = recover(root)
    wanted = list(range(plan.config.dataset.count)) if indices is None else list(indices)
    done = set(state["done"])
    todo = [i for i in wanted if i not in done]
    if threads is None and scheduler is None and workers != 0:
        threads = 1
    plan_json = plan.to_json()
    t0 = time.perf_counter()
    failures: dict[int, str] = {}
    written = 0
    bar = tqdm(
        total=len(wanted),
        initial=len(wanted) - len(todo),
        unit="sample",
        desc="dataset",
        disable=not progress,
        smoothing=0.1,
    )
    if client is not None:
        ctx: Any = contextlib.nullcontext(client)
    elif workers == 0 and not scheduler:
        ctx = contextlib.nullcontext(None)
    else:
        ctx = dask_client(scheduler, workers)
    tag = hashlib.sha256(json.dumps(plan_json, sort_keys=True).encode()).hexdigest()[:12]
    with ctx as client, open(root / MANIFEST, "a") as fh:
        where = "local" if client is None else str(client.scheduler.address)
        args = [(plan_json, i, str(root.resolve()), threads) for i in todo]
        keys = [f"scopetwin-sample-{tag}-{i:06d}" for i in todo]
        for k, rec, err in run_tasks(generate_sample, args, client, keys):
            if err is not None:
                failures[todo[k]] = failure_text(err)
            else:
                _append(fh, _manifest_line(rec, where))
                written += rec["status"] == "written"
            bar.update(1)
    bar.close()
    for p in (root / SAMPLES).glob(f"{TMP_PREFIX}*"):  # left by a worker that died mid-sample (its task was redone)
        shutil.rmtree(p, ignore_errors=True)
    seconds = time.perf_counter() - t0
    result = {
        "out": str(root),
        "requested": len(wanted),
        "already_done": len(wanted) - len(todo),
        "written": written,
        "failed": failures,
        "seconds": seconds,
        "samples_per_minute": 60.0 * len(todo) / seconds if todo and seconds > 0 else None,
        "recovery": state,
    }
    if failures:
        first = next(iter(failures.items()))
        raise DatasetError(
            f"{len(failures)} sample(s) failed (first: sample {first[0]}: {first[1]}); the others are "
            f"written; fix the cause and run `scopetwin dataset resume {root}`"
        )
    return result


def load_plan(root: str | Path) -> Plan:
    """The plan stored in a dataset folder."""
    path = Path(root) / CONFIG_FILE
    if not path.is_file():
        raise DatasetError(f"{root} is not a dataset folder (no {CONFIG_FILE})")
    try:
        return Plan.from_json(json.loads(path.read_text()))
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{path} is not valid JSON: {exc}") from None


def verify(root: str | Path) -> dict[str, Any]:
    """Check every sample against the manifest and its hashes (DESIGN.md ``dataset verify`` contract).

    Returns ``{"complete": n, "missing": [...], "corrupt": [...], "duplicates": [...]}`` plus ``count``,
    ``unlisted`` (finished folders the manifest lacks), ``temporary`` (left-over temporary folders),
    ``bad_manifest_lines`` and ``ok``.
    """
    root = Path(root)
    plan = load_plan(root)
    count = plan.config.dataset.count
    rows, bad = _read_manifest(root)
    by_index: dict[int, list[dict[str, Any]]] = {}
    for row in rows:
        by_index.setdefault(int(row["index"]), []).append(row)
    samples = root / SAMPLES
    entries = list(samples.iterdir()) if samples.is_dir() else []
    temporary = sorted(p.name for p in entries if p.name.startswith("."))
    folders = {p.name: p for p in entries if p.is_dir() and not p.name.startswith(".")}
    duplicates = sorted(i for i, r in by_index.items() if len(r) > 1)
    stray = sorted(n for n in folders if not (n.isdigit() and len(n) == 6 and int(n) < count))
    missing, corrupt, unlisted, complete = [], [], [], 0
    for i in range(count):
        folder = folders.get(sample_name(i))
        if folder is None:
            missing.append(i)
            continue
        listed = by_index.get(i)
        reason = _check_sample(folder, listed[0]["files"] if listed else None)
        if reason is not None:
            corrupt.append({"index": i, "reason": reason})
        elif not listed:
            unlisted.append(i)
        elif i not in duplicates:
            complete += 1
    extra = sorted(i for i in by_index if not 0 <= i < count)
    result = {
        "complete": complete,
        "missing": missing,
        "corrupt": corrupt,
        "duplicates": duplicates,
        "count": count,
        "unlisted": unlisted,
        "temporary": temporary,
        "stray_folders": stray,
        "manifest_out_of_range": extra,
        "bad_manifest_lines": bad,
    }
    result["ok"] = complete == count and not (
        missing or corrupt or duplicates or unlisted or temporary or stray or extra or bad
    )
    return result
