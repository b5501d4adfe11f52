"""The pattern on a stage: the setup of a second image with the pattern moved along its normal (thesis §1.3).

One image of a reflected marker pattern leaves the height-normal ambiguity of thesis §1.3: the camera ray of a marker
is known, the surface point on it is not, and every point on it has a normal that reflects the marker into the
camera. The thesis resolves it with a-priori knowledge (the holding frame, §1.4). A stage that moves the pattern along
its normal N_z by a known distance gives a second image of the same surface with every marker at a known second
position; the surface whose traced gradients explain both images has one absolute height
(:mod:`scopetwin.recon.two_positions`). The setup's ``[pattern_stage]`` table
(:class:`scopetwin.scenes.setup.PatternStageSpec`) names the distance; :func:`shift_pattern` is the setup of the
second image (the same scene with the pattern moved), which every renderer and the reconstruction take as it is.
"""

from __future__ import annotations

import json

import numpy as np

from scopetwin.scenes.errors import SetupError
from scopetwin.scenes.setup import Setup, setup_from_dict


def shift_pattern(setup: Setup, shift_mm: float) -> Setup:
    """The same setup with the pattern moved by ``shift_mm`` along its normal N_z (mm; positive along N_z).

    The setup of a second image taken with the pattern on a stage (thesis §1.3). Everything else — camera, substrate,
    surface, render and sensor options — is unchanged; the ``[pattern_stage]`` table is dropped (the moved setup is
    one position, not a pair) and the name says where the pattern is.

    Raises
    ------
    SetupError
        ``shift_mm`` is not finite, or the moved setup does not validate.
    """
    if not np.isfinite(shift_mm):
        raise SetupError(f"the pattern shift must be a finite number of mm, got {shift_mm!r}")
    data = json.loads(setup.to_json())
    origin = np.asarray(setup.pattern.origin, dtype=np.float64) + float(shift_mm) * np.asarray(setup.pattern.n_z)
    data["pattern"]["origin"] = [float(v) for v in origin]
    data["pattern_stage"] = None
    data["name"] = f"{setup.name} (pattern {float(shift_mm):+g} mm along N_z)"
    return setup_from_dict(data, f"{setup.name} with the pattern moved {float(shift_mm):+g} mm")


def stage_shift(setup: Setup, shift_mm: float | None = None) -> float:
    """The distance of the second pattern position: ``shift_mm`` where given, else the setup's ``[pattern_stage]``.

    Raises
    ------
    SetupError
        Neither is given, or the distance is 0 or not finite.
    """
    if shift_mm is None:
        if setup.pattern_stage is None:
            raise SetupError(
                f"setup {setup.name} has no [pattern_stage] table: give the second pattern position's shift (mm)"
            )
        shift_mm = setup.pattern_stage.shift_mm
    shift = float(shift_mm)
    if not np.isfinite(shift) or shift == 0:
        raise SetupError(f"the pattern shift must be a finite, non-zero number of mm, got {shift_mm!r}")
    return shift
