"""A run's NeXus file (``DATA/runs/<run>.nxs``): every exposure's particles, grown by appending.

Layout::

    /entry                NXentry, title = the run
    /entry/data           NXdata: one 1-D column per quantity plus ``frame``; rows sorted by frame
    /entry/process        NXprocess: program, version, parameters (those of the last frame)
    /entry/exposures      NXcollection, one row per exposure by frame: id, frame, particles,
                          first_row (its rows are first_row .. first_row + particles - 1),
                          parameters (JSON, fixed-width bytes)

Every dataset is chunked and resizable (``maxshape=(None,)``). The usual update -- the next
frame of a run, or the last frame again when a job ran twice -- resizes the datasets and
writes that frame's rows only, so its cost does not grow with the run. Anything else (a frame
before the last, a column whose type the file cannot hold, a file in the older fixed-size
layout, a file another process holds open) is merged in memory and written whole to a
temporary file that is renamed into place (:func:`write_run`): rare, and it costs a full rewrite.

Crash safety. HDF5 promises nothing about a file whose writer died mid-write, so before
touching the file in place :func:`put_frame` creates a marker ``.<run>.nxs.writing`` beside it
(and syncs the folder), and removes it only once the file is closed and synced. A marker found
later, a file that cannot be opened, or one whose bookkeeping disagrees (column lengths,
``first_row`` against ``particles``, frames out of order) means the file may be half-written:
it is rebuilt from the per-exposure result files, the source of truth (the caller supplies
them), with a log warning. A whole-file rewrite never needs the marker: the rename is atomic.

Readers must hold the same lock as writers (:class:`service.store.Store` takes a thread lock
and an ``flock`` on ``.<run>.lock``), and should go through :func:`read_run_table` or
:func:`copy_run_file`, which repair a damaged file first. HDF5's own file locking keeps
outside h5py readers safe too: while an append is under way they cannot open the file, and
while one holds it open the next update rewrites and renames instead of appending. Only a
reader that bypasses the locks (``cp``, ``rsync``, HDF5 locking turned off) can catch an append
half-done: copy a run file through the API (:func:`copy_run_file` under the lock) instead.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

from analysis.formats.atomic_write import atomic_path
from analysis.formats.particle_table import (create_nx_column, decode_strings, nx_entry, nx_group, parameters_json,
                                             read_nx_columns, set_nx_parameters, signal_column, write_nx_columns,
                                             write_nx_process)

log = logging.getLogger(__name__)

#: Rows per chunk of a particle column: an append rewrites at most two chunks per column.
ROW_CHUNK = 1024
#: Rows per chunk of the exposures collection, and of its (compressed) parameters.
EXPOSURE_CHUNK = 256
PARAMETER_CHUNK = 32
# What reading a damaged HDF5 file can raise besides OSError.
_DAMAGE = (OSError, KeyError, ValueError, TypeError, RuntimeError, AttributeError)


class RunFileDamaged(Exception):
    """The run file cannot be opened or its bookkeeping disagrees; rebuild it from the results."""


class RunFileBusy(Exception):
    """Another process holds the run file open, so it cannot be changed in place."""


@dataclass
class RunContents:
    """A whole run in memory: its particle table (rows by frame) and its exposures by frame.

    Each exposure is a dict with ``id``, ``frame``, ``particles`` and ``parameters``.
    """

    table: dict[str, np.ndarray] = field(default_factory=dict)
    exposures: list[dict] = field(default_factory=list)


Rebuild = Callable[[], RunContents]


def marker_path(path: Path) -> Path:
    """The marker that exists while ``path`` is being changed in place."""
    return path.with_name(f".{path.name}.writing")


def frame_rows(columns: Mapping[str, np.ndarray], frame: int) -> dict[str, np.ndarray]:
    """One exposure's particle columns with its ``frame`` column added."""
    n = len(next(iter(columns.values()))) if columns else 0
    return {**{name: np.asarray(col) for name, col in columns.items()},
            "frame": np.full(n, frame, dtype=np.int64)}


