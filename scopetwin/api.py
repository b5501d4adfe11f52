"""The Python front door: the main jobs of scopetwin in a few lines, with the command line's defaults.

Every function here is a thin, documented entry to the layers below (:mod:`scopetwin.scenes`, :mod:`scopetwin.recon`,
:mod:`scopetwin.calib`, :mod:`scopetwin.instrument`, :mod:`scopetwin.sim`); each imports what it needs when it is
called, so ``import scopetwin`` loads neither Mitsuba nor the reconstruction. Lengths are mm, angles rad, heights of
a reconstruction mm (uncertainties µm, as their names say).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

if TYPE_CHECKING:
    from contextlib import AbstractContextManager

    import numpy as np
    from numpy.typing import NDArray

    from scopetwin.calib.oneshot.refinement import Calibration
    from scopetwin.calib.setup_calibration import CalibratedSetup
    from scopetwin.instrument.rig import Rig
    from scopetwin.recon.policy import ReconstructionPolicy
    from scopetwin.recon.strategy import Reconstruction
    from scopetwin.scenes.setup import Setup
    from scopetwin.scenes.surface import HeightMap
    from scopetwin.sim.datasets.reader import Dataset
    from scopetwin.sim.fringes import FringeMeasurement
    from scopetwin.sim.truth import MarkerTruth


def load_setup(name_or_toml: Setup | str | Path, overrides: dict[str, Any] | None = None) -> Setup:
    """A setup of the thesis by preset name, or from a TOML file (which may start from a preset), validated.

    Parameters
    ----------
    name_or_toml : Setup, str or path
        A preset name (``scopetwin presets`` lists them, e.g. ``"thesis-1.10-deflectometry"``), a TOML file, or a
        setup (returned as it is when there are no ``overrides``).
    overrides : dict, optional
        Fields to change, nested as in the TOML (``{"render": {"spp": 4}}``).

    Returns
    -------
    Setup
        The validated setup (lengths in mm).

    Raises
    ------
    scopetwin.scenes.setup.SetupError
        Unknown preset, unreadable file, or a field out of range (the message names it).

    Examples
    --------
    >>> import scopetwin
    >>> setup = scopetwin.load_setup("thesis-1.10-deflectometry", {"render": {"spp": 4}})
    >>> setup.render.spp
    4
    """
    from scopetwin.scenes.setup import Setup as _Setup
    from scopetwin.scenes.setup import load_setup as _load

    if isinstance(name_or_toml, _Setup):
        if not overrides:
            return name_or_toml
        from scopetwin.scenes.setup import setup_from_json

        return _load_with(setup_from_json(name_or_toml.to_json()), overrides)
    return _load(name_or_toml, overrides)


def _load_with(setup: Setup, overrides: dict[str, Any]) -> Setup:
    """``setup`` with ``overrides`` merged into its fields, validated."""
    import json

    from scopetwin.scenes.setup import setup_from_dict
    from scopetwin.sim.datasets.config import merge

    return setup_from_dict(merge(json.loads(setup.to_json()), overrides), setup.name)


@dataclass
class Measurement:
    """A rendered camera image with its truth.

    Attributes
    ----------
    image : ndarray, (rows, cols), float32
        The camera image (digital numbers with sensor noise, or irradiance without).
    setup : Setup
        The setup rendered.
    heights : HeightMap or None
        The substrate's true surface (deflectometry), mm.
    truth : MarkerTruth or None
        The exact image of every marker centre (deflectometry and calibration scenes).
    spp, seed : int
        Samples per pixel and the seed of the render and the sensor noise.
    seconds : float
        Wall time of the render and the sensor model.
    second : Measurement or None
        The second image of a pattern stage (``render(..., pattern_shift_mm=...)``): the same scene with the pattern
        moved along its normal, its own setup and truth, rendered with seed + 1 (thesis §1.3).
    """

    image: NDArray[np.float32]
    setup: Setup
    heights: HeightMap | None
    truth: MarkerTruth | None
    spp: int
    seed: int
    seconds: float
    second: Measurement | None = None


def render(
    setup: Setup | str | Path,
    surface: HeightMap | str | Path | NDArray[Any] | None = None,
    spp: int | None = None,
    noise: bool = True,
    seed: int | None = None,
    renderer: Literal["mitsuba", "analytic"] = "mitsuba",
    extrapolate: bool = False,
    pattern_shift_mm: float | None = None,
) -> Measurement | FringeMeasurement:
    """Render one setup as its camera would see it, with its exact truth (``scopetwin render``); a ``[fringes]`` setup
    (e.g. ``"thesis-1.10-fringes"``): every frame of its sequence (:func:`scopetwin.sim.fringes.render_fringes`).

    Parameters
    ----------
    setup : Setup, str or path
        A setup or what :func:`load_setup` takes.
    surface : HeightMap, path, ndarray or None
        The substrate's heights (deflectometry): None for the setup's own surface (thesis §1.9), a height-map EXR, a
        :class:`~scopetwin.scenes.surface.HeightMap`, or a 2-D array of heights in mm spanning the substrate (row 0
        at its -y end, column 0 at its -x end).
    spp : int, optional
        Samples per pixel (default: the setup's).
    noise : bool
        Apply the setup's EMVA 1288 sensor model (photon and read noise, quantisation).
    seed : int, optional
        Seed of the render and the noise (default: the setup's); the same seed gives the same image.
    renderer : {"mitsuba", "analytic"}
        Mitsuba 3 (default) or the project's own ray model (§1.6), the independent cross-check.
    extrapolate : bool
        Accept a height map (EXR or :class:`~scopetwin.scenes.surface.HeightMap`) smaller than the substrate; it
        continues with its edge values. Without it the map must cover the substrate; heights must lie within
        ±10 mm either way (:func:`scopetwin.scenes.io.check_surface`).
    pattern_shift_mm : float, optional
        Also render the second image of a pattern stage, the pattern moved this far along its normal N_z (mm), as
        ``.second`` (thesis §1.3); without it, where the setup has a ``[pattern_stage]`` table, its ``shift_mm``.

    Returns
    -------
    Measurement or FringeMeasurement
        ``.image`` and its truth (``.heights``, ``.truth``); ``.second`` with a second pattern position (for a
        fringe setup the (K, rows, cols) stack ``.images``, ``.frames``, ``.heights``, ``.second``).

    Raises
    ------
    ScopetwinError
        A surface that does not fit the substrate, or a render that is not finite or carries no signal.

    Examples
    --------
    The §1.10 measurement, its camera at a quarter of the pixels (each four times as large: a few seconds on a CPU);
    ``scopetwin.render("thesis-1.10-deflectometry")`` renders the thesis's 1360 x 1024 pixels:

    >>> import scopetwin
    >>> setup = scopetwin.load_setup(
    ...     "thesis-1.10-deflectometry", {"camera": {"pixels": [340, 256], "pixel_pitch": 0.0186}}
    ... )
    >>> m = scopetwin.render(setup, spp=4, seed=1)  # Mitsuba; renderer="analytic" for the project's ray model
    >>> m.image.shape  # rows, columns
    (256, 340)
    >>> m.spp, m.seed, m.second is None
    (4, 1, True)
    >>> bool(m.truth.visible.any())  # each marker's exact image (m.truth.center_px: column, row)
    True"""
    from scopetwin.sim.measurement import render_measurement

    s = load_setup(setup)
    heights = _surface(s, surface, extrapolate)
    n = int(spp if spp is not None else s.render.spp)
    sd = int(seed if seed is not None else s.render.seed)
    if s.fringes is not None:
        return _render_fringes(s, heights, n, sd, noise, renderer, pattern_shift_mm)
    image, seconds = render_measurement(s, heights, n, sd, noise, renderer)
    second = None
    if pattern_shift_mm is not None or s.pattern_stage is not None:
        from scopetwin.sim.measurement import render_second_position

        moved, image2, seconds2 = render_second_position(s, heights, n, sd, noise, renderer, pattern_shift_mm)
        second = Measurement(image2, moved, heights, _truth(moved, heights), n, (sd + 1) % 2**32, seconds2)
    return Measurement(image, s, heights, _truth(s, heights), n, sd, seconds, second)


def _render_fringes(
    setup: Setup,
    heights: HeightMap | None,
    spp: int,
    seed: int,
    noise: bool,
    renderer: str,
    pattern_shift_mm: float | None,
) -> FringeMeasurement:
    """:func:`render` of a ``[fringes]`` setup: the sequence, and at the second display position where asked."""
    from dataclasses import replace

    from scopetwin.scenes.errors import ScopetwinError
    from scopetwin.sim.fringes import render_fringes, render_second_fringes

    if renderer != "mitsuba":
        raise ScopetwinError(f"{setup.name} shows fringes: only the Mitsuba renderer renders a fringe display")
    first = render_fringes(setup, heights, spp, seed, noise)
    if pattern_shift_mm is None and setup.pattern_stage is None:
        return first
    return replace(first, second=render_second_fringes(setup, heights, spp, seed, noise, pattern_shift_mm))


def _surface(
    setup: Setup, surface: HeightMap | str | Path | NDArray[Any] | None, extrapolate: bool = False
) -> HeightMap | None:
    """The substrate's heights of :func:`render` (checked against the substrate's extent and the height range)."""
    import numpy as np

    from scopetwin.scenes.errors import ScopetwinError
    from scopetwin.scenes.io import check_surface, read_heightmap
    from scopetwin.scenes.surface import HeightMap as _HeightMap
    from scopetwin.sim.surfaces import surface_for

    if surface is None:
        return surface_for(setup)
    if setup.scene != "deflectometry" or setup.substrate is None:
        raise ScopetwinError(f"a surface applies to deflectometry setups; {setup.name} is a {setup.scene} scene")
    size = setup.substrate.size
    if isinstance(surface, _HeightMap):
        return check_surface(surface, size, "the height map", extrapolate)
    if isinstance(surface, str | Path):
        return check_surface(read_heightmap(surface), size, f"height map {surface}", extrapolate)
    z = np.asarray(surface, dtype=np.float64)
    if z.ndim != 2 or min(z.shape) < 4 or not np.all(np.isfinite(z)):
        raise ScopetwinError(f"a height array must be 2-D, at least 4 x 4 and finite, got shape {z.shape}")
    sx, sy = size
    return check_surface(_HeightMap(z, -0.5 * sx, 0.5 * sx, -0.5 * sy, 0.5 * sy), size, "the height array")


def _truth(setup: Setup, heights: HeightMap | None) -> MarkerTruth | None:
    """The exact marker images of a deflectometry or target scene (None for the other scenes)."""
    from scopetwin.sim.truth import marker_truth

    if setup.scene not in ("deflectometry", "target", "mirror"):
        return None
    return marker_truth(setup, heights)


def _check_reconstruct_options(
    method: str | None, second: object, previous: Reconstruction | None, hold: bool = False
) -> None:
    """One clear error for options :func:`reconstruct` cannot combine (before any work starts)."""
    from scopetwin.recon.errors import ReconstructionError

    if hold and previous is None:
        raise ReconstructionError("hold=True holds the scale and prior of previous=; give previous=")
    if hold and getattr(previous, "held_prior", None) is None:
        raise ReconstructionError("hold=True: previous= has no posterior prior to hold (reconstructed without one)")
    if previous is not None and (second is not None or method not in (None, "centroid")):
        raise ReconstructionError("previous= takes one image and the centroid method (no second=, no inverse)")
    if second is not None and method == "inverse":
        raise ReconstructionError("a second pattern position takes the centroid or the fringe method")


def reconstruct(
    image: NDArray[Any],
    setup: Setup | str | Path,
    method: Literal["centroid", "inverse", "fringes"] | None = None,
    *,
    policy: ReconstructionPolicy | None = None,
    second: tuple[NDArray[Any], float | None] | NDArray[Any] | None = None,
    previous: Reconstruction | None = None,
    hold: bool = False,
) -> Reconstruction:
    """The substrate's heights from one deflectometry image (``scopetwin reconstruct``, thesis §1.4-§1.8).

    One strategy for every entry point (:mod:`scopetwin.recon.strategy`): markers found and indexed, the nested
    start-height iteration (the basis scale chosen from the data, the centroid bias corrected), every fallback of the
    :class:`~scopetwin.recon.policy.ReconstructionPolicy`; a ``[fringes]`` setup's stack: every pixel decoded.

    Parameters
    ----------
    image : ndarray, (rows, cols) or (K, rows, cols)
        The camera image (any scale); for a fringe setup the stack of its sequence's K frames, in order.
    setup : Setup, str or path
        The (calibrated) deflectometry setup, or what :func:`load_setup` takes.
    method : {"centroid", "inverse", "fringes"}, optional
        Marker centroids (a marker setup's default), the inverse fit through a differentiable render (slower), or
        fringes (a fringe setup's only one); a misfit: :class:`~scopetwin.recon.errors.MethodMismatchError`.
    policy : ReconstructionPolicy, optional
        The fallbacks and their thresholds (default: :data:`scopetwin.recon.policy.DEFAULT_POLICY`).
    second : (ndarray, float or None) or ndarray, optional
        A second image with the pattern moved along its normal by a stage, and the shift in mm (None or the image
        alone: the setup's ``[pattern_stage]`` shift): the absolute height from both images, combined with the frame
        criterion's (:mod:`scopetwin.recon.two_positions`, thesis §1.3; centroid method). ``.result.estimate``
        then holds the frame criterion's, the two positions' and the combined height (fringes: the second display
        position's stack, the height from the two positions' display points per pixel).
    previous : Reconstruction, optional
        The centroid reconstruction of an earlier frame of the same setup (a rig's live loop; one image): the search
        starts on the scale that frame ended on (:attr:`Reconstruction.scale`, still chosen from the data), the prior
        is searched by evidence from that frame's. The result then depends on it within the evidence's flatness
        (tests/recon/test_warm_evidence.py); leave it out where each frame must stand alone (accuracy studies).
    hold : bool
        With ``previous`` (frames of one surface): its scale held, its prior read as it is where plausible
        (:func:`scopetwin.recon.uncertainty.held_prior_z`).

    Returns
    -------
    Reconstruction
        ``.height_at(x_mm, y_mm)`` (vectorised, mm), ``.heightmap()``, ``.uncertainty.absolute_um`` and
        ``.uncertainty.shape_um`` (one standard uncertainty each), ``.strategy`` (the path taken).

    Raises
    ------
    scopetwin.recon.errors.ReconstructionError
        Only when every path failed; the message names what each tried.

    Examples
    --------
    The heights of a rendered measurement (the camera at a quarter of its pixels, as in :func:`render`) against the
    surface it was rendered with, in µm:

    >>> import numpy as np
    >>> import scopetwin
    >>> setup = scopetwin.load_setup(
    ...     "thesis-1.10-deflectometry", {"camera": {"pixels": [340, 256], "pixel_pitch": 0.0186}}
    ... )
    >>> m = scopetwin.render(setup, spp=4, seed=1)
    >>> r = scopetwin.reconstruct(m.image, m.setup)
    >>> x, y = np.meshgrid(np.linspace(-10, 10, 21), np.linspace(-20, 20, 41))  # substrate coordinates, mm
    >>> error_um = (r.height_at(x, y) - m.heights.height(x, y)) * 1e3
    >>> bool(abs(error_um.mean()) < 1.0), bool(error_um.std() < 0.5), bool(r.uncertainty.absolute_um < 1.0)
    (True, True, True)
    >>> r_next = scopetwin.reconstruct(m.image, m.setup, previous=r, hold=True)  # a live loop's next frame

    With a second image, the pattern moved 30 mm by a stage (thesis §1.3; shown, not run here):

    >>> m2 = scopetwin.render("thesis-1.10-deflectometry", spp=4, seed=1, pattern_shift_mm=30.0)  # doctest: +SKIP
    >>> r2 = scopetwin.reconstruct(m2.image, m2.setup, second=(m2.second.image, 30.0))  # doctest: +SKIP
    >>> r2.result.estimate.height_um, r2.uncertainty.absolute_um  # doctest: +SKIP
    >>> f = scopetwin.render("thesis-1.10-fringes", spp=4)  # 24 fringe frames  # doctest: +SKIP
    >>> rf = scopetwin.reconstruct(f.images, f.setup)  # every pixel a slope  # doctest: +SKIP"""
    _check_reconstruct_options(method, second, previous, hold)
    return _reconstruct_checked(image, load_setup(setup), method, policy, second, previous, hold)


def _reconstruct_checked(
    image: NDArray[Any],
    setup: Setup,
    method: Literal["centroid", "inverse", "fringes"] | None,
    policy: ReconstructionPolicy | None,
    second: tuple[NDArray[Any], float | None] | NDArray[Any] | None,
    previous: Reconstruction | None,
    hold: bool = False,
) -> Reconstruction:
    """:func:`reconstruct` once its options are checked: both images of a pattern stage, or the one strategy."""
    import numpy as np

    from scopetwin.recon.policy import DEFAULT_POLICY
    from scopetwin.recon.strategy import reconstruct as _reconstruct

    if previous is not None and setup.fringes is not None:
        from scopetwin.recon.errors import MethodMismatchError

        raise MethodMismatchError(f"previous= is the centroid method's warm start; setup {setup.name} shows fringes")
    pair = None
    if second is not None:
        image2, shift = second if isinstance(second, tuple) else (second, None)
        pair = (np.asarray(image2), shift)
    from scopetwin.recon.config import ReconstructionConfig

    start = previous.prior if previous is not None else None
    config = ReconstructionConfig().starting_at(previous.scale if previous is not None else None)
    policy = policy or DEFAULT_POLICY
    return _reconstruct(
        np.asarray(image),
        setup,
        method,
        config=config,
        policy=policy.with_changes(rechoose_scale=False) if hold else policy,
        evidence_start=start,
        held_prior=previous.held_prior if hold and previous is not None else None,
        second=pair,
    )


def calibrate(
    image: NDArray[Any],
    target: Setup | str | Path,
    *,
    focal_length: float | None = None,
    distortion: bool = False,
    bias_correction: bool = True,
) -> Calibration:
    """One-shot camera calibration from one image of a calibration target (``scopetwin calibrate``, thesis ch. 2).

    Parameters
    ----------
    image : ndarray, (rows, cols)
        The camera image of the target.
    target : Setup, str or path
        A ``target`` scene: the target's markers and pose, the camera's a-priori values.
    focal_length : float, optional
        A-priori focal length, mm (default: the setup camera's).
    distortion : bool
        Fit the radial distortion too (thesis §2.5.2).
    bias_correction : bool
        Correct the markers' centroid bias (thesis §2.8.2).

    Returns
    -------
    Calibration
        ``.camera`` (the calibrated :class:`~scopetwin.scenes.camera.Camera`), residuals, ``.as_dict()``, and the
        standard uncertainties.

    Examples
    --------
    The target of §2.8.1 seen perpendicularly from 233.24 mm (its camera at the thesis's 1360 x 1024 pixels):

    >>> import scopetwin
    >>> m = scopetwin.render("thesis-2.8.1-perpendicular", spp=4)
    >>> cal = scopetwin.calibrate(m.image, m.setup)
    >>> float(round(cal.camera.center[2], 1))  # the camera's distance above the target, mm
    233.2
    """
    import numpy as np

    from scopetwin.calib.oneshot.from_image import calibrate_image

    cal, _ = calibrate_image(
        np.asarray(image),
        load_setup(target),
        focal_length=focal_length,
        distortion=distortion,
        bias_correction=bias_correction,
    )
    return cal


def calibrate_setup(
    target_image: NDArray[Any],
    mirror_image: NDArray[Any],
    target: Setup | str | Path = "thesis-2.8.3-substrate",
    mirror: Setup | str | Path = "thesis-2.8.3-mirror",
    *,
    focal_length: float | None = None,
    bias_correction: bool = True,
) -> CalibratedSetup:
    """Calibrate the deflectometry setup from its two calibration images (``scopetwin calibrate-setup``, thesis §2.7).

    Parameters
    ----------
    target_image : ndarray
        The calibration target lying on the holding frame (§2.7.1).
    mirror_image : ndarray
        The marker pattern seen in a flat mirror on the frame (§2.7.2).
    target, mirror : Setup, str or path
        The two calibration scenes (default: the thesis's §2.8.3 presets).
    focal_length : float, optional
        A-priori focal length, mm.
    bias_correction : bool
        Correct the markers' centroid bias.

    Returns
    -------
    CalibratedSetup
        ``.setup`` (the calibrated deflectometry setup, ready for :func:`reconstruct`), ``.toml`` (its file),
        ``.uncertainties`` (of the camera and pattern poses).

    Examples
    --------
    The two calibration images of §2.8.3 (the thesis's camera, 1360 x 1024 pixels; a few seconds):

    >>> import numpy as np
    >>> import scopetwin
    >>> t = scopetwin.render("thesis-2.8.3-substrate", spp=4)
    >>> m = scopetwin.render("thesis-2.8.3-mirror", spp=4)
    >>> calibrated = scopetwin.calibrate_setup(t.image, m.image)
    >>> bool(np.allclose(calibrated.setup.camera.origin, [0.0, -200.0, 120.0], atol=0.05))  # the camera, mm (§1.10)
    True
    >>> bool(calibrated.uncertainties["camera"]["shift_mm"] < 0.05)  # one standard uncertainty
    True
    """
    import numpy as np

    from scopetwin.calib.setup_calibration import calibrate_setup_from_images

    return calibrate_setup_from_images(
        np.asarray(target_image),
        np.asarray(mirror_image),
        load_setup(target),
        load_setup(mirror),
        focal_length=focal_length,
        bias_correction=bias_correction,
    )


def open_rig(path: str | Path) -> AbstractContextManager[Rig]:
    """Open a rig file: simulated devices or the hardware, with the same interfaces (``scopetwin rig``).

    Parameters
    ----------
    path : str or path
        A rig TOML (your own, with real ports), or a rig shipped with scopetwin by its bare name or its path in the
        checkout: ``sim-deflectometry`` (``rigs/sim-deflectometry.toml``), ``sim-cmu``, ``emulated-hardware``
        (:mod:`scopetwin.shipped`).

    Returns
    -------
    context manager of Rig
        ``with`` gives the rig, its devices initialised: ``rig.devices`` by name (cameras, stages, focus drives,
        lights, shutters, trigger); on every exit — an error or a signal included — every light is off, every
        shutter closed and every port closed.

    Examples
    --------
    >>> import scopetwin
    >>> with scopetwin.open_rig("sim-deflectometry") as rig:  # a shipped rig: its bare name
    ...     print(sorted(rig.devices), rig.camera().name)
    ['camera', 'pattern', 'x'] camera
    """
    from scopetwin.instrument.rig import open_rig as _open

    return _open(path)


def open_dataset(path: str | Path) -> Dataset:
    """A dataset written by ``scopetwin dataset generate``, as a lazy sequence of samples.

    Parameters
    ----------
    path : str or path
        The dataset folder (it holds ``dataset.json`` and ``samples/``).

    Returns
    -------
    Dataset
        ``len(ds)``, ``ds[i]``, ``ds[a:b]``, iteration; each sample has ``.image``, ``.maps`` (the per-pixel truth of
        ``maps.exr``: ``mask``, ``point``, ``surface_xy``, ``height``, ``normal``, ``pattern_xy``, ``marker`` ... per
        kind), ``.camera`` (OpenCV's ``K``, ``dist``, ``R``, ``t``), ``.truth``, ``.setup``, ``.meta``, each read from
        its files when first asked for. A ``torch.utils.data.DataLoader`` batches ``ds.arrays("image", ...,
        camera=True, markers=True)``: the samples as plain dicts of numpy arrays, with the camera and the marker
        truth (docs/contract.md, "Batches for PyTorch"). docs/contract.md, "Datasets", lists every file and channel.

    Examples
    --------
    >>> import scopetwin
    >>> ds = scopetwin.open_dataset("ds-deflectometry")  # doctest: +SKIP
    >>> sample = ds[0]  # doctest: +SKIP
    >>> sample.image.shape  # doctest: +SKIP
    """
    from scopetwin.sim.datasets.reader import open_dataset as _open

    return _open(path)
