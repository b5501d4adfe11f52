"""OME-TIFF and OME-Zarr of an MDA, with the metadata readers use (ome-writers, pymmcore-plus's writers).

Optional dependency: ``pip install scopetwin[mm]`` (ome-writers comes with pymmcore-plus, tifffile).
:class:`OmeOutput` takes the planes of one MDA in the order they come and writes them through ome-writers'
streams (the writers pymmcore-plus uses), then completes the metadata its readers look for:

- OME-TIFF: ``SignificantBits`` (the camera's bit depth), the channels' colours (from each light's emission band,
  else its wavelength, else white) and excitation / emission wavelengths, an ``Instrument`` with the ``Objective``
  (magnification, NA) and the camera as ``Detector``, every plane's position (in µm, with its unit, rounded to the
  pm: :func:`position_um`) and exposure as the devices reported them. Several positions give one file each in a
  folder (ome-writers' layout) or, with ``single_file``, one multi-series file (one OME ``Image`` per position,
  written here with tifffile: ome-writers does not write one).
- OME-Zarr (NGFF 0.5): for several positions an NGFF plate at the root (one well per position in row ``A``) that
  ome-zarr-py's Reader and napari-ome-zarr open at the root (readers of single images, such as bioio-ome-zarr, open
  each position's image at ``A/<N>/0``); each image with scales in µm, a translation from the
  stage and focus as they reported at its first plane, display windows from the bit depth, channel colours; the
  camera, objective and wavelengths under the attribute ``scopetwin``.

Nothing records a value that was asked for: positions and exposures are the ones the devices reported.
"""

from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from scopetwin.instrument.errors import RigError

TIFF_SUFFIXES = (".ome.tif", ".ome.tiff")
ZARR_SUFFIX = ".ome.zarr"
WHITE = "FFFFFF"


def wavelength_color(nm: float | None) -> str:
    """``RRGGBB`` of light of wavelength ``nm`` as the eye sees it (white for ``None``; clamped to 380-700 nm).

    A piecewise-linear spectrum (Bruton's approximation) at full brightness: 455 nm is blue, 525 nm green, 620 nm red;
    ultraviolet shows as violet and infrared as deep red.
    """
    if nm is None:
        return WHITE
    wl = min(max(float(nm), 380.0), 700.0)
    bands = [
        (440.0, lambda w: (-(w - 440) / 60, 0.0, 1.0)),
        (490.0, lambda w: (0.0, (w - 440) / 50, 1.0)),
        (510.0, lambda w: (0.0, 1.0, -(w - 510) / 20)),
        (580.0, lambda w: ((w - 510) / 70, 1.0, 0.0)),
        (645.0, lambda w: (1.0, -(w - 645) / 65, 0.0)),
        (math.inf, lambda w: (1.0, 0.0, 0.0)),
    ]
    rgb = next(f(wl) for top, f in bands if wl < top or top == math.inf)
    return "".join(f"{round(255 * max(0.0, min(1.0, c))):02X}" for c in rgb)


#: Decimals a position in µm keeps (1 pm): below any stage's step, above the noise of a mm <-> µm conversion.
POSITION_DECIMALS = 6


def position_um(value: float | None) -> float | None:
    """A reported position in µm rounded to :data:`POSITION_DECIMALS` (75100.00000000001 -> 75100.0), or ``None``."""
    return None if value is None else round(float(value), POSITION_DECIMALS)


@dataclass(frozen=True)
class ChannelInfo:
    """One channel of an acquisition: its preset name, the light it selects and the light's wavelengths (nm)."""

    name: str
    light: str | None = None
    excitation_nm: float | None = None
    emission_nm: float | None = None

    @property
    def color(self) -> str:
        """``RRGGBB``: the emission band's colour, else the light's, else white."""
        return wavelength_color(self.emission_nm if self.emission_nm is not None else self.excitation_nm)


@dataclass(frozen=True)
class AcquisitionInfo:
    """What the rig says about the frames of an acquisition."""

    shape: tuple[int, int]
    dtype: str
    bit_depth: int
    pixel_size_um: float
    channels: tuple[ChannelInfo, ...] = ()
    camera: str = ""
    rig: str = ""
    magnification: float | None = None
    numerical_aperture: float | None = None


