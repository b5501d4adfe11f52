"""The measurement the inverse fit works on: the setup, the camera image and its pixel variances, the window of
pixels fitted (the image of the region of interest), and the state the fit carries between its steps (the pose of
camera and pattern, the span the coefficients keep to, the steps taken)."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from scopetwin.recon.errors import ReconstructionError
from scopetwin.recon.inverse.config import InverseConfig
from scopetwin.recon.inverse.objective import pixel_variance
from scopetwin.recon.inverse.render import _Level
from scopetwin.recon.inverse.result import InverseStep
from scopetwin.recon.spline import SplineSurface
from scopetwin.recon.substrate import Substrate2D
from scopetwin.scenes.geometry import Array
from scopetwin.scenes.setup import Setup


class _Measurement:
    """The image, its setup and the fit's state (the base of :class:`InverseReconstructor`, which documents the
    parameters)."""

    def __init__(
        self,
        setup: Setup,
        image: NDArray[Any],
        config: InverseConfig | None = None,
        variant: str | None = None,
        window: tuple[int, int, int, int] | None = None,
    ) -> None:
        if setup.scene != "deflectometry" or setup.substrate is None:
            raise ReconstructionError(f"setup {setup.name} is a {setup.scene!r} scene, not a deflectometry setup")
        cam = setup.camera_model
        img = np.asarray(image, dtype=np.float64)
        if img.shape != (cam.ny, cam.nx):
            raise ReconstructionError(
                f"image is {img.shape[1]} x {img.shape[0]} px, the camera has {cam.nx} x {cam.ny}"
            )
        self.setup = setup
        self.image = img
        self.config = config or InverseConfig()
        self.variant = variant
        self.sub = Substrate2D.from_setup(setup)
        self.camera = cam
        self.pattern = setup.marker_pattern
        self.var = pixel_variance(img, setup, self.config.noise)
        self.window: tuple[int, int, int, int] = (
            self._window() if window is None else (int(window[0]), int(window[1]), int(window[2]), int(window[3]))
        )
        self.history: list[InverseStep] = []
        self._t0 = time.perf_counter()
        self.pose = np.zeros(12)
        fx, fy = self.sub.frame_grid(1, self.config.frame_step)
        gx, gy = self.sub.frame_grid(2, self.config.frame_step)
        self._frame_pts = ((fx, fy), (gx, gy))
        #: spline coefficients of the start's basis (columns) when the fit keeps to its span, else None
        self._span: Array | None = None

    def _window(self) -> tuple[int, int, int, int]:
        """Pixel window of the ROI's image (its corners and edges projected, at the frame height), padded."""
        sub = self.sub
        t = np.linspace(-1.0, 1.0, 64)
        hx, hy = 0.5 * sub.size_x, 0.5 * sub.roi_length
        edge = np.concatenate(
            [np.stack([hx * t, np.full_like(t, s * hy)], -1) for s in (-1, 1)]
            + [np.stack([np.full_like(t, s * hx), hy * t], -1) for s in (-1, 1)]
        )
        pts = np.concatenate([edge, np.zeros((len(edge), 1))], axis=1)
        px = self.camera.project(pts)
        if not np.all(np.isfinite(px)):
            raise ReconstructionError("the substrate's region of interest is not in front of the camera")
        c0, r0 = np.floor(px.min(axis=0)).astype(int) - 8
        c1, r1 = np.ceil(px.max(axis=0)).astype(int) + 8
        c0, r0 = max(int(c0), 0), max(int(r0), 0)
        c1, r1 = min(int(c1), self.camera.nx), min(int(r1), self.camera.ny)
        if c1 - c0 < 8 or r1 - r0 < 8:
            raise ReconstructionError("the camera does not see the substrate's region of interest")
        return (r0, r1, c0, c1)

    def _level(self, b: int, sub: int, near: tuple[SplineSurface, int] | None = None) -> _Level:
        """The resolution level of b x b pixel blocks with ``sub`` x ``sub`` rays each, over the fitted window (only
        the pixels near the markers' images through a surface traced: ``near`` = (surface, margin))."""
        return _Level(
            self.camera,
            self.pattern,
            self.setup,
            self.image,
            self.var,
            self.window,
            b,
            sub,
            self.variant,
            self.config.jitter,
            near,
        )

    def _linearise(
        self, lev: _Level, surf: SplineSurface, need_jac: bool = True
    ) -> tuple[Array, NDArray[np.bool_], sp.csr_matrix | None, Array | None]:
        """Model pixel values, usable-pixel mask, sparse Jacobian (usable pixels x coefficients), pose Jacobian (with
        ``refine_setup``)."""
        return lev.linearise(surf, need_jac, need_jac and self.config.refine_setup)
