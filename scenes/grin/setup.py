"""GRIN objective setups (thesis §7.5.2, §8.2.2, §8.3.1, §8.3.2) as pydantic v2 models, and their layer stack.

The objective of the miniaturised parallel microscope is a stack of flat layers along z
(thesis §7.5.2, Fig. 7.6; §8.3): the object lies on a 160 µm cover glass; an air gap; the
first GRIN rod on a 500 µm AF32 substrate; the 2 mm beam-splitter layer (B270 stands in for
the polymer, §8.3); the second substrate and GRIN rod; air; the image plane (the camera).

The published layout is under-determined; the readings are fields here:

* ``layout.substrate1_side`` / ``substrate2_side`` -- ``"inner"``: the substrate lies between its
  rod and the beam splitter (the reading of §7.5.2's sentence order: "the first GRIN rod lens ...
  is located on a 500 µm glass substrate ... the next component is the beam splitter layer ...
  followed by a glass substrate ... and the second GRIN rod lens"); ``"outer"``: the substrate
  faces the object (resp. the camera).
* ``object.distance_includes_cover`` -- whether the object distance (0.8 mm, 0.807 mm) is the air
  gap behind the cover glass (False) or runs from the object through the cover glass (True).
* ``rod*.profile.wavelength_ref_nm`` -- at which wavelength GrinTech's n0, nr2, nr4 hold (None:
  at the design wavelength itself).

Every length is in mm, wavelengths in nm (docs/contract.md, "Units"). The stack starts with the object plane at
z = 0 and runs towards the camera (+z).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from scopetwin.scenes.camera_spec import PixelGridSpec
from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.grin.glass import AIR, Glass, glass
from scopetwin.scenes.grin.profiles import (
    GradientDispersion,
    ParabolicN2Profile,
    PolynomialProfile,
    RadialProfile,
    SechProfile,
)
from scopetwin.scenes.limits import check_image_size

Positive = Annotated[float, Field(gt=0, ge=1e-9, le=1e9)]  # finite and in a physical range
#: Most RKN steps through one rod: 0.01 mm steps (float64 position error ~0.005 nm, docs/rendering.md) through a
#: 40 mm rod are 4000; beyond 1e5 a trace only costs time.
MAX_RKN_STEPS = 100_000
NonNegative = Annotated[float, Field(ge=0, le=1e9)]
#: A wavelength of light, nm: ultraviolet to infrared (the glasses' dispersion data hold there).
Wavelength = Annotated[float, Field(ge=200.0, le=5000.0)]


def _known_glass(name: str) -> str:
    """Validator body: the glass must be in the catalogue (scenes.grin.glass); returns its canonical name."""
    try:
        glass(name)
    except SetupError as exc:
        raise ValueError(str(exc)) from None
    return name.upper()


class _Model(BaseModel):
    """Base of the GRIN setup tables: unknown keys and non-finite numbers (``inf``, ``nan``) are rejected."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# -- profiles -------------------------------------------------------------------------------
class PolynomialSpec(_Model):
    """GrinTech Taylor profile n = n0 + nr2 r² + nr4 r⁴ + nr6 r⁶ (thesis §7.5.1) with its dispersion.

    ``wavelength_ref_nm = None`` means the coefficients are taken as they are at the design
    wavelength (the thesis gives no wavelength for them). Otherwise they hold at
    ``wavelength_ref_nm`` and :class:`~scopetwin.scenes.grin.profiles.GradientDispersion` with ``abbe_n0``
    and ``abbe_gradient`` moves them to the design wavelength. The two Abbe numbers are
    assumptions (no GrinTech dispersion data was available to this project): 35 for the
    high-index silver-containing base glass, 25 for the gradient (ion-exchange profiles
    disperse more than their base glass).
    """

    kind: Literal["polynomial"] = "polynomial"
    n0: Annotated[float, Field(gt=1)] = 1.62893
    nr2: float = -0.077
    nr4: float = 0.00315
    nr6: float = 0.0
    wavelength_ref_nm: Positive | None = None
    abbe_n0: Positive = 35.0
    abbe_gradient: Positive = 25.0

    def at(self, wavelength_nm: float) -> RadialProfile:
        """Monochromatic profile at ``wavelength_nm``."""
        base = PolynomialProfile(self.n0, self.nr2, self.nr4, self.nr6)
        if self.wavelength_ref_nm is None:
            return base
        disp = GradientDispersion(self.wavelength_ref_nm, self.abbe_n0, self.abbe_gradient)
        return disp.apply(base, wavelength_nm)