@dataclass(frozen=True)
class Layout:
    """The regular array an MDA fills: axes in acquisition order, sizes, position names, z step and time interval."""

    axes: tuple[str, ...]
    sizes: dict[str, int]
    positions: tuple[tuple[int, int], ...] = ()  # (p, g) of each flattened position, in the order they are stored
    names: tuple[str, ...] = ()
    z_step_um: float | None = None
    interval_s: float | None = None

    def position_index(self, index: dict[str, int]) -> int:
        """The flattened position of an event's index (0 without positions)."""
        if not self.positions:
            return 0
        return self.positions.index((int(index.get("p", 0)), int(index.get("g", 0))))


@dataclass
class _Reported:
    """What the devices reported, by flattened position and plane."""

    first: dict[int, tuple[float | None, float | None, float | None]] = field(default_factory=dict)
    planes: list[tuple[int, dict[str, int], dict[str, Any]]] = field(default_factory=list)


def _channel(info: ChannelInfo) -> Any:
    from ome_writers import Channel

    def whole(nm: float | None) -> int | None:
        return None if nm is None else max(1, round(nm))

    return Channel(
        name=info.name,
        color=f"#{info.color}",
        excitation_wavelength_nm=whole(info.excitation_nm),
        emission_wavelength_nm=whole(info.emission_nm),
    )


def _dimensions(layout: Layout, info: AcquisitionInfo, plate: bool) -> list[Any]:
    """ome-writers dimensions in acquisition order (positions named; a plate well each for OME-Zarr)."""
    from ome_writers import Dimension, Position

    dims: list[Any] = []
    for axis in layout.axes:
        if axis == "p":  # in a plate every well holds field "0" (ome-zarr-py reads the first well's field names)
            coords = [
                Position(name="0", plate_row="A", plate_column=str(i + 1)) if plate else Position(name=n)
                for i, n in enumerate(layout.names)
            ]
            dims.append(Dimension(name="p", type="position", coords=coords))
        elif axis == "t":
            dims.append(
                Dimension(name="t", type="time", count=layout.sizes["t"], scale=layout.interval_s, unit="second")
            )
        elif axis == "c":
            dims.append(Dimension(name="c", type="channel", coords=[_channel(c) for c in info.channels]))
        elif axis == "z":
            dims.append(
                Dimension(name="z", type="space", count=layout.sizes["z"], scale=layout.z_step_um, unit="micrometer")
            )
    rows, cols = info.shape
    for name, count in (("y", rows), ("x", cols)):
        dims.append(Dimension(name=name, type="space", count=count, scale=info.pixel_size_um, unit="micrometer"))
    return dims


def output_kind(path: str | Path) -> str:
    """``"tiff"`` or ``"zarr"`` from an output path's suffix (``.ome.tif``, ``.ome.tiff``, ``.ome.zarr``)."""
    name = str(path).lower().rstrip("/")
    if name.endswith(TIFF_SUFFIXES):
        return "tiff"
    if name.endswith(ZARR_SUFFIX):
        return "zarr"
    raise RigError(f"output {str(path)!r} must end in one of {', '.join((*TIFF_SUFFIXES, ZARR_SUFFIX))}")


def layout_of(seq: Any, sizes: dict[str, int], grid_points: list[int]) -> Layout:
    """The array layout of ``seq`` from its closed-form ``sizes`` and the grid points of each stage position.

    Positions and grid points make one position axis (``p`` then ``g``, or ``g`` then ``p`` for a shared grid
    visited first, as useq visits them); names are the positions' names (else their index), ``_gNNNN`` per grid point.
    """
    order = [str(a) for a in seq.axis_order]
    axes = [a for a in order if sizes.get(a, 0) and a not in "pg"]
    has_positions = bool(sizes.get("p") or sizes.get("g"))
    if has_positions:
        first = min(order.index(a) for a in "pg" if a in order and sizes.get(a, 0))
        axes.insert(sum(1 for a in axes if order.index(a) < first), "p")
    stage = list(seq.stage_positions) or [None]
    grid_first = seq.grid_plan is not None and "g" in order and "p" in order and order.index("g") < order.index("p")
    if grid_first and len(set(grid_points)) == 1:
        pairs = [(p, g) for g in range(grid_points[0]) for p in range(len(stage))]
    else:
        pairs = [(p, g) for p, n in enumerate(grid_points) for g in range(n)]
    gridded = sizes.get("g", 0) > 0

    def name(p: int, g: int) -> str:
        base = (getattr(stage[p], "name", None) or str(p)) if stage[p] is not None else str(p)
        return f"{base}_g{g:04d}" if gridded else base

    names = [name(p, g) for p, g in pairs] if has_positions else []
    if len(set(names)) != len(names):  # positions sharing a name: number them
        names = [f"{n}_{i}" for i, n in enumerate(names)]
    z_step = getattr(seq.z_plan, "step", None) if seq.z_plan is not None else None
    interval = getattr(seq.time_plan, "interval", None) if seq.time_plan is not None else None
    seconds = interval.total_seconds() if interval is not None and hasattr(interval, "total_seconds") else None
    sizes = dict(sizes, p=len(pairs) if has_positions else 0)
    return Layout(tuple(axes), sizes, tuple(pairs) if has_positions else (), tuple(names), z_step, seconds)


