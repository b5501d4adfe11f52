"""Setup models: pydantic v2, loaded from TOML, with the thesis's setups as presets.

A setup describes one physical scene of Part I of the thesis:

* ``scene = "deflectometry"`` — camera, deflectometry pattern, bent substrate on a
  holding frame (thesis §1.10);
* ``scene = "target"`` — camera and a calibration target lying in the substrate
  plane z = 0 (thesis §2.7.1, §2.8);
* ``scene = "mirror"`` — camera, deflectometry pattern and a flat mirror on the
  holding frame (thesis §2.7.2, §2.8.3).

An optional ``[fringes]`` table replaces the marker pattern of a deflectometry or mirror setup by a display showing
phase-shifted fringes in the pattern plane (:mod:`scopetwin.scenes.fringes`): ``[fringes.display]`` and
``[fringes.sequence]``. Setups without it are marker setups, unchanged.

Presets live in ``scenes/presets/NAME.toml``; each names the section it comes
from. A TOML file may say ``base = "PRESET"`` and override any field (tables
merge key by key). All lengths are mm, angles rad (docs/contract.md, "Units").
"""

from __future__ import annotations

import os
from functools import cached_property
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from scopetwin.scenes import fringes as fr
from scopetwin.scenes.camera import Camera, ThinLens
from scopetwin.scenes.camera_spec import CameraGridSpec
from scopetwin.scenes.emva1288 import EmvaSensor
from scopetwin.scenes.errors import GeometryError, SetupError
from scopetwin.scenes.geometry import Frame
from scopetwin.scenes.inputs import InputError, load_toml_input, parse_json
from scopetwin.scenes.limits import check_image_size
from scopetwin.scenes.pattern import MarkerPattern

PRESET_DIR = Path(__file__).resolve().parent / "presets"

#: Every number of a setup is finite and in a physical range, checked when the setup is loaded: a
#: coordinate within 1 km of the origin, a positive quantity between 1e-9 and 1e9 of its unit (mm, µm, nm, s,
#: electrons); fields with a narrower physical range say so (a pixel pitch of 0.1 µm to 1 mm, a focal length of
#: 0.1 mm to 10 m, an f-number of 0.5 or more, a tilt within one turn).
MAX_COORD_MM = 1.0e6
Coord = Annotated[float, Field(ge=-MAX_COORD_MM, le=MAX_COORD_MM)]
Vec3 = tuple[Coord, Coord, Coord]
Vec2 = tuple[Coord, Coord]
Positive = Annotated[float, Field(gt=0, ge=1e-9, le=1e9)]
PositiveInt = Annotated[int, Field(gt=0)]
TURN_RAD = 2 * np.pi


