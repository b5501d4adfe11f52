"""One rendered measurement: render (plus the sensor model), write image + truth + preview, staged output folders.

A measurement is what ``scopetwin render`` writes and what every Part I dataset sample holds (docs/contract.md,
"Images"): the camera image as OpenEXR (channel ``Y``; the setup and the provenance in the header), its truth
JSON (the image of every marker centre, thesis §1.5 / §2.6, and the height map of the surface), and an 8-bit
preview PNG.

:class:`StagedOutput` is the one stage-then-rename helper of the package: every command and library function
that writes an output folder (``render``, ``run``, a study report, a dataset sample) collects its files in a
hidden staging folder beside the destination and moves them into place only when everything succeeded, so an
interrupted or failed job leaves no partial output behind. Inside :func:`deferred_commits` (the command line)
the move waits until the ``--json`` result is written. Every stage is locked (an exclusive ``flock`` on the folder
while it lives), so a clean-up in another process removes only stages of dead processes (:func:`remove_stale_stage`):
a new stage of the same output removes the ones a killed run left (``render --out o`` after a SIGKILL).

Nothing is written through a link scopetwin did not make: the stage is made by :func:`tempfile.mkdtemp` (a new
name, mode 0700 until it is finished, so no one else can plant anything in it), and a destination folder that is a
symbolic link is refused.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import time
from collections.abc import Iterator, Sequence
from contextvars import ContextVar
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.io import check_surface, write_json_atomic

if TYPE_CHECKING:  # the command line enters deferred_commits for every command: no scipy, no setup model for it
    from scopetwin.scenes.setup import Setup
    from scopetwin.scenes.surface import HeightMap

#: Packages whose versions a rendered image's provenance records.
PROVENANCE_PACKAGES = ("scopetwin", "mitsuba", "drjit", "numpy")


class StagedOutput:
    """Collects output files in a hidden staging folder beside ``out`` and moves them into place on success.

    Two ways to finish: :meth:`commit` moves the staged entries into ``out`` (created if needed; an entry of the
    same name is replaced), :meth:`rename` renames the whole staging folder to ``out`` in one atomic step (POSIX)
    and refuses when ``out`` already exists. :meth:`discard` removes the staging folder. Used as a context manager,
    the folder is discarded when the block raises or when it was neither committed nor renamed.

    Inside :func:`deferred_commits` (the command line runs every command in one), :meth:`commit` only records the
    stage and returns where its entries will be; the command line moves them into place after it has written the
    ``--json`` file, so a failing ``--json`` leaves no result behind (:mod:`scopetwin.cli.outputs`).

    Parameters
    ----------
    out : Path
        The destination folder.
    prefix : str, optional
        Name prefix of the staging folder (default ``.NAME.staging-``); it is created in ``out``'s parent folder by
        :func:`tempfile.mkdtemp` (mode 0700 while it is written; renamed into place, it gets the permissions a new
        folder gets under the current umask). Stages of the same prefix left by dead processes are removed first.
    lock : bool
        Hold an exclusive ``flock`` on the staging folder until it is renamed or discarded (the default), so that a
        clean-up in another process (:func:`remove_stale_stage`) can tell a live stage from one left by a dead
        process. A stage that was removed and re-created meanwhile is never renamed into place.

    Raises
    ------
    ScopetwinError
        ``out`` is a symbolic link (scopetwin writes through no link it did not make).
    """

    def __init__(self, out: str | Path, prefix: str | None = None, lock: bool = True) -> None:
        self.out = Path(out)
        _refuse_link(self.out)
        self.out.parent.mkdir(parents=True, exist_ok=True)
        name_prefix = prefix or f".{self.out.name}.staging-"
        remove_stale_stages(self.out.parent, name_prefix)
        self.stage = Path(tempfile.mkdtemp(prefix=name_prefix, dir=self.out.parent))
        self._lock_fd: int | None = _lock_folder(self.stage) if lock else None

    def path(self, name: str) -> Path:
        """Where the file ``name`` is written while staged."""
        return self.stage / name

    def planned(self) -> dict[str, Path]:
        """``{name: final path}`` of the staged entries, as :meth:`commit` will place them."""
        return {f.name: self.out / f.name for f in sorted(self.stage.iterdir())}

    def commit(self) -> dict[str, Path]:
        """Move every staged entry into ``out``; returns ``{name: final path}`` (deferred: see the class)."""
        pending = _DEFERRED.get()
        if pending is not None:
            if self not in pending:
                pending.append(self)
            return self.planned()
        return self.commit_now()

    def commit_now(self) -> dict[str, Path]:
        """Move every staged entry into ``out`` now, deferred or not; returns ``{name: final path}``.

        An entry of ``out`` with the name of a staged one is replaced (a symbolic link there is replaced, never
        followed).

        Raises
        ------
        ScopetwinError
            ``out`` became a symbolic link meanwhile.
        """
        _refuse_link(self.out)
        self.out.mkdir(parents=True, exist_ok=True)
        moved = {}
        for f in sorted(self.stage.iterdir()):
            dest = self.out / f.name
            if dest.is_symlink():
                dest.unlink()
            elif dest.is_dir():
                shutil.rmtree(dest)
            f.replace(dest)
            moved[f.name] = dest
        self.stage.rmdir()
        self._unlock()
        return moved

    def rename(self) -> bool:
        """Rename the staging folder to ``out`` (atomic); False, and the stage discarded, when ``out`` exists.

        Raises
        ------
        ScopetwinError
            The locked staging folder was removed (and re-created) by someone else while it was being written.
        """
        if self._lock_fd is not None and not _same_folder(self._lock_fd, self.stage):
            self._unlock()
            self.discard()
            raise ScopetwinError(f"the staging folder {self.stage} was removed while it was written; not renamed")
        umask = os.umask(0)
        os.umask(umask)
        self.stage.chmod(0o777 & ~umask)  # mkdtemp made it 0700; the finished folder gets the usual permissions
        try:
            os.rename(self.stage, self.out)
        except OSError:  # ``out`` exists (e.g. another worker finished it first)
            self.discard()
            return False
        finally:
            self._unlock()
        return True

    def discard(self) -> None:
        """Remove the staging folder and everything in it."""
        shutil.rmtree(self.stage, ignore_errors=True)
        self._unlock()

    def _unlock(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)
            self._lock_fd = None

    def __enter__(self) -> StagedOutput:
        return self

    def __exit__(self, *exc: object) -> None:
        if self.stage.exists():
            pending = _DEFERRED.get()
            if exc[0] is None and pending is not None and self in pending:
                return  # committed, deferred: the command line moves it into place
            self.discard()
        self._unlock()


#: The stages whose commit is deferred (None: commits happen at once).
_DEFERRED: ContextVar[list[StagedOutput] | None] = ContextVar("scopetwin_deferred_commits", default=None)


@contextlib.contextmanager
def deferred_commits() -> Iterator[list[StagedOutput]]:
    """Within the block, :meth:`StagedOutput.commit` only records its stage in the yielded list.

    The caller finishes them with :meth:`StagedOutput.commit_now` (or discards them); on leaving the block, stages
    that are still pending are discarded, so nothing half-done is left when the caller failed before finishing.
    """
    pending: list[StagedOutput] = []
    token = _DEFERRED.set(pending)
    try:
        yield pending
    finally:
        _DEFERRED.reset(token)
        for stage in pending:
            if stage.stage.exists():
                stage.discard()


def _flock() -> Any:
    """:mod:`fcntl` on POSIX; None where the platform has no ``flock`` (Windows: staging folders are not locked)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        return None
    return fcntl


