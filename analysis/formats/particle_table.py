"""The particle table on disk, in one place: CSV, and the NeXus (HDF5) pieces every file that
holds a table is made of.

A table is a mapping of column name to 1-D array (:data:`COLUMNS`, plus ``frame`` for a batch).
``index`` numbers an exposure's particles (0 ... n-1, by image position); ``particle`` is reserved
for a trajectory id, as in trackpy (:mod:`analysis.tracking`). A table written before that
rename has ``particle`` for the row number: :func:`read_csv` and :func:`read_hdf5_columns` read
it as ``index``.

CSV: a header row, one row per particle, ``\\n`` line endings, floats at full precision
(``repr``), NaN as an empty cell. NeXus: ``/entry`` (NXentry) holds ``/entry/data`` (NXdata:
one dataset per column, its names in order in the ``columns`` attribute, ``signal`` = ``Z``,
units where a column has them) and ``/entry/process`` (NXprocess: program, version, parameters
as JSON). The CLI's files (:func:`write_hdf5`), the service's result and run files and its
downloads are all built from :func:`nx_entry`, :func:`write_nx_columns` and
:func:`write_nx_process`, and read back with :func:`read_nx_columns`.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from analysis.errors import ParameterError

from .atomic_write import atomic_path

#: Columns of the particle table, in this order.
COLUMNS: tuple[str, ...] = ("index", "x", "y", "alpha", "X", "Y", "Z", "brightness",
                            "peak_height", "peak_width", "residual", "prominence", "alpha_std", "prior_std",
                            "intensity", "n_lit", "blur_pitches", "leftover")
#: Units of the columns that have them (NeXus `units` attributes).
UNITS = {"x": "pixel", "y": "pixel", "X": "mm", "Y": "mm", "Z": "mm", "alpha": "1", "peak_width": "1"}
#: Columns that hold whole numbers (read back as int64 from CSV).
INTEGER_COLUMNS = ("index", "frame", "particle")


def combine(tables: Iterable[Mapping[str, np.ndarray]],
            times: Sequence[float | None] | None = None) -> dict[str, np.ndarray]:
    """One table for a batch, with a ``frame`` column first (the index of each table) and, given
    each table's shot time (s; all known), ``t``: seconds since the earliest of them."""
    parts = []
    known = times is not None and all(t is not None for t in times)
    start = min(times) if known and times else 0.0
    for i, table in enumerate(tables):
        n = len(next(iter(table.values()))) if table else 0
        when = {"t": np.full(n, float(times[i]) - start)} if known else {}
        parts.append({"frame": np.full(n, i, dtype=np.int64), **when, **table})
    if not parts:
        return {name: np.empty(0) for name in ("frame",) + COLUMNS}
    names = list(dict.fromkeys(name for p in parts for name in p))
    return {name: np.concatenate([np.asarray(p[name]) for p in parts]) for name in names}


# -- CSV ---------------------------------------------------------------------------------------

def csv_text(columns: Mapping[str, np.ndarray]) -> str:
    """The table as CSV text (see the module docstring)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    names = list(columns)
    writer.writerow(names)
    for row in zip(*[np.asarray(columns[n]).tolist() for n in names], strict=True):
        writer.writerow(["" if isinstance(v, float) and math.isnan(v) else repr(v) if isinstance(v, float) else v
                         for v in row])
    return buf.getvalue()


def write_csv(columns: Mapping[str, np.ndarray], path: str | Path) -> Path:
    """Write the table as CSV, atomically."""
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_text(csv_text(columns), encoding="utf-8", newline="")
    return path


def read_csv(path: str | Path) -> dict[str, np.ndarray]:
    """Read a table written by :func:`write_csv` (empty cells become NaN).

    Raises
    ------
    ParameterError
        If the file is empty or a cell is not a number.
    """
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    if not rows:
        raise ParameterError(f"{path} is empty; expected a particle table with a header row")
    names, body = rows[0], rows[1:]
    out: dict[str, np.ndarray] = {}
    try:
        for k, name in enumerate(names):
            values = [r[k] for r in body]
            if name in INTEGER_COLUMNS and all(v != "" for v in values):
                out[name] = np.array([int(v) for v in values], dtype=np.int64)
            else:
                out[name] = np.array([float(v) if v != "" else math.nan for v in values], dtype=np.float64)
    except (ValueError, IndexError) as exc:
        raise ParameterError(f"{path} is not a particle table ({exc}); expected a header row and numbers") from None
    return legacy_index(out)


def legacy_index(columns: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A table written before ``particle`` meant a trajectory: its ``particle`` (the row number)
    renamed ``index``. Recognised by having ``particle`` without ``index`` or ``t``."""
    if "particle" in columns and "index" not in columns and "t" not in columns:
        return {("index" if k == "particle" else k): v for k, v in columns.items()}
    return columns


# -- NeXus -------------------------------------------------------------------------------------

def nx_group(parent: h5py.Group, name: str, nx_class: str) -> h5py.Group:
    """A new group of NeXus class ``nx_class``."""
    group = parent.create_group(name)
    group.attrs["NX_class"] = nx_class
    return group


def nx_entry(f: h5py.File, *, title: str) -> h5py.Group:
    """The file's ``/entry`` (NXentry, the file's and its own default: ``data``)."""
    f.attrs["default"] = "entry"
    f.attrs["creator"] = "plenodust"
    entry = nx_group(f, "entry", "NXentry")
    entry.attrs["default"] = "data"
    entry["title"] = title
    return entry