class _Model(BaseModel):
    """Base of the setup tables: unknown keys and non-finite numbers (``inf``, ``nan``) are rejected."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _make_frame(origin: Vec3, t_x: Vec3, t_y: Vec3, n_z: Vec3) -> Frame:
    """The :class:`Frame` of four 3-tuples (a setup's TOML values)."""
    return Frame(*(np.asarray(v, dtype=np.float64) for v in (origin, t_x, t_y, n_z)))


def _frame(origin: Vec3, t_x: Vec3, t_y: Vec3, n_z: Vec3) -> Frame:
    try:
        return _make_frame(origin, t_x, t_y, n_z)
    except GeometryError as exc:
        raise ValueError(str(exc)) from None


class FrameSpec(_Model):
    """A frame: origin r_c and unit axes T_x, T_y, N_z (right-handed, orthonormal)."""

    origin: Vec3
    t_x: Vec3
    t_y: Vec3
    n_z: Vec3

    @model_validator(mode="after")
    def _check(self) -> FrameSpec:
        _frame(self.origin, self.t_x, self.t_y, self.n_z)
        return self

    def frame(self) -> Frame:
        """The frame (r_c, T_x, T_y, N_z)."""
        return _make_frame(self.origin, self.t_x, self.t_y, self.n_z)


class CameraSpec(CameraGridSpec):
    """Camera of thesis §1.6.2 / §2.5.2: the pixel grid (:class:`scopetwin.scenes.camera_spec.CameraGridSpec`) and the
    pose.

    Give the pose either as axes (``t_x``, ``t_y``, ``n_z`` and ``image_distance``)
    or as the optimisation parameters of §2.5.2 (``r_0``, ``phi``; b then follows from
    the thin-lens equation b = g f/(g - f) with ``g = |r_c - r_0|``). Every number must be finite, and one image of
    ``pixels`` must fit in this machine's memory (:func:`scopetwin.scenes.limits.check_image_size`).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    origin: Vec3 = Field(description="camera centre r_c, mm")
    t_x: Vec3 | None = None
    t_y: Vec3 | None = None
    n_z: Vec3 | None = None
    r_0: Vec2 | None = Field(None, description="point where the optical axis meets z = 0, mm (§2.5.2)")
    phi: float | None = Field(None, ge=-TURN_RAD, le=TURN_RAD, description="sensor tilt angle, rad (§2.5.2)")
    image_distance: Positive | None = Field(None, description="b, mm")
    focal_length: float = Field(25.0, ge=0.1, le=1.0e4, description="f, mm (0.1 mm to 10 m)")
    pixels: tuple[PositiveInt, PositiveInt] = Field((1360, 1024), description="(NP_x, NP_y)")
    pixel_pitch: float = Field(0.00465, ge=1.0e-4, le=1.0, description="square pixel size, mm (0.1 µm to 1 mm)")
    r_cs: Vec2 = Field((0.0, 0.0), description="pixel-grid centre relative to the optical axis, mm")
    c0: float = Field(1.0, ge=1.0e-3, le=1.0e3, description="pixel scale factor")
    c2: float = Field(0.0, ge=-1.0e3, le=1.0e3, description="radial distortion, 1/mm")
    f_number: float | None = Field(None, ge=0.5, le=1.0e4, description="thin-lens f-number; None = pinhole")
    focus_distance: Positive | None = Field(None, description="distance of the plane in focus, mm")

    @model_validator(mode="after")
    def _check(self) -> CameraSpec:
        check_image_size(self.pixels[0], self.pixels[1], "pixels")
        axes = (self.t_x, self.t_y, self.n_z)
        pose = (self.r_0, self.phi)
        if all(a is not None for a in axes):
            if any(p is not None for p in pose):
                raise ValueError("give either the axes t_x, t_y, n_z or the pose r_0, phi, not both")
            if self.image_distance is None:
                raise ValueError("image_distance is required when the axes are given")
            _frame(self.origin, *axes)  # type: ignore[arg-type]
        elif all(p is not None for p in pose):
            if any(a is not None for a in axes):
                raise ValueError("give either the axes t_x, t_y, n_z or the pose r_0, phi, not both")
        else:
            raise ValueError("the camera needs either all of t_x, t_y, n_z or both r_0 and phi")
        try:
            self.camera()
        except GeometryError as exc:
            raise ValueError(str(exc)) from None
        return self

    def grid_fields(self) -> tuple[int, int, float, tuple[float, float]]:
        """(nx, ny, pitch, r_cs) from ``pixels``, ``pixel_pitch`` (mm) and ``r_cs``."""
        return self.pixels[0], self.pixels[1], self.pixel_pitch, self.r_cs

    def camera(self) -> Camera:
        """The camera model of thesis §1.6.2 / §2.5.2 (pose, :meth:`grid`, distortion, thin lens)."""
        lens = None
        if self.f_number is not None:
            lens = ThinLens(self.focal_length, self.f_number, self.focus_distance)
        grid = self.grid()
        nx, ny, pitch = grid.nx, grid.ny, grid.pitch
        if self.t_x is not None:
            assert self.t_y is not None and self.n_z is not None and self.image_distance is not None  # _check
            frame = _make_frame(self.origin, self.t_x, self.t_y, self.n_z)
            return Camera(frame, float(self.image_distance), nx, ny, pitch, grid.r_cs, self.c0, self.c2, lens)
        assert self.r_0 is not None and self.phi is not None  # _check
        cam = Camera.from_pose(
            self.origin,
            self.r_0,
            float(self.phi),
            self.focal_length,
            nx,
            ny,
            pitch,
            r_cs=grid.r_cs,
            c0=self.c0,
            c2=self.c2,
            lens=lens,
        )
        if self.image_distance is not None:
            cam = cam.with_(b=self.image_distance)
        return cam


class PatternSpec(FrameSpec):
    """A marker pattern (thesis §1.6.3, §2.2)."""

    markers: tuple[PositiveInt, PositiveInt] = Field(description="(NM_x, NM_y)")
    pitch: Vec2 = Field(description="(P_x, P_y), mm")
    radius: Positive = Field(description="marker radius r_m, mm")
    ref_radius: Positive = Field(description="reference marker radius, mm")
    layout: Literal["deflectometry", "calibration"] = "deflectometry"
    size: Vec2 | None = Field(None, description="plate size, mm; default: grid plus one pitch")
    radiance: Positive = Field(1.0, description="radiance of a marker centre (a white texel)")

    @model_validator(mode="after")
    def _check_pattern(self) -> PatternSpec:
        if min(self.pitch) <= 0:
            raise ValueError(f"pitch must be > 0 mm, got {self.pitch}")
        if self.size is not None and min(self.size) <= 0:
            raise ValueError(f"size must be > 0 mm, got {self.size}")
        try:
            self.pattern()
        except GeometryError as exc:
            raise ValueError(str(exc)) from None
        return self

    def pattern(self) -> MarkerPattern:
        sx, sy = self.size if self.size is not None else (0.0, 0.0)
        return MarkerPattern(
            self.frame(),
            self.markers[0],
            self.markers[1],
            self.pitch[0],
            self.pitch[1],
            self.radius,
            self.ref_radius,
            self.layout,
            sx,
            sy,
        )


class FeatureSpec(_Model):
    """A local feature of a substrate: a rotationally symmetric Gaussian of full width at half maximum ``width_mm``
    centred at (``x``, ``y``) on the substrate, ``height_um`` high (negative: a dimple)."""

    x: Coord = Field(description="centre x on the substrate, mm")
    y: Coord = Field(description="centre y on the substrate, mm")
    width_mm: Positive = Field(le=100.0, description="full width at half maximum, mm")
    height_um: float = Field(ge=-1.0e3, le=1.0e3, description="height at the centre (negative: a dimple), µm")


class SurfaceSpec(_Model):
    """How the substrate's height map is made (by :mod:`scopetwin.sim.surfaces`) or where it is read from.

    ``random`` is the thesis's §1.9 generator (Gaussian low-pass of scale ``correlation_length``); ``psd`` draws a
    Gaussian random surface from a power spectral density as glass flatness and waviness are specified: the
    K-correlation (ABC) model PSD(f) = A / (1 + (B f)^2)^(C/2) (``spectrum = "abc"``, B = ``correlation_length``,
    C = ``psd_exponent``) or a power law f^-C rolled off below f = 1/B (``spectrum = "power"``), times a Gaussian
    high-frequency roll-off of scale ``psd_rolloff_mm`` (waviness: without it the spectrum's tail bends the glass
    far beyond what deflectometry images resolve). Both are levelled on the frame and scaled to ``range_um`` like
    §1.9. ``broadband_rms_nm`` adds a flat-spectrum part of that RMS at wavelengths between
    ``broadband_min_wavelength_mm`` and ``broadband_wavelength_mm`` (kinds ``random`` and ``psd``), the nm-level
    short-wavelength content real glass has. ``bow_um`` adds a paraboloidal bow of that sagitta (centre above the
    corners for a positive value) after the scaling, then the surface is levelled on the frame again: ``range_um`` is
    then the waviness's range, not the whole surface's (kinds ``random`` and ``psd``). A cut sheet's edges roll off:
    ``edge_rolloff_um`` lowers the heights within ``edge_rolloff_mm`` of each of the four edges by
    depth x (1 - d / width)^3 at distance d from the edge (slope 3 x depth / width at the edge; the two bands add up
    at the corners); ``features`` adds local dimples and bumps (:class:`FeatureSpec`). Bow, roll-off and features are
    added after the scaling and the surface is levelled on the frame once more (kinds ``random`` and ``psd``).
    """

    kind: Literal["random", "psd", "plane", "sphere", "saddle", "cylinder", "file"] = "random"
    range_um: float = Field(40.0, ge=0, le=2.0e4, description="peak-to-valley height range, µm (§1.10: 40 µm)")
    correlation_length: Positive = Field(12.0, description="low-pass correlation length (§1.9) or PSD B, mm")
    seed: int = Field(1, ge=0, le=2**32 - 1)
    grid: tuple[Annotated[int, Field(ge=4)], Annotated[int, Field(ge=4)]] = Field(
        (256, 512), description="height-map nodes (nx, ny)"
    )
    path: str | None = Field(None, description="height-map EXR (kind = 'file')")
    spectrum: Literal["abc", "power"] = Field("abc", description="PSD model of kind 'psd'")
    psd_exponent: float = Field(3.0, gt=0, le=12, description="C of the ABC model / power-law exponent")
    psd_rolloff_mm: float = Field(
        6.0, ge=0, le=1.0e4, description="high-frequency roll-off of kind 'psd': PSD x exp(-4 pi^2 s^2 f^2), s in mm"
    )
    broadband_rms_nm: float = Field(0.0, ge=0, le=1000, description="RMS of the broadband part, nm")
    broadband_wavelength_mm: Positive = Field(4.0, description="longest wavelength of the broadband part, mm")
    broadband_min_wavelength_mm: Positive = Field(0.5, description="shortest wavelength of the broadband part, mm")
    bow_um: float = Field(0.0, ge=-1.0e3, le=1.0e3, description="sagitta of a paraboloidal bow (centre - corners), µm")
    edge_rolloff_um: float = Field(
        0.0, ge=-1.0e3, le=1.0e3, description="drop of the heights at each cut edge (negative: the edges rise), µm"
    )
    edge_rolloff_mm: Positive = Field(3.0, le=100.0, description="width of the band each edge rolls off over, mm")
    features: tuple[FeatureSpec, ...] = Field((), max_length=256, description="local dimples and bumps")

    @model_validator(mode="after")
    def _check(self) -> SurfaceSpec:
        if self.kind == "file" and not self.path:
            raise ValueError("surface kind 'file' needs a path")
        if self.broadband_min_wavelength_mm >= self.broadband_wavelength_mm:
            raise ValueError(
                f"broadband_min_wavelength_mm ({self.broadband_min_wavelength_mm}) must be below "
                f"broadband_wavelength_mm ({self.broadband_wavelength_mm})"
            )
        if self.broadband_rms_nm > 0 and self.kind not in ("random", "psd"):
            raise ValueError(f"broadband_rms_nm needs surface kind 'random' or 'psd', not {self.kind!r}")
        for name, used in (
            ("bow_um", self.bow_um != 0),
            ("edge_rolloff_um", self.edge_rolloff_um != 0),
            ("features", bool(self.features)),
        ):
            if used and self.kind not in ("random", "psd"):
                raise ValueError(f"{name} needs surface kind 'random' or 'psd', not {self.kind!r}")
        return self


#: 4-byte numbers per height-map node while a surface is generated and written (float64 noise, its FFT, the
#: filtered and levelled copies): an estimate for :func:`scopetwin.scenes.limits.check_image_size`.
SURFACE_FLOATS_PER_NODE = 24


class SubstrateSpec(_Model):
    """The bent substrate on its holding frame (thesis §1.4, §1.10)."""

    size: Vec2 = Field((25.2, 57.0), description="(x, y) extent, mm")
    roi_length: Positive = Field(48.0, description="gap between the frame regions along y, mm")
    surface: SurfaceSpec = SurfaceSpec()

    @model_validator(mode="after")
    def _check(self) -> SubstrateSpec:
        if min(self.size) <= 0:
            raise ValueError(f"size must be > 0 mm, got {self.size}")
        if self.roi_length > self.size[1]:
            raise ValueError(f"roi_length {self.roi_length} mm exceeds the substrate length {self.size[1]} mm")
        nx, ny = self.surface.grid
        check_image_size(nx, ny, "surface.grid", SURFACE_FLOATS_PER_NODE)
        return self


class MirrorSpec(_Model):
    """A flat mirror lying on the holding frame, in the plane z = 0 (thesis §2.7.2)."""

    size: tuple[Positive, Positive] = Field((60.0, 80.0), description="(x, y) extent, mm")


class PatternStageSpec(_Model):
    """A stage that moves the pattern along its normal N_z to a second known position (thesis §1.3: a second
    measurement resolves the height-normal ambiguity; :mod:`scopetwin.scenes.pattern_stage`).

    The first position is the pattern's pose above; the second lies ``shift_mm`` from it along N_z (positive towards
    the substrate in the §1.10 setup, whose N_z faces it).
    """

    shift_mm: float = Field(ge=-500.0, le=500.0, description="second position's distance along the pattern's N_z, mm")

    @model_validator(mode="after")
    def _check(self) -> PatternStageSpec:
        if self.shift_mm == 0:
            raise ValueError("shift_mm must not be 0 (the second position must differ from the first)")
        return self


class DisplaySpec(_Model):
    """The fringe display in the pattern plane (:class:`scopetwin.scenes.fringes.FringeDisplay`)."""

    pixel_pitch: Positive = Field(fr.DEFAULT_PITCH_MM, description="display pixel pitch, mm")
    size: tuple[Positive, Positive] = Field(fr.DEFAULT_SIZE_MM, description="active area (x, y), mm")
    gamma: float = Field(fr.DEFAULT_GAMMA, gt=0, le=10.0, description="radiance = driven value ** gamma")
    gamma_correction: float = Field(fr.DEFAULT_GAMMA, gt=0, le=10.0, description="gamma the driver's LUT inverts")
    black_level: float = Field(fr.DEFAULT_BLACK_LEVEL, ge=0, lt=1, description="relative radiance at driven 0")
    blur_px: float = Field(fr.DEFAULT_BLUR_PX, ge=0, le=100.0, description="Gaussian blur sigma, display pixels")
    bit_depth: int = Field(fr.DEFAULT_BIT_DEPTH, ge=1, le=16, description="bits of the driven value")

    def display(self) -> fr.FringeDisplay:
        """The display model."""
        return fr.FringeDisplay(
            self.pixel_pitch,
            self.size,
            self.gamma,
            self.black_level,
            self.blur_px,
            self.bit_depth,
            self.gamma_correction,
        )


class FringeSequenceSpec(_Model):
    """The phase-shifting sequence (:class:`scopetwin.scenes.fringes.FringeSequence`)."""

    periods: tuple[Positive, ...] = Field(fr.DEFAULT_PERIODS_MM, description="fringe periods, mm, coarsest first")
    steps: int = Field(fr.DEFAULT_STEPS, ge=4, le=1024, description="phase steps per period and direction")

    def sequence(self) -> fr.FringeSequence:
        """The sequence."""
        return fr.FringeSequence(tuple(self.periods), self.steps)


class FringesSpec(_Model):
    """A fringe display replacing the marker pattern (phase-measuring deflectometry; :mod:`scopetwin.scenes.fringes`).

    The display lies in the pattern's plane and frame (``[pattern]`` origin and axes); the pattern's ``radiance``
    scales the display's relative radiance.
    """

    display: DisplaySpec = DisplaySpec()
    sequence: FringeSequenceSpec = FringeSequenceSpec()

    @model_validator(mode="after")
    def _check(self) -> FringesSpec:
        try:
            self.sequence.sequence().check_display(self.display.display())
        except SetupError as exc:
            raise ValueError(str(exc)) from None
        return self


class RenderSpec(_Model):
    """Rendering options."""

    spp: PositiveInt = Field(16, le=2**31 - 1, description="samples per pixel (the render time is checked on use)")
    seed: int = Field(0, ge=0, le=2**32 - 1, description="sampler seed (Mitsuba takes 32 bits)")
    noise: bool = Field(False, description="apply the EMVA sensor model")


class NoiseModelSpec(_Model):
    """The camera's EMVA 1288 noise model and exposure (:class:`scopetwin.scenes.emva1288.EmvaSensor`).

    The setup field that holds it keeps its TOML key ``[sensor]``.
    """

    quantum_efficiency: Annotated[float, Field(gt=0, le=1)] = 0.55
    full_well_e: Positive = 18000.0
    dark_noise_e: Annotated[float, Field(ge=0, le=1.0e9)] = 10.0
    gain_dn_per_e: Positive = 4000.0 / 18000.0
    black_level_dn: Annotated[float, Field(ge=0, le=2.0**32)] = 32.0
    bit_depth: Annotated[int, Field(ge=1, le=32)] = 12
    photons_per_unit_s: float = Field(
        1.0e6, ge=1.0e-9, le=1.0e15, description="photons per pixel and second at irradiance 1"
    )
    exposure_s: Positive | None = Field(None, description="None: fill `fill_fraction` of the full well")
    fill_fraction: Annotated[float, Field(gt=0, le=1)] = 0.7

    def sensor(self) -> EmvaSensor:
        return EmvaSensor(
            self.quantum_efficiency,
            self.full_well_e,
            self.dark_noise_e,
            self.gain_dn_per_e,
            self.black_level_dn,
            self.bit_depth,
        )


class PoseUncertaintySpec(_Model):
    """Standard deviations of a calibrated pose (thesis §2.7): position (mm) and orientation (rad)."""

    shift_mm: float = Field(ge=0.0, le=MAX_COORD_MM, description="standard deviation of the position, mm")
    rotation_rad: float = Field(ge=0.0, le=TURN_RAD, description="standard deviation of the orientation, rad")


class CalibrationSpec(_Model):
    """The uncertainties of a calibrated setup's camera and pattern poses (``calibrate-setup`` writes them)."""

    camera: PoseUncertaintySpec
    pattern: PoseUncertaintySpec