def _lock_folder(folder: Path) -> int | None:
    """An open descriptor of ``folder`` holding an exclusive flock on it (None where the file system or the
    platform has none)."""
    fcntl = _flock()
    if fcntl is None:  # pragma: no cover - not POSIX
        return None
    fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY)
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:  # e.g. a network file system without flock on folders: no lock, as before
        os.close(fd)
        return None
    return fd


def _same_folder(fd: int, path: Path) -> bool:
    try:
        a, b = os.fstat(fd), os.stat(path)
    except OSError:
        return False
    return (a.st_dev, a.st_ino) == (b.st_dev, b.st_ino)


def _refuse_link(out: Path) -> None:
    if out.is_symlink():
        raise ScopetwinError(f"{out} is a symbolic link; scopetwin writes through no link it did not make")


def remove_stale_stages(parent: Path, prefix: str) -> list[Path]:
    """Remove the staging folders ``parent/PREFIX*`` that dead processes left (:func:`remove_stale_stage`); returns
    them. Where the platform has no ``flock`` (Windows) a live stage cannot be told from a dead one: none is removed."""
    if _flock() is None or not parent.is_dir():  # pragma: no cover - not POSIX
        return []
    removed = []
    for entry in parent.iterdir():
        if entry.name.startswith(prefix) and remove_stale_stage(entry):
            removed.append(entry)
    return removed


