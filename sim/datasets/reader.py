"""Reading a dataset written by ``scopetwin dataset generate``: a lazy, indexable sequence of samples.

:func:`open_dataset` lists the finished samples of a dataset folder (those whose ``sample.json`` is in place: a
sample folder is renamed into place only when complete, :mod:`scopetwin.sim.datasets.store`) and returns a
:class:`Dataset`: ``len``, ``ds[i]`` (negative indices too), ``ds[a:b]`` (another dataset), iteration. A
:class:`Sample` reads its files when an attribute is first asked for, so opening a dataset of 10,000 samples reads
only its folder listing, and reading a sample costs what reading its files costs. A ``torch.utils.data.DataLoader``
accepts a :class:`Dataset` as a map-style dataset (``__len__`` and ``__getitem__``) without scopetwin importing torch.
"""

from __future__ import annotations

import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, overload

import numpy as np
from numpy.typing import NDArray

from scopetwin.scenes.errors import ScopetwinError
from scopetwin.sim.datasets.store import CONFIG_FILE, SAMPLE_FILE, SAMPLES


class DatasetReadError(ScopetwinError):
    """A folder that is not a dataset, or a sample whose files cannot be read."""


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
        """The sample's ``sample.json``: its kind and its files with their SHA-256 and sizes."""
        return _read_json(self.folder / SAMPLE_FILE)

    @cached_property
    def truth(self) -> dict[str, Any]:
        """The sample's ``truth.json``: the parameters drawn for it, the setup, marker images, poses (per kind)."""
        return _read_json(self.folder / "truth.json")

    @property
    def kind(self) -> str:
        """The sample kind: ``deflectometry``, ``calibration``, ``grin`` or ``cmu``."""
        return str(self.meta.get("kind", self.truth.get("kind", "")))

    @cached_property
    def images(self) -> dict[str, NDArray[np.float32]]:
        """Every camera image of the sample by name: ``{"image": ...}``, or one per channel for ``cmu``
        (``{"image_blue": ..., ...}``), float32 (rows, cols)."""
        from scopetwin.scenes.io import read_image

        names = sorted(n for n in self.meta.get("files", {}) if n.startswith("image") and n.endswith(".exr"))
        if not names:
            raise DatasetReadError(f"{self.folder}: the sample lists no image file")
        return {n.removesuffix(".exr"): read_image(self.folder / n)[0] for n in names}

    @property
    def image(self) -> NDArray[np.float32]:
        """The camera image (float32, rows x cols); for a ``cmu`` sample the first channel's."""
        images = self.images
        return images["image"] if "image" in images else images[sorted(images)[0]]

    @cached_property
    def setup(self) -> Any:
        """The sample's setup (:class:`scopetwin.scenes.setup.Setup`; the GRIN and CMU kinds: their JSON)."""
        data = self.truth.get("setup_json")
        if data is None:
            return self.truth.get("setup")
        from scopetwin.scenes.setup import setup_from_dict

        return setup_from_dict(data if isinstance(data, dict) else json.loads(data), str(self.folder))


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

    def __repr__(self) -> str:
        return f"Dataset({str(self.root)!r}, kind={self.kind!r}, samples={len(self)})"


def open_dataset(path: str | Path) -> Dataset:
    """The finished samples of a dataset folder as a lazy sequence (:class:`Dataset`).

    Parameters
    ----------
    path : str or path
        A folder written by ``scopetwin dataset generate`` (``dataset.json``, ``samples/NNNNNN/``).

    Raises
    ------
    DatasetReadError
        The folder does not exist or holds no ``dataset.json``.
    """
    root = Path(path)
    if not root.is_dir():
        raise DatasetReadError(f"{root} is not a folder")
    if not (root / CONFIG_FILE).is_file():
        raise DatasetReadError(f"{root} is not a dataset folder (no {CONFIG_FILE})")
    config = _read_json(root / CONFIG_FILE)
    samples = root / SAMPLES
    indices = (
        sorted(
            int(p.name) for p in samples.iterdir() if p.is_dir() and p.name.isdigit() and (p / SAMPLE_FILE).is_file()
        )
        if samples.is_dir()
        else []
    )
    return Dataset(root, config, indices)


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise DatasetReadError(f"{path} is missing") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise DatasetReadError(f"{path} cannot be read: {exc}") from None
    if not isinstance(data, dict):
        raise DatasetReadError(f"{path} does not hold a JSON object")
    return data
