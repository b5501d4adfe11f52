"""The OME-XML parts :mod:`scopetwin.instrument.ome` adds to what ome-writers writes, and the whole OME-XML of a
single multi-series OME-TIFF (ome-types' model). ``info`` is an :class:`~scopetwin.instrument.ome.AcquisitionInfo`,
``out`` an :class:`~scopetwin.instrument.ome.OmeOutput` (typed ``Any`` here: this module is imported by that one).

Every name the XML carries (the output file's name, position names from the plan, channel presets, the camera) is
written by ome-types, which escapes quotes, ``<``, ``&`` and line breaks, so such a name reads back as it was.
What XML 1.0 cannot hold at all (and, in OME-Zarr's JSON, text that is not Unicode) is refused before the first
file is opened (:func:`check_names`).
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

from scopetwin.instrument.errors import RigError

INSTRUMENT_ID = "Instrument:0"
OBJECTIVE_ID = "Objective:0"
DETECTOR_ID = "Detector:0"
#: OME's order of the non-plane axes of a plane index.
ORDER = "zct"


def _xml_char(c: str) -> bool:
    """Whether XML 1.0 can hold ``c`` (its production ``Char``)."""
    o = ord(c)
    return o in (0x9, 0xA, 0xD) or 0x20 <= o <= 0xD7FF or 0xE000 <= o <= 0xFFFD or o >= 0x10000


def xml_text_problem(value: str) -> str | None:
    """Why ``value`` cannot be text in an XML document (an OME-XML attribute), or None.

    XML 1.0 has no way to write a NUL or another control character other than tab, line feed and carriage return
    (not even escaped), nor U+FFFE, U+FFFF or a lone surrogate (the form Python gives a file name in another
    encoding than UTF-8). Quotes, ``<``, ``&`` and line breaks are no problem: they are escaped.
    """
    bad = sorted({c for c in value if not _xml_char(c)})
    if bad:
        return f"holds the character(s) {', '.join(repr(c) for c in bad)}, which XML cannot hold"
    return None


def json_text_problem(value: str) -> str | None:
    """Why ``value`` cannot be a string of OME-Zarr's JSON (UTF-8), or None: only a lone surrogate (text that is
    not Unicode, such as a file name in another encoding); every other character is escaped."""
    bad = sorted({c for c in value if "\ud800" <= c <= "\udfff"})
    if bad:
        return f"holds the character(s) {', '.join(repr(c) for c in bad)}, which is not Unicode text"
    return None


def ome_names(path: str | Path, layout: Any, info: Any, kind: str = "tiff") -> Iterable[tuple[str, str]]:
    """``(what, name)`` of every name an OME file of ``kind`` (``"tiff"``, ``"zarr"``) for ``layout`` and ``info`` at
    ``path`` writes into its metadata."""
    if kind == "tiff":
        yield "output file name", Path(path).name
    yield from (("position", name) for name in layout.names)
    yield from (("channel", channel.name) for channel in info.channels)
    yield "camera", info.camera
    if kind == "zarr":  # the attribute ``scopetwin`` names the rig and the lights too
        yield "rig", info.rig
        yield from (("light", channel.light) for channel in info.channels if channel.light is not None)


def check_names(path: str | Path, layout: Any, info: Any, kind: str = "tiff") -> None:
    """Refuse an OME file whose metadata could not hold one of its names: for OME-TIFF what XML cannot hold
    (:func:`xml_text_problem`), for OME-Zarr what JSON cannot (:func:`json_text_problem`).

    Raises
    ------
    RigError
        One line naming the first such name, where it comes from and why; nothing is written.
    """
    problem_of, label = (xml_text_problem, "an OME-TIFF") if kind == "tiff" else (json_text_problem, "an OME-Zarr")
    for what, name in ome_names(path, layout, info, kind):
        problem = problem_of(name)
        if problem is not None:
            hint = "rename it, or write .ome.zarr" if kind == "tiff" else "rename it"
            raise RigError(f"{what} {name!r} {problem}: {label} cannot carry it; {hint}")


def instrument(info: Any) -> Any:
    """The OME ``Instrument``: the objective (magnification, NA) and the camera as detector."""
    from ome_types import model

    objective = model.Objective(
        id=OBJECTIVE_ID, nominal_magnification=info.magnification, lens_na=info.numerical_aperture
    )
    detector = model.Detector(id=DETECTOR_ID, model=info.camera or None, type="CCD")
    return model.Instrument(id=INSTRUMENT_ID, objectives=[objective], detectors=[detector])


def complete_image(image: Any, info: Any) -> None:
    """Bit depth, instrument references, the planes' position units, channel colours and exact wavelengths of one
    OME ``Image``."""
    from ome_types import model

    image.instrument_ref = model.InstrumentRef(id=INSTRUMENT_ID)
    image.objective_settings = model.ObjectiveSettings(id=OBJECTIVE_ID)
    image.pixels.significant_bits = info.bit_depth
    for plane in image.pixels.planes:  # stage and focus positions in µm (OME's default unit is the reference frame)
        plane.position_x_unit = plane.position_y_unit = plane.position_z_unit = model.UnitsLength.MICROMETER
    by_name = {c.name: c for c in info.channels}
    for channel in image.pixels.channels:
        known = by_name.get(channel.name or "")
        channel.detector_settings = model.DetectorSettings(id=DETECTOR_ID)
        if known is None:
            continue
        channel.color = model.Color(f"#{known.color}")
        channel.excitation_wavelength = known.excitation_nm
        channel.emission_wavelength = known.emission_nm


def _pixels(out: Any, piece: Any, number: int, ifds: list[int], file: tuple[str, str] | None = None) -> Any:
    """The ``Pixels`` of one piece (:class:`~scopetwin.instrument.ome_pieces.Piece`): its sizes and channels, its
    planes as reported, a ``TiffData`` per plane (page ``ifds[k]`` of the file, named with its UUID in ``file``)."""
    from ome_types import model

    info = out.info
    rows, cols = info.shape
    first_c = piece.at("c")
    held = info.channels[first_c : first_c + piece.size("c")] if "c" in piece.axes else info.channels
    channels = [model.Channel(id=f"Channel:{number}:{k}", name=c.name) for k, c in enumerate(held)]
    if not channels:
        channels = [model.Channel(id=f"Channel:{number}:0")]
    reference = None if file is None else model.TiffData.UUID(file_name=file[0], value=file[1])
    planes, tiff_data = [], []
    for n, ifd in zip(piece.planes, ifds, strict=True):
        _position, index, meta = out.reported.planes[n]
        at = piece.relative(index)
        z, c, t = (at[axis] for axis in ORDER)
        planes.append(
            model.Plane(
                the_z=z,
                the_c=c,
                the_t=t,
                exposure_time=meta.get("exposure_time"),
                delta_t=meta.get("delta_t"),
                position_x=meta.get("position_x"),
                position_y=meta.get("position_y"),
                position_z=meta.get("position_z"),
                position_x_unit="µm",
                position_y_unit="µm",
                position_z_unit="µm",
            )
        )
        tiff_data.append(model.TiffData(ifd=ifd, first_z=z, first_c=c, first_t=t, plane_count=1, uuid=reference))
    return model.Pixels(
        id=f"Pixels:{number}",
        dimension_order="XYZCT",
        type=info.dtype,
        size_x=cols,
        size_y=rows,
        size_z=piece.size("z"),
        size_c=max(1, len(channels)),
        size_t=piece.size("t"),
        physical_size_x=info.pixel_size_um,
        physical_size_y=info.pixel_size_um,
        physical_size_z=out.layout.z_step_um or None,
        channels=channels,
        planes=planes,
        tiff_data_blocks=tiff_data,
    )


def _image(out: Any, piece: Any, number: int, ifds: list[int], file: tuple[str, str] | None = None) -> Any:
    """The OME ``Image`` of one piece: named after its position (else the output file), an extra piece with its
    :attr:`~scopetwin.instrument.ome_pieces.Piece.label` after the name."""
    from ome_types import model

    name = out.layout.names[piece.position] if out.layout.names else out.path.name
    if not piece.main:
        name = f"{name} {piece.label}"
    pixels = _pixels(out, piece, number, ifds, file)
    image = model.Image(id=f"Image:{number}", name=name, pixels=pixels)
    complete_image(image, out.info)
    return image


def single_file_ome(out: Any, pieces: dict[int, list[Any]]) -> Any:
    """The OME-XML of a single multi-series OME-TIFF: each position's ``pieces`` (one ``Image`` for a complete
    position; :func:`scopetwin.instrument.ome_pieces.pieces`), their planes in file order."""
    from ome_types import model

    images: list[Any] = []
    for found in pieces.values():
        for piece in found:
            images.append(_image(out, piece, len(images), list(piece.planes)))
    return model.OME(instruments=[instrument(out.info)], images=images, creator="scopetwin (tifffile)")


def position_file_ome(out: Any, found: list[Any], file: tuple[str, str]) -> Any:
    """The OME-XML of the OME-TIFF file of one position (``file``: its name and UUID) holding ``found``, that
    position's pieces: each plane named by the file and its page there (a file of its own, as tifffile reads
    pages of another file of a multi-file OME through the file it opened)."""
    from ome_types import model

    position = found[0].position
    numbers = [n for n, (p, _index, _meta) in enumerate(out.reported.planes) if p == position]
    page = {n: k for k, n in enumerate(numbers)}
    images = [_image(out, piece, k, [page[n] for n in piece.planes], file) for k, piece in enumerate(found)]
    return model.OME(
        uuid=file[1], instruments=[instrument(out.info)], images=images, creator="scopetwin (ome-writers, tifffile)"
    )
