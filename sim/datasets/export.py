"""Bulk export of a dataset (``scopetwin dataset export DIR --to zarr | hdf5 OUT``): every sample stacked as named
arrays with named dimensions, so that 10,000 samples open as one array (xarray, dask, h5py, zarr).

Variables (one per image and per map layer, :mod:`scopetwin.sim.datasets.maps`), each with the sample as its first
dimension and one chunk per sample:

* ``image`` (``sample``, ``y``, ``x``) float32 — ``image_<channel>`` for four-channel samples;
* each map layer: ``mask``/``roi`` as uint8 (0/1), ``marker_id`` int32 (-1: none), the rest float32 (NaN where
  undefined); vector layers have a last dimension ``xyz`` (``point``, ``normal``), ``xy`` (``surface_xy``,
  ``pattern_xy``, ``object_xy_<channel>``) or ``ij`` (``marker``);
* each numeric varied quantity of the samples' truth (``parameters``), (``sample``) or (``sample``, ``<name>_dim``);
* the camera of Part I samples in OpenCV's convention (:class:`scopetwin.scenes.opencv_camera.OpenCVCamera`),
  float64: ``K`` (``sample``, ``cam_row``, ``cam_col``) px, ``dist`` (``sample``, ``dist_coef``: k1, k2, p1, p2,
  k3), ``R`` (``sample``, ``cam_row``, ``cam_col``) world -> camera, ``t`` (``sample``, ``xyz``) mm;
* the marker truth of Part I samples (``truth.json``'s ``markers``; row k is ``marker_id`` k of the maps):
  ``marker_ij`` int32 (``sample``, ``markers``, ``ij``), ``marker_px`` float64 (``sample``, ``markers``, ``xy``)
  the exact image of each marker centre (col, row) in the thesis's pixel convention (centres at +0.5), and
  ``marker_visible`` uint8 (``sample``, ``markers``); samples with fewer markers than the most are padded with
  ``marker_ij`` -1, ``marker_px`` NaN, ``marker_visible`` 0;
* coordinates ``sample`` (the sample indices), ``y`` and ``x`` (pixel rows and columns), and an index per other
  dimension.

Zarr stores (format 3) name the dimensions in each array's ``dimension_names``; HDF5 files attach netCDF-style
dimension scales (``sample``, ``y``, ``x``, ...), which ``xarray.open_dataset(path, engine="h5netcdf")`` reads as
dimensions. Each variable's attributes give its meaning (``description``) and, where it has a physical unit, a
CF-style ``units`` (``mm``, ``um``, ``nm``, ``rad``, ``degree``, ``s``, ``px``; ``1`` for dimensionless
quantities; none for flags and indices); the root's attributes name the dataset, its kind and its format. Everything
is checked (samples, target, backend, ``--only``, the names: :func:`check_names`) before the first sample is written;
the export is written under a temporary name and moved into place when complete.
"""

from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from scopetwin.sim.datasets.config import DOMAINS, DatasetError

Backend = Literal["zarr", "hdf5"]
_COMPONENT_DIMS = {3: "xyz", 2: "xy"}


def _component_dim(name: str, k: int) -> str:
    return "ij" if name == "marker" else _COMPONENT_DIMS.get(k, f"{name}_dim")


def _as_exported(name: str, arr: NDArray[Any]) -> NDArray[Any]:
    if arr.dtype == bool:
        return arr.astype(np.uint8)
    return arr


#: CF ``units`` of the units the varied quantities' domains name (``""``: dimensionless).
_CF_UNITS = {"": "1", "µm": "um", "deg": "degree", "1/mm": "mm-1"}
#: Map layers that are dimensionless quantities (``units = "1"``); the other unitless layers are flags or indices.
_DIMENSIONLESS_LAYERS = ("normal",)


def cf_units(unit: str) -> str:
    """The CF (UDUNITS) spelling of a unit as the project writes it: ``µm`` -> ``um``, ``deg`` -> ``degree``."""
    return _CF_UNITS.get(unit, unit)


@dataclass(frozen=True)
class Variable:
    """One exported per-sample variable: its shape per sample, dtype, dimension names, meaning and CF units."""

    shape: tuple[int, ...]
    dtype: Any
    dims: tuple[str, ...]
    description: str
    units: str | None = None

    def attrs(self) -> dict[str, str]:
        """The variable's attributes: ``description`` and, where it has one, ``units``."""
        return {"description": self.description} | ({"units": self.units} if self.units else {})