class OmeOutput:
    """The planes of one MDA into an OME-TIFF or OME-Zarr, in the order they come (see the module's docstring).

    Parameters
    ----------
    path : str or Path
        ``X.ome.tif`` / ``X.ome.tiff`` (several positions: a folder ``X`` of ``X_pNNN.ome.tif``, or one file with
        ``single_file``) or ``X.ome.zarr``.
    layout : Layout
        The array the planes fill (:func:`layout_of`).
    info : AcquisitionInfo
        The frames' shape, type, bit depth, pixel size, channels and optics.
    single_file : bool
        OME-TIFF only: all positions in one multi-series file.

    Raises
    ------
    RigError
        An output path of another kind, a symbolic link at the output (or at the folder of per-position files), or
        a name its metadata cannot hold (OME-TIFF: XML; OME-Zarr: JSON;
        :func:`~scopetwin.instrument.ome_xml.check_names`), before anything is written.
    """

    def __init__(self, path: str | Path, layout: Layout, info: AcquisitionInfo, *, single_file: bool = False) -> None:
        self.path = Path(path)
        self.kind = output_kind(path)
        from scopetwin.instrument.ome_xml import check_names

        check_names(path, layout, info, self.kind)
        self.layout, self.info = layout, info
        self.single_file = single_file and self.kind == "tiff"
        folders = [self.path.parent / _stem(self.path.name)] if self.kind == "tiff" and not self.single_file else []
        for target in (self.path, *folders):  # the per-position files' folder too
            if target.is_symlink():
                raise RigError(
                    f"output {str(target)!r} is a symbolic link; scopetwin writes through no link it did not make"
                )
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.reported = _Reported()
        self.planes = 0
        self._stream: Any = None
        self._tiff: Any = None
        self._staged = contextlib.ExitStack()
        if self.single_file:
            import tifffile

            from scopetwin.scenes.io import atomic_path

            staged = self._staged.enter_context(atomic_path(self.path))  # renamed onto the path when closed
            self._tiff = tifffile.TiffWriter(staged, bigtiff=True)
            self._staged_path = staged
        else:
            self._stream = self._open_stream()

    def _open_stream(self) -> Any:
        from ome_writers import AcquisitionSettings, Plate, create_stream

        plate = self.kind == "zarr" and len(self.layout.names) > 1
        settings = AcquisitionSettings(
            root_path=str(self.path),
            dimensions=_dimensions(self.layout, self.info, plate),
            dtype=self.info.dtype,
            plate=Plate(row_names=["A"], column_names=[str(i + 1) for i in range(len(self.layout.names))])
            if plate
            else None,
        )
        return create_stream(settings)

    def append(self, image: np.ndarray, index: dict[str, int], reported: dict[str, Any]) -> None:
        """One plane: its event index (``{"t": 0, "p": 1, "c": 0, "z": 2}``) and what the devices reported (``x_um``,
        ``y_um``, ``z_um``, ``exposure_ms``, ``elapsed_s``)."""
        position = self.layout.position_index(index)
        x, y, z = (position_um(reported.get(f"{axis}_um")) for axis in "xyz")
        where = (x, y, z)
        self.reported.first.setdefault(position, where)
        meta = {"exposure_time": float(reported["exposure_ms"]) * 1e-3}
        if reported.get("elapsed_s") is not None:
            meta["delta_t"] = float(reported["elapsed_s"])
        meta |= {f"position_{axis}": v for axis, v in zip("xyz", where, strict=True) if v is not None}
        if self._tiff is not None:
            # the first page carries the description that the OME-XML replaces when the file is closed
            first = {"description": "OME-XML"} if not self.planes else {}
            self._tiff.write(np.asarray(image), contiguous=False, metadata=None, photometric="minisblack", **first)
        else:
            self._stream.append(np.asarray(image), frame_metadata=meta)
        self.reported.planes.append((position, {k: int(v) for k, v in index.items()}, meta))
        self.planes += 1

    def close(self) -> list[str]:
        """Close the files and complete their metadata; the files written.

        A run stopped before its first plane leaves nothing: the single file, the Zarr store, or the per-position
        files and their folder are removed (they would hold no image). A run stopped before some position's first
        plane removes that position's file (an OME-Zarr plate its well), and the files kept refer to the files
        kept only. A run stopped before its last plane leaves files that declare only the planes acquired
        (:mod:`~scopetwin.instrument.ome_pieces`)."""
        if self._tiff is not None:
            self._tiff.close()
            self._tiff = None
            if self.planes:
                import tifffile

                from scopetwin.instrument.ome_pieces import pieces
                from scopetwin.instrument.ome_xml import single_file_ome

                with self._staged:  # renamed into place at the end of the block; removed if it raises
                    ome = single_file_ome(self, pieces(self))
                    tifffile.tiffcomment(self._staged_path, ome.to_xml().encode())
            else:  # a TIFF header without a page: the staged file goes
                with contextlib.suppress(RigError), self._staged:
                    raise RigError("no plane")
        elif self._stream is not None:
            stream, self._stream = self._stream, None
            stream.close()
            if self.planes:
                self._complete(stream)
            elif self.kind == "zarr":
                import shutil

                shutil.rmtree(self.path, ignore_errors=True)  # arrays declared, not one plane in them
            if self.kind != "zarr":  # one OME-TIFF per position
                _remove_pageless(self.files())
                folder = self.path.parent / _stem(self.path.name)
                if not self.path.exists() and folder.is_dir() and not any(folder.iterdir()):
                    folder.rmdir()  # an empty folder would block the rerun
        return self.files()

    def _complete(self, stream: Any) -> None:
        """Complete the metadata of ome-writers' files; after a stop, make them declare what they hold."""
        from scopetwin.instrument.ome_pieces import complete, rewrite_tiff_files, shrink_zarr

        stopped = not complete(self)
        metadata = stream.get_metadata()
        if self.kind == "zarr":
            _complete_zarr(metadata, self)
            stream.update_metadata(metadata)
            _version_plate(self.path)
            if stopped:
                shrink_zarr(self)
            return
        _complete_tiff(metadata, self)
        # a run stopped before a position's first plane leaves that position's file without a page: no metadata to
        # complete there, and the empty file goes (nor do the others refer to it)
        metadata = {p: m for p, m in metadata.items() if p in self.reported.first}
        _remove_pageless(self.files())
        if stopped:
            rewrite_tiff_files(self, _position_files(metadata, self.files()))
        else:
            _drop_missing_references(metadata, {Path(f).name for f in self.files()})
            stream.update_metadata(metadata)

    def files(self) -> list[str]:
        """The files (or the Zarr store) written so far."""
        if self.path.exists():
            return [str(self.path)]
        folder = self.path.parent / _stem(self.path.name)
        return sorted(str(p) for p in folder.glob("*.ome.tif*")) if folder.is_dir() else []