def write_nx_columns(group: h5py.Group, columns: Mapping[str, np.ndarray], *, chunk_rows: int | None = None) -> None:
    """The table's columns into an NXdata group; ``chunk_rows``: resizable datasets in chunks of
    that many rows (a file that grows by appending), else fixed-size ones."""
    names = list(columns)
    group.attrs["signal"] = signal_column(names)
    group.attrs["columns"] = json.dumps(names)
    for name in names:
        create_nx_column(group, name, np.asarray(columns[name]), chunk_rows=chunk_rows)


def create_nx_column(group: h5py.Group, name: str, data: np.ndarray, *, chunk_rows: int | None = None) -> h5py.Dataset:
    """One column (text columns as variable-length strings), with its units."""
    kwargs: dict[str, Any] = {}
    if chunk_rows is not None:
        kwargs.update(maxshape=(None,), chunks=(chunk_rows,))
    if data.dtype.kind == "U":
        ds = group.create_dataset(name, data=data.astype(object), dtype=h5py.string_dtype(), **kwargs)
    else:
        if chunk_rows is not None and data.dtype.kind == "f":
            kwargs["fillvalue"] = np.nan
        ds = group.create_dataset(name, data=data, **kwargs)
    if name in UNITS:
        ds.attrs["units"] = UNITS[name]
    return ds


def signal_column(names: Sequence[str]) -> str:
    """NXdata's ``signal``: ``Z`` where there is one."""
    return "Z" if "Z" in names else (names[0] if names else "")


def read_nx_columns(group: h5py.Group, *, start: int = 0) -> dict[str, np.ndarray]:
    """The table of an NXdata group written by :func:`write_nx_columns` (rows from ``start``)."""
    return {name: decode_strings(group[name][start:]) for name in json.loads(group.attrs["columns"])}


def decode_strings(values: Any) -> Any:
    """Text read from HDF5 (bytes, or arrays of them) as ``str``; anything else unchanged."""
    if isinstance(values, bytes):
        return values.decode()
    if isinstance(values, np.ndarray) and values.dtype.kind in "OS":
        return np.array([v.decode() if isinstance(v, bytes) else v for v in values.tolist()], dtype=str)
    return values


def parameters_json(parameters: Mapping[str, Any]) -> str:
    """Parameters as the files store them: JSON, keys sorted."""
    return json.dumps(parameters, sort_keys=True, default=str)


def write_nx_process(entry: h5py.Group, parameters: Mapping[str, Any]) -> h5py.Group:
    """``/entry/process`` (NXprocess): program, version, the parameters (:func:`set_nx_parameters`)."""
    from importlib.metadata import PackageNotFoundError, version

    process = nx_group(entry, "process", "NXprocess")
    process["program"] = "plenodust"
    try:
        process["version"] = version("plenodust")
    except PackageNotFoundError:
        process["version"] = "unknown"
    set_nx_parameters(process, parameters)
    return process


def set_nx_parameters(process: h5py.Group, parameters: Mapping[str, Any]) -> None:
    """The parameters as JSON (``parameters``) and, for a viewer such as HDFView, each plain value
    as an attribute (None as ``"none"``); replaces what was there."""
    text = parameters_json(parameters)
    if "parameters" in process:
        if decode_strings(process["parameters"][()]) == text:
            return
        del process["parameters"]
    process["parameters"] = text
    for name in list(process.attrs):
        if name != "NX_class":
            del process.attrs[name]
    for name, value in parameters.items():
        if value is None:
            process.attrs[name] = "none"
        elif isinstance(value, (bool, int, float, str)) or (
                isinstance(value, (list, tuple)) and all(isinstance(v, (int, float)) for v in value)):
            process.attrs[name] = value


def table_h5_bytes(columns: Mapping[str, np.ndarray], *, title: str) -> bytes:
    """A small NeXus file holding just the table (a download)."""
    buf = io.BytesIO()
    with h5py.File(buf, "w") as f:
        write_nx_columns(nx_group(nx_entry(f, title=title), "data", "NXdata"), columns)
    return buf.getvalue()


def write_hdf5(path: str | Path, columns: Mapping[str, np.ndarray], *, parameters: Mapping[str, Any],
               frames: Sequence[Mapping[str, Any]] = (), title: str = "plenodust") -> Path:
    """A NeXus file of one exposure's table or a batch's (then with a ``frame`` column), atomically.

    Besides ``/entry/data`` and ``/entry/process``, each exposure's extras go to
    ``/entry/frames/<n>`` (NXcollection): ``frames[n]`` maps ``metadata`` (a JSON-able dict, kept as
    an attribute), arrays (``alpha``, ``curves``, ``stack``, ``subaperture``) and tables (mappings
    of columns, e.g. ``rejected``: NXdata groups); None is left out.
    """
    path = Path(path)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        entry = nx_entry(f, title=title)
        write_nx_columns(nx_group(entry, "data", "NXdata"), columns)
        write_nx_process(entry, parameters)
        group = nx_group(entry, "frames", "NXcollection")
        for i, frame in enumerate(frames):
            g = nx_group(group, str(i), "NXcollection")
            g.attrs["metadata"] = json.dumps(frame.get("metadata", {}), sort_keys=True, default=str)
            for name, values in frame.items():
                if name == "metadata" or values is None:
                    continue
                if isinstance(values, Mapping):
                    write_nx_columns(nx_group(g, name, "NXdata"), values)
                    continue
                values = np.asarray(values)
                big = values.ndim >= 2
                g.create_dataset(name, data=values, compression="gzip" if big else None,
                                 chunks=(1,) + values.shape[1:] if values.ndim == 3 else None)
    return path


def read_hdf5_columns(path: str | Path) -> dict[str, np.ndarray]:
    """The particle table of any of the project's NeXus files."""
    with h5py.File(path, "r") as f:
        return legacy_index(read_nx_columns(f["entry/data"]))


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
