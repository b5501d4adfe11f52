"""Reading a dataset written by ``scopetwin dataset generate``: a lazy, indexable sequence of samples.

:func:`open_dataset` lists the finished samples of a dataset folder (those whose ``sample.json`` is in place: a
sample folder is renamed into place only when complete, :mod:`scopetwin.sim.datasets.store`) and returns a
:class:`Dataset`: ``len``, ``ds[i]`` (negative indices too), ``ds[a:b]`` (another dataset), iteration. A
:class:`Sample` reads its files when an attribute is first asked for, so opening a dataset of 10,000 samples reads
only its folder listing, and reading a sample costs what reading its files costs:

* ``.image`` / ``.images``: the camera image(s), float32 (rows, cols); a sample of a fringe setup (``[fringes]``:
  phase-measuring deflectometry) has its K frames as ``.fringes`` (:class:`scopetwin.sim.fringes.FringeMeasurement`)
  and ``.images`` holds them by file name (``fringe_0000`` ...);
* ``.maps``: the per-pixel truth aligned with the image (``maps.exr``, :mod:`scopetwin.sim.datasets.maps`), a dict
  of (rows, cols[, k]) arrays: ``mask``, ``point``, ``height``, ``pattern_xy``, ``marker``, ...;
* ``.camera``: the camera in OpenCV's convention (``K``, ``dist``, ``R``, ``t``;
  :class:`scopetwin.scenes.opencv_camera.OpenCVCamera`), ``.thesis_camera`` the thesis's own model;
* ``.truth``: ``truth.json`` as a :class:`Truth` (a dict with typed accessors), ``.setup``, ``.meta``.

A ``torch.utils.data.DataLoader`` accepts a :class:`Dataset` as a map-style dataset (``__len__`` and
``__getitem__``; it pickles for worker processes) without scopetwin importing torch. Its items are :class:`Sample`
objects, which torch's default collate cannot batch: :meth:`Dataset.arrays` gives the same samples as plain dicts
of numpy arrays, numbers and strings, which it can (``DataLoader(ds.arrays("image", "height", camera=True,
markers=True), batch_size=8)``):

* ``index`` (int) and ``kind`` (str), always; then the named images and map layers;
* ``camera=True``: ``K`` (3, 3) px, ``dist`` (5,), ``R`` (3, 3), ``t`` (3,) mm, OpenCV's camera (``.camera``);
* ``markers=True``: ``marker_ij`` int64 (n, 2), ``marker_px`` float64 (n, 2) (col, row) px of the thesis's
  convention (NaN where none), ``marker_visible`` bool (n,) (``.truth.markers``); one row per pattern marker, so
  samples of one pattern stack into a batch.

Formats: this reader reads dataset formats 1 and 2 (``dataset.json`` ``"format"``). Format 1 samples have no
``maps.exr`` and no ``camera_opencv``: both are computed from the sample's setup and surface when asked for, with
the same code the writer uses. A newer format is refused with a message naming the format it needs.

Safety: a dataset may come from someone else, so every file is read through :mod:`scopetwin.scenes.safe_read`.
The names a sample's files give (``sample.json``'s ``files``, ``truth.json``'s ``surface``) must stay inside the
sample folder (no absolute path, no ``..``, no link leading out of it); each file must be a regular file under a
size limit (a FIFO or ``/dev/zero`` is refused before it is opened); JSON nests at most
:data:`scopetwin.scenes.inputs.MAX_DEPTH` levels; ``sample.json`` and ``truth.json`` of a newer format are
refused; an image's or map's size is read from its EXR header and checked against the sample's camera before a pixel
is decoded. A sample folder that is a symbolic link is not listed. Each refusal is one
:class:`DatasetReadError`.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, overload

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.scenes.safe_read import check_format, read_json_inside, resolve_inside
from scopetwin.sim.datasets.store import CONFIG_FILE, SAMPLE_FILE, SAMPLES


class DatasetReadError(ScopetwinError):
    """A folder that is not a dataset, or a sample whose files cannot be read."""


@dataclass(frozen=True)
class MarkerTable:
    """The markers of a Part I sample's truth as arrays (docs/contract.md, "Truth"), aligned by row.

    Attributes
    ----------
    ij : ndarray of int, (n, 2)
        Marker indices (i, j) (docs/contract.md, "Marker indices"); row k is ``marker_id`` k of the maps.
    center_px : ndarray, (n, 2)
        The exact image of each marker centre, continuous pixel coordinates (col, row) of the thesis's convention
        (pixel centres at +0.5); NaN where the trace found none. OpenCV's coordinates are ``center_px - 0.5``.
    visible : ndarray of bool, (n,)
        Whether the whole marker is imaged inside the picture through the reflecting region.
    """

    ij: NDArray[np.int64]
    center_px: NDArray[np.float64]
    visible: NDArray[np.bool_]


class Truth(dict[str, Any]):
    """A sample's ``truth.json``: the JSON object itself (a dict, equal to what ``json.load`` gives), with typed
    accessors for what every kind has (docs/contract.md, "Truth")."""

    @property
    def format(self) -> int:
        """The file's format version (1: written before truth files carried one)."""
        return int(self.get("format", 1))

    @property
    def kind(self) -> str:
        """``deflectometry``, ``calibration``, ``grin`` or ``cmu``."""
        return str(self.get("kind", ""))

    @property
    def index(self) -> int:
        """The sample's index."""
        return int(self["sample"])

    @property
    def parameters(self) -> dict[str, Any]:
        """The varied quantities drawn for the sample (keys of the config's ``[vary]``; units as their names)."""
        return dict(self.get("parameters", {}))

    @property
    def seeds(self) -> dict[str, Any]:
        """Every seed the sample used (surface, render, noise; per channel for ``cmu``)."""
        return dict(self.get("seeds", {}))

    @property
    def markers(self) -> MarkerTable:
        """The marker truth as arrays (Part I kinds); raises for kinds without markers."""
        if "markers" not in self:
            raise DatasetReadError(f"a {self.kind!r} sample has no marker truth")
        rows = self["markers"]
        ij = np.array([[m["i"], m["j"]] for m in rows], dtype=np.int64).reshape(-1, 2)
        centre = np.array(
            [
                [
                    np.nan if m["center_col"] is None else m["center_col"],
                    np.nan if m["center_row"] is None else m["center_row"],
                ]
                for m in rows
            ],
            dtype=np.float64,
        ).reshape(-1, 2)
        return MarkerTable(ij, centre, np.array([bool(m["visible"]) for m in rows], dtype=bool))