def _remove_pageless(paths: list[str]) -> None:
    """Remove the TIFF files among ``paths`` that hold no image (positions an interrupted run never reached)."""
    import logging

    import tifffile

    quiet = logging.getLogger("tifffile")
    for path in paths:
        level = quiet.level
        quiet.setLevel(logging.ERROR)  # its "contains no pages" warning is the finding here
        try:
            with tifffile.TiffFile(path) as tif:
                empty = len(tif.pages) == 0
        except (OSError, ValueError, IndexError, tifffile.TiffFileError):
            empty = os.path.getsize(path) <= 16  # a (Big)TIFF header alone, or less: nothing was written
        finally:
            quiet.setLevel(level)
        if empty:
            os.remove(path)


def _position_files(metadata: dict[int, Any], files: list[str]) -> dict[int, Path]:
    """``{position: path}`` of ome-writers' OME-TIFF files: the file whose UUID each position's OME carries."""
    by_name = {Path(f).name: Path(f) for f in files}
    if len(metadata) == 1 and len(files) == 1:  # one position: its file (whose OME names no file)
        return {next(iter(metadata)): Path(files[0])}
    found = {}
    for position, ome in metadata.items():
        for image in ome.images:
            for block in image.pixels.tiff_data_blocks:
                if block.uuid is not None and block.uuid.value == ome.uuid and block.uuid.file_name in by_name:
                    found[position] = by_name[block.uuid.file_name]
    return found


