"""What the OME output of a stopped MDA declares: each position's acquired planes as pieces of its plan.

An MDA stopped before its last plane (a device stopped answering, a signal) has acquired, at every position it
reached, a first part of that position's planes in the plan's order (the axes ``t``, ``c``, ``z`` in the plan's
axis order, the first the outermost). :class:`~scopetwin.instrument.ome.OmeOutput` then stores those planes so that
every image declares exactly the planes it holds, and no reader fills in a plane that was never acquired:

- The **main image** of a position (its OME-TIFF ``Image``; its OME-Zarr image at the root or at ``A/<N>/0``)
  holds the whole indices of the outermost axis that were acquired; where not one was, the whole indices of the next
  axis within the first index of the outermost; and so on. In an OME-Zarr plate the wells' main images have one
  shape, the smallest of them: plate readers (ome-zarr-py, napari) lay the wells side by side in one array.
- Every other acquired plane is in an **extra image**, again a box of whole indices of the plan, named by the plan
  index of its first plane (:func:`label`: ``t2c1z0``). OME-TIFF: a further ``Image`` (series) in the position's
  file, named ``<position> t2c1z0``, and each file's OME-XML lists its own images only (tifffile reads the pages of
  another file of a multi-file OME through the file it opened). OME-Zarr: an image group beside the main image,
  ``t2c1z0`` in the root image, ``A/<N>/t2c1z0`` in a plate (not one of the well's fields, which plate readers
  expect to be of one shape); the main image's ``scopetwin`` attribute lists them (``more_images``), and every
  image gives the plan index of its first plane (``plan_index``).

A TIFF file's pages stay where they are: only its OME-XML is rewritten, on a copy beside it that is then renamed
over it (:func:`scopetwin.scenes.io.atomic_path`). An OME-Zarr image's extra images are copied out first, each
built in a new hidden folder beside it and renamed into place; then the main image is resized (zarr removes the
chunks beyond it, and writes each metadata document beside its place and renames it). ``out`` below is an
:class:`~scopetwin.instrument.ome.OmeOutput` (typed ``Any``: that module imports this one).
"""

from __future__ import annotations

import itertools
import math
import os
import shutil
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from scopetwin.scenes.io import atomic_path

#: The Zarr attribute (under ``scopetwin``) of a main image that lists its extra images, store-relative paths.
MORE_IMAGES = "more_images"


def boxes(sizes: Sequence[int], start: int, stop: int) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
    """The boxes of whole indices that the planes ``start`` to ``stop - 1`` (row-major order) of an array of
    ``sizes`` make, in order: ``(first index, shape)`` each.

    The planes 0 to 3 of a 2 x 3 array are the first row (index (0, 0), shape (1, 3)) and the first plane of the
    second ((1, 0), shape (1, 1)). An array without axes has one plane (``sizes`` ``()``: one box ``((), ())``).
    """
    if start >= stop:
        return []
    if not sizes:
        return [((), ())]
    inner = math.prod(sizes[1:])
    first, skip = divmod(start, inner)
    last, rest = divmod(stop, inner)

    def within(index: int, lo: int, hi: int) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
        return [((index, *at), (1, *shape)) for at, shape in boxes(sizes[1:], lo, hi)]

    if first == last:
        return within(first, skip, rest)
    out = []
    if skip:
        out += within(first, skip, inner)
        first += 1
    if last > first:
        out.append(((first, *(0,) * (len(sizes) - 1)), (last - first, *sizes[1:])))
    if rest:
        out += within(last, 0, rest)
    return out


def label(axes: Sequence[str], start: Sequence[int]) -> str:
    """The name of a piece that starts at plan index ``start`` along ``axes``: ``t2c1z0`` (alphanumeric, as an
    NGFF path must be)."""
    return "".join(f"{axis}{index}" for axis, index in zip(axes, start, strict=True))


