"""What the inverse reconstruction returns: the fitted surface, the start height found, the Gauss-Newton steps and
the (refined) setup."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from scopetwin.recon.spline import SplineSurface
from scopetwin.recon.substrate import Substrate2D
from scopetwin.scenes.camera import Camera
from scopetwin.scenes.pattern import MarkerPattern
from scopetwin.scenes.surface import HeightMap


@dataclass
class InverseStep:
    """One Gauss-Newton step: level, start height, loss (chi^2 per pixel), RMS step, seconds since the start."""

    level: int
    binning: int
    start_height_um: float
    chi2: float
    step_rms_um: float
    pixels: int
    seconds: float


@dataclass
class InverseResult:
    """The fitted surface, the start height found, the iteration history and the (refined) setup."""

    surface: SplineSurface
    substrate: Substrate2D
    start_height_um: float
    criterion_um: float
    delta_h_max_um: float
    history: list[InverseStep]
    outer_iterations: int
    converged: bool
    seconds: float
    camera: Camera
    pattern: MarkerPattern
    shape_std_um: float | None = None
    extras: dict[str, Any] = field(default_factory=dict)

    def heightmap(self, nx: int = 128, ny: int = 288) -> HeightMap:
        return self.surface.heightmap(self.substrate, nx, ny)

    def summary(self) -> dict[str, Any]:
        from dataclasses import asdict

        return {
            "method": "inverse",
            "outer_iterations": self.outer_iterations,
            "inner_iterations": len(self.history),
            "delta_h_max_um": self.delta_h_max_um,
            "start_height_um": self.start_height_um,
            "criterion_um": self.criterion_um,
            "converged": self.converged,
            "seconds": self.seconds,
            "knot_spacing_mm": self.surface.dx,
            "coefficients": int(self.surface.coef.size),
            "shape_std_um": self.shape_std_um,
            "history": [asdict(h) for h in self.history],
            **self.extras,
        }
