"""The particle table on disk: CSV and NeXus-style HDF5, each written atomically.

A table is a mapping of column name to array (:data:`COLUMNS`, plus ``frame`` for a batch).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import TYPE_CHECKING, Iterable, Mapping

import numpy as np

from .atomic_write import atomic_path
from analysis.errors import ParameterError

if TYPE_CHECKING:
    from analysis.pipeline.result import Result

#: Columns of the particle table, in this order.
COLUMNS: tuple[str, ...] = ("particle", "x", "y", "alpha", "X", "Y", "Z", "brightness",
                            "peak_height", "peak_width", "residual", "prominence", "alpha_std", "intensity")
#: Units of the columns that have them (NeXus `units` attributes).
UNITS = {"x": "pixel", "y": "pixel", "X": "mm", "Y": "mm", "Z": "mm", "alpha": "1", "peak_width": "1"}


def combine(results: Iterable[Result]) -> dict[str, np.ndarray]:
    """One particle table for a batch, with a ``frame`` column (index of the exposure)."""
    parts = [dict(r.particles, frame=np.full(len(r), i, dtype=np.int64)) for i, r in enumerate(results)]
    names = ("frame",) + COLUMNS
    if not parts:
        return {name: np.empty(0) for name in names}
    return {name: np.concatenate([p[name] for p in parts]) for name in names}


def write_csv(columns: Mapping[str, np.ndarray], path: str | Path) -> Path:
    """Write columns as CSV: a header row, then one row per particle (floats with full precision)."""
    path = Path(path)
    names = list(columns)
    arrays = [np.asarray(columns[n]) for n in names]
    with atomic_path(path) as tmp, open(tmp, "w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(names)
        for row in zip(*[a.tolist() for a in arrays]):
            writer.writerow(["" if isinstance(v, float) and math.isnan(v) else repr(v) if isinstance(v, float)
                             else v for v in row])
    return path


def read_csv(path: str | Path) -> dict[str, np.ndarray]:
    """Read a particle table written by :func:`write_csv` (empty cells become NaN)."""
    with open(path, newline="") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise ParameterError(f"{path} is empty; expected a particle table with a header row")
    names, body = rows[0], rows[1:]
    out: dict[str, np.ndarray] = {}
    for k, name in enumerate(names):
        values = [r[k] for r in body]
        if name in ("particle", "frame"):
            out[name] = np.array([int(v) for v in values], dtype=np.int64)
        else:
            out[name] = np.array([float(v) if v != "" else math.nan for v in values], dtype=np.float64)
    return out


def write_hdf5(results: list[Result], path: str | Path) -> Path:
    """NeXus-style HDF5 of one result or a batch (then with a ``frame`` column).

    Layout: ``/entry`` (NXentry) with ``/entry/data`` (NXdata: one dataset per column, ``signal``
    ``Z``), ``/entry/process`` (NXprocess: ``program``, ``parameters`` as JSON and each
    parameter as an attribute), and per exposure ``/entry/frames/<n>`` (NXcollection: provenance,
    ``curves`` and ``alpha``, and ``stack``/``subaperture`` when kept).
    """
    import h5py

    path = Path(path)
    columns = dict(results[0].particles) if len(results) == 1 else combine(results)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        entry = f.create_group("entry")
        entry.attrs["NX_class"] = "NXentry"
        data = entry.create_group("data")
        data.attrs["NX_class"] = "NXdata"
        data.attrs["signal"] = "Z"
        data.attrs["columns"] = json.dumps(list(columns))
        for name, values in columns.items():
            ds = data.create_dataset(name, data=np.asarray(values))
            if name in UNITS:
                ds.attrs["units"] = UNITS[name]
        process_group = entry.create_group("process")
        process_group.attrs["NX_class"] = "NXprocess"
        process_group["program"] = "plenodust"
        params = results[0].params.to_dict() if results else {}
        process_group["parameters"] = json.dumps(params, sort_keys=True)
        for name, value in params.items():
            process_group.attrs[name] = "none" if value is None else value
        frames = entry.create_group("frames")
        frames.attrs["NX_class"] = "NXcollection"
        for i, r in enumerate(results):
            g = frames.create_group(str(i))
            g.attrs["NX_class"] = "NXcollection"
            g.attrs["metadata"] = json.dumps(r.metadata(), sort_keys=True, default=str)
            g.create_dataset("alpha", data=r.alphas)
            if r.curves is not None:
                g.create_dataset("curves", data=r.curves, compression="gzip")
            if r.stack is not None:
                g.create_dataset("stack", data=r.stack, compression="gzip", chunks=(1,) + r.stack.shape[1:])
            if r.subaperture is not None:
                g.create_dataset("subaperture", data=r.subaperture, compression="gzip")
    return path


def read_hdf5_columns(path: str | Path) -> dict[str, np.ndarray]:
    """The particle table of a file written by :func:`write_hdf5`."""
    import h5py

    with h5py.File(path, "r") as f:
        data = f["entry/data"]
        return {name: data[name][()] for name in json.loads(data.attrs["columns"])}


def read_table(path: str | Path, *, frame: int | None = None,
               required: Iterable[str] = ("X", "Y", "Z")) -> dict[str, np.ndarray]:
    """A particle table from ``.csv`` (:func:`read_csv`) or HDF5 (:func:`read_hdf5_columns`),
    optionally only the rows of one ``frame`` of a batch.

    Raises
    ------
    ParameterError
        If a ``required`` column is missing, or ``frame`` is asked of a single-exposure table.
    """
    path = Path(path)
    columns = read_csv(path) if path.suffix.lower() == ".csv" else read_hdf5_columns(path)
    missing = [c for c in required if c not in columns]
    if missing:
        raise ParameterError(f"{path} has no column(s) {missing}")
    if frame is not None:
        if "frame" not in columns:
            raise ParameterError(f"{path} holds one exposure; leave out the frame")
        keep = columns["frame"] == frame
        columns = {k: np.asarray(v)[keep] for k, v in columns.items()}
    return columns

