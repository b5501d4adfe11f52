"""The camera images of a fringe sequence read by their setup: checked, split by direction and period, decoded.

A phase-measuring deflectometry measurement (the §1.10 setup with a fringe display, thesis §1.2) is a stack of K
camera images, one per frame of the setup's ``[fringes]`` sequence (:class:`scopetwin.scenes.fringes.FringeSequence`:
for each direction x then y, for each period coarsest first, the N phase steps 2 pi k / N). The frames' meaning comes
from the sequence alone, so the stack is checked against it — K frames, the camera's size, finite values — before
any work, and split into one (N, rows, cols) view per direction and period for
:func:`scopetwin.recon.fringes.phase.decode_display`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.recon.errors import MethodMismatchError
from scopetwin.recon.fringes.phase import DisplayCoordinates, FringeDecodingError, decode_display
from scopetwin.scenes.fringes import FringeDisplay, FringeSequence
from scopetwin.scenes.setup import Setup


def fringe_parts(setup: Setup) -> tuple[FringeDisplay, FringeSequence]:
    """The display and the sequence of a deflectometry setup with a ``[fringes]`` table.

    Raises
    ------
    MethodMismatchError
        A marker setup (no ``[fringes]`` table) or a setup that is not a deflectometry scene.
    """
    if setup.scene != "deflectometry":
        raise MethodMismatchError(
            f"setup {setup.name} is a {setup.scene!r} scene; a fringe reconstruction needs a deflectometry setup"
        )
    display, sequence = setup.fringe_display, setup.fringe_sequence
    if display is None or sequence is None:
        raise MethodMismatchError(
            f"setup {setup.name} has no [fringes] table: it is a marker setup (reconstruct its image with the "
            "centroid or the inverse method)"
        )
    return display, sequence


def check_fringe_stack(images: Any, setup: Setup, what: str = "the fringe images") -> NDArray[Any]:
    """The stack as an array, checked against the setup's sequence and camera before any work.

    Parameters
    ----------
    images : array_like, (K, rows, cols)
        One camera image per frame of the setup's sequence, in its order.
    setup : Setup
        A deflectometry setup with a ``[fringes]`` table.
    what : str
        How the message names the stack.

    Returns
    -------
    ndarray
        The stack (float32 or float64 kept as given, other types as float64).

    Raises
    ------
    MethodMismatchError
        A marker setup.
    FringeDecodingError
        Not three-dimensional, another number of frames than the sequence's, another image size than the camera's,
        or a non-finite value (the message says which frame).
    """
    _, sequence = fringe_parts(setup)
    stack = np.asarray(images)
    if stack.dtype not in (np.float32, np.float64):
        stack = stack.astype(np.float64)
    cam = setup.camera_model
    if stack.ndim != 3:
        raise FringeDecodingError(
            f"{what}: a fringe measurement is a (K, rows, cols) stack of {len(sequence)} images, got shape "
            f"{stack.shape}"
        )
    if stack.shape[0] != len(sequence):
        raise FringeDecodingError(
            f"{what}: {stack.shape[0]} frames, but the sequence of setup {setup.name} has {len(sequence)} "
            f"({len(sequence.periods_mm)} periods x {sequence.steps} steps x 2 directions)"
        )
    if stack.shape[1:] != (cam.ny, cam.nx):
        raise FringeDecodingError(
            f"{what}: images of {stack.shape[2]} x {stack.shape[1]} px, but the camera of setup {setup.name} has "
            f"{cam.nx} x {cam.ny}"
        )
    finite = np.isfinite(stack).all(axis=(1, 2))
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise FringeDecodingError(f"{what}: frame(s) {bad[:8].tolist()} hold non-finite values (NaN or inf)")
    return stack


def split_stack(stack: NDArray[Any], sequence: FringeSequence) -> tuple[list[NDArray[Any]], list[NDArray[Any]]]:
    """One (N, rows, cols) view per period for the x frames and for the y frames (the sequence's order)."""
    n = sequence.steps
    periods = range(len(sequence.periods_mm))
    xs = [stack[sequence.index("x", p, 0) : sequence.index("x", p, 0) + n] for p in periods]
    ys = [stack[sequence.index("y", p, 0) : sequence.index("y", p, 0) + n] for p in periods]
    return xs, ys


@dataclass(frozen=True)
class DecodeReport:
    """What the decode of one stack gave: pixels decoded and why the others were not."""

    pixels: int
    valid: int
    low_modulation: int
    inconsistent: int
    off_display: int

    @classmethod
    def of(cls, coords: DisplayCoordinates) -> DecodeReport:
        return cls(
            int(coords.valid.size),
            int(coords.valid.sum()),
            int(coords.low_modulation.sum()),
            int(coords.inconsistent.sum()),
            int(coords.off_display.sum()),
        )

    def line(self, label: str) -> str:
        """One line of the strategy's path."""
        share = 100.0 * self.valid / max(self.pixels, 1)
        return (
            f"{label}: {self.valid} of {self.pixels} pixels decoded ({share:.1f} %); not decoded: "
            f"{self.low_modulation} low modulation (no display seen through the substrate, or too dark), "
            f"{self.inconsistent} inconsistent unwrapping, {self.off_display} off the display"
        )


def decode_stack(stack: NDArray[Any], setup: Setup) -> DisplayCoordinates:
    """The display point of every pixel from a checked stack (:func:`check_fringe_stack`), the periods and display
    size from the setup's ``[fringes]`` table; the image noise fitted from the phase-step residuals."""
    display, sequence = fringe_parts(setup)
    xs, ys = split_stack(stack, sequence)
    return decode_display(xs, ys, sequence.periods_mm, display.size_mm)