def put_frame(path: Path, run: str, frame: int, exposure_id: str, rows: Mapping[str, np.ndarray] | None,
              parameters: dict, rebuild: Rebuild) -> str:
    """Put one exposure's rows (from :func:`frame_rows`) into the run file, replacing earlier
    ones, or remove them (``rows=None``). The caller holds the run's lock.

    Parameters
    ----------
    rebuild : callable
        Returns the run as the result files record it; called only when the file is missing
        or damaged.

    Returns
    -------
    str
        How: ``"in place"``, ``"rewritten"`` or ``"rebuilt"`` (whole file).
    """
    marker = marker_path(path)
    contents, how = None, "rewritten"
    if marker.exists():
        _warn_rebuild(path, "was left half-written (a process stopped or a write failed)")
        contents, how = rebuild(), "rebuilt"
    elif not path.exists():
        contents = rebuild()  # empty for a new run; the whole run if someone deleted the file
        if contents.exposures:
            _warn_rebuild(path, "is missing")
            how = "rebuilt"
    else:
        _mark(marker)
        done = False
        try:
            done = _splice_in_place(path, frame, exposure_id, rows, parameters)
        except RunFileBusy:
            pass  # nothing was written; the rename below leaves the other reader its old file
        except RunFileDamaged as exc:
            _warn_rebuild(path, f"is damaged ({exc})")
            contents, how = rebuild(), "rebuilt"
        # Any other error leaves the marker: the file may be half-written and is rebuilt next time.
        if done:
            _fsync(path)
            marker.unlink()
            return "in place"
        if contents is None:
            marker.unlink()  # nothing was written
            try:
                contents = read_run(path)
            except RunFileDamaged as exc:
                _warn_rebuild(path, f"is damaged ({exc})")
                contents, how = rebuild(), "rebuilt"
    write_run(path, run, merge_frame(contents, frame, exposure_id, rows, parameters))
    marker.unlink(missing_ok=True)
    return how


def repair(path: Path, run: str, rebuild: Rebuild) -> bool:
    """Rebuild the run file from the results if it is marked half-written or is damaged; True if
    it was. The caller holds the run's lock. A missing file is left missing.
    """
    marker = marker_path(path)
    if marker.exists():
        _warn_rebuild(path, "was left half-written (a process stopped or a write failed)")
    elif not path.exists():
        return False
    else:
        try:
            with _open(path, "r") as f:
                _bookkeeping(f)
            return False
        except RunFileBusy:
            return False  # someone else is writing it; not ours to replace
        except RunFileDamaged as exc:
            _warn_rebuild(path, f"is damaged ({exc})")
    write_run(path, run, rebuild())
    marker.unlink(missing_ok=True)
    return True


def read_run_table(path: Path) -> dict[str, np.ndarray]:
    """The particle table of a run file, with its ``frame`` column.

    Raises
    ------
    RunFileDamaged
        If the file cannot be read or its bookkeeping disagrees.
    RunFileBusy
        If another process has it open for writing.
    """
    with _checked(path) as f:
        return read_nx_columns(f["entry/data"])


def read_frames(path: Path, first: int, last: int | None = None) -> dict[str, np.ndarray]:
    """The rows of frames ``first`` ... ``last`` (inclusive; ``last`` None: to the end) only, at a
    cost of those rows, not of the run.

    Raises
    ------
    RunFileDamaged, RunFileBusy
        As :func:`read_run_table`.
    """
    with _checked(path) as f:
        coll, data = f["entry/exposures"], f["entry/data"]
        frames = coll["frame"][()]
        start_row = coll["first_row"][()] if "first_row" in coll else \
            np.concatenate([[0], np.cumsum(coll["particles"][()])[:-1]]).astype(np.int64)
        a = int(np.searchsorted(frames, first))
        b = len(frames) if last is None else int(np.searchsorted(frames, last, side="right"))
        names = json.loads(data.attrs["columns"])
        if a >= b:
            return {name: data[name][:0] for name in names}
        lo = int(start_row[a])
        hi = int(start_row[b]) if b < len(frames) else data[names[0]].shape[0]
        return {name: decode_strings(data[name][lo:hi]) for name in names}


