"""Inverse rendering: the substrate's surface fitted to the whole image through a differentiable render.

The method and its loss are described in :mod:`scopetwin.recon.inverse.reconstructor`; this package re-exports its
names, so that ``from scopetwin.recon.inverse import ...`` reaches them.
"""

from scopetwin.recon.inverse.reconstructor import (
    InverseConfig,
    InverseReconstructor,
    InverseResult,
    InverseStep,
    bin_image,
    pixel_variance,
    pose_sigma_for,
    reconstruct_inverse,
    spline_grid,
    without_plane,
)

# also reached through this package: the fitted surface's type, and the pose and binning helpers that the tests and
# benchmarks check on their own
from scopetwin.recon.inverse.reconstructor import SplineSurface as SplineSurface
from scopetwin.recon.inverse.reconstructor import _binned_camera as _binned_camera
from scopetwin.recon.inverse.reconstructor import _box_fraction as _box_fraction
from scopetwin.recon.inverse.reconstructor import _pose_update as _pose_update

__all__ = [
    "InverseConfig",
    "InverseReconstructor",
    "InverseResult",
    "InverseStep",
    "bin_image",
    "pixel_variance",
    "pose_sigma_for",
    "reconstruct_inverse",
    "spline_grid",
    "without_plane",
]