class SechSpec(_Model):
    """n = n0 sech(g r) (thesis §7.5.1: the ideal profile), no dispersion."""

    kind: Literal["sech"]
    n0: Annotated[float, Field(gt=1)]
    g: Positive

    def at(self, wavelength_nm: float) -> RadialProfile:
        return SechProfile(self.n0, self.g)


class ParabolicN2Spec(_Model):
    """n² = n0² (1 - g² r²), no dispersion (exact-solution test profile)."""

    kind: Literal["parabolic_n2"]
    n0: Annotated[float, Field(gt=1)]
    g: Positive

    def at(self, wavelength_nm: float) -> RadialProfile:
        return ParabolicN2Profile(self.n0, self.g)


ProfileSpec = Annotated[PolynomialSpec | SechSpec | ParabolicN2Spec, Field(discriminator="kind")]


class RodSpec(_Model):
    """A radial GRIN rod: cylinder of ``radius`` and ``length`` (mm) with flat faces."""

    length: Positive
    radius: Positive = 1.0
    profile: ProfileSpec = PolynomialSpec()
    step_mm: Positive = 0.1

    @model_validator(mode="after")
    def _steps(self) -> RodSpec:
        if self.length / self.step_mm > MAX_RKN_STEPS:
            raise ValueError(
                f"step_mm = {self.step_mm:g} mm gives {self.length / self.step_mm:.3g} RKN steps through the "
                f"{self.length:g} mm rod, more than {MAX_RKN_STEPS} (the trace time grows with the steps)"
            )
        return self


class PlateSpec(_Model):
    """A homogeneous plate of ``thickness`` mm of a catalogue glass."""

    thickness: Positive
    glass: str

    _known = field_validator("glass")(classmethod(lambda cls, v: _known_glass(v)))


class ObjectSpec(_Model):
    """Object side: cover glass, object distance and field (thesis §7.5.2: 160 µm, 0.8 mm, FOV 400 µm)."""

    distance: Positive = 0.8
    distance_includes_cover: bool = False
    cover_thickness: NonNegative = 0.16
    cover_glass: str = "D263"
    field_radius: Positive = 0.2

    _known = field_validator("cover_glass")(classmethod(lambda cls, v: _known_glass(v)))


class LayoutSpec(_Model):
    """On which side of each rod its substrate lies (see the module docstring)."""

    substrate1_side: Literal["inner", "outer"] = "inner"
    substrate2_side: Literal["inner", "outer"] = "inner"


class ImageSpec(_Model):
    """Image distance from the last surface (mm); None: our own best focus is used."""

    distance: Positive | None = None


class ApertureSpec(_Model):
    """An aperture stop on the back face of the first rod, sized to give object-side NA ``na_object``."""

    na_object: Annotated[float, Field(gt=0, lt=1)] | None = None


class ArraySpec(_Model):
    """Objectives on a square grid (thesis §8.2.2): nx x ny axes at pitch d_L on a substrate of side length."""

    nx: Annotated[int, Field(ge=1, le=64)] = 1
    ny: Annotated[int, Field(ge=1, le=64)] = 1
    pitch: Positive = 2.25
    substrate_side: Positive = 14.6

    def axes(self) -> list[tuple[float, float]]:
        """(x, y) of every optical axis, centred on the substrate, row-major from -x/-y."""
        x0 = -0.5 * (self.nx - 1) * self.pitch
        y0 = -0.5 * (self.ny - 1) * self.pitch
        return [(x0 + i * self.pitch, y0 + j * self.pitch) for j in range(self.ny) for i in range(self.nx)]


class GrinCameraSpec(PixelGridSpec):
    """The camera behind the objective (thesis §8.4.3: AVT Guppy, 2.2 µm pixels; S_min = 4.28 mm, §8.2.2).

    Numbers must be finite and one image must fit in this machine's memory
    (:func:`scopetwin.scenes.limits.check_image_size`).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    width_px: Annotated[int, Field(ge=1)] = 2592
    height_px: Annotated[int, Field(ge=1)] = 1944
    pixel_um: Annotated[float, Field(ge=0.1, le=1000.0)] = 2.2  # 0.1 µm to 1 mm

    @model_validator(mode="after")
    def _fits(self) -> GrinCameraSpec:
        check_image_size(self.width_px, self.height_px, "width_px x height_px")
        return self


class IlluminationSpec(_Model):
    """Illumination path of thesis §7.5.3 (unfolded at the beam splitter).

    Square Lambertian LED (0.5 mm, 488 nm, 1 mW) at ``led_distance`` in front of an illumination
    GRIN rod of ``rod_length``; the light crosses half of the beam-splitter layer, is reflected at
    the 45° splitter (``splitter_reflectance``, not given in the thesis: an assumption), crosses
    the other half, the substrate and the object-side rod backwards, to the object plane.
    """

    led_side: Positive = 0.5
    wavelength_nm: Wavelength = 488.0
    power_mw: Positive = 1.0
    led_distance: Positive = 2.427
    rod_length: Positive = 2.369
    rod1_length: Positive | None = None
    splitter_reflectance: Annotated[float, Field(gt=0, le=1)] = 0.9
    fresnel: bool = True


class SeedNumbers(_Model):
    """The thesis's Zemax figures for this design (for side-by-side printing only, never for tuning; nan: not given)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=True)

    magnification: float | None = None
    na_object: float | None = None
    rms_axis_um: float | None = None
    rms_edge_um: float | None = None
    airy_um: float | None = None
    image_distance: float | None = None
    object_distance: float | None = None
    efficiency: float | None = None