@dataclass(frozen=True)
class Piece:
    """A box of one position's acquired planes: its axes (plan order), plan index of its first plane, shape, and
    its planes as positions in :attr:`OmeOutput.reported.planes <scopetwin.instrument.ome.OmeOutput>`, in the
    box's row-major order."""

    position: int
    axes: tuple[str, ...]
    start: tuple[int, ...]
    shape: tuple[int, ...]
    planes: tuple[int, ...]

    @property
    def main(self) -> bool:
        """Whether the piece starts at the plan's first plane (a position's main image)."""
        return not any(self.start)

    @property
    def label(self) -> str:
        """:func:`label` of the piece."""
        return label(self.axes, self.start)

    def at(self, axis: str) -> int:
        """The plan index of the first plane along ``axis`` (0 for an axis the plan does not have)."""
        return self.start[self.axes.index(axis)] if axis in self.axes else 0

    def size(self, axis: str) -> int:
        """The number of planes along ``axis`` (1 for an axis the plan does not have)."""
        return self.shape[self.axes.index(axis)] if axis in self.axes else 1

    def relative(self, index: dict[str, int]) -> dict[str, int]:
        """A plane's plan index within the piece (``the_z`` etc. of its OME ``Plane``)."""
        return {axis: int(index.get(axis, 0)) - self.at(axis) for axis in "tcz"}


def image_axes(layout: Any) -> tuple[str, ...]:
    """The axes of one position's image: the layout's axes without the positions, in the plan's order."""
    return tuple(axis for axis in layout.axes if axis != "p")


def planes_per_position(layout: Any) -> int:
    """The planes the plan takes at each position."""
    return math.prod(layout.sizes[axis] for axis in image_axes(layout))


def complete(out: Any) -> bool:
    """Whether every position of the plan holds all its planes."""
    return len(out.reported.planes) == (len(out.layout.positions) or 1) * planes_per_position(out.layout)


def _acquired(out: Any) -> dict[int, dict[int, int]]:
    """``{position: {row-major plane number: position in reported.planes}}`` of the planes acquired."""
    axes = image_axes(out.layout)
    sizes = [out.layout.sizes[axis] for axis in axes]
    acquired: dict[int, dict[int, int]] = {}
    for n, (position, index, _meta) in enumerate(out.reported.planes):
        flat = 0
        for axis, size in zip(axes, sizes, strict=True):
            flat = flat * size + int(index.get(axis, 0))
        acquired.setdefault(position, {}).setdefault(flat, n)
    return acquired


def _runs(numbers: Sequence[int]) -> Iterator[tuple[int, int]]:
    """``(start, stop)`` of each run of consecutive numbers of the sorted ``numbers``."""
    start = prev = numbers[0]
    for n in numbers[1:]:
        if n != prev + 1:
            yield start, prev + 1
            start = n
        prev = n
    yield start, prev + 1


def pieces(out: Any, *, one_shape: bool = False) -> dict[int, list[Piece]]:
    """Each reached position's pieces, the main image first (see the module's docstring).

    Parameters
    ----------
    out : OmeOutput
        The output, after its last plane.
    one_shape : bool
        Give every position's main image one shape, the shortest (an OME-Zarr plate).
    """
    axes = image_axes(out.layout)
    sizes = [out.layout.sizes[axis] for axis in axes]
    acquired = _acquired(out)
    ranges = {position: list(_runs(sorted(flats))) for position, flats in acquired.items()}

    def main_length(position: int) -> int:
        start, stop = ranges[position][0]
        return math.prod(boxes(sizes, start, stop)[0][1]) if start == 0 else 0

    cut = min(main_length(p) for p in ranges) if one_shape and ranges else 0
    result: dict[int, list[Piece]] = {}
    for position in sorted(ranges):
        spans = ranges[position]
        if cut and spans[0][0] == 0:  # the main image of one shape, then the rest of the first run
            spans = [(0, cut), (cut, spans[0][1]), *spans[1:]]
        found = []
        for start, stop in spans:
            for first, shape in boxes(sizes, start, stop):
                numbers = []
                for offset in itertools.product(*map(range, shape)):
                    flat = 0
                    for axis_first, step, size in zip(first, offset, sizes, strict=True):
                        flat = flat * size + axis_first + step
                    numbers.append(acquired[position][flat])
                found.append(Piece(position, axes, first, shape, tuple(numbers)))
        result[position] = found
    return result


