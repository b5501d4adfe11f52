"""The dataset config: its schema (pydantic), the distributions and the domains of the varied quantities.

:func:`load_config` / :func:`config_from_dict` check a config completely before any work: unknown keys, a
distribution whose support leaves the key's domain (a negative range, a viewing angle above 90 degrees) and a key
that does not apply to the sample kind are rejected with a message naming the key.
"""

from __future__ import annotations

import json
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.inputs import parse_toml, read_text_input
from scopetwin.shipped import find_input

KINDS = ("deflectometry", "calibration", "grin", "cmu")
#: Most samples one dataset may have: the plan keeps every sample's setup in memory (a few kB each).
MAX_COUNT = 1_000_000
#: Packages whose versions every sample's truth and image headers record.
SAMPLE_PACKAGES = ("scopetwin", "mitsuba", "drjit", "numpy", "OpenEXR")


class DatasetError(ScopetwinError, ValueError):
    """A dataset config, folder or request that cannot be used; the message names the key or file."""


# -- distributions --------------------------------------------------------------------------------
class _Model(BaseModel):
    """Base of the config tables: unknown keys and non-finite numbers (``inf``, ``nan``) are rejected."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


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
        """The name of the given field (fixed, uniform, normal, loguniform, choice or sweep)."""
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
    #: The physical range every value must lie in (a drawn one included): finite bounds where ``lo``/``hi`` are not.
    limit: tuple[float, float] | None = None

    def names_any(self) -> bool:
        """Whether the quantity is a name (for some kind), not a number."""
        return bool(self.strings)

    def names(self, kind: str) -> tuple[str, ...]:
        """The allowed names of a string-valued quantity for samples of ``kind`` (empty: numeric)."""
        return self.strings.get(kind, ()) if isinstance(self.strings, dict) else self.strings

    def contains(self, v: float) -> bool:
        """Whether ``v`` lies in the domain (an infinite bound of an unbounded domain counts as inside)."""
        if math.isinf(v) and v in (self.lo, self.hi):  # an unbounded distribution on an unbounded domain
            return True
        above = v > self.lo if self.lo_open else v >= self.lo
        below = v < self.hi if self.hi_open else v <= self.hi
        return bool(above and below)

    def describe(self) -> str:
        """The domain as an interval, e.g. ``(0, 90]``."""
        return f"{'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"

    def physical(self) -> tuple[float, float]:
        """The finite range every value must lie in (:attr:`limit`, else the domain's own bounds)."""
        return self.limit if self.limit is not None else (self.lo, self.hi)

    def check_value(self, v: Any) -> str | None:
        """Why a value cannot be used (not a finite number, outside the domain or the physical range), or None."""
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            return f"{v!r} is not a finite number"
        if not self.contains(v):
            return f"{v:g} {self.unit} lies outside {self.describe()}".replace("  ", " ")
        lo, hi = self.physical()
        if not lo <= v <= hi:
            return f"{v:g} {self.unit} lies outside the physical range [{lo:g}, {hi:g}]".replace("  ", " ")
        return None


_INF = math.inf
_PART1 = ("deflectometry", "calibration")
_SURFACE_KINDS = ("random", "psd", "plane", "sphere", "saddle", "cylinder")
DOMAINS: dict[str, Domain] = {
    "surface_range_um": Domain(
        0, _INF, False, True, ("deflectometry",), 1, "µm", "peak-to-valley range (§1.9)", limit=(0, 10_000)
    ),
    "surface_correlation_length": Domain(
        0, _INF, True, True, ("deflectometry",), 1, "mm", "low-pass correlation length (§1.9)", limit=(0, 10_000)
    ),
    "surface_kind": Domain(0, 0, False, False, ("deflectometry",), 1, "", "surface generator", strings=_SURFACE_KINDS),
    "surface_broadband_rms_nm": Domain(
        0, 1000, False, False, ("deflectometry",), 1, "nm", "broadband (short-wavelength) RMS of the surface"
    ),
    "view_angle_deg": Domain(
        0, 90, True, False, ("calibration",), 1, "deg", "camera elevation over the target (§2.8.2 angle scan)"
    ),
    "view_distance": Domain(
        0, _INF, True, True, ("calibration",), 1, "mm", "camera distance from the target centre", limit=(0, 100_000)
    ),
    "camera_shift": Domain(
        -_INF, _INF, True, True, _PART1, 3, "mm", "camera centre jitter, per axis", limit=(-10_000, 10_000)
    ),
    "camera_rotation": Domain(
        -_INF, _INF, True, True, _PART1, 3, "rad", "camera rotation vector, per axis", limit=(-math.pi, math.pi)
    ),
    "f_number": Domain(0, _INF, True, True, _PART1, 1, "", "thin-lens f-number", limit=(0, 1000)),
    "defocus": Domain(
        -_INF, _INF, True, True, _PART1, 1, "mm", "plane in focus minus the nominal one", limit=(-10_000, 10_000)
    ),
    "distortion_c2": Domain(-_INF, _INF, True, True, _PART1, 1, "1/mm", "radial distortion c2 (§2.5.1)", limit=(-1, 1)),
    "principal_offset": Domain(-_INF, _INF, True, True, _PART1, 2, "mm", "r_cs, per axis (§2.8.5)", limit=(-100, 100)),
    "exposure_fill": Domain(0, 1, True, False, (*_PART1, "cmu"), 1, "", "fraction of the full well at the image peak"),
    "exposure_s": Domain(0, _INF, True, True, _PART1, 1, "s", "exposure time", limit=(0, 3600)),
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
    "target_offset": Domain(
        -_INF, _INF, True, True, ("grin",), 2, "mm", "target offset from the axis, per axis", limit=(-100, 100)
    ),
    "bow_range_um": Domain(
        0,
        _INF,
        False,
        True,
        ("cmu",),
        1,
        "µm",
        "bow range of each beam splitter (§5.1.1)",
        per="splitter",
        limit=(0, 10_000),
    ),
    "bow_scale": Domain(
        0,
        _INF,
        False,
        True,
        ("cmu",),
        1,
        "",
        "factor on each splitter's bow range of the setup",
        per="splitter",
        limit=(0, 1000),
    ),
    "residual_rms_um": Domain(
        0,
        _INF,
        False,
        True,
        ("cmu",),
        1,
        "µm",
        "RMS of each splitter's smooth residual",
        per="splitter",
        limit=(0, 1000),
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
        limit=(-100, 100),
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
        limit=(-100_000, 100_000),
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
    surface_broadband_rms_nm: Dist | None = None
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
        """The given (name, distribution) pairs, in field order (the sweep order)."""
        return [(k, getattr(self, k)) for k in type(self).model_fields if getattr(self, k) is not None]


class DatasetSection(_Model):
    """The ``[dataset]`` table."""

    kind: Literal["deflectometry", "calibration", "grin", "cmu"]
    setup: str = Field(description="preset name or setup TOML path")
    count: int = Field(gt=0, le=MAX_COUNT, description="samples (at most MAX_COUNT: the plan holds every one)")
    master_seed: int = Field(ge=0)
    spp: int = Field(16, gt=0, le=2**31 - 1)
    noise: bool = False
    description: str = ""
    preview: bool = Field(True, description="write preview.png beside each image")
    maps: bool = Field(True, description="write the per-pixel truth maps (maps.exr) of each sample")
    maps_compression: Literal["zstd", "zip"] = Field(
        "zstd", description="maps.exr's lossless compression: zstd (read by OpenEXR 3.5 and later) or zip (any reader)"
    )


class GrinSection(_Model):
    """The ``[grin]`` table: image size of GRIN target images."""

    width: int | None = Field(None, gt=0, le=1_000_000)
    height: int | None = Field(None, gt=0, le=1_000_000)
    step_mm: float = Field(
        0.3, ge=1e-4, description="RKN step of the images, mm (>= 0.1 µm: the trace time grows as 1/step)"
    )

    @model_validator(mode="after")
    def _fits(self) -> GrinSection:
        from scopetwin.scenes.limits import check_image_size

        if self.width is not None and self.height is not None:
            check_image_size(self.width, self.height, "width x height")
        return self


class CmuSection(_Model):
    """The ``[cmu]`` table: which channels, which part of the sensor, the tube-lens stop (thesis §5.1.2)."""

    channels: list[str] | None = Field(None, min_length=1, description="default: every channel of the setup")
    window: tuple[int, int, int, int] | None = Field(None, description="(row0, col0, height, width) of the sensor")
    stop: bool = Field(False, description="the 4 mm aperture in front of every tube lens")
    n_pupil: int = Field(21, ge=5, le=101, description="pupil grid of the numpy tracer (refocus and truth)")


class DatasetConfig(_Model):
    """A whole dataset config (the format is described in :mod:`scopetwin.sim.datasets`)."""

    dataset: DatasetSection
    setup: dict[str, Any] = Field(default_factory=dict)
    vary: VarySpec = VarySpec()
    grin: GrinSection = GrinSection()
    cmu: CmuSection = CmuSection()


# -- loading and validation -------------------------------------------------------------------------
def _loc(err: Mapping[str, Any]) -> str:
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
            flat: list[Any] = []
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
            why = next((w for w in map(dom.check_value, flat) if w is not None), None)
            if why is not None:
                raise DatasetError(f"{where}: impossible value: {why} (the {dom.text})")
            continue
        lo, hi = dist.support()  # type: ignore[misc]
        if not (dom.contains(lo) and dom.contains(hi)):
            raise DatasetError(
                f"{where}: impossible distribution {dist.kind} {list(getattr(dist, dist.kind))}: it "
                f"can give values outside {dom.describe()} {dom.unit} (the {dom.text})"
            )
        plo, phi = dom.physical()
        # a normal distribution on an unbounded domain: its mean here, every drawn value when the plan is built
        ends = (dist.normal[0],) if dist.normal is not None and dist.normal[1] > 0 else (lo, hi)
        if not all(plo <= v <= phi for v in ends):
            raise DatasetError(
                f"{where}: impossible distribution {dist.kind} {list(getattr(dist, dist.kind))}: it can give "
                f"values outside the physical range [{plo:g}, {phi:g}] {dom.unit} (the {dom.text})"
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


def check_parameters(params: dict[str, Any], index: int) -> None:
    """Check the varied values drawn for sample ``index`` like fixed ones: every number finite, in its domain and in
    its physical range (:meth:`Domain.check_value`), before any work is done with them.

    Raises
    ------
    DatasetError
        A value that cannot be used; the message names the key, the sample and the value.
    """
    for name, value in params.items():
        dom = DOMAINS.get(name)
        if dom is None or dom.names_any():
            continue
        members = value.items() if isinstance(value, dict) else [("", value)]
        for member, v in members:
            for comp in v if isinstance(v, list) else [v]:
                why = dom.check_value(comp)
                if why is not None:
                    who = f" ({dom.per} {member})" if member else ""
                    raise DatasetError(f"sample {index}: key vary.{name}{who}: drawn value {why} (the {dom.text})")


#: ``--set`` keys that name a setup's render option, which a dataset config keeps in its ``[dataset]`` table.
SET_ALIASES = {"render.spp": "dataset.spp", "render.noise": "dataset.noise"}


def apply_overrides(data: dict[str, Any], overrides: list[str]) -> dict[str, Any]:
    """``data`` with ``key=value`` overrides applied (``--set``): a dotted key into the config's tables
    (``dataset.spp=4``, ``setup.camera.pixels=[340, 256]``, ``vary.surface_range_um.uniform=[10, 30]``;
    ``render.spp`` and ``render.noise`` mean ``dataset.spp`` / ``dataset.noise``), the value in TOML syntax (a bare
    word is a string). The result is validated like the file (:func:`config_from_dict`), so a bad key or value is
    named as it would be in the file.

    Raises
    ------
    DatasetError
        An override that is not ``key=value`` or whose value is not a TOML value.
    """
    out = json.loads(json.dumps(data))
    for item in overrides:
        key, sep, text = item.partition("=")
        key = SET_ALIASES.get(key.strip(), key.strip())
        parts = key.split(".")
        if not sep or not all(parts):
            raise DatasetError(f"--set {item!r}: give key=value with a dotted key, e.g. --set dataset.spp=4")
        try:
            value = parse_toml(f"v = {text.strip()}", "--set value", repr(item))["v"]  # bounded depth
        except tomllib.TOMLDecodeError:
            if not text.strip() or any(c in text for c in "[]{}\"'="):
                raise DatasetError(f"--set {item!r}: {text.strip()!r} is not a TOML value") from None
            value = text.strip()  # a bare word: a string (a preset name, a surface kind)
        table = out
        for k, part in enumerate(parts[:-1]):
            nxt = table.setdefault(part, {})
            if not isinstance(nxt, dict):
                raise DatasetError(f"--set {item!r}: {'.'.join(parts[: k + 1])} is a value, not a table")
            table = nxt
        table[parts[-1]] = value
    return out


def load_config(path: str | Path, count: int | None = None, overrides: list[str] | None = None) -> DatasetConfig:
    """Read and validate a dataset config TOML (``count`` overrides ``[dataset] count``; ``overrides``: ``--set``
    items, :func:`apply_overrides`)."""
    p = find_input(path)  # a documented examples/datasets/... path reads the shipped config from any folder
    try:
        # bounded size and nesting depth
        data = parse_toml(read_text_input(p, "dataset configuration"), "dataset configuration", str(p))
    except OSError as exc:
        raise DatasetError(f"cannot read dataset config {p}: {exc.strerror}") from None
    except tomllib.TOMLDecodeError as exc:
        raise DatasetError(f"dataset config {p} is not valid TOML: {exc}") from None
    if overrides:
        data = apply_overrides(data, overrides)
    return config_from_dict(data, str(p), p.resolve().parent, count)


def merge(base: dict[str, Any], over: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``over`` merged in, table by table (nested dicts merge, other values replace)."""
    out = dict(base)
    for k, v in over.items():
        out[k] = merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out