class GrinSetup(_Model):
    """One GRIN objective design (thesis §7.5.2 / §8.3.1 / §8.3.2) with its array, camera and thesis figures."""

    name: str = ""
    section: str
    description: str = ""
    wavelength_nm: Wavelength
    object: ObjectSpec = ObjectSpec()
    rod1: RodSpec
    rod2: RodSpec
    substrate: PlateSpec = PlateSpec(thickness=0.5, glass="AF32")
    beam_splitter: PlateSpec = PlateSpec(thickness=2.0, glass="B270")
    layout: LayoutSpec = LayoutSpec()
    image: ImageSpec = ImageSpec()
    aperture: ApertureSpec = ApertureSpec()
    array: ArraySpec = ArraySpec()
    camera: GrinCameraSpec = GrinCameraSpec()
    illumination: IlluminationSpec | None = None
    seed: SeedNumbers = SeedNumbers()
    scene_depth: Positive = 40.0

    @model_validator(mode="after")
    def _check(self) -> GrinSetup:
        for key in ("rod1", "rod2"):
            rod: RodSpec = getattr(self, key)
            if rod.length > self.scene_depth:
                raise ValueError(
                    f"{key}.length = {rod.length} mm is longer than the scene (scene_depth = {self.scene_depth} mm)"
                )
            try:
                rod.profile.at(self.wavelength_nm).check(rod.radius)
            except SetupError as exc:
                raise ValueError(f"{key}.profile: {exc}") from None
            if self.array.nx * self.array.ny > 1 and 2 * rod.radius > self.array.pitch:
                raise ValueError(
                    f"{key}.radius: rods of diameter {2 * rod.radius} mm overlap at the array "
                    f"pitch {self.array.pitch} mm"
                )
        if self.object.distance_includes_cover and self.object.distance <= self.object.cover_thickness:
            raise ValueError("object.distance must exceed the cover glass thickness when it includes it")
        half = 0.5 * self.array.substrate_side
        for x, y in self.array.axes():
            r = max(self.rod1.radius, self.rod2.radius)
            if abs(x) + r > half or abs(y) + r > half:
                raise ValueError(
                    f"array: an objective at ({x:g}, {y:g}) mm does not fit on the "
                    f"{self.array.substrate_side} mm substrate"
                )
        stack_length = self.stack(image_distance=self.image.distance or 0.0).length
        if stack_length > self.scene_depth:
            raise ValueError(
                f"the objective ({stack_length:.3f} mm from object to image) is longer than the "
                f"scene (scene_depth = {self.scene_depth} mm)"
            )
        return self

    def profile1(self) -> RadialProfile:
        """Monochromatic profile of rod 1 at the design wavelength."""
        return self.rod1.profile.at(self.wavelength_nm)

    def profile2(self) -> RadialProfile:
        """Monochromatic profile of rod 2 at the design wavelength."""
        return self.rod2.profile.at(self.wavelength_nm)

    def stack(self, image_distance: float | None = None, wavelength_nm: float | None = None) -> Stack:
        """The layer stack from the object plane (z = 0) to the image plane (see :func:`build_stack`)."""
        return build_stack(self, image_distance, wavelength_nm)

    def to_json(self) -> str:
        """Compact JSON of the setup (for image headers)."""
        return self.model_dump_json()


# -- the layer stack ------------------------------------------------------------------------
@dataclass(frozen=True)
class Layer:
    """One slab z0 <= z <= z1 of the stack: homogeneous (``glass``) or a GRIN rod (``rod``, ``profile``).

    Outside a rod's radius a rod layer is ``glass`` (air: the holding structures are not modelled);
    rays that meet the rod's wall are absorbed (thesis §8.4.1: blackened SU-8 holders).
    """

    name: str
    z0: float
    z1: float
    glass: Glass
    index: float
    rod: RodSpec | None = None
    profile: RadialProfile | None = None

    @property
    def thickness(self) -> float:
        return self.z1 - self.z0


