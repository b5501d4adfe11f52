"""The compact microscope unit as a pydantic setup (thesis §4.1, §5.1.2), loaded from ``thesis-cmu`` or a TOML file.

Global frame: the object plane is z = 0, the objective's axis is +z, the objective (a perfect thin lens) sits at
z = f_objective so that the object lies in its front focal plane and every object point leaves it as a plane wave
(infinity-corrected, §3.4.1). The emission paths of §4.1.3 fold in the x-z plane. Each plate has its own frame
(origin = centre, N_z = ``normal`` facing the light coming from the objective, T_y = ``long_axis`` (the 36 mm
side), T_x = T_y x N_z); its coated front surface is z_local = h(x, y), its back surface h(x, y) - thickness.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from scopetwin.scenes.camera_spec import PixelGridSpec
from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.geometry import Frame
from scopetwin.scenes.limits import check_image_size

Vec3 = tuple[float, float, float]
Positive = Annotated[float, Field(gt=0, ge=1e-9, le=1e9)]  # finite and in a physical range
CHANNEL_NAMES = ("blue", "green", "red", "nir")


class _Model(BaseModel):
    """Base of the unit's tables: unknown keys and non-finite numbers (``inf``, ``nan``) are rejected."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _unit(v: Vec3, name: str) -> np.ndarray:
    a = np.asarray(v, dtype=np.float64)
    n = np.linalg.norm(a)
    if not n > 0:
        raise ValueError(f"{name} must be a non-zero vector")
    return a / n


class ObjectiveSpec(_Model):
    """The objective of §4.1.2, modelled as a perfect lens (§5.1.2)."""

    focal_length: Positive = 16.45
    beam_diameter: Positive = 20.0
    na: Annotated[float, Field(gt=0, lt=1)] = 0.45


class TubeSpec(_Model):
    """Tube lens (§4.1.2) and the optional aperture stop in front of it (§5.1.2)."""

    focal_length: Positive = 164.5
    stop_diameter: Positive = 4.0
    stop_gap: Positive = 5.0


