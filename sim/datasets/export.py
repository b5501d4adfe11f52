"""Bulk export of a dataset (``scopetwin dataset export DIR --to zarr | hdf5 OUT``): every sample stacked as named
arrays with named dimensions, so that 10,000 samples open as one array (xarray, dask, h5py, zarr).

Variables (one per image and per map layer, :mod:`scopetwin.sim.datasets.maps`), each with the sample as its first
dimension and one chunk per sample:

* ``image`` (``sample``, ``y``, ``x``) float32 — ``image_<channel>`` for four-channel samples;
* each map layer: ``mask``/``roi`` as uint8 (0/1), ``marker_id`` int32 (-1: none), the rest float32 (NaN where
  undefined); vector layers have a last dimension ``xyz`` (``point``, ``normal``), ``xy`` (``surface_xy``,
  ``pattern_xy``, ``object_xy_<channel>``) or ``ij`` (``marker``);
* each numeric varied quantity of the samples' truth (``parameters``), (``sample``) or (``sample``, ``<name>_dim``);
* coordinates ``sample`` (the sample indices), ``y`` and ``x`` (pixel rows and columns).

Zarr stores (format 3) name the dimensions in each array's ``dimension_names``; HDF5 files attach netCDF-style
dimension scales (``sample``, ``y``, ``x``, ...), which ``xarray.open_dataset(path, engine="h5netcdf")`` reads as
dimensions. Each variable's attributes give its unit and meaning; the root's attributes name the dataset, its kind
and its format. The export is written under a temporary name and moved into place when complete.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence
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


def _layout(sample: Any, names: Sequence[str] | None) -> dict[str, tuple[tuple[int, ...], Any, tuple[str, ...], str]]:
    """Variable -> (per-sample shape, dtype, dimension names, description) from the first sample."""
    from scopetwin.sim.datasets.maps import layer_doc

    out: dict[str, tuple[tuple[int, ...], Any, tuple[str, ...], str]] = {}
    for key, img in sample.images.items():
        out[key] = (img.shape, np.float32, ("sample", "y", "x"), "camera image (linear: irradiance or DN)")
    try:
        maps = sample.maps
    except Exception:  # noqa: BLE001 - a kind without maps (grin): images only
        maps = {}
    for key, arr in maps.items():
        a = _as_exported(key, arr)
        dims = ("sample", "y", "x") + ((_component_dim(key, a.shape[2]),) if a.ndim == 3 else ())
        doc = layer_doc(key) if key in _known_layers() or key.startswith("object_xy_") else None
        text = f"{doc.text} ({doc.unit})" if doc and doc.unit else (doc.text if doc else key)
        out[key] = (a.shape, a.dtype, dims, text)
    if names is not None:
        unknown = [n for n in names if n not in out]
        if unknown:
            raise DatasetError(f"--only: no variable {unknown[0]!r} in these samples (they have {', '.join(out)})")
        out = {k: v for k, v in out.items() if k in names}
    return out


def _known_layers() -> set[str]:
    from scopetwin.sim.datasets.maps import LAYERS

    return set(LAYERS)


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


def export(
    dataset: Any,
    out: str | Path,
    to: Backend,
    names: Sequence[str] | None = None,
    progress: Callable[[int], None] | None = None,
) -> dict[str, Any]:
    """Write every sample of ``dataset`` (:class:`~scopetwin.sim.datasets.reader.Dataset`) to one zarr store or HDF5
    file (module docstring); returns ``{"out", "to", "samples", "variables": {name: shape}}``.

    Raises
    ------
    DatasetError
        No samples, samples of different image sizes, ``out`` already exists, or the backend is not installed.
    """
    out = Path(out)
    if len(dataset) == 0:
        raise DatasetError(f"{dataset.root} has no finished samples to export")
    if out.exists() or out.is_symlink():
        raise DatasetError(f"{out} already exists; choose a new path for the export")
    layout = _layout(dataset[0], names)
    params = _parameters(list(dataset))
    n = len(dataset)
    attrs = {
        "title": f"scopetwin dataset {dataset.root.name}",
        "scopetwin_dataset": str(dataset.root),
        "kind": dataset.kind,
        "dataset_format": dataset.format,
    }
    writer = _write_zarr if to == "zarr" else _write_hdf5
    if to not in ("zarr", "hdf5"):
        raise DatasetError(f"--to must be zarr or hdf5, not {to!r}")
    import shutil
    import tempfile

    # written inside a fresh private folder (0700, made here) beside OUT and renamed into place: no link planted at a
    # predictable temporary name can be written through
    stage = Path(tempfile.mkdtemp(prefix=f".{out.name}.export-", dir=out.parent))
    try:
        tmp = stage / out.name
        writer(tmp, dataset, layout, params, attrs, progress)
        os.replace(tmp, out)
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    variables = {k: [n, *shape] for k, (shape, _, _, _) in layout.items()}
    variables |= {k: list(v.shape) for k, v in params.items()}
    return {"out": str(out), "to": to, "samples": n, "variables": variables}


def _sample_arrays(sample: Any, layout: dict[str, Any]) -> dict[str, NDArray[Any]]:
    arrays = sample.arrays([k for k in layout])
    got = {}
    for key, (shape, dtype, _, _) in layout.items():
        a = _as_exported(key, arrays[key])
        if a.shape != shape:
            raise DatasetError(
                f"sample {sample.index}: {key} is {a.shape}, the first sample's {shape}: samples of different sizes "
                "do not stack into one array"
            )
        got[key] = a.astype(dtype, copy=False)
    return got


def _write_zarr(
    path: Path,
    dataset: Any,
    layout: dict[str, Any],
    params: dict[str, NDArray[np.float64]],
    attrs: dict[str, Any],
    progress: Callable[[int], None] | None,
) -> None:
    try:
        import zarr
    except ImportError:
        raise DatasetError("--to zarr needs the zarr package (pip install zarr)") from None
    n = len(dataset)
    root = zarr.open_group(str(path), mode="w", zarr_format=3)
    root.attrs.update(attrs)
    arrays = {}
    for key, (shape, dtype, dims, text) in layout.items():
        arr = root.create_array(key, shape=(n, *shape), chunks=(1, *shape), dtype=dtype, dimension_names=list(dims))
        arr.attrs["description"] = text
        arrays[key] = arr
    first = dataset[0].images[next(iter(dataset[0].images))].shape
    root.create_array("sample", data=np.asarray(dataset.indices, dtype=np.int64), dimension_names=["sample"])
    for axis, count in (("y", first[0]), ("x", first[1])):
        root.create_array(axis, data=np.arange(count, dtype=np.int32), dimension_names=[axis])
    for name, values in params.items():
        dims = ["sample"] if values.ndim == 1 else ["sample", f"{name}_dim"]
        p = root.create_array(name, data=values, dimension_names=dims)
        p.attrs["description"] = f"varied quantity ({DOMAINS[name].unit})" if DOMAINS[name].unit else "varied"
    for k, sample in enumerate(dataset):
        for key, a in _sample_arrays(sample, layout).items():
            arrays[key][k] = a
        if progress is not None:
            progress(1)
    import warnings

    with warnings.catch_warnings():  # zarr warns that consolidated metadata is not yet in the zarr 3 specification
        warnings.simplefilter("ignore")
        zarr.consolidate_metadata(str(path))  # one read opens the whole store (xarray.open_zarr)


def _write_hdf5(
    path: Path,
    dataset: Any,
    layout: dict[str, Any],
    params: dict[str, NDArray[np.float64]],
    attrs: dict[str, Any],
    progress: Callable[[int], None] | None,
) -> None:
    try:
        import h5py
    except ImportError:
        raise DatasetError("--to hdf5 needs the h5py package (pip install h5py)") from None
    n = len(dataset)
    first = dataset[0].images[next(iter(dataset[0].images))].shape
    with h5py.File(path, "w") as f:
        f.attrs.update({k: str(v) if not isinstance(v, int) else v for k, v in attrs.items()})
        scales = {
            "sample": np.asarray(dataset.indices, dtype=np.int64),
            "y": np.arange(first[0], dtype=np.int32),
            "x": np.arange(first[1], dtype=np.int32),
        }
        for shape, _, dims, _ in layout.values():
            for d, size in zip(dims[3:], shape[2:], strict=True):
                scales.setdefault(d, np.arange(size, dtype=np.int32))
        for name, values in params.items():
            if values.ndim == 2:
                scales.setdefault(f"{name}_dim", np.arange(values.shape[1], dtype=np.int32))
        for name, values in scales.items():
            f.create_dataset(name, data=values).make_scale(name)
        datasets = {}
        for key, (shape, dtype, dims, text) in layout.items():
            ds = f.create_dataset(
                key, shape=(n, *shape), chunks=(1, *shape), dtype=dtype, compression="gzip", compression_opts=1
            )
            ds.attrs["description"] = text
            for axis, d in enumerate(dims):
                ds.dims[axis].attach_scale(f[d])
            datasets[key] = ds
        for name, values in params.items():
            ds = f.create_dataset(name, data=values)
            for axis, d in enumerate(["sample"] if values.ndim == 1 else ["sample", f"{name}_dim"]):
                ds.dims[axis].attach_scale(f[d])
            ds.attrs["description"] = f"varied quantity ({DOMAINS[name].unit})" if DOMAINS[name].unit else "varied"
        for k, sample in enumerate(dataset):
            for key, a in _sample_arrays(sample, layout).items():
                datasets[key][k] = a
            if progress is not None:
                progress(1)


def to_json(result: dict[str, Any]) -> str:
    """The export summary as JSON text."""
    return json.dumps(result)