def update_columns(path: Path, frames: Mapping[int, Mapping[str, np.ndarray]]) -> bool:
    """Overwrite columns of existing frames' rows in place (all of a frame's rows, in file order),
    e.g. trajectory ids and velocities once a later shot is linked. The caller holds the run's
    lock. Columns not yet in the file are added (NaN, or -1 for whole numbers, elsewhere).

    Returns False, having written nothing, when the file is missing, busy or damaged, or a frame is
    not in it (the caller may rebuild the run file and link again).
    """
    if not path.exists() or marker_path(path).exists():
        return False
    marker = marker_path(path)
    _mark(marker)
    try:
        with _open(path, "r+") as f:
            book = _bookkeeping(f)
            if not book.appendable:
                marker.unlink()
                return False
            data = f["entry/data"]
            names = list(book.names)
            spans = {}
            for frame, columns in frames.items():
                p = int(np.searchsorted(book.frames, frame))
                if p >= len(book.frames) or book.frames[p] != frame:
                    marker.unlink()
                    return False
                end = int(book.first_row[p + 1]) if p + 1 < len(book.frames) else book.rows
                spans[frame] = (int(book.first_row[p]), end)
            for columns in frames.values():
                for name, values in columns.items():
                    if name not in names:
                        values = np.asarray(values)
                        fill = -1 if values.dtype.kind in "iu" else np.nan
                        create_nx_column(data, name, np.full(book.rows, fill, values.dtype if values.dtype.kind in "iuf"
                                                             else np.float64), chunk_rows=ROW_CHUNK)
                        names.append(name)
                        data.attrs["columns"] = json.dumps(names)
            for frame, columns in frames.items():
                lo, hi = spans[frame]
                for name, values in columns.items():
                    values = np.asarray(values)
                    if values.shape != (hi - lo,):
                        raise ValueError(f"frame {frame}: {name} has {values.shape[0]} values for {hi - lo} rows")
                    data[name][lo:hi] = values.astype(data[name].dtype)
    except (RunFileBusy, RunFileDamaged):
        marker.unlink(missing_ok=True)
        return False
    _fsync(path)
    marker.unlink()
    return True


def read_run(path: Path) -> RunContents:
    """A whole run file (this layout or the older fixed-size one) in memory.

    Raises
    ------
    RunFileDamaged
        If the file cannot be read or its bookkeeping disagrees.
    RunFileBusy
        If another process has it open for writing.
    """
    with _checked(path) as f:
        return RunContents(read_nx_columns(f["entry/data"]), _read_exposures(f["entry/exposures"], 0))


@contextmanager
def _checked(path: Path) -> Iterator[h5py.File]:
    """A run file opened read-only once its bookkeeping agrees; what reading it raises on damage
    becomes RunFileDamaged."""
    with _open(path, "r") as f:
        try:
            _bookkeeping(f)
            yield f
        except _DAMAGE as exc:
            raise RunFileDamaged(f"{type(exc).__name__}: {exc}") from exc


def copy_run_file(path: Path, dest: Path) -> None:
    """Copy the run file to ``dest`` (the caller holds the run's lock, so the copy is whole)."""
    shutil.copyfile(path, dest)


def merge_frame(contents: RunContents, frame: int, exposure_id: str, rows: Mapping[str, np.ndarray] | None,
                parameters: dict) -> RunContents:
    """``contents`` with ``frame``'s rows replaced by ``rows`` (or removed), rows sorted by frame."""
    table = contents.table
    keep = table.get("frame", np.zeros(0, np.int64)) != frame
    table = {name: column[keep] for name, column in table.items()}
    exposures = [e for e in contents.exposures if e["frame"] != frame]
    if rows is not None:
        table = concat_tables([table, dict(rows)])
        exposures.append({"id": exposure_id, "frame": frame, "particles": len(rows["frame"]),
                          "parameters": parameters})
        exposures.sort(key=lambda e: e["frame"])
    if "frame" in table:
        order = np.argsort(table["frame"], kind="stable")
        table = {name: column[order] for name, column in table.items()}
    return RunContents(table, exposures)