def remove_stale_stage(folder: Path) -> bool:
    """Remove a staging folder unless a live process holds its lock (:class:`StagedOutput` ``lock=True``).

    Returns True when the folder was removed (or was already gone), False when it is in use. Where the platform
    has no ``flock`` (Windows) no stage is locked, and every staging folder counts as stale.
    """
    fcntl = _flock()
    if fcntl is None:  # pragma: no cover - not POSIX
        shutil.rmtree(folder, ignore_errors=True)
        with contextlib.suppress(OSError):
            folder.unlink()  # a stray file
        return True
    try:
        fd = os.open(folder, os.O_RDONLY | os.O_DIRECTORY | getattr(os, "O_NOFOLLOW", 0))
    except FileNotFoundError:
        return True
    except OSError:  # not a folder (a stray file, a link): remove it, never what it points to
        with contextlib.suppress(OSError):
            folder.unlink()
        return True
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            return False
        except OSError:
            pass  # no flock on this file system: the folder counts as stale
        shutil.rmtree(folder, ignore_errors=True)
        return True
    finally:
        os.close(fd)


def versions(packages: Sequence[str] = PROVENANCE_PACKAGES) -> dict[str, str]:
    """Installed versions of ``packages`` ("unknown" for one that is not installed)."""
    import importlib.metadata as md  # ~10 ms of imports that no command needs before it records a provenance

    out = {}
    for pkg in packages:
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            out[pkg] = "unknown"
    return out


def provenance(seed: int, spp: int, renderer: str) -> dict[str, Any]:
    """The ``scopetwin_provenance`` header of a render (docs/contract.md, "Images"): seed, spp, renderer, versions."""
    return {"seed": seed, "spp": spp, "renderer": renderer, "versions": versions()}


def write_preview(path: Path, image: NDArray[Any]) -> None:
    """An 8-bit PNG of an image: scaled to its 99.9th percentile, gamma 1/2.2; written atomically (beside ``path``,
    then renamed over it: a link there is replaced, never written through)."""
    import cv2

    from scopetwin.scenes.io import atomic_path

    top = float(np.percentile(image, 99.9)) or 1.0
    img8 = np.clip(255.0 * (np.clip(image / top, 0, 1) ** (1 / 2.2)), 0, 255).astype(np.uint8)
    ok, data = cv2.imencode(".png", img8)
    if not ok:  # pragma: no cover - OpenCV cannot fail on a valid 8-bit image
        raise ScopetwinError(f"could not encode the preview {path}")
    with atomic_path(path) as tmp:
        tmp.write_bytes(data.tobytes())


def check_rendered(image: NDArray[Any], what: str) -> NDArray[Any]:
    """Refuse a rendered image that is not finite everywhere or carries no signal (every pixel zero); returns it.

    Raises
    ------
    ScopetwinError
        One line: ``WHAT: ...; nothing written``.
    """
    if not np.all(np.isfinite(image)):
        bad = int(np.count_nonzero(~np.isfinite(image)))
        raise ScopetwinError(f"{what}: {bad} pixel(s) are NaN or infinite; nothing written")
    if not np.any(image):
        raise ScopetwinError(f"{what}: every pixel is zero (no light reaches the camera); nothing written")
    return image


def load_measurement(
    setup_arg: str,
    surface: str | None,
    spp: int | None,
    seed: int | None,
    noise: bool | None,
    extrapolate: bool = False,
) -> tuple[Setup, HeightMap | None]:
    """A setup (preset name or TOML) with render overrides, and its surface (``surface`` EXR or the generated one).

    A ``surface`` EXR must cover the substrate (unless ``extrapolate``) with heights in a physical range
    (:func:`check_surface`).

    Raises
    ------
    ScopetwinError
        The setup cannot be loaded, ``surface`` is given for a scene without a substrate, or is refused by
        :func:`check_surface`.
    """
    from scopetwin.scenes.io import read_heightmap
    from scopetwin.scenes.setup import load_setup
    from scopetwin.sim.surfaces import surface_for

    overrides: dict[str, Any] = {}
    render_over = {k: v for k, v in (("spp", spp), ("seed", seed), ("noise", noise)) if v is not None}
    if render_over:
        overrides["render"] = render_over
    setup = load_setup(setup_arg, overrides)
    if surface is not None:
        if setup.scene != "deflectometry":
            raise ScopetwinError(f"--surface applies to deflectometry setups; {setup.name} is a {setup.scene} scene")
        size = setup.substrate.size if setup.substrate is not None else None
        return setup, check_surface(read_heightmap(surface), size, f"--surface {surface}", extrapolate)
    return setup, surface_for(setup)


