"""The inverse reconstruction's parameters: the surfaces searched, the coarse-to-fine schedule, the loss's weights,
the start-height search (thesis §1.4) and the setup's refinement with its prior from the calibration (thesis §2.7)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from scopetwin.recon.frame_criterion import FrameCriterion
from scopetwin.scenes.setup import Setup


@dataclass(frozen=True)
class InverseConfig:
    """Parameters of the inverse reconstruction.

    Attributes
    ----------
    spacing : float
        B-spline knot spacing, mm (0.5 mm resolves the 3 mm correlation length).
    surface : {"start-basis", "spline"}
        The surfaces the fit searches. "start-basis" (from a centroid start): the span of the centroid method's
        shifted basis (its scale chosen from the data by :func:`scopetwin.recon.reconstruct.select_sigma`) as B-splines,
        :meth:`SplineSurface.span` — the prior the centroid method found for this surface, now fitted to every
        pixel; measured (Mitsuba 16 spp, seed 2): with EMVA 1288 noise 0.0012-0.0022 µm shape against the centroid
        method's 0.0016-0.0032 at 5-20 mm / 40 µm, and 3 mm / 60 µm tilt-removed 0.014 µm against 0.060; the free
        spline with its thin-plate prior passes more noise (0.0041 with noise at 12 mm). "spline": every
        coefficient free (always so from a plane start, which has no basis, and with ``absolute="frame"``: the
        basis's extrapolation into the frame regions moved the height searched on it by -28 µm at 3 mm / 60 µm).
    levels : tuple of (int, int)
        Coarse-to-fine schedule: (pixel binning b, rays per super-pixel and axis) per level, coarse first. The
        finest level needs 4 x 4 rays per pixel: with 2 x 2 the midpoint rule's error on the marker cones (measured
        against Mitsuba renders: chi^2 per pixel 1.7e-6 at 2 x 2, 5.8e-7 at 3 x 3, 4.2e-7 at 4 x 4, 3.2e-7 at 8 x 8)
        biases the fit more than the surface's own signal. 6 x 6 jittered rays (``jitter``): shape error at
        5 mm / 40 µm 0.0022 µm against 0.0030-0.0032 µm with 4 x 4 centred or jittered rays. Default 8 x 8: chi^2
        per pixel 3.6e-7 against 5.4e-7 at 6 x 6 on a Mitsuba 16 spp render (its own floor 3.2e-7), shape at
        12 mm / 40 µm 0.00112 against 0.00126 µm (basis span), 28 against 16 s per fit when every pixel of the
        window was traced (:attr:`near_margin`), about twice the memory.
    plane_levels : tuple of (int, int)
        The schedule for a start from a plane (no centroid result): binned levels first, to widen the basin.
    absolute : {"start", "frame"}
        Where the absolute height comes from when the fit starts from the centroid method's surface: "start" keeps
        its mean ROI height (the centroid method's frame criterion, whose Gaussian-process basis extrapolates into
        the frame regions better than the thin-plate prior here: measured -0.025 vs -0.071 µm at 5 mm / 40 µm);
        "frame" searches the start height on the fitted surface (always done for a plane start).
    iterations : tuple of int
        Largest number of Gauss-Newton steps per level (the last entry repeats).
    outer_iterations : int
        Gauss-Newton steps at the finest level for each further start height (warm-started: the surfaces depend
        almost linearly on the start height).
    smoothness : float
        Weight lambda of the thin-plate prior relative to the mean diagonal of J^T W J.
    jitter : bool
        Rays at fixed pseudo-random positions inside the sub-pixels instead of their centres.
    tol_um : float
        A level stops when the RMS coefficient step falls below this, µm.
    criterion : {"level", "delta"}
        Frame criterion of the start-height search (thesis §1.4).
    outer_max : int
        Largest number of start heights tried.
    outer_tol_um : float
        Start-height search stops when ``|criterion|`` falls below this, µm.
    frame_step : float
        Spacing of the evaluation grid over the frame regions, mm.
    noise : {"auto", "emva", "none"}
        Pixel variances: EMVA 1288 (camera images in DN), constant, or chosen from the image (peak > 2: DN).
    refine_setup : bool
        Add camera and pattern rigid motions to the unknowns.
    pose_sigma : (float, float, float, float)
        Prior standard deviations of those motions: camera shift (mm), camera rotation (rad), pattern shift (mm),
        pattern rotation (rad) — the calibration's uncertainties where the setup carries them
        (:func:`pose_sigma_for`, ``[calibration]`` of a setup that ``calibrate-setup`` wrote).
    near_margin : int
        From the centroid method's surface, its start height held and the setup not refined, only the pixels within
        this many of one whose centre ray sees a marker (or misses the substrate) are traced at each level
        (:func:`scopetwin.recon.inverse.render._near_pixels`): the others see the dark ground between the markers,
        and the fit's equations are the same without their rays as long as the markers' images move by less than
        the margin (from that start, hundredths of a pixel). The fit's surface is checked at the end, and the pixels
        it needs beyond those traced are added and fitted again (:meth:`scopetwin.recon.inverse.render._Level.widen`,
        the result's ``extras["pixels_added"]``). 0: every pixel traced.
    pose_box : float
        The pose stays within this many of those standard deviations of the setup (each step shortened to keep
        it so): the pixels of an unknown specular surface hardly tell a camera motion from a change of the surface's
        slopes, and on a full Mitsuba image the free fit (the Gaussian prior alone) moved the camera by 2 mm against
        a 27 µm sigma, the shape 1.5 -> 17.7 µm (``benchmarks/refine_setup.py``); within the box the shape is
        1.39 against 1.45 µm unrefined, but the poses run to its walls (camera 69 µm / 274 µrad off, from 27 µm / 71
        µrad): the pose is not identifiable from such an image.
    """

    spacing: float = 0.5
    surface: Literal["spline", "start-basis"] = "start-basis"
    levels: tuple[tuple[int, int], ...] = ((1, 8),)
    plane_levels: tuple[tuple[int, int], ...] = ((4, 4), (2, 4), (1, 8))
    iterations: tuple[int, ...] = (3,)
    absolute: Literal["start", "frame"] = "start"
    outer_iterations: int = 1
    smoothness: float = 1e-3
    jitter: bool = True
    tol_um: float = 2e-3
    criterion: FrameCriterion = "level"
    outer_max: int = 3
    outer_tol_um: float = 2e-3
    frame_step: float = 0.2
    noise: str = "auto"
    refine_setup: bool = False
    pose_sigma: tuple[float, float, float, float] = (0.05, 2e-4, 0.05, 2e-4)
    pose_box: float = 3.0
    near_margin: int = 3

    def __post_init__(self) -> None:
        if self.near_margin < 0:
            raise ValueError(f"near_margin must be >= 0 pixels, got {self.near_margin}")


def pose_sigma_for(
    setup: Setup, default: tuple[float, float, float, float] | None = None
) -> tuple[float, float, float, float]:
    """The prior standard deviations of ``--refine-setup`` (:class:`InverseConfig` ``pose_sigma``) for a setup.

    A setup written by ``calibrate-setup`` carries its calibration's uncertainties (``[calibration]``: camera and
    pattern, shift mm and rotation rad, thesis §2.7); other setups get ``default`` (that of :class:`InverseConfig`).
    """
    cal = setup.calibration
    if cal is None:
        return default or InverseConfig().pose_sigma
    return (cal.camera.shift_mm, cal.camera.rotation_rad, cal.pattern.shift_mm, cal.pattern.rotation_rad)
