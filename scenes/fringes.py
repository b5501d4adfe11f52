"""Phase-shifted fringes on a display: the pattern of phase-measuring deflectometry, pure numpy.

The §1.10 setup (thesis §1.10, §1.2) with the marker pattern of §1.6.3 replaced by a display in the same plane: the
display shows sinusoidal fringes along its x and its y axis, ``N >= 4`` phase steps each, at several periods for
temporal (multi-frequency) phase unwrapping. Every camera pixel then decodes its own pattern point, the point its
reflected ray meets (§1.2, eq. 1.1 needs that point and the camera ray), not only the pixels that see a marker.

Coordinates
-----------
Display coordinates (u, v) are mm in the pattern plane's own frame, T_x and T_y from its centre — the coordinates of
the per-pixel truth ``pattern_xy`` of :mod:`scopetwin.sim.datasets.maps`. A frame's *ideal driven value* is

    I(u, v) = 0.5 + 0.5 cos(2 pi w / period + shift),   w = u (direction "x") or v (direction "y"),

so a camera pixel sees I = A + B cos(phi + shift) with phi = 2 pi w / period, the interface of the decoding side.

The display (:class:`FringeDisplay`)
------------------------------------
A grid of square pixels of pitch ``p`` over its active area (centred on the pattern origin). Each display pixel holds
the ideal driven value at its centre, pre-corrected by the driver's look-up table (I ** (1 / gamma_correction)) and
quantised to ``bit_depth`` bits: the driven value d. It emits the relative radiance

    L = black_level + (1 - black_level) * d ** gamma,

uniformly over the pixel (a box), and the panel spreads it by a Gaussian of standard deviation ``blur_px`` display
pixels. Outside the active area the display emits nothing (before the blur). Because a fringe varies along one axis
only, the emitted radiance is separable: ``profile(w) * edge(w_across)`` with, per axis,
``sum_k L_k [Phi((w - a_k) / s) - Phi((w - a_k - p) / s)]`` (a_k the left edge of pixel k, s = blur_px * p, Phi the
normal CDF), evaluated exactly (:meth:`FringeDisplay.radiance`). :meth:`FringeDisplay.texture` rasterises it at texel
centres for the renderer (the light the blur spreads beyond the active area, < 3 s, is cut off there).

Default choices (the §1.10 geometry: camera 233 mm from the substrate, pattern 93 mm beyond it, b = 28 mm, 4.65 µm
pixels)
-------------------------------------------------------------------------------------------------------------------
* Camera footprint on the display: 4.65 µm x (233 + 93) mm / 28 mm = 0.054 mm per camera pixel (in a flat mirror;
  the 40 µm bow changes it by a few %).
* Display pitch 0.05 mm (a 508 ppi panel, as phone displays have): about one display pixel per camera pixel, so the
  pixel grid would show as a staircase. A blur of 0.5 display pixels (the panel's diffuser / cover glass) leaves of
  the grid's first harmonic exp(-2 pi^2 0.5^2) = 0.7 % — below one 8-bit step of the fringe (0.4 %) at the finest
  period's steepest slope.
* Periods 64, 8, 1 mm (coarsest first). 64 mm covers the 50 mm display (|2 pi u / 64| <= 0.78 pi: the coarsest phase
  is unambiguous with 0.2 pi of margin, :meth:`FringeSequence.check_display`). Ratio 8 between successive periods:
  temporal unwrapping fails where the coarser phase times the ratio errs by pi, i.e. at a coarser phase error of
  pi / 8 = 0.39 rad, about 40 times the per-pixel phase noise at 16 spp with sensor noise (docs/rendering.md).
  The finest period, 1 mm, is 20 display pixels (display box and blur keep 98 % of the modulation) and 18 camera
  footprints (the camera pixel's box keeps 99.5 %); its phase noise of ~0.01 rad is 1.6 µm on the display.
* 4 steps (the textbook 4-step formula; shifts 0, pi/2, pi, 3 pi/2), so 24 frames. The decoding is insensitive to
  harmonics of the fringe profile up to order N - 2 = 2: the display's gamma is therefore corrected by the driver's
  look-up table (``gamma_correction = gamma = 2.2``), as a phase-measuring deflectometry system calibrates its screen;
  8 bits leave a quantisation residue of at most half a step.
* Black level 0.001 (a 1000:1 panel).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from scopetwin.scenes.errors import SetupError

if TYPE_CHECKING:
    from scopetwin.scenes.pattern import MarkerPattern

Direction = Literal["x", "y"]
DIRECTIONS: tuple[Direction, Direction] = ("x", "y")

#: Defaults of the display and the sequence (module docstring, "Default choices").
DEFAULT_PITCH_MM = 0.05
DEFAULT_SIZE_MM = (50.0, 50.0)
DEFAULT_GAMMA = 2.2
DEFAULT_BLACK_LEVEL = 0.001
DEFAULT_BLUR_PX = 0.5
DEFAULT_BIT_DEPTH = 8
DEFAULT_PERIODS_MM = (64.0, 8.0, 1.0)
DEFAULT_STEPS = 4
#: Largest ratio of successive periods: temporal unwrapping then fails where the coarser phase errs by pi / 20 =
#: 0.16 rad, still 15 times the per-pixel phase noise at 16 spp with sensor noise.
MAX_PERIOD_RATIO = 20.0
#: The finest period spans at least this many display pixels (the display box and blur keep >= 90 % modulation).
MIN_PERIOD_PX = 4.0
#: A sequence holds at most this many frames (2 directions x periods x steps).
MAX_FRAMES = 4096
#: Gaussian tails beyond this many standard deviations are dropped from the blur (relative weight < 6e-7).
_BLUR_REACH = 5.0


def _finite_positive(value: float, name: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise SetupError(f"{name} must be a finite number > 0, got {value!r}")
    return v


@dataclass(frozen=True)
class FringeFrame:
    """One displayed frame: fringes along ``direction`` of ``period_mm``, phase-shifted by ``shift_rad``.

    The ideal driven value is I = 0.5 + 0.5 cos(2 pi w / period_mm + shift_rad), w the display coordinate (mm)
    along ``direction`` (module docstring).
    """

    direction: Direction
    period_mm: float
    shift_rad: float

    def __post_init__(self) -> None:
        if self.direction not in DIRECTIONS:
            raise SetupError(f"fringe direction must be 'x' or 'y', got {self.direction!r}")
        object.__setattr__(self, "period_mm", _finite_positive(self.period_mm, "fringe period_mm"))
        if not math.isfinite(float(self.shift_rad)):
            raise SetupError(f"fringe shift_rad must be finite, got {self.shift_rad!r}")
        object.__setattr__(self, "shift_rad", float(self.shift_rad))

    def along(self, u_mm: ArrayLike, v_mm: ArrayLike) -> NDArray[np.float64]:
        """The display coordinate along the fringe direction, mm (u for "x", v for "y"), broadcast."""
        u, v = np.broadcast_arrays(np.asarray(u_mm, dtype=np.float64), np.asarray(v_mm, dtype=np.float64))
        return np.array(u if self.direction == "x" else v, dtype=np.float64)

    def phase(self, u_mm: ArrayLike, v_mm: ArrayLike) -> NDArray[np.float64]:
        """The unwrapped fringe phase 2 pi w / period at display points (u, v) mm, rad (without the shift)."""
        return 2.0 * np.pi * self.along(u_mm, v_mm) / self.period_mm

    def ideal(self, u_mm: ArrayLike, v_mm: ArrayLike) -> NDArray[np.float64]:
        """The ideal driven value 0.5 + 0.5 cos(phase + shift) in [0, 1] at display points (u, v) mm."""
        return 0.5 + 0.5 * np.cos(self.phase(u_mm, v_mm) + self.shift_rad)

    def to_dict(self) -> dict[str, Any]:
        """``{"direction", "period_mm", "shift_rad"}`` (the JSON of a fringe measurement)."""
        return {"direction": self.direction, "period_mm": self.period_mm, "shift_rad": self.shift_rad}

    @classmethod
    def from_dict(cls, data: object) -> FringeFrame:
        """Inverse of :meth:`to_dict`.

        Raises
        ------
        SetupError
            Not an object with exactly those keys, or values out of range.
        """
        keys = {"direction", "period_mm", "shift_rad"}
        if not isinstance(data, dict) or set(data) != keys:
            raise SetupError(f"a fringe frame is an object with the keys {sorted(keys)}, got {data!r:.200}")
        for key in ("period_mm", "shift_rad"):
            if isinstance(data[key], bool) or not isinstance(data[key], int | float):
                raise SetupError(f"fringe frame {key} must be a number, got {data[key]!r:.80}")
        return cls(data["direction"], data["period_mm"], data["shift_rad"])


@dataclass(frozen=True)
class FringeSequence:
    """The frames of a phase-shifting measurement: ``steps`` phase steps per period and direction.

    Parameters
    ----------
    periods_mm : sequence of float
        Fringe periods, mm, coarsest first (strictly decreasing; successive ratios at most
        :data:`MAX_PERIOD_RATIO`).
    steps : int
        Phase steps N >= 4 per period and direction; step k shifts by 2 pi k / N.

    Frame order (:meth:`frames`): for each direction ("x", then "y"), for each period (coarsest first), for each step
    k = 0 .. N-1. :meth:`index` gives a frame's position.
    """

    periods_mm: tuple[float, ...] = DEFAULT_PERIODS_MM
    steps: int = DEFAULT_STEPS

    def __post_init__(self) -> None:
        periods = tuple(_finite_positive(p, "fringe period") for p in self.periods_mm)
        if not periods:
            raise SetupError("a fringe sequence needs at least one period")
        for a, b in zip(periods, periods[1:], strict=False):
            if not b < a:
                raise SetupError(f"fringe periods must be strictly decreasing (coarsest first), got {periods}")
            if a / b > MAX_PERIOD_RATIO:
                raise SetupError(
                    f"fringe periods {a:g} -> {b:g} mm: ratio {a / b:.3g} exceeds {MAX_PERIOD_RATIO:g} (temporal "
                    "unwrapping would need a coarser phase error below pi / ratio); add an intermediate period"
                )
        if isinstance(self.steps, bool) or int(self.steps) != self.steps or self.steps < 4:
            raise SetupError(f"fringe steps must be an integer >= 4, got {self.steps!r}")
        object.__setattr__(self, "periods_mm", periods)
        object.__setattr__(self, "steps", int(self.steps))
        if len(self) > MAX_FRAMES:
            raise SetupError(f"a fringe sequence of {len(self)} frames exceeds {MAX_FRAMES}")

    def __len__(self) -> int:
        return 2 * len(self.periods_mm) * self.steps

    def shifts(self) -> NDArray[np.float64]:
        """The phase shifts 2 pi k / N, k = 0 .. N-1, rad."""
        return 2.0 * np.pi * np.arange(self.steps) / self.steps

    def index(self, direction: Direction, period: int, step: int) -> int:
        """Position in :meth:`frames` of ``direction``, period number ``period`` (0 = coarsest), step ``step``."""
        if direction not in DIRECTIONS or not 0 <= period < len(self.periods_mm) or not 0 <= step < self.steps:
            raise SetupError(f"no fringe frame ({direction!r}, period {period}, step {step}) in this sequence")
        return (DIRECTIONS.index(direction) * len(self.periods_mm) + period) * self.steps + step

    def frames(self) -> tuple[FringeFrame, ...]:
        """Every frame in the documented order (class docstring)."""
        return tuple(FringeFrame(d, p, float(s)) for d in DIRECTIONS for p in self.periods_mm for s in self.shifts())

    def check_display(self, display: FringeDisplay) -> None:
        """Refuse a sequence that does not fit ``display``.

        The coarsest period must exceed the display's active extent along both axes (its phase is then unambiguous
        over the display) and the finest must span at least :data:`MIN_PERIOD_PX` display pixels.

        Raises
        ------
        SetupError
            The message names the period and the display size or pitch.
        """
        extent = max(display.size_mm)
        if not self.periods_mm[0] > extent:
            raise SetupError(
                f"the coarsest fringe period {self.periods_mm[0]:g} mm does not cover the display's "
                f"{extent:g} mm: its phase would be ambiguous; use a period > {extent:g} mm"
            )
        finest = self.periods_mm[-1]
        if finest < MIN_PERIOD_PX * display.pixel_pitch_mm:
            raise SetupError(
                f"the finest fringe period {finest:g} mm spans fewer than {MIN_PERIOD_PX:g} display pixels of "
                f"{display.pixel_pitch_mm:g} mm"
            )

    def to_dict(self) -> dict[str, Any]:
        """``{"periods_mm", "steps"}``."""
        return {"periods_mm": list(self.periods_mm), "steps": self.steps}


@dataclass(frozen=True)
class FringeDisplay:
    """A display in the pattern plane emitting fringe frames (module docstring, "The display").

    Parameters
    ----------
    pixel_pitch_mm : float
        Display pixel pitch p, mm.
    size_mm : (float, float)
        Active area (x, y), mm, centred on the pattern origin; a whole number of pixels along each axis.
    gamma : float
        The panel's non-linearity: relative radiance d ** gamma of a driven value d in [0, 1].
    black_level : float
        Relative radiance of a driven value 0, in [0, 1).
    blur_px : float
        Standard deviation of the panel's Gaussian blur, display pixels (0: sharp pixels).
    bit_depth : int
        Bits of the driven value (1 .. 16).
    gamma_correction : float
        The gamma the driver's look-up table inverts: the ideal value I is driven as I ** (1 / gamma_correction)
        before quantisation (1: none; equal to ``gamma``: radiance linear in I up to quantisation).
    """

    pixel_pitch_mm: float = DEFAULT_PITCH_MM
    size_mm: tuple[float, float] = DEFAULT_SIZE_MM
    gamma: float = DEFAULT_GAMMA
    black_level: float = DEFAULT_BLACK_LEVEL
    blur_px: float = DEFAULT_BLUR_PX
    bit_depth: int = DEFAULT_BIT_DEPTH
    gamma_correction: float = DEFAULT_GAMMA

    def __post_init__(self) -> None:
        pitch = _finite_positive(self.pixel_pitch_mm, "display pixel_pitch_mm")
        if len(self.size_mm) != 2:
            raise SetupError(f"display size_mm must be (x, y), got {self.size_mm!r}")
        size = tuple(_finite_positive(s, "display size_mm") for s in self.size_mm)
        for axis, s in zip("xy", size, strict=True):
            n = round(s / pitch)
            if n < 2 or abs(n * pitch - s) > 1e-6 * s:
                raise SetupError(
                    f"display size_mm {axis} = {s:g} mm is not a whole number (>= 2) of {pitch:g} mm pixels"
                )
            if n > 1 << 20:
                raise SetupError(f"display size_mm {axis} = {s:g} mm holds {n} pixels of {pitch:g} mm, over 2^20")
        object.__setattr__(self, "pixel_pitch_mm", pitch)
        object.__setattr__(self, "size_mm", size)
        object.__setattr__(self, "gamma", _finite_positive(self.gamma, "display gamma"))
        object.__setattr__(self, "gamma_correction", _finite_positive(self.gamma_correction, "gamma_correction"))
        black = float(self.black_level)
        if not (math.isfinite(black) and 0.0 <= black < 1.0):
            raise SetupError(f"display black_level must be in [0, 1), got {self.black_level!r}")
        object.__setattr__(self, "black_level", black)
        blur = float(self.blur_px)
        if not (math.isfinite(blur) and 0.0 <= blur <= 100.0):
            raise SetupError(f"display blur_px must be in [0, 100] display pixels, got {self.blur_px!r}")
        object.__setattr__(self, "blur_px", blur)
        if isinstance(self.bit_depth, bool) or int(self.bit_depth) != self.bit_depth or not 1 <= self.bit_depth <= 16:
            raise SetupError(f"display bit_depth must be an integer in 1 .. 16, got {self.bit_depth!r}")
        object.__setattr__(self, "bit_depth", int(self.bit_depth))

    @property
    def pixels(self) -> tuple[int, int]:
        """Display pixels (x, y) of the active area."""
        return round(self.size_mm[0] / self.pixel_pitch_mm), round(self.size_mm[1] / self.pixel_pitch_mm)

    def driven(self, ideal: ArrayLike) -> NDArray[np.float64]:
        """The driven value d of ideal values I in [0, 1]: look-up table, then quantised to ``bit_depth`` bits."""
        top = float((1 << self.bit_depth) - 1)
        i = np.clip(np.asarray(ideal, dtype=np.float64), 0.0, 1.0)
        return np.round(i ** (1.0 / self.gamma_correction) * top) / top

    def emitted(self, driven: ArrayLike) -> NDArray[np.float64]:
        """Relative radiance black_level + (1 - black_level) d ** gamma of driven values d in [0, 1]."""
        return self.black_level + (1.0 - self.black_level) * np.asarray(driven, dtype=np.float64) ** self.gamma

    def pixel_radiance(self, frame: FringeFrame) -> NDArray[np.float64]:
        """The radiance each display pixel column (direction "x") or row ("y") emits in ``frame``, before the blur.

        Pixel k spans [-size/2 + k p, -size/2 + (k + 1) p] along the fringe direction; its value is the emitted
        radiance of the driven ideal value at its centre.
        """
        axis = DIRECTIONS.index(frame.direction)
        n = self.pixels[axis]
        centres = (np.arange(n) + 0.5) * self.pixel_pitch_mm - 0.5 * self.size_mm[axis]
        ideal = 0.5 + 0.5 * np.cos(2.0 * np.pi * centres / frame.period_mm + frame.shift_rad)
        return self.emitted(self.driven(ideal))

    def _axis(self, w: NDArray[np.float64], values: NDArray[np.float64] | None, axis: int) -> NDArray[np.float64]:
        """The blurred box sum ``sum_k values_k [Phi((w - a_k)/s) - Phi((w - a_k - p)/s)]`` along one axis (module
        docstring); ``values`` None: every pixel 1 (the active area's edge). NaN where ``w`` is not finite."""
        p = self.pixel_pitch_mm
        n = self.pixels[axis]
        finite = np.isfinite(w)
        t = (np.where(finite, w, 0.0) + 0.5 * self.size_mm[axis]) / p  # pixels from the active area's lower edge
        t = np.clip(t, -float(1 << 40), float(1 << 40))  # far outside is far outside (no integer overflow)
        return np.where(finite, self._boxes(t, values, n), np.nan)

    def _boxes(self, t: NDArray[np.float64], values: NDArray[np.float64] | None, n: int) -> NDArray[np.float64]:
        """:meth:`_axis` at positions ``t`` in pixels from the lower edge of the ``n`` pixels."""
        from scipy.special import ndtr

        if self.blur_px == 0.0:
            k = np.floor(t).astype(np.int64)
            inside = (k >= 0) & (k < n)
            if values is None:
                return inside.astype(np.float64)
            return np.where(inside, values[np.clip(k, 0, n - 1)], 0.0)
        s = self.blur_px
        if values is None:
            return ndtr(t / s) - ndtr((t - n) / s)
        reach = int(math.ceil(_BLUR_REACH * s)) + 1
        k0 = np.floor(t).astype(np.int64)
        out = np.zeros(t.shape, dtype=np.float64)
        for m in range(-reach, reach + 1):
            k = k0 + m
            ok = (k >= 0) & (k < n)
            weight = ndtr((t - k) / s) - ndtr((t - k - 1) / s)
            out += np.where(ok, values[np.clip(k, 0, n - 1)] * weight, 0.0)
        return out

    def radiance(self, u_mm: ArrayLike, v_mm: ArrayLike, frame: FringeFrame) -> NDArray[np.float64]:
        """The relative radiance the display emits in ``frame`` at display points (u, v), mm (broadcast).

        Exact for the model of the module docstring: the pixels' boxes of the driven, gamma-mapped values, blurred
        by the Gaussian; 0 far outside the active area; NaN where a coordinate is NaN (a ray that misses the plane,
        as ``pattern_xy`` marks it).
        """
        u, v = np.broadcast_arrays(np.asarray(u_mm, dtype=np.float64), np.asarray(v_mm, dtype=np.float64))
        axis = DIRECTIONS.index(frame.direction)
        along, across = (u, v) if axis == 0 else (v, u)
        return self._axis(along, self.pixel_radiance(frame), axis) * self._axis(across, None, 1 - axis)

    def texel_centres(self, texel_mm: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Display coordinates (u of the columns, v of the rows), mm, of a texture of ``texel_mm`` texels over the
        active area; row 0 / column 0 is the (-x, -y) corner, as the renderer's rectangle lays out its uv."""
        texel = _finite_positive(texel_mm, "texel_mm")
        sx, sy = self.size_mm
        nx, ny = max(2, math.ceil(sx / texel)), max(2, math.ceil(sy / texel))
        return (np.arange(nx) + 0.5) / nx * sx - 0.5 * sx, (np.arange(ny) + 0.5) / ny * sy - 0.5 * sy

    def texture(self, frame: FringeFrame, texel_mm: float) -> NDArray[np.float32]:
        """The radiance of ``frame`` rasterised at the texel centres of :meth:`texel_centres`, float32 (rows, cols).

        Each texel holds :meth:`radiance` at its centre (quantised, gamma-mapped, blurred); computed per axis and
        multiplied, as the model is separable.
        """
        u, v = self.texel_centres(texel_mm)
        if frame.direction == "x":
            cols = self._axis(u, self.pixel_radiance(frame), 0)
            rows = self._axis(v, None, 1)
        else:
            cols = self._axis(u, None, 0)
            rows = self._axis(v, self.pixel_radiance(frame), 1)
        return np.multiply.outer(rows.astype(np.float32), cols.astype(np.float32))

    def pixel_centres(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Display coordinates (u of the pixel columns, v of the pixel rows), mm, of the display pixels' centres; row 0
        / column 0 is the (-x, -y) corner."""
        nx, ny = self.pixels
        p = self.pixel_pitch_mm
        u = (np.arange(nx, dtype=np.float64) + 0.5) * p - 0.5 * self.size_mm[0]
        return u, (np.arange(ny, dtype=np.float64) + 0.5) * p - 0.5 * self.size_mm[1]

    def marker_values(self, pattern: MarkerPattern) -> NDArray[np.float64]:
        """The ideal values (rows, cols of display pixels) of the display showing a marker pattern (thesis §1.6.3):
        each pixel the pattern's grey value g = max(0, 1 - r / r_m) at its centre (:meth:`MarkerPattern.grey_local`,
        the pattern in the display's own frame)."""
        u, v = self.pixel_centres()
        uu, vv = np.meshgrid(u, v)
        return np.asarray(pattern.grey_local(np.stack([uu, vv], axis=-1)), dtype=np.float64)

    def image_texture(self, values: ArrayLike, texel_mm: float) -> NDArray[np.float32]:
        """The radiance of the display showing an image of ideal values (rows, cols of display pixels), rasterised at
        the texel centres of :meth:`texel_centres`, float32.

        Each pixel is driven as a fringe frame's (look-up table, ``bit_depth`` bits; :meth:`driven`), emits
        :meth:`emitted` over its box, and the panel's Gaussian blur of ``blur_px`` pixels spreads it: the box is
        sampled at the texel centres and the blur applied on the texel grid (:func:`scipy.ndimage.gaussian_filter`,
        nothing emitted beyond the active area). Unlike a fringe frame the image need not be separable.

        Raises
        ------
        SetupError
            ``values`` not of the display's (rows, cols) of pixels.
        """
        from scipy.ndimage import gaussian_filter

        nx, ny = self.pixels
        ideal = np.asarray(values, dtype=np.float64)
        if ideal.shape != (ny, nx):
            raise SetupError(f"a display image must have the display's {ny} x {nx} pixels, got shape {ideal.shape}")
        radiance = self.emitted(self.driven(ideal))
        u, v = self.texel_centres(texel_mm)
        p = self.pixel_pitch_mm
        cols = np.clip(np.floor((u + 0.5 * self.size_mm[0]) / p).astype(np.int64), 0, nx - 1)
        rows = np.clip(np.floor((v + 0.5 * self.size_mm[1]) / p).astype(np.int64), 0, ny - 1)
        tex = radiance[np.ix_(rows, cols)]
        if self.blur_px > 0.0:
            sigma = (self.blur_px * p / (self.size_mm[1] / len(v)), self.blur_px * p / (self.size_mm[0] / len(u)))
            tex = gaussian_filter(tex, sigma, mode="constant", cval=0.0, truncate=_BLUR_REACH)
        return tex.astype(np.float32)

    def to_dict(self) -> dict[str, Any]:
        """The display's parameters as JSON-ready values (keys as the dataclass fields)."""
        return {
            "pixel_pitch_mm": self.pixel_pitch_mm,
            "size_mm": list(self.size_mm),
            "gamma": self.gamma,
            "black_level": self.black_level,
            "blur_px": self.blur_px,
            "bit_depth": self.bit_depth,
            "gamma_correction": self.gamma_correction,
        }

    @classmethod
    def from_dict(cls, data: object) -> FringeDisplay:
        """Inverse of :meth:`to_dict`.

        Raises
        ------
        SetupError
            Not an object with exactly the keys of :meth:`to_dict`, or a value out of range.
        """
        keys = set(cls().to_dict())
        if not isinstance(data, dict) or set(data) != keys:
            raise SetupError(f"a fringe display is an object with the keys {sorted(keys)}, got {data!r:.200}")
        size = data["size_mm"]
        if not isinstance(size, list) or len(size) != 2:
            raise SetupError(f"display size_mm must be a list [x, y], got {size!r:.80}")
        for key, value in [*((k, data[k]) for k in keys - {"size_mm"}), ("size_mm", size[0]), ("size_mm", size[1])]:
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise SetupError(f"display {key} must be a number, got {value!r:.80}")
        return cls(
            data["pixel_pitch_mm"],
            (size[0], size[1]),
            data["gamma"],
            data["black_level"],
            data["blur_px"],
            data["bit_depth"],
            data["gamma_correction"],
        )