def render_measurement(
    setup: Setup, heights: HeightMap | None, spp: int, seed: int, noise: bool, renderer: str = "mitsuba"
) -> tuple[NDArray[np.float32], float]:
    """Render one setup and, with ``noise``, apply the EMVA 1288 sensor model (thesis §1.11 camera class).

    Without a fixed exposure the exposure fills the setup's fraction of the full well at the image peak.
    A render that is not finite or carries no signal is refused (:func:`check_rendered`).

    Returns
    -------
    image : ndarray
        The image (row, col).
    seconds : float
        Wall time of render and sensor model.
    """
    t0 = time.perf_counter()
    if renderer == "analytic":
        from scopetwin.scenes.analytic import render

        image = render(setup, heights, spp=spp, seed=seed)
    else:
        from scopetwin.scenes.mitsuba.render import render_setup

        image = render_setup(setup, heights, spp=spp, seed=seed)
    check_rendered(image, f"the render of {setup.name}")
    if noise:
        image = check_rendered(apply_sensor(setup, image, seed), f"the sensor model of {setup.name}")
    return image, time.perf_counter() - t0


def render_second_position(
    setup: Setup,
    heights: HeightMap | None,
    spp: int,
    seed: int,
    noise: bool,
    renderer: str = "mitsuba",
    shift_mm: float | None = None,
) -> tuple[Setup, NDArray[np.float32], float]:
    """The second image of a pattern stage (thesis §1.3): the same scene with the pattern moved ``shift_mm`` along its
    normal N_z (default: the setup's ``[pattern_stage]``), rendered as :func:`render_measurement` renders the first,
    with seed ``seed + 1`` (its own sampler and sensor noise).

    Returns
    -------
    moved : Setup
        The setup of the second image (:func:`scopetwin.scenes.pattern_stage.shift_pattern`).
    image : ndarray
        The image (row, col).
    seconds : float
        Wall time.
    """
    from scopetwin.scenes.pattern_stage import shift_pattern, stage_shift

    moved = shift_pattern(setup, stage_shift(setup, shift_mm))
    image, seconds = render_measurement(moved, heights, spp, (seed + 1) % 2**32, noise, renderer)
    return moved, image, seconds


def apply_sensor(setup: Setup, image: NDArray[Any], seed: int) -> NDArray[Any]:
    """The setup's EMVA 1288 sensor model applied to a rendered irradiance image (thesis §1.11 camera class).

    The exposure is the setup's ``sensor.exposure_s`` or, without one, the exposure at which the image peak fills
    ``sensor.fill_fraction`` of the full well; ``seed`` seeds the photon and read noise.

    Raises
    ------
    ScopetwinError
        The image is black, so no exposure can be chosen.
    """
    exposure = sensor_exposure(setup, image)
    return setup.sensor.sensor().capture(image, setup.sensor.photons_per_unit_s, exposure, rng=seed)


def sensor_exposure(setup: Setup, image: NDArray[Any]) -> float:
    """The exposure, s, at which :func:`apply_sensor` captures a rendered irradiance image: the setup's
    ``sensor.exposure_s`` or, without one, the exposure at which the image peak fills ``sensor.fill_fraction`` of the
    full well (EMVA 1288 model, :mod:`scopetwin.scenes.emva1288`).

    Raises
    ------
    ScopetwinError
        The image is black, so no exposure can be chosen.
    """
    if setup.sensor.exposure_s is not None:
        return float(setup.sensor.exposure_s)
    peak = float(image.max())
    if peak <= 0:
        raise ScopetwinError("the rendered image is black: cannot choose an exposure for the noise model")
    sensor = setup.sensor.sensor()
    return float(sensor.exposure_for(peak, setup.sensor.photons_per_unit_s, setup.sensor.fill_fraction))


def write_measurement(
    stage: StagedOutput,
    prefix: str,
    setup: Setup,
    heights: HeightMap | None,
    image: NDArray[Any],
    spp: int,
    seed: int,
    renderer: str,
) -> dict[str, str]:
    """Write image EXR, truth JSON (and height map), preview PNG into the staging folder; returns the file names.

    The truth holds the image of every marker centre (:func:`scopetwin.sim.truth.marker_truth`, thesis §1.5 / §2.6).
    """
    from scopetwin.scenes.io import write_heightmap, write_image
    from scopetwin.sim.truth import marker_truth

    names = {"image": f"{prefix}image.exr", "truth": f"{prefix}truth.json", "preview": f"{prefix}preview.png"}
    write_image(stage.path(names["image"]), image, setup.to_json(), provenance(seed, spp, renderer))
    truth: dict[str, Any] = {"setup": setup.name, "scene": setup.scene, "surface": None}
    if heights is not None:
        names["surface"] = f"{prefix}surface.exr"
        write_heightmap(stage.path(names["surface"]), heights)
        truth["surface"] = names["surface"]
    truth["markers"] = marker_truth(setup, heights).as_records()
    write_json_atomic(stage.path(names["truth"]), truth)
    write_preview(stage.path(names["preview"]), image)
    return names