#: The camera's variables (OpenCV's convention): per-sample shape, dimensions, units, meaning.
_CAMERA: dict[str, tuple[tuple[int, ...], tuple[str, ...], str, str]] = {
    "K": ((3, 3), ("sample", "cam_row", "cam_col"), "px", "camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]"),
    "dist": ((5,), ("sample", "dist_coef"), "1", "distortion coefficients k1, k2, p1, p2, k3 (OpenCV's order)"),
    "R": ((3, 3), ("sample", "cam_row", "cam_col"), "1", "rotation world -> camera (X_cam = R P + t)"),
    "t": ((3,), ("sample", "xyz"), "mm", "translation world -> camera (X_cam = R P + t)"),
}
#: The marker truth's variables: dtype, dimensions, units, meaning (per-sample shape: the marker count first).
_MARKERS: dict[str, tuple[Any, tuple[str, ...], str | None, str]] = {
    "marker_ij": (np.int32, ("sample", "markers", "ij"), None, "marker index (i, j); -1: padding"),
    "marker_px": (
        np.float64,
        ("sample", "markers", "xy"),
        "px",
        "exact image of the marker centre (col, row), pixel centres at +0.5 (OpenCV: minus 0.5); NaN: none",
    ),
    "marker_visible": (np.uint8, ("sample", "markers"), None, "the whole marker is imaged in the picture: 1, else 0"),
}


def _layout(sample: Any) -> dict[str, Variable]:
    """The image and map variables of the samples, from the first sample."""
    from scopetwin.sim.datasets.maps import layer_doc

    out: dict[str, Variable] = {}
    for key, img in sample.images.items():
        out[key] = Variable(img.shape, np.float32, ("sample", "y", "x"), "camera image (linear: irradiance or DN)")
    try:
        maps = sample.maps
    except Exception:  # noqa: BLE001 - a kind without maps (grin): images only
        maps = {}
    for key, arr in maps.items():
        a = _as_exported(key, arr)
        dims = ("sample", "y", "x") + ((_component_dim(key, a.shape[2]),) if a.ndim == 3 else ())
        doc = layer_doc(key) if key in _known_layers() or key.startswith("object_xy_") else None
        text = f"{doc.text} ({doc.unit})" if doc and doc.unit else (doc.text if doc else key)
        units = doc.unit if doc and doc.unit else ("1" if key in _DIMENSIONLESS_LAYERS else None)
        out[key] = Variable(a.shape, a.dtype, dims, text, units)
    return out


def _truth_arrays(samples: Sequence[Any]) -> tuple[dict[str, Variable], dict[str, NDArray[Any]]]:
    """The camera and marker truth of every sample (Part I kinds) as stacked arrays, with their variables."""
    first = samples[0]
    if first.kind not in ("deflectometry", "calibration"):
        return {}, {}
    variables: dict[str, Variable] = {}
    values: dict[str, NDArray[Any]] = {}
    cameras = [s.camera for s in samples]
    for name, (shape, dims, unit, text) in _CAMERA.items():
        values[name] = np.stack([np.asarray(getattr(c, name), dtype=np.float64).reshape(shape) for c in cameras])
        variables[name] = Variable(shape, np.float64, dims, text, unit)
    if "markers" not in first.truth:
        return variables, values
    tables = [s.truth.markers for s in samples]
    n = max(len(t.ij) for t in tables)
    ij = np.full((len(tables), n, 2), -1, dtype=np.int32)
    px = np.full((len(tables), n, 2), np.nan, dtype=np.float64)
    visible = np.zeros((len(tables), n), dtype=np.uint8)
    for k, t in enumerate(tables):
        ij[k, : len(t.ij)], px[k, : len(t.ij)], visible[k, : len(t.ij)] = t.ij, t.center_px, t.visible
    for name, arr in (("marker_ij", ij), ("marker_px", px), ("marker_visible", visible)):
        dtype, marker_dims, marker_unit, marker_text = _MARKERS[name]
        values[name] = arr
        variables[name] = Variable(arr.shape[1:], dtype, marker_dims, marker_text, marker_unit)
    return variables, values


def _known_layers() -> set[str]:
    from scopetwin.sim.datasets.maps import LAYERS

    return set(LAYERS)


def _parameter_variables(params: dict[str, NDArray[np.float64]]) -> dict[str, Variable]:
    """The variables of the numeric varied quantities: unit and meaning from their domains."""
    out = {}
    for name, values in params.items():
        dom = DOMAINS[name]
        dims = ("sample",) if values.ndim == 1 else ("sample", f"{name}_dim")
        text = f"varied quantity: {dom.text}" + (f" ({dom.unit})" if dom.unit else "")
        out[name] = Variable(values.shape[1:], np.float64, dims, text, cf_units(dom.unit))
    return out