class Setup(_Model):
    """One physical scene of Part I (module docstring)."""

    name: str = "custom"
    section: str = Field("", description="thesis section the setup comes from")
    description: str = ""
    scene: Literal["deflectometry", "target", "mirror"]
    camera: CameraSpec
    pattern: PatternSpec
    substrate: SubstrateSpec | None = None
    mirror: MirrorSpec | None = None
    render: RenderSpec = RenderSpec()
    sensor: NoiseModelSpec = NoiseModelSpec()
    calibration: CalibrationSpec | None = None
    pattern_stage: PatternStageSpec | None = None
    fringes: FringesSpec | None = None

    @model_validator(mode="after")
    def _check(self) -> Setup:
        if self.fringes is not None and self.scene == "target":
            raise ValueError("a [fringes] display needs a deflectometry or mirror setup, not a target scene")
        if self.scene == "deflectometry" and self.substrate is None:
            raise ValueError("a deflectometry setup needs a [substrate] table")
        if self.pattern_stage is not None and self.scene != "deflectometry":
            raise ValueError("a [pattern_stage] needs a deflectometry setup")
        if self.scene == "mirror" and self.mirror is None:
            raise ValueError("a mirror setup needs a [mirror] table")
        return self

    @cached_property
    def camera_model(self) -> Camera:
        return self.camera.camera()

    @cached_property
    def marker_pattern(self) -> MarkerPattern:
        return self.pattern.pattern()

    @cached_property
    def fringe_display(self) -> fr.FringeDisplay | None:
        """The fringe display of a ``[fringes]`` setup, None for a marker setup."""
        return None if self.fringes is None else self.fringes.display.display()

    @cached_property
    def fringe_sequence(self) -> fr.FringeSequence | None:
        """The fringe sequence of a ``[fringes]`` setup, None for a marker setup."""
        return None if self.fringes is None else self.fringes.sequence.sequence()

    def to_json(self) -> str:
        """Compact JSON of the setup (for image headers); a marker setup's holds no ``fringes`` key."""
        return self.model_dump_json(exclude={"fringes"} if self.fringes is None else None)