def rewrite_tiff_files(out: Any, files: dict[int, Path]) -> None:
    """Give every position's OME-TIFF file (``{position: path}``, one file each) the OME-XML of its pieces.

    Each file's OME lists the images of that file, each plane referred to by the file's UUID and name and its page
    there. The pages stay as they are; each file is copied beside itself, given its new OME-XML and renamed over
    itself.
    """
    import tifffile

    from scopetwin.instrument.ome_xml import position_file_ome

    found = pieces(out)
    for position, path in files.items():
        ome = position_file_ome(out, found[position], (path.name, f"urn:uuid:{uuid.uuid4()}"))
        with atomic_path(path) as tmp:
            shutil.copyfile(path, tmp)
            tifffile.tiffcomment(tmp, ome.to_xml().encode())


def _image_groups(out: Any) -> dict[int, str]:
    """``{position: store-relative path}`` of each position's main image (``""``: the store's root)."""
    names = out.layout.names
    if len(names) > 1:
        return {position: f"A/{position + 1}/0" for position in range(len(names))}
    return {0: ""}


def shrink_zarr(out: Any) -> None:
    """Make every image of a stopped run's OME-Zarr declare only acquired planes (the module's docstring):
    extra images copied out first, then each main image resized, then the wells of positions never reached taken
    out of the plate and removed."""
    import zarr

    store = Path(out.path)
    groups = _image_groups(out)
    found = pieces(out, one_shape=len(groups) > 1)
    for position, group_path in groups.items():
        if position not in found:
            continue
        group = store / group_path
        attrs: dict[str, Any] = zarr.open_group(str(group), mode="r").attrs.asdict()
        main, *more = found[position]
        well = group.parent if group_path else group
        extra_paths = []
        for piece in more:
            _extra_image(out, group, attrs, piece, well / piece.label)
            extra_paths.append(str((well / piece.label).relative_to(store)))
        _shrink_image(out, group, attrs, main, extra_paths)
    reached = [groups[p] for p in sorted(found)]
    if len(groups) > 1 and len(reached) < len(groups):
        _drop_wells(out, store, reached)


def _datasets(attrs: dict[str, Any]) -> list[str]:
    return [d["path"] for d in attrs["ome"]["multiscales"][0]["datasets"]]


def _in_array(attrs: dict[str, Any], piece: Piece) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """The first index and shape of ``piece`` along the axes of the image's arrays but ``y``, ``x`` (NGFF orders
    them ``t``, ``c``, ``z``, whatever order the plan took them in)."""
    axes = [a["name"] for a in attrs["ome"]["multiscales"][0]["axes"]][:-2]
    return tuple(piece.at(axis) for axis in axes), tuple(piece.size(axis) for axis in axes)


def _piece_attrs(out: Any, attrs: dict[str, Any], piece: Piece, more: list[str] | None) -> dict[str, Any]:
    """The attributes of an image holding ``piece``: the channels it holds, a translation from where the devices
    reported its first plane (and its first time point), its plan index; a main image lists ``more``."""
    import copy

    new = copy.deepcopy(attrs)
    ome = new["ome"]
    multiscale = ome["multiscales"][0]
    axes = [a["name"] for a in multiscale["axes"]]
    first_meta = out.reported.planes[piece.planes[0]][2]
    for dataset in multiscale["datasets"]:
        transforms = dataset["coordinateTransformations"]
        scale = next((t["scale"] for t in transforms if t["type"] == "scale"), [1.0] * len(axes))
        shift = {axis: first_meta.get(f"position_{axis}") for axis in "xyz"}
        shift["t"] = piece.at("t") * float(scale[axes.index("t")]) if "t" in axes else None
        translation = [float(shift.get(axis) or 0.0) for axis in axes]
        kept = [t for t in transforms if t["type"] != "translation"]
        dataset["coordinateTransformations"] = [*kept, {"type": "translation", "translation": translation}]
    channels = ome.get("omero", {}).get("channels")
    if channels is not None and "c" in piece.axes:
        ome["omero"]["channels"] = channels[piece.at("c") : piece.at("c") + piece.size("c")]
    extra = new.setdefault("scopetwin", {})
    extra["plan_index"] = dict(zip(piece.axes, piece.start, strict=True))
    if more is not None:
        extra[MORE_IMAGES] = more
    return new