class CmuCameraSpec(PixelGridSpec):
    """A channel camera: Basler scA1400-30gm, 1392 x 1040 px of 6.45 µm, 12 bit (§4.1.4); TOML table ``[camera]``.

    Numbers must be finite and one image must fit in this machine's memory
    (:func:`scopetwin.scenes.limits.check_image_size`).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    width_px: Annotated[int, Field(gt=0)] = 1392
    height_px: Annotated[int, Field(gt=0)] = 1040
    pixel_um: Annotated[float, Field(ge=0.1, le=1000.0)] = 6.45  # 0.1 µm to 1 mm
    bit_depth: Annotated[int, Field(ge=1, le=16)] = 12

    @model_validator(mode="after")
    def _fits(self) -> CmuCameraSpec:
        check_image_size(self.width_px, self.height_px, "width_px x height_px")
        return self


class PlateSpec(_Model):
    """Size and glass of the beam-splitter plates (§4.1.3)."""

    width: Positive = 25.5
    height: Positive = 36.0
    thickness: Positive = 1.0
    glass: Literal["fused silica"] = "fused silica"


class ElementSpec(_Model):
    """A splitter or mirror: pose, and its surface (a spherical bow of ``bow_range_um`` plus a residual, or a map)."""

    center: Vec3
    normal: Vec3
    long_axis: Vec3
    bow_range_um: Annotated[float, Field(ge=0)] = 0.0
    residual_rms_um: Annotated[float, Field(ge=0)] = 0.0
    residual_seed: int = 0
    concave: bool = True
    height_map: str | None = Field(default=None, description="EXR height map (plate-local mm), replaces the model")

    @model_validator(mode="after")
    def _check(self) -> ElementSpec:
        n = _unit(self.normal, "normal")
        t = _unit(self.long_axis, "long_axis")
        if abs(float(n @ t)) > 1e-6:
            raise ValueError("long_axis must be perpendicular to normal")
        return self

    def frame(self) -> Frame:
        """Plate frame: N_z = normal, T_y = long axis, T_x = T_y x N_z."""
        nz = _unit(self.normal, "normal")
        ty = _unit(self.long_axis, "long_axis")
        return Frame(np.asarray(self.center, dtype=np.float64), np.cross(ty, nz), ty, nz)


class ChannelSpec(_Model):
    """One emission channel: its path through the splitters/mirrors (``NAME:R`` or ``NAME:T``) and its tube lens."""

    path: list[str]
    tube_center: Vec3
    tube_axis: Vec3 = (0.0, 0.0, 1.0)
    filter: str

    @model_validator(mode="after")
    def _check(self) -> ChannelSpec:
        for step in self.path:
            name, _, mode = step.partition(":")
            if mode not in ("R", "T") or not name:
                raise ValueError(f"path step {step!r} must be NAME:R or NAME:T")
        _unit(self.tube_axis, "tube_axis")
        return self

    def steps(self) -> list[tuple[str, str]]:
        return [tuple(s.split(":", 1)) for s in self.path]  # type: ignore[misc]


class TargetSpec(_Model):
    """Siemens star with a square frame (§5.2.2)."""

    spokes: Annotated[int, Field(ge=4)] = 30
    star_radius: Positive = 0.2
    frame_side: Positive = 0.5
    frame_line: Positive = 0.01

    @model_validator(mode="after")
    def _check(self) -> TargetSpec:
        if 2 * self.star_radius >= self.frame_side:
            raise ValueError(
                f"the star (diameter {2 * self.star_radius} mm) must fit inside the frame ({self.frame_side} mm)"
            )
        return self


class CellsSpec(_Model):
    """Dummy cells of §5.1.2."""

    count: Annotated[int, Field(ge=1)] = 500
    length: Positive = 0.05
    width: Positive = 0.025
    seed: int = 5


class CmuSetup(_Model):
    """The whole unit (thesis §4.1, §5.1.2, §5.2.2)."""

    name: str = ""
    kind: Literal["cmu"] = "cmu"
    section: str = ""
    description: str = ""
    objective: ObjectiveSpec = ObjectiveSpec()
    tube: TubeSpec = TubeSpec()
    camera: CmuCameraSpec = CmuCameraSpec()
    plate: PlateSpec = PlateSpec()
    splitters: dict[str, ElementSpec]
    mirrors: dict[str, ElementSpec] = {}
    channels: dict[str, ChannelSpec]
    target: TargetSpec = TargetSpec()
    cells: CellsSpec = CellsSpec()

    @model_validator(mode="after")
    def _check(self) -> CmuSetup:
        known = set(self.splitters) | set(self.mirrors)
        for cname, ch in self.channels.items():
            if cname not in CHANNEL_NAMES:
                raise ValueError(f"unknown channel {cname!r} (channels: {', '.join(CHANNEL_NAMES)})")
            for name, mode in ch.steps():
                if name not in known:
                    raise ValueError(f"channel {cname}: unknown element {name!r}")
                if name in self.mirrors and mode != "R":
                    raise ValueError(f"channel {cname}: mirror {name} can only reflect")
        return self

    def element(self, name: str) -> ElementSpec:
        return self.splitters[name] if name in self.splitters else self.mirrors[name]

    @property
    def field_mm(self) -> tuple[float, float]:
        """Object-side field of the camera at magnification 10: 0.8978 x 0.6708 mm (§4.1.1, §5.1.2)."""
        m = self.tube.focal_length / self.objective.focal_length
        p = self.camera.pixel_um * 1e-3 / m
        return self.camera.width_px * p, self.camera.height_px * p

    def to_json(self) -> str:
        return self.model_dump_json()


def cmu_setup_from_dict(data: dict[str, Any], label: str = "<dict>") -> CmuSetup:
    """Validate a CMU setup dictionary (errors name the field)."""
    from scopetwin.scenes.setup import _format_validation

    data = dict(data)
    data.pop("base", None)
    if data.get("kind", "cmu") != "cmu":
        raise SetupError(f"{label} is a {data.get('kind')!r} preset, not a 'cmu' setup")
    try:
        return CmuSetup.model_validate(data)
    except ValidationError as exc:
        raise SetupError(_format_validation(exc, label)) from None


def load_cmu_setup(name_or_path: str | Path = "thesis-cmu", overrides: dict[str, Any] | None = None) -> CmuSetup:
    """Load ``thesis-cmu`` (or a TOML with ``base = "thesis-cmu"``), apply overrides, validate.

    Raises
    ------
    SetupError
        Unknown preset, unreadable/invalid TOML, not ``kind = "cmu"``, or a field that fails validation.
    """
    from scopetwin.scenes.setup import _merge, resolve_toml

    data, label = resolve_toml(name_or_path)
    if overrides:
        data = _merge(data, overrides)
    return cmu_setup_from_dict(data, label)