@dataclass(frozen=True)
class Sample:
    """One sample of a dataset; its files are read when an attribute is first asked for.

    Attributes
    ----------
    index : int
        The sample's index in the dataset (its folder's name).
    folder : Path
        The sample's folder.
    """

    index: int
    folder: Path

    @cached_property
    def meta(self) -> dict[str, Any]:
        """The sample's ``sample.json``: its format, kind and files with their SHA-256 and sizes."""
        meta = _read_json(self.folder, SAMPLE_FILE)
        _check_format(meta, self.folder / SAMPLE_FILE)
        return meta

    @cached_property
    def truth(self) -> Truth:
        """The sample's ``truth.json`` (:class:`Truth`): parameters, setup, marker images, cameras, poses (per kind)."""
        truth = _read_json(self.folder, "truth.json")
        _check_format(truth, self.folder / "truth.json")
        return Truth(truth)

    @property
    def format(self) -> int:
        """The sample's format version (``sample.json`` ``"format"``; 1 before it carried one)."""
        return int(self.meta.get("format", 1))

    @property
    def kind(self) -> str:
        """The sample kind: ``deflectometry``, ``calibration``, ``grin`` or ``cmu``."""
        return str(self.meta.get("kind", self.truth.get("kind", "")))

    @cached_property
    def images(self) -> dict[str, NDArray[np.float32]]:
        """Every camera image of the sample by name: ``{"image": ...}``, or one per channel for ``cmu``
        (``{"image_blue": ..., ...}``), float32 (rows, cols)."""
        from scopetwin.scenes.io import read_image

        files = self.meta.get("files", {})
        names = sorted(str(n) for n in files if str(n).startswith(("image", "fringe_")) and str(n).endswith(".exr"))
        if not names:
            raise DatasetReadError(f"{self.folder}: the sample lists no image file")
        shape = self.image_shape
        try:
            return {n.removesuffix(".exr"): read_image(self._file(n), shape)[0] for n in names}
        except ScopetwinError as exc:
            raise DatasetReadError(f"sample {self.index}: {exc}") from None

    @cached_property
    def fringes(self) -> Any:
        """The fringe measurement of a sample rendered with a ``[fringes]`` setup
        (:class:`scopetwin.sim.fringes.FringeMeasurement`: ``images`` (K, rows, cols) float32 in the sequence's
        order, ``frames``, ``display``, ``sequence``, ``exposure_s``, the true ``heights``), read from its
        ``fringes.json`` with :func:`scopetwin.sim.fringes.read_fringes`'s checks. The per-pixel truth of every frame
        is :attr:`maps` (``pattern_xy``: the display point each pixel sees)."""
        from scopetwin.sim.fringes import FRINGES_FILE, read_fringes

        if FRINGES_FILE not in self.meta.get("files", {}):
            raise DatasetReadError(f"sample {self.index}: not a fringe sample (it lists no {FRINGES_FILE})")
        try:
            return read_fringes(self.folder)
        except ScopetwinError as exc:
            raise DatasetReadError(f"sample {self.index}: {exc}") from None

    @cached_property
    def image_shape(self) -> tuple[int, int] | None:
        """(rows, cols) every image and map of the sample has: the camera's pixels of a Part I sample, the window of
        a ``cmu`` sample; None where the truth does not say. Checked against each EXR's header before decoding."""
        from scopetwin.sim.datasets.validate import sample_image_shape

        try:
            return sample_image_shape(self.truth, self.kind)
        except ScopetwinError as exc:
            raise DatasetReadError(f"sample {self.index}: {exc}") from None

    def _file(self, name: object) -> Path:
        """The path of the sample's file ``name`` (as a file of the sample names it), kept inside its folder."""
        try:
            return resolve_inside(self.folder, name, f"sample {self.index} file")
        except ScopetwinError as exc:
            raise DatasetReadError(str(exc)) from None

    @property
    def image(self) -> NDArray[np.float32]:
        """The camera image (float32, rows x cols); for a ``cmu`` sample the first channel's."""
        images = self.images
        return images["image"] if "image" in images else images[sorted(images)[0]]

    @cached_property
    def maps(self) -> dict[str, NDArray[Any]]:
        """The per-pixel truth aligned with the image (:mod:`scopetwin.sim.datasets.maps`): layer -> (rows, cols)
        or (rows, cols, k) array; ``mask``/``roi`` bool, ``marker_id`` int32 (-1: no marker), the rest float32 with
        NaN where a value does not exist. A sample written without ``maps.exr`` (format 1, or ``maps = false``)
        has its Part I maps computed from its setup and surface file, the ``cmu`` ones from its truth."""
        from scopetwin.sim.datasets.maps import MAPS_FILE, cmu_object_maps, part1_maps, read_maps

        path = self.folder / MAPS_FILE
        try:
            if path.is_file() or path.is_symlink():
                return read_maps(self._file(MAPS_FILE), self.image_shape)
            if self.kind in ("deflectometry", "calibration"):
                return part1_maps(self.setup, self.heights)
            if self.kind == "cmu":
                r0, c0, h, w = self.truth["window"]
                return {k: v.astype(np.float32) for k, v in cmu_object_maps(self.truth["channels"], h, w).items()}
        except ScopetwinError as exc:
            raise DatasetReadError(f"{self.folder}: {exc}") from None
        raise DatasetReadError(f"{self.folder}: a {self.kind!r} sample has no per-pixel maps")

    @cached_property
    def heights(self) -> Any:
        """The true height map of a deflectometry sample (:class:`scopetwin.scenes.surface.HeightMap`), else None."""
        name = self.truth.get("surface")
        if not name:
            return None
        from scopetwin.scenes.io import read_heightmap

        path = self._file(name)
        try:
            return read_heightmap(path)
        except ScopetwinError as exc:
            raise DatasetReadError(f"sample {self.index}: {exc}") from None

    @cached_property
    def camera(self) -> Any:
        """The sample's camera in OpenCV's convention (:class:`scopetwin.scenes.opencv_camera.OpenCVCamera`: ``K``,
        ``dist``, ``R``, ``t``, pixel centres at integer coordinates, and the size of the distortion's
        approximation in px). Part I kinds only."""
        from scopetwin.scenes.opencv_camera import OpenCVCamera, opencv_camera

        if "camera_opencv" in self.truth:
            return OpenCVCamera.from_dict(self.truth["camera_opencv"])
        if self.kind in ("deflectometry", "calibration"):
            return opencv_camera(self.thesis_camera)
        raise DatasetReadError(
            f"a {self.kind!r} sample has no single pinhole camera (see truth['channels'] or truth['magnification'])"
        )

    @property
    def thesis_camera(self) -> Any:
        """The sample's camera in the thesis's model (:class:`scopetwin.scenes.camera.Camera`, thesis §1.6.2)."""
        return self.setup.camera_model

    @cached_property
    def setup(self) -> Any:
        """The sample's setup (:class:`scopetwin.scenes.setup.Setup`; the GRIN and CMU kinds: their JSON)."""
        data = self.truth.get("setup_json")
        if data is None or self.kind in ("grin", "cmu"):
            return data if data is not None else self.truth.get("setup")
        from scopetwin.scenes.inputs import parse_json
        from scopetwin.scenes.setup import setup_from_dict

        try:
            body = data if isinstance(data, dict) else parse_json(str(data), "truth.json", "setup_json")
            if not isinstance(body, dict):
                raise DatasetReadError(f"sample {self.index}: truth.json setup_json is not a JSON object")
            return setup_from_dict(body, str(self.folder))
        except DatasetReadError:
            raise
        except ScopetwinError as exc:
            raise DatasetReadError(f"sample {self.index}: {exc}") from None

    def arrays(
        self, names: Sequence[str] = ("image",), *, camera: bool = False, markers: bool = False
    ) -> dict[str, Any]:
        """The sample as one plain dict that torch's default collate batches (module docstring): ``index``,
        ``kind``, the named images (``image`` or ``image_<channel>``) and map layers; with ``camera`` the OpenCV
        camera's ``K``, ``dist``, ``R``, ``t``; with ``markers`` the marker truth ``marker_ij``, ``marker_px``,
        ``marker_visible``. Values are numpy arrays, ints and strings only."""
        out: dict[str, Any] = {"index": self.index, "kind": self.kind}
        for name in names:
            if name.startswith("image"):
                out[name] = self.image if name == "image" else self.images[name]
            else:
                maps = self.maps
                if name not in maps:
                    raise DatasetReadError(f"sample {self.index} has no map {name!r} (it has {', '.join(maps)})")
                out[name] = maps[name]
        if camera:
            cam = self.camera
            out |= {
                "K": np.asarray(cam.K, dtype=np.float64),
                "dist": np.asarray(cam.dist, dtype=np.float64),
                "R": np.asarray(cam.R, dtype=np.float64),
                "t": np.asarray(cam.t, dtype=np.float64),
            }
        if markers:
            table = self.truth.markers
            out |= {"marker_ij": table.ij, "marker_px": table.center_px, "marker_visible": table.visible}
        return out