def _array_json(path: Path) -> dict[str, Any]:
    import json

    return dict(json.loads((path / "zarr.json").read_text()))


def _extra_image(out: Any, group: Path, attrs: dict[str, Any], piece: Piece, dest: Path) -> None:
    """Copy ``piece``'s planes from the main image at ``group`` into a new image at ``dest``: built in a new hidden
    folder beside it, then renamed into place."""
    import json

    import zarr

    stage = dest.parent / f".{dest.name}.{uuid.uuid4().hex}.partial"
    stage.mkdir()  # a new name: nothing there to follow
    try:
        node = {"zarr_format": 3, "node_type": "group", "attributes": _piece_attrs(out, attrs, piece, None)}
        (stage / "zarr.json").write_text(json.dumps(node, indent=2))
        start, shape = _in_array(attrs, piece)
        for path in _datasets(attrs):
            source = zarr.open_array(str(group / path), mode="r")
            meta = _array_json(group / path)
            meta["shape"] = [*shape, *source.shape[len(shape) :]]
            (stage / path).mkdir(parents=True)
            (stage / path / "zarr.json").write_text(json.dumps(meta))
            target = zarr.open_array(str(stage / path), mode="r+")
            for offset in itertools.product(*map(range, shape)):
                target[offset] = source[tuple(first + step for first, step in zip(start, offset, strict=True))]
        os.replace(stage, dest)
    finally:
        if stage.exists():
            shutil.rmtree(stage)


def _shrink_image(out: Any, group: Path, attrs: dict[str, Any], piece: Piece, more: list[str]) -> None:
    """Resize the main image at ``group`` to ``piece`` (chunks beyond it removed) and rewrite its attributes."""
    import zarr

    start, shape = _in_array(attrs, piece)
    for path in _datasets(attrs):
        array = zarr.open_array(str(group / path), mode="r+")
        if any(start):  # a first plane other than the plan's: its planes moved to the start, in row-major order
            for offset in itertools.product(*map(range, shape)):
                array[offset] = array[tuple(first + step for first, step in zip(start, offset, strict=True))]
        array.resize((*shape, *array.shape[len(shape) :]))
    zarr.open_group(str(group), mode="r+").attrs.put(_piece_attrs(out, attrs, piece, more))


def _drop_wells(out: Any, store: Path, reached: list[str]) -> None:
    """Take the wells of positions never reached out of the plate (and the columns they alone had), then remove
    them."""
    import zarr

    root = zarr.open_group(str(store), mode="r+")
    attrs: dict[str, Any] = root.attrs.asdict()
    plate = attrs["ome"]["plate"]
    keep = {path.rsplit("/", 1)[0] for path in reached}
    wells = [w for w in plate["wells"] if w["path"] in keep]
    columns = [c for c in plate["columns"] if any(w["path"].split("/")[1] == c["name"] for w in wells)]
    for well in wells:
        well["columnIndex"] = next(i for i, c in enumerate(columns) if c["name"] == well["path"].split("/")[1])
    dropped = [w["path"] for w in plate["wells"] if w["path"] not in keep]
    plate["wells"], plate["columns"] = wells, columns
    root.attrs.put(attrs)
    for path in dropped:
        shutil.rmtree(store / path, ignore_errors=True)