@dataclass(frozen=True)
class Stack:
    """The sequential layers of one objective at one wavelength, object plane z = 0 to image plane."""

    layers: tuple[Layer, ...]
    wavelength_nm: float
    image_distance: float
    stop_z: float
    stop_radius: float | None

    @property
    def length(self) -> float:
        return self.layers[-1].z1 if self.layers else 0.0

    @property
    def last_surface_z(self) -> float:
        """z of the objective's last surface (the image-side air gap begins here)."""
        return self.layers[-1].z0

    def rods(self) -> list[Layer]:
        return [layer for layer in self.layers if layer.rod is not None]

    def with_stop_radius(self, radius: float | None) -> Stack:
        return Stack(self.layers, self.wavelength_nm, self.image_distance, self.stop_z, radius)

    def with_image_distance(self, distance: float) -> Stack:
        last = self.layers[-1]
        layers = self.layers[:-1] + (Layer(last.name, last.z0, last.z0 + distance, last.glass, last.index),)
        return Stack(layers, self.wavelength_nm, distance, self.stop_z, self.stop_radius)


def build_stack(setup: GrinSetup, image_distance: float | None = None, wavelength_nm: float | None = None) -> Stack:
    """Layers of ``setup`` at ``wavelength_nm`` (default: the design wavelength), object at z = 0.

    The order follows the readings in ``setup.layout`` and ``setup.object``; the image-side air gap
    has length ``image_distance`` (default: the setup's, else 0 as a placeholder for analysis).
    """
    lam = setup.wavelength_nm if wavelength_nm is None else wavelength_nm
    air = AIR
    items: list[tuple[str, Glass, float, RodSpec | None]] = []
    obj = setup.object
    cover = glass(obj.cover_glass)
    if obj.cover_thickness > 0:
        items.append(("cover", cover, obj.cover_thickness, None))
    gap = obj.distance - (obj.cover_thickness if obj.distance_includes_cover else 0.0)
    items.append(("object_gap", air, gap, None))
    sub = glass(setup.substrate.glass)
    bs = glass(setup.beam_splitter.glass)
    rod1 = ("rod1", air, setup.rod1.length, setup.rod1)
    rod2 = ("rod2", air, setup.rod2.length, setup.rod2)
    sub1 = ("substrate1", sub, setup.substrate.thickness, None)
    sub2 = ("substrate2", sub, setup.substrate.thickness, None)
    items += [sub1, rod1] if setup.layout.substrate1_side == "outer" else [rod1, sub1]
    items.append(("beam_splitter", bs, setup.beam_splitter.thickness, None))
    items += [rod2, sub2] if setup.layout.substrate2_side == "outer" else [sub2, rod2]
    dist = setup.image.distance if image_distance is None else image_distance
    items.append(("image_gap", air, dist or 0.0, None))
    layers = []
    z = 0.0
    stop_z = 0.0
    for name, gl, t, rod in items:
        profile = rod.profile.at(lam) if rod is not None else None
        layers.append(Layer(name, z, z + t, gl, gl.index(lam), rod, profile))
        z += t
        if name == "rod1":
            stop_z = z
    return Stack(tuple(layers), lam, dist or 0.0, stop_z, None)


# -- loading --------------------------------------------------------------------------------
def _format(exc: ValidationError, label: str) -> str:
    err = exc.errors()[0]
    loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
    msg = err["msg"].removeprefix("Value error, ")
    return f"GRIN setup {label}: field {loc}: {msg}"


def grin_setup_from_dict(data: dict[str, Any], label: str = "<dict>") -> GrinSetup:
    """Validate a GRIN setup dictionary; a :class:`SetupError` names the field and the reason."""
    data = dict(data)
    kind = data.pop("kind", "grin")
    if kind != "grin":
        raise SetupError(f'{label} is a {kind!r} setup, not a GRIN objective (kind = "grin")')
    try:
        return GrinSetup.model_validate(data)
    except ValidationError as exc:
        raise SetupError(_format(exc, label)) from None