# -- loading ------------------------------------------------------------------------------
def preset_names() -> list[str]:
    """Names of all presets shipped in scenes/presets/."""
    return sorted(p.stem for p in PRESET_DIR.glob("*.toml"))


def preset_info() -> list[dict[str, str]]:
    """Name, kind, section and description of every preset."""
    out = []
    for name in preset_names():
        data = _read_toml(PRESET_DIR / f"{name}.toml")
        out.append(
            {
                "name": name,
                "kind": str(data.get("kind", data.get("scene", ""))),
                "section": str(data.get("section", "")),
                "description": str(data.get("description", "")),
            }
        )
    return out


def _read_toml(path: Path) -> dict[str, Any]:
    """A setup TOML: a regular file of at most 16 MiB, nested at most 64 levels (:mod:`scopetwin.scenes.inputs`)."""
    try:
        return load_toml_input(path, "setup")
    except InputError as exc:
        raise SetupError(str(exc)) from None


def _merge(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _merge(out[key], value)
        else:
            out[key] = value
    return out


def resolve_toml(name_or_path: str | Path, _depth: int = 0, _folder: Path | None = None) -> tuple[dict[str, Any], str]:
    """Raw dictionary of a preset or TOML file with its ``base`` chain merged in; and a label for messages.

    A ``base`` that names a file is found beside the TOML that names it (a relative path is relative to that
    TOML's folder, not to the current one); a ``base`` that names a preset is the preset.
    """
    if _depth > 8:
        raise SetupError("setup 'base' chain is too deep (a cycle?)")
    text = str(name_or_path)
    path = Path(text)
    if text in preset_names():
        path = PRESET_DIR / f"{text}.toml"
    else:
        if _folder is not None and not path.is_absolute():
            path = _folder / path
        if not (path.suffix == ".toml" or os.path.lexists(path)):
            raise SetupError(f"unknown preset {text!r} (known presets: {', '.join(preset_names())})")
        if not os.path.lexists(path):
            where = f" (base of a setup in {_folder})" if _folder is not None else ""
            raise SetupError(f"setup file {path} does not exist{where}")
    data = _read_toml(path)
    base = data.pop("base", None)
    if base is not None:
        if not isinstance(base, str):
            raise SetupError(f"setup file {path}: base must be a preset name or a TOML file name, got {base!r}")
        base_data, _ = resolve_toml(base, _depth + 1, path.parent)
        base_data.pop("name", None)
        data = _merge(base_data, data)
    data.setdefault("name", path.stem)
    return data, str(text)


def _format_validation(exc: ValidationError, label: str) -> str:
    err = exc.errors()[0]
    loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
    msg = err["msg"].removeprefix("Value error, ")
    more = f" (and {len(exc.errors()) - 1} more problems)" if len(exc.errors()) > 1 else ""
    return f"setup {label}: field {loc}: {msg}{more}"


def setup_from_dict(data: dict[str, Any], label: str = "<dict>") -> Setup:
    """Validate a setup dictionary; errors name the field and the reason."""
    data = dict(data)
    data.pop("kind", None)
    try:
        return Setup.model_validate(data)
    except ValidationError as exc:
        raise SetupError(_format_validation(exc, label)) from None


def load_setup(name_or_path: str | Path, overrides: dict[str, Any] | None = None) -> Setup:
    """Load a preset by name or a TOML file (with its ``base`` chain), apply ``overrides``, validate.

    Raises
    ------
    SetupError
        Unknown preset, unreadable file, invalid TOML, or a field that fails validation
        (the message names the field and the reason).
    """
    data, label = resolve_toml(name_or_path)
    kind = data.get("kind")
    if kind not in (None, "setup"):
        raise SetupError(f"{label} is a {kind!r} preset, not a Part I setup")
    if overrides:
        data = _merge(data, overrides)
    return setup_from_dict(data, label)


def setup_from_json(text: str) -> Setup:
    """Inverse of :meth:`Setup.to_json` (e.g. from an image header)."""
    try:
        data = parse_json(text, "setup", "JSON")  # bounded nesting: an image header's setup is input too
    except InputError as exc:
        raise SetupError(str(exc)) from None
    if not isinstance(data, dict):
        raise SetupError(f"setup JSON must be an object, got {type(data).__name__}")
    return setup_from_dict(data, "<json>")