def concat_tables(tables: Iterable[Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Tables one after the other; a column one table lacks is NaN there (missing, not zero)."""
    tables = [t for t in tables if t]
    if not tables:
        return {}
    if len(tables) == 1:
        return {k: np.asarray(v) for k, v in tables[0].items()}
    lengths = [len(next(iter(t.values()))) for t in tables]
    names = list(dict.fromkeys(name for t in tables for name in t))
    return {name: np.concatenate([np.asarray(t[name]) if name in t else np.full(n, np.nan)
                                  for t, n in zip(tables, lengths)]) for name in names}


def write_run(path: Path, run: str, contents: RunContents) -> None:
    """Write a whole run file to a temporary name and rename it into place."""
    table, exposures = dict(contents.table), contents.exposures
    if "frame" not in table:
        table["frame"] = np.zeros(0, np.int64)
    counts = np.array([e["particles"] for e in exposures], dtype=np.int64)
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        entry = nx_entry(f, title=run)
        write_nx_columns(nx_group(entry, "data", "NXdata"), table, chunk_rows=ROW_CHUNK)
        write_nx_process(entry, exposures[-1]["parameters"] if exposures else {})
        coll = nx_group(entry, "exposures", "NXcollection")
        _create(coll, "id", np.array([e["id"] for e in exposures], dtype="S40"), EXPOSURE_CHUNK)
        _create(coll, "frame", np.array([e["frame"] for e in exposures], dtype=np.int64), EXPOSURE_CHUNK)
        _create(coll, "particles", counts, EXPOSURE_CHUNK)
        _create(coll, "first_row", np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
                if len(counts) else counts, EXPOSURE_CHUNK)
        texts = [parameters_json(e["parameters"]).encode() for e in exposures]
        # Mostly the same text, padded: compressed in small chunks, an append recompresses one.
        _create(coll, "parameters", np.array(texts, dtype=f"S{_width(texts)}"), PARAMETER_CHUNK,
                compression="gzip", compression_opts=1)


# -- in place ----------------------------------------------------------------------------


@dataclass
class _Bookkeeping:
    names: list[str]
    frames: np.ndarray
    first_row: np.ndarray
    rows: int
    appendable: bool  # this layout (resizable, with first_row), not the older fixed-size one


def _bookkeeping(f: h5py.File) -> _Bookkeeping:
    """Check that the file's parts agree, reading only the small exposures collection and the
    last frame's ``frame`` values; raises RunFileDamaged if they do not."""
    try:
        data, coll = f["entry/data"], f["entry/exposures"]
        names = json.loads(data.attrs["columns"])
        columns = [data[name] for name in names]
        lengths = {c.shape for c in columns}
        if "frame" not in names or len(lengths) != 1 or len(next(iter(lengths))) != 1:
            raise RunFileDamaged(f"columns {names} have shapes {sorted(lengths)}")
        rows = columns[0].shape[0]
        if "parameters" not in f["entry/process"]:
            raise RunFileDamaged("entry/process lacks its parameters")
        missing = [name for name in ("id", "frame", "particles", "parameters") if name not in coll]
        if missing:
            raise RunFileDamaged(f"the exposures collection lacks {missing}")
        frames, particles = coll["frame"][()], coll["particles"][()]
        listed = [coll[name] for name in ("id", "frame", "particles", "parameters", "first_row") if name in coll]
        if {d.shape for d in listed} != {frames.shape} or frames.ndim != 1:
            raise RunFileDamaged("the exposures collection's datasets differ in length")
        starts = np.concatenate([[0], np.cumsum(particles)[:-1]]) if len(particles) else particles
        if np.any(particles < 0) or int(particles.sum()) != rows or np.any(np.diff(frames) <= 0):
            raise RunFileDamaged(f"{int(particles.sum())} particles listed for {rows} rows, "
                                 "or frames out of order")
        has_first = "first_row" in coll
        if has_first and not np.array_equal(coll["first_row"][()], starts):
            raise RunFileDamaged("first_row disagrees with the particle counts")
        if len(frames) and np.any(data["frame"][int(starts[-1]):] != frames[-1]):
            raise RunFileDamaged("the last frame's rows carry another frame number")
        resizable = all(d.maxshape == (None,) and d.chunks is not None for d in columns + listed)
        resizable &= coll["parameters"].dtype.kind == "S"
    except RunFileDamaged:
        raise
    except _DAMAGE as exc:
        raise RunFileDamaged(f"{type(exc).__name__}: {exc}") from exc
    return _Bookkeeping(names, frames, starts, rows, has_first and resizable)


def _splice_in_place(path: Path, frame: int, exposure_id: str, rows: Mapping[str, np.ndarray] | None,
                     parameters: dict) -> bool:
    """Put ``frame``'s rows in place: rows of later frames (usually none) are read, and written
    back after it, so the cost is that of the frame and the frames after it.

    Returns False, having written nothing, when it cannot be done in place.
    """
    with _open(path, "r+") as f:
        book = _bookkeeping(f)
        if not book.appendable:
            return False
        k = len(book.frames)
        p = int(np.searchsorted(book.frames, frame))  # first exposure at or after ``frame``
        present = p < k and book.frames[p] == frame
        if rows is None and not present:
            return True  # removing a frame that is not there changes nothing
        cut = int(book.first_row[p]) if p < k else book.rows
        data, coll = f["entry/data"], f["entry/exposures"]
        tail: dict[str, np.ndarray] = {}
        tail_exposures: list[dict] = []
        if p < k:  # not the usual next frame: the later frames are read to be written back
            try:
                tail = read_nx_columns(data, start=cut)
                tail_exposures = _read_exposures(coll, p)
            except _DAMAGE as exc:
                raise RunFileDamaged(f"{type(exc).__name__}: {exc}") from exc
        if present:
            keep = tail["frame"] != frame
            tail = {name: column[keep] for name, column in tail.items()}
            tail_exposures = tail_exposures[1:]
        segment = concat_tables([rows or {}, tail])
        exposures = tail_exposures
        if rows is not None:
            exposures = [{"id": exposure_id, "frame": frame, "particles": len(rows["frame"]),
                          "parameters": parameters}] + exposures
        if segment and not _fits(data, book.names, segment, cut):
            return False
        width = coll["parameters"].dtype.itemsize
        if any(len(parameters_json(e["parameters"]).encode()) > width for e in exposures):
            return False  # longer than the column holds: a rewrite widens it
        try:
            _write_segment(f, book.names, cut, p, segment, exposures)
        except _DAMAGE as exc:
            # The marker stays: the caller sees an ordinary error, and the next update rebuilds.
            raise OSError(f"writing {path} in place failed: {exc}") from exc
    return True


def _read_exposures(coll: h5py.Group, start: int) -> list[dict]:
    return [{"id": i.decode(), "frame": int(fr), "particles": int(n), "parameters": json.loads(p)}
            for i, fr, n, p in zip(coll["id"][start:], coll["frame"][start:], coll["particles"][start:],
                                   coll["parameters"][start:], strict=True)]


def _fits(data: h5py.Group, names: list[str], segment: Mapping[str, np.ndarray], cut: int) -> bool:
    """Whether ``segment`` can be written into the existing columns without changing their
    types, as concatenating in memory would (a column missing before ``cut`` becomes NaN there)."""
    for name, values in segment.items():
        if values.ndim != 1:
            return False
        if name in names:
            dtype = data[name].dtype
            if h5py.check_string_dtype(dtype) is not None:
                if values.dtype.kind not in "US":
                    return False
            elif values.dtype.kind in "USO" or not np.can_cast(values.dtype, dtype, "safe"):
                return False
        elif cut and values.dtype.kind not in "biuf":
            return False  # earlier rows get NaN: only a numeric column can hold it
    return all(data[name].dtype.kind == "f" for name in names if name not in segment)


def _write_segment(f: h5py.File, names: list[str], cut: int, p: int, segment: Mapping[str, np.ndarray],
                   exposures: list[dict]) -> None:
    """Cut the columns at row ``cut`` and the exposures at ``p``, then write ``segment`` and
    ``exposures`` there."""
    data, coll = f["entry/data"], f["entry/exposures"]
    m = len(segment["frame"]) if segment else 0
    new = [name for name in segment if name not in names]
    for name in new:
        values = segment[name]
        dtype = np.result_type(values.dtype, np.float64) if cut else values.dtype
        create_nx_column(data, name, np.full(cut, np.nan, dtype) if cut else values[:0], chunk_rows=ROW_CHUNK)
    if new:
        names = names + new
        data.attrs["columns"] = json.dumps(names)
        data.attrs["signal"] = signal_column(names)
    for name in names:
        column = data[name]
        column.resize((cut + m,))
        if m:
            values = segment[name] if name in segment else np.full(m, np.nan)
            column[cut:] = values.astype(object) if values.dtype.kind == "U" else values
    count = p + len(exposures)
    for name in ("id", "frame", "particles", "first_row", "parameters"):
        coll[name].resize((count,))
    if exposures:
        counts = np.array([e["particles"] for e in exposures], dtype=np.int64)
        coll["id"][p:] = np.array([e["id"] for e in exposures], dtype="S40")
        coll["frame"][p:] = np.array([e["frame"] for e in exposures], dtype=np.int64)
        coll["particles"][p:] = counts
        coll["first_row"][p:] = cut + np.concatenate([[0], np.cumsum(counts)[:-1]])
        coll["parameters"][p:] = np.array([parameters_json(e["parameters"]).encode() for e in exposures],
                                          dtype=coll["parameters"].dtype)
    # As a rule unchanged within a run, and then not rewritten.
    set_nx_parameters(f["entry/process"], json.loads(decode_strings(coll["parameters"][count - 1])) if count else {})


# -- helpers -----------------------------------------------------------------------------


def _width(texts: list[bytes]) -> int:
    """Bytes per parameters entry: room to spare, as a variable-length string would cost a new
    4 KiB heap block on every append (HDF5 does not reuse heap blocks across opens)."""
    longest = max((len(t) for t in texts), default=0)
    return max(256, 1 << (longest + longest // 4).bit_length())


def _create(group: h5py.Group, name: str, data: np.ndarray, chunk: int, **kwargs) -> h5py.Dataset:
    return group.create_dataset(name, data=data, maxshape=(None,), chunks=(chunk,), **kwargs)


def _mark(marker: Path) -> None:
    """Create the marker and make it durable before the file changes (so power loss cannot
    leave a half-written file without one)."""
    os.close(os.open(marker, os.O_CREAT | os.O_WRONLY, 0o644))
    _fsync_folder(marker.parent)


def _fsync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _fsync_folder(folder: Path) -> None:
    try:
        _fsync(folder)
    except OSError:
        pass  # some file systems cannot sync a folder; the marker is then only as durable as they are


def _open(path: Path, mode: str) -> h5py.File:
    """Open a run file, telling a file another process holds (HDF5 locks files it opens) from a
    damaged one."""
    try:
        return h5py.File(path, mode)
    except BlockingIOError as exc:
        raise RunFileBusy(f"{path} is open in another process; close it (the job will retry)") from exc
    except _DAMAGE as exc:
        if mode != "r" and _readable(path):
            # Open read-only in this process outside the lock: HDF5 refuses a second, writing open.
            raise RunFileBusy(f"{path} is open read-only here: {exc}") from exc
        raise RunFileDamaged(f"cannot open it: {exc}") from exc


def _readable(path: Path) -> bool:
    try:
        with h5py.File(path, "r") as f:
            _bookkeeping(f)
        return True
    except (RunFileDamaged, *_DAMAGE):
        return False


def _warn_rebuild(path: Path, why: str) -> None:
    log.warning("run file %s %s; rebuilding it from the per-exposure result files", path, why)