class Dataset(Sequence[Sample]):
    """The finished samples of a dataset folder, in index order (see the module docstring).

    Attributes
    ----------
    root : Path
        The dataset folder.
    config : dict
        Its ``dataset.json`` (the normalised config and plan).
    indices : list of int
        The indices of the samples in this (possibly sliced) view.
    """

    def __init__(self, root: Path, config: dict[str, Any], indices: list[int]) -> None:
        self.root = root
        self.config = config
        self.indices = indices

    def __len__(self) -> int:
        return len(self.indices)

    @overload
    def __getitem__(self, i: int) -> Sample: ...

    @overload
    def __getitem__(self, i: slice) -> Dataset: ...

    def __getitem__(self, i: int | slice) -> Sample | Dataset:
        if isinstance(i, slice):
            return Dataset(self.root, self.config, self.indices[i])
        if isinstance(i, bool) or not isinstance(i, int | np.integer):
            raise TypeError(f"dataset indices are integers or slices, not {type(i).__name__}")
        index = self.indices[int(i)]  # IndexError past the end, as a sequence should
        return Sample(index, self.root / SAMPLES / f"{index:06d}")

    def __iter__(self) -> Iterator[Sample]:
        for k in range(len(self)):
            yield self[k]

    @property
    def kind(self) -> str:
        """The dataset's sample kind."""
        return str(self.config.get("config", {}).get("dataset", {}).get("kind", ""))

    @property
    def format(self) -> int:
        """The dataset's format version (``dataset.json`` ``"format"``)."""
        return int(self.config.get("format", 1))

    def arrays(self, *names: str, camera: bool = False, markers: bool = False) -> ArrayView:
        """A view whose items are plain dicts (:meth:`Sample.arrays`): ``index``, ``kind``, the named images and
        map layers (default ``image``; e.g. ``"height"``, ``"mask"``), with ``camera`` the OpenCV camera (``K``,
        ``dist``, ``R``, ``t``), with ``markers`` the marker truth (``marker_ij``, ``marker_px``,
        ``marker_visible``): what torch's default collate stacks into a batch, e.g.
        ``DataLoader(ds.arrays("image", "height", camera=True), batch_size=8)``."""
        return ArrayView(self, names or ("image",), camera=camera, markers=markers)

    def __repr__(self) -> str:
        return f"Dataset({str(self.root)!r}, kind={self.kind!r}, format={self.format}, samples={len(self)})"