def _parameters(samples: Sequence[Any]) -> dict[str, NDArray[np.float64]]:
    """The numeric varied quantities of every sample (scalars and fixed-length vectors; per-member ones left out)."""
    rows = [s.truth.get("parameters", {}) for s in samples]
    out: dict[str, NDArray[np.float64]] = {}
    for name in rows[0] if rows else {}:
        dom = DOMAINS.get(name)
        if dom is None or dom.names_any() or dom.per:
            continue
        try:
            out[name] = np.asarray([r[name] for r in rows], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            continue
    return out


def node_name_problem(name: str) -> str | None:
    """Why ``name`` cannot name an array of a Zarr store and of an HDF5 file, or None.

    Both formats read a name as a path: a ``/`` hides the array in a group, ``.`` and ``..`` are path steps; a NUL
    ends the name in HDF5 (``image_\\0x`` would be written as ``image_``), Zarr reserves names that begin with ``__``,
    and neither takes a control character or text that is not Unicode (a file name in another encoding). The names
    come from the samples (image files, map layers, channels), which may be someone else's.
    """
    if not name:
        return "is empty"
    bad = sorted({c for c in name if not c.isprintable()})
    if bad:
        return f"holds the character(s) {', '.join(repr(c) for c in bad)}"
    if "/" in name:
        return "holds a '/' (a path separator in Zarr and HDF5)"
    if name in (".", ".."):
        return "is a path step"
    if name.startswith("__"):
        return "begins with '__' (reserved by Zarr)"
    return None


def check_names(variables: dict[str, Variable], first: int) -> None:
    """Refuse variable and dimension names that Zarr or HDF5 cannot take (:func:`node_name_problem`) or that two
    arrays would share (a variable named like a dimension, whose coordinate is an array of that name).

    Raises
    ------
    DatasetError
        One line naming the first such name (of sample ``first``, whose layout the export follows).
    """
    dims = {d for var in variables.values() for d in var.dims}
    for what, name in [*(("variable", n) for n in variables), *(("dimension", d) for d in sorted(dims))]:
        problem = node_name_problem(name)
        if problem is not None:
            raise DatasetError(
                f"sample {first}: {what} {name!r} {problem}: a Zarr or HDF5 array cannot be called that"
                + ("; leave it out with --only" if what == "variable" else "")
            )
    shared = sorted(dims.intersection(variables))
    if shared:
        raise DatasetError(
            f"sample {first}: variable {shared[0]!r} has the name of a dimension (its coordinate array); "
            "leave it out with --only"
        )


def _text(value: str) -> str:
    """``value`` as Unicode text for an attribute (a folder name in another encoding: its bytes as ``\\x..``)."""
    return value.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace")


@dataclass(frozen=True)
class ExportPlan:
    """An export checked and laid out, nothing written yet (:func:`plan_export`); :func:`write_export` writes it.

    Attributes
    ----------
    dataset : Dataset
        The samples to export.
    out : Path
        The target (does not exist yet).
    to : {"zarr", "hdf5"}
        The backend.
    per_sample : dict
        The image and map variables, read from each sample while writing.
    stacked : dict
        The variables known before writing (varied quantities, camera, marker truth): name -> :class:`Variable`.
    values : dict
        Their values, (samples, ...) arrays.
    attrs : dict
        The root's attributes.
    """

    dataset: Any
    out: Path
    to: Backend
    per_sample: dict[str, Variable]
    stacked: dict[str, Variable]
    values: dict[str, NDArray[Any]]
    attrs: dict[str, Any]

    def dimensions(self) -> dict[str, int]:
        """Every dimension's size, the sample's first."""
        sizes: dict[str, int] = {"sample": len(self.dataset)}
        for var in (*self.per_sample.values(), *self.stacked.values()):
            for d, size in zip(var.dims[1:], var.shape, strict=True):
                sizes.setdefault(d, size)
        return sizes


def check_target(dataset: Any, out: str | Path, to: str) -> Path:
    """Refuse an export before any work: no samples, an ``out`` that exists, an unknown or uninstalled backend."""
    out = Path(out)
    if to not in ("zarr", "hdf5"):
        raise DatasetError(f"--to must be zarr or hdf5, not {to!r}")
    if len(dataset) == 0:
        raise DatasetError(f"{dataset.root} has no finished samples to export")
    if out.exists() or out.is_symlink():
        raise DatasetError(f"{out} already exists; choose a new path for the export")
    package = "zarr" if to == "zarr" else "h5py"
    try:
        __import__(package)
    except ImportError:
        raise DatasetError(f"--to {to} needs the {package} package (pip install {package})") from None
    return out


def plan_export(dataset: Any, out: str | Path, to: Backend, names: Sequence[str] | None = None) -> ExportPlan:
    """Check an export and lay out its variables (module docstring), reading every sample's truth but no image.

    Raises
    ------
    DatasetError
        No samples, ``out`` already exists, the backend is unknown or not installed, ``names`` names a variable
        the samples do not have, or a variable's name cannot name an array (:func:`check_names`).
    """
    target = check_target(dataset, out, to)
    samples = list(dataset)
    per_sample = _layout(samples[0])
    params = _parameters(samples)
    truth_vars, truth_values = _truth_arrays(samples)
    stacked = _parameter_variables(params) | truth_vars
    values: dict[str, NDArray[Any]] = {**params, **truth_values}
    if names is not None:
        have = [*per_sample, *stacked]
        unknown = [n for n in names if n not in have]
        if unknown:
            raise DatasetError(f"--only: no variable {unknown[0]!r} in these samples (they have {', '.join(have)})")
        per_sample = {k: v for k, v in per_sample.items() if k in names}
        stacked = {k: v for k, v in stacked.items() if k in names}
        values = {k: v for k, v in values.items() if k in stacked}
    if set(per_sample) & set(stacked):
        twice = sorted(set(per_sample) & set(stacked))[0]
        raise DatasetError(f"sample {samples[0].index}: two variables are called {twice!r}; leave one out with --only")
    check_names(per_sample | stacked, samples[0].index)
    attrs = {
        "title": _text(f"scopetwin dataset {dataset.root.name}"),
        "scopetwin_dataset": _text(str(dataset.root)),
        "kind": _text(str(dataset.kind)),
        "dataset_format": dataset.format,
    }
    return ExportPlan(dataset, target, to, per_sample, stacked, values, attrs)


def write_export(plan: ExportPlan, progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Write a planned export (:func:`plan_export`), calling ``progress(1)`` after each sample; returns ``{"out",
    "to", "samples", "variables": {name: shape}}``."""
    import shutil
    import tempfile

    out, n = plan.out, len(plan.dataset)
    writer = _write_zarr if plan.to == "zarr" else _write_hdf5
    # written inside a fresh private folder (0700, made here) beside OUT and renamed into place: no link planted at a
    # predictable temporary name can be written through
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.export-", dir=out.parent))
    try:
        tmp = stage / out.name
        writer(tmp, plan, progress)
        _move_into_place(tmp, out)
    finally:
        shutil.rmtree(stage, ignore_errors=True)  # the stage only: never OUT, which may be someone else's
    variables = {k: [n, *v.shape] for k, v in (plan.per_sample | plan.stacked).items()}
    return {"out": str(out), "to": plan.to, "samples": n, "variables": variables}


def _move_into_place(tmp: Path, out: Path) -> None:
    """Move the finished export ``tmp`` to ``out`` only if nothing is at ``out``: a file by a hard link (which fails
    if ``out`` exists), a folder (a Zarr store) by renaming it over an empty folder made here with ``mkdir``
    (which fails if ``out`` exists). A target that another process created meanwhile is never replaced, and
    nothing it put there is removed.

    Raises
    ------
    DatasetError
        ``out`` appeared while the export ran.
    """
    appeared = DatasetError(f"{out} appeared while the export ran; it was left as it is and the export not written")
    if tmp.is_dir():
        try:
            os.mkdir(out, 0o700)
        except FileExistsError:
            raise appeared from None
        try:
            os.replace(tmp, out)  # over the empty folder made above
        except OSError:
            with contextlib.suppress(OSError):
                os.rmdir(out)  # only if still empty: a file someone put there stays
            raise appeared from None
        return
    try:
        os.link(tmp, out)
    except FileExistsError:
        raise appeared from None
    except OSError:  # a file system without hard links: claim the name first
        try:
            os.close(os.open(out, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o600))
        except FileExistsError:
            raise appeared from None
        os.replace(tmp, out)


def export(
    dataset: Any,
    out: str | Path,
    to: Backend,
    names: Sequence[str] | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Write every sample of ``dataset`` (:class:`~scopetwin.sim.datasets.reader.Dataset`) to one zarr store or HDF5
    file (module docstring): :func:`plan_export` then :func:`write_export`; returns ``{"out", "to", "samples",
    "variables": {name: shape}}``.

    Raises
    ------
    DatasetError
        No samples, samples of different image sizes, ``out`` already exists, or the backend is not installed.
    """
    return write_export(plan_export(dataset, out, to, names), progress)


def _sample_arrays(sample: Any, layout: dict[str, Variable]) -> dict[str, NDArray[Any]]:
    arrays = sample.arrays(list(layout))
    got = {}
    for key, var in layout.items():
        a = _as_exported(key, arrays[key])
        if a.shape != var.shape:
            raise DatasetError(
                f"sample {sample.index}: {key} is {a.shape}, the first sample's {var.shape}: samples of different "
                "sizes do not stack into one array"
            )
        got[key] = a.astype(var.dtype, copy=False)
    return got


def _coordinates(plan: ExportPlan) -> dict[str, tuple[NDArray[Any], dict[str, str]]]:
    """The coordinate of each dimension: the sample indices, pixel rows and columns, else 0..n-1."""
    coords: dict[str, tuple[NDArray[Any], dict[str, str]]] = {}
    for d, size in plan.dimensions().items():
        if d == "sample":
            coords[d] = (np.asarray(plan.dataset.indices, dtype=np.int64), {"description": "sample index"})
        elif d in ("y", "x"):
            text = "pixel row" if d == "y" else "pixel column"
            coords[d] = (
                np.arange(size, dtype=np.int32),
                {"description": f"{text} (OpenCV: its centre)", "units": "px"},
            )
        else:
            coords[d] = (np.arange(size, dtype=np.int32), {"description": f"component of {d}"})
    return coords


def _write_zarr(path: Path, plan: ExportPlan, progress: Callable[[int], None] | None) -> None:
    import zarr

    n = len(plan.dataset)
    root = zarr.open_group(str(path), mode="w", zarr_format=3)
    root.attrs.update(plan.attrs)
    arrays = {}
    for key, var in plan.per_sample.items():
        shape = (n, *var.shape)
        arr = root.create_array(
            key, shape=shape, chunks=(1, *var.shape), dtype=var.dtype, dimension_names=list(var.dims)
        )
        arr.attrs.update(var.attrs())
        arrays[key] = arr
    for name, (values, attrs) in _coordinates(plan).items():
        root.create_array(name, data=values, dimension_names=[name]).attrs.update(attrs)
    for name, var in plan.stacked.items():
        data = plan.values[name].astype(var.dtype, copy=False)
        root.create_array(name, data=data, dimension_names=list(var.dims)).attrs.update(var.attrs())
    for k, sample in enumerate(plan.dataset):
        for key, a in _sample_arrays(sample, plan.per_sample).items():
            arrays[key][k] = a
        if progress is not None:
            progress(1)
    import warnings

    with warnings.catch_warnings():  # zarr warns that consolidated metadata is not yet in the zarr 3 specification
        warnings.simplefilter("ignore")
        zarr.consolidate_metadata(str(path))  # one read opens the whole store (xarray.open_zarr)


def _write_hdf5(path: Path, plan: ExportPlan, progress: Callable[[int], None] | None) -> None:
    import h5py

    n = len(plan.dataset)
    with h5py.File(path, "w") as f:
        f.attrs.update({k: str(v) if not isinstance(v, int) else v for k, v in plan.attrs.items()})
        for name, (values, attrs) in _coordinates(plan).items():
            scale = f.create_dataset(name, data=values)
            scale.make_scale(name)
            scale.attrs.update(attrs)
        datasets = {}
        for key, var in plan.per_sample.items():
            ds = f.create_dataset(
                key,
                shape=(n, *var.shape),
                chunks=(1, *var.shape),
                dtype=var.dtype,
                compression="gzip",
                compression_opts=1,
            )
            datasets[key] = ds
        for name, var in plan.stacked.items():
            datasets[name] = f.create_dataset(name, data=plan.values[name].astype(var.dtype, copy=False))
        for key, var in (plan.per_sample | plan.stacked).items():
            datasets[key].attrs.update(var.attrs())
            for axis, d in enumerate(var.dims):
                datasets[key].dims[axis].attach_scale(f[d])
        for k, sample in enumerate(plan.dataset):
            for key, a in _sample_arrays(sample, plan.per_sample).items():
                datasets[key][k] = a
            if progress is not None:
                progress(1)


def to_json(result: dict[str, Any]) -> str:
    """The export summary as JSON text."""
    return json.dumps(result)