def _drop_missing_references(metadata: dict[Any, Any], kept: set[str]) -> None:
    """Each kept file's OME holds the images of every position's file (ome-writers' companion layout): the images
    stored in files that are not ``kept`` are taken out, so that no reader looks for a removed file."""
    for ome in metadata.values():
        images = []
        for image in ome.images:
            names = {b.uuid.file_name for b in image.pixels.tiff_data_blocks if b.uuid is not None and b.uuid.file_name}
            if names <= kept:
                images.append(image)
        ome.images = images


def _stem(name: str) -> str:
    for suffix in (*TIFF_SUFFIXES, ZARR_SUFFIX):
        if name.lower().endswith(suffix):
            return name[: -len(suffix)]
    return name


def _complete_zarr(metadata: dict[str, Any], out: OmeOutput) -> None:
    """Translation per position (as reported at its first plane), windows from the bit depth, the optics."""
    top = float(2**out.info.bit_depth - 1)
    names = list(out.layout.names)
    for path, attrs in metadata.items():
        ome = attrs.get("ome", {})
        if "multiscales" not in ome:
            continue
        parts = str(path).strip("/").split("/")
        if len(parts) == 3 and parts[0] == "A" and parts[1].isdigit():  # plate well A/<column>/0
            position = int(parts[1]) - 1
        else:
            position = names.index(parts[-1]) if parts[-1] in names else 0
        first = out.reported.first.get(position, (None, None, None))
        multiscale = ome["multiscales"][0]
        axes = [a["name"] for a in multiscale["axes"]]
        shift = {"x": first[0], "y": first[1], "z": first[2]}
        translation = [float(shift.get(a) or 0.0) for a in axes]
        for dataset in multiscale["datasets"]:
            transforms = [t for t in dataset["coordinateTransformations"] if t["type"] != "translation"]
            dataset["coordinateTransformations"] = [*transforms, {"type": "translation", "translation": translation}]
        for channel in ome.get("omero", {}).get("channels", []):
            channel["window"] = {"min": 0.0, "max": top, "start": 0.0, "end": top}
        attrs["scopetwin"] = _optics_attrs(out, first) | {"position": names[position] if names else None}


def _version_plate(store: Path) -> None:
    """The plate's own ``version`` (0.5), which ome-zarr-models looks for beside the ``ome`` version."""
    import json

    from scopetwin.scenes.io import write_json_atomic

    root = store / "zarr.json"
    meta = json.loads(root.read_text())
    plate = meta.get("attributes", {}).get("ome", {}).get("plate")
    if plate is not None and "version" not in plate:
        plate["version"] = meta["attributes"]["ome"].get("version", "0.5")
        write_json_atomic(root, meta)


def _optics_attrs(out: OmeOutput, first: tuple[float | None, ...]) -> dict[str, Any]:
    info = out.info
    return {
        "significant_bits": info.bit_depth,
        "rig": info.rig,
        "camera": info.camera,
        "objective": {"magnification": info.magnification, "numerical_aperture": info.numerical_aperture},
        "stage_um": {"x": first[0], "y": first[1], "z": first[2]},
        "channels": [
            {"name": c.name, "light": c.light, "excitation_nm": c.excitation_nm, "emission_nm": c.emission_nm}
            for c in info.channels
        ],
    }


def _complete_tiff(metadata: dict[int, Any], out: OmeOutput) -> None:
    """SignificantBits, the instrument (objective, detector), exact wavelengths and the channel colours per file."""
    from scopetwin.instrument.ome_xml import complete_image, instrument

    for ome in metadata.values():
        ome.instruments = [instrument(out.info)]
        for image in ome.images:
            complete_image(image, out.info)