class ArrayView(Sequence[dict[str, Any]]):
    """The samples of a :class:`Dataset` as plain dicts (:meth:`Sample.arrays`), a map-style dataset."""

    def __init__(self, dataset: Dataset, names: Sequence[str], *, camera: bool = False, markers: bool = False) -> None:
        self.dataset = dataset
        self.names = tuple(names)
        self.camera = camera
        self.markers = markers

    def __len__(self) -> int:
        return len(self.dataset)

    @overload
    def __getitem__(self, i: int) -> dict[str, Any]: ...

    @overload
    def __getitem__(self, i: slice) -> ArrayView: ...

    def __getitem__(self, i: int | slice) -> dict[str, Any] | ArrayView:
        if isinstance(i, slice):
            return ArrayView(self.dataset[i], self.names, camera=self.camera, markers=self.markers)
        return self.dataset[i].arrays(self.names, camera=self.camera, markers=self.markers)


def open_dataset(path: str | Path) -> Dataset:
    """The finished samples of a dataset folder as a lazy sequence (:class:`Dataset`).

    Parameters
    ----------
    path : str or path
        A folder written by ``scopetwin dataset generate`` (``dataset.json``, ``samples/NNNNNN/``).

    Raises
    ------
    DatasetReadError
        The folder does not exist, holds no ``dataset.json``, or holds a dataset of a format this scopetwin does not
        read (the message names it).
    """
    from scopetwin.sim.datasets.plan import FORMAT_VERSION, READABLE_FORMATS

    root = Path(path)
    if not root.is_dir():
        raise DatasetReadError(f"{root} is not a folder")
    if not (root / CONFIG_FILE).exists():
        raise DatasetReadError(f"{root} is not a dataset folder (no {CONFIG_FILE})")
    config = _read_json(root, CONFIG_FILE)
    fmt = config.get("format")
    if fmt not in READABLE_FORMATS:
        newer = isinstance(fmt, int) and fmt > FORMAT_VERSION
        raise DatasetReadError(
            f"{root} is a dataset of format {fmt!r}; this scopetwin reads formats "
            f"{', '.join(map(str, READABLE_FORMATS))}" + ("; install a newer scopetwin to read it" if newer else "")
        )
    samples = root / SAMPLES
    listed = samples.is_dir() and not samples.is_symlink()
    indices = sorted(int(p.name) for p in samples.iterdir() if _finished(p)) if listed else []
    return Dataset(root, config, indices)


def _finished(folder: Path) -> bool:
    """Whether ``folder`` is a finished sample folder: a real folder (not a link) named by digits with its
    ``sample.json`` in place."""
    return folder.name.isdigit() and not folder.is_symlink() and folder.is_dir() and (folder / SAMPLE_FILE).exists()


def _read_json(folder: Path, name: str) -> dict[str, Any]:
    """The JSON object in ``folder / name``, read through :func:`scopetwin.scenes.safe_read.read_json_inside`."""
    path = folder / name
    if not (path.exists() or path.is_symlink()):
        raise DatasetReadError(f"{path} is missing")
    try:
        return read_json_inside(folder, name, name)
    except ScopetwinError as exc:
        raise DatasetReadError(str(exc)) from None


def _check_format(data: dict[str, Any], path: Path) -> None:
    """Refuse a sample file of a format this scopetwin does not read (1 where the file names none)."""
    from scopetwin.sim.datasets.plan import READABLE_FORMATS

    try:
        check_format(data.get("format", 1), READABLE_FORMATS, str(path))
    except ScopetwinError as exc:
        raise DatasetReadError(str(exc)) from None
