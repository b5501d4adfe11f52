"""The errors a reconstruction reports to its user (thesis §1.4); the strategy raises them only when every path failed.

Inside the reconstruction a failed step is a value (:class:`scopetwin.recon.reconstruct.LoopOutcome`), which the
strategy (:mod:`scopetwin.recon.strategy`) acts on; these classes are what a caller sees, each naming the paths tried.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from scopetwin.scenes.errors import ScopetwinError


class ReconstructionError(ScopetwinError, ValueError):
    """The reconstruction cannot be done with this input; the message says why."""


class TooFewMarkersError(ReconstructionError):
    """Too few markers overall, or next to one of the frame regions."""


class SubstrateNotVisibleError(ReconstructionError):
    """The setup's camera does not see the substrate (or the markers' rays miss it)."""


class InconsistentError(ReconstructionError):
    """The converged surface violates the frame condition that was not searched on (wrong indexing or setup)."""


class MismatchedPairError(ReconstructionError):
    """The second pattern position's image does not belong to the first: no one surface explains both images'
    markers (an image of another substrate, or a pattern shift other than the one given)."""


class MethodMismatchError(ReconstructionError):
    """The method does not fit the measurement: marker centroids asked of a fringe setup, fringes of a marker setup,
    or a single image where a fringe sequence's stack is needed (and the other way round)."""


class NotConvergedError(ReconstructionError):
    """The outer start-height loop did not converge; ``history`` holds what was done, ``surface`` its last surface."""

    def __init__(
        self, message: str, history: list[dict[str, Any]], history_path: Path | None, surface: Any = None
    ) -> None:
        super().__init__(message)
        self.history = history
        self.history_path = history_path
        self.surface = surface