def load_grin_setup(name_or_path: str | Path, overrides: dict[str, Any] | None = None) -> GrinSetup:
    """Load a GRIN preset by name (``thesis-8.3.2-grin-realized``) or a TOML file (``base = ...`` allowed).

    Raises
    ------
    SetupError
        Unknown preset, unreadable/invalid TOML, not a ``kind = "grin"`` file, or a field that fails
        validation (a profile with n < 1 inside the rod, a rod longer than the scene, ...).
    """
    from scopetwin.scenes.setup import _merge, resolve_toml

    data, label = resolve_toml(name_or_path)
    if overrides:
        data = _merge(data, overrides)
    return grin_setup_from_dict(data, label)


def profile_override(setup: GrinSetup, toml_path: str | Path) -> GrinSetup:
    """Replace rod profiles from a TOML file with tables ``[rod1.profile]`` and/or ``[rod2.profile]``.

    Example (the sech form)::

        [rod1.profile]
        kind = "sech"
        n0 = 1.62893
        g = 0.3075
    """
    from scopetwin.scenes.setup import _merge, _read_toml

    extra = _read_toml(Path(toml_path))
    unknown = set(extra) - {"rod1", "rod2"}
    if unknown:
        raise SetupError(
            f"profile file {toml_path}: only [rod1.profile] / [rod2.profile] tables are allowed, "
            f"got {', '.join(sorted(unknown))}"
        )
    data = json.loads(setup.model_dump_json())
    for key, table in extra.items():
        if not isinstance(table, dict) or set(table) - {"profile"}:
            raise SetupError(f"profile file {toml_path}: [{key}] may only contain a 'profile' table")
        data[key]["profile"] = table["profile"]
    return grin_setup_from_dict(_merge({}, data), str(toml_path))


# -- image windows ----------------------------------------------------------------------------
#: Margin of an objective's image disk over |m| x the target's reach: 5 % for aberrations and distortion at the
#: field edge (the thesis's RMS edge spots are a few µm), plus 4 pixels.
IMAGE_DISK_MARGIN = 0.05
IMAGE_DISK_MARGIN_PX = 4


def image_disks(setup: GrinSetup, magnification: float, reach_mm: float) -> list[tuple[float, float, float]]:
    """(x, y, radius) in mm on the image plane of each objective's image of the object disk of radius ``reach_mm``.

    The objectives' axes are parallel (thesis §8.2.2), so objective k images its field around its own axis (x_k,
    y_k); the target is chrome outside its disk (thesis §8.5), so outside these disks the image is black.
    """
    radius = abs(magnification) * reach_mm * (1 + IMAGE_DISK_MARGIN) + IMAGE_DISK_MARGIN_PX * setup.camera.pitch_mm
    return [(x, y, radius) for x, y in setup.array.axes()]


def _window_misses(disks: list[tuple[float, float, float]], cx: float, cy: float, hx: float, hy: float) -> bool:
    for x, y, r in disks:
        dx = max(abs(x - cx) - hx, 0.0)
        dy = max(abs(y - cy) - hy, 0.0)
        if dx * dx + dy * dy < r * r:
            return False
    return True


def check_image_window(
    setup: GrinSetup,
    width: int,
    height: int,
    center: tuple[float, float],
    magnification: float,
    reach_mm: float,
) -> None:
    """Refuse an image window that misses the image of every objective (it would render all black).

    Parameters
    ----------
    width, height : int
        The image in pixels (of ``setup.camera.pixel_um``), centred on ``center`` (mm, image plane).
    magnification : float
        The objective's lateral magnification (its sign is ignored).
    reach_mm : float
        How far the lit part of the target reaches from an objective's axis, mm (offset + radius).

    Raises
    ------
    SetupError
        Naming the window, the lens centres, the radius of their image disks and the smallest square image
        (in pixels, centred the same) that would see one of them.
    """
    p = setup.camera.pitch_mm
    hx, hy = 0.5 * width * p, 0.5 * height * p
    disks = image_disks(setup, magnification, reach_mm)
    cx, cy = center
    if not _window_misses(disks, cx, cy, hx, hy):
        return
    need = min(max(abs(x - cx), abs(y - cy)) - r / 2**0.5 for x, y, r in disks)  # a square reaching a disk
    side_px = int(2 * max(need, 0.0) / p) + 2
    centres = ", ".join(f"({x:g}, {y:g})" for x, y, _ in disks)
    raise SetupError(
        f"the {width} x {height} px image ({2 * hx:.3g} x {2 * hy:.3g} mm centred on ({cx:g}, {cy:g}) mm) misses "
        f"the image of every objective: lens centres {centres} mm, each imaging its field into a disk of radius "
        f"{disks[0][2]:.3g} mm; the image would be black. Use the camera's full size (no --width/--height) or at "
        f"least --width {side_px} --height {side_px}"
    )
