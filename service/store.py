"""Storage under one data folder: raw exposures by SHA-1, results, NeXus run files, index.

Layout::

    DATA/plenodust.sqlite                 queue and index (see service.database)
    DATA/raw/ab/<sha1>.lfp                an uploaded .lfp, or
    DATA/raw/ab/<sha1>.RAW, .TXT          a camera .RAW + .TXT pair
    DATA/results/ab/<sha1>.h5             one exposure's particle table, curves, slices
    DATA/runs/<run>.nxs                   every exposure of a run (NeXus: NXentry/NXdata),
                                          grown by appending (see service.run_file)
    DATA/calibrations/<serial>/MOD_*      white images per camera
    DATA/metric-calibrations/<serial>/    target calibrations per camera, zoom and focus (JSON)
    DATA/cache/                           calibration cache

Every file but a run file is written to a temporary name and renamed into place, so a crash
leaves either the old file or the new one. A run file is appended to in place under a lock, and
rebuilt from the result files (the source of truth, with the index) if a crash interrupted that.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import sqlite3
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from analysis.formats.atomic_write import atomic_path, write_all_atomic
from service import run_file
from service.database import Database
from analysis.formats.particle_table import (decode_strings, nx_entry, nx_group, read_nx_columns,
                                             write_nx_columns, write_nx_process)
from service.results import JobOutput

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ExposureRecord:
    """One stored exposure."""

    id: str
    run: str
    frame: int
    kind: str
    source: str
    serial: str | None
    created_at: float
    raw_removed_at: float | None = None

    @property
    def raw_kept(self) -> bool:
        return self.raw_removed_at is None

    @classmethod
    def from_row(cls, row: sqlite3.Row) -> ExposureRecord:
        return cls(**{name: row[name] for name in cls.__dataclass_fields__})


class Store:
    """Files under ``data_dir`` and their index in the shared :class:`Database`."""

    def __init__(self, data_dir: Path, db: Database) -> None:
        self.data_dir = Path(data_dir)
        self.db = db
        self.raw_dir = self.data_dir / "raw"
        self.results_dir = self.data_dir / "results"
        self.runs_dir = self.data_dir / "runs"
        self.calibrations_dir = self.data_dir / "calibrations"
        self.cache_dir = self.data_dir / "cache"
        self.metric_dir = self.data_dir / "metric-calibrations"  # service.metric_calibrations
        for folder in (self.raw_dir, self.results_dir, self.runs_dir, self.calibrations_dir, self.cache_dir,
                       self.metric_dir):
            folder.mkdir(parents=True, exist_ok=True)
        # One writer per run file at a time within this process.
        self._run_locks: dict[str, threading.Lock] = {}
        self._locks_lock = threading.Lock()
        # Told the run whose file was rebuilt from the result files (its trajectories are gone).
        self.on_run_rebuilt: Callable[[str], None] | None = None

    # -- raw exposures ---------------------------------------------------------------

    def raw_paths(self, exposure_id: str, kind: str) -> list[Path]:
        folder = self.raw_dir / exposure_id[:2]
        suffixes = [".lfp"] if kind == "lfp" else [".RAW", ".TXT"]
        return [folder / f"{exposure_id}{s}" for s in suffixes]

    def put_raw(self, exposure_id: str, files: Mapping[str, bytes]) -> str:
        """Store an exposure's files under its SHA-1 (that of its raw sensor bytes); returns the kind.

        ``files`` maps ``.lfp`` to the container, or ``.RAW`` and ``.TXT`` to the pair.
        Writing the same exposure again changes nothing.
        """
        kind = "lfp" if ".lfp" in files else "raw"
        paths = self.raw_paths(exposure_id, kind)
        missing = {path: files[path.suffix] for path in paths if not path.exists()}
        if missing:
            paths[0].parent.mkdir(parents=True, exist_ok=True)
            write_all_atomic(missing)  # a .RAW appears only with its .TXT
        return kind

    def prune_raw(self, *, keep: int) -> int:
        """Remove the raw files of all but the newest ``keep`` exposures, where their job is done
        (their particle tables stay); returns how many exposures lost their raw files."""
        rows = self.db.read(
            "SELECT e.id, e.kind FROM exposures e WHERE e.raw_removed_at IS NULL AND e.id NOT IN "
            "(SELECT id FROM exposures ORDER BY created_at DESC, rowid DESC LIMIT ?) AND "
            "(SELECT state FROM jobs WHERE exposure_id = e.id ORDER BY seq DESC LIMIT 1) = 'done'", (keep,))
        for row in rows:
            for path in self.raw_paths(row["id"], row["kind"]):
                path.unlink(missing_ok=True)
            with self.db.write() as conn:
                conn.execute("UPDATE exposures SET raw_removed_at = ? WHERE id = ?", (time.time(), row["id"]))
        if rows:
            log.debug("removed the raw files of %d exposure(s) beyond the newest %d", len(rows), keep)
        return len(rows)

    def register(self, conn: sqlite3.Connection, exposure_id: str, *, run: str, kind: str,
                 source: str, serial: str | None) -> tuple[ExposureRecord, bool]:
        """Index an exposure inside the caller's transaction; ``(record, created)``.

        An exposure already known keeps its run and frame (same bytes, same exposure).
        """
        row = conn.execute("SELECT * FROM exposures WHERE id = ?", (exposure_id,)).fetchone()
        if row is not None:
            if row["raw_removed_at"] is not None:  # sent again: put_raw has just written its files back
                row = conn.execute("UPDATE exposures SET raw_removed_at = NULL WHERE id = ? RETURNING *",
                                   (exposure_id,)).fetchone()
            return ExposureRecord.from_row(row), False
        frame = conn.execute("SELECT COALESCE(MAX(frame) + 1, 0) FROM exposures WHERE run = ?",
                             (run,)).fetchone()[0]
        row = conn.execute(
            "INSERT INTO exposures (id, run, frame, kind, source, serial, created_at) "
            "VALUES (?, ?, ?, ?, ?, ?, ?) RETURNING *",
            (exposure_id, run, frame, kind, source, serial, time.time())).fetchone()
        return ExposureRecord.from_row(row), True

    def exposure(self, exposure_id: str) -> ExposureRecord | None:
        rows = self.db.read("SELECT * FROM exposures WHERE id = ?", (exposure_id,))
        return ExposureRecord.from_row(rows[0]) if rows else None

    # -- results ---------------------------------------------------------------------

    def result_path(self, exposure_id: str) -> Path:
        return self.results_dir / exposure_id[:2] / f"{exposure_id}.h5"

    def write_result(self, record: ExposureRecord, output: JobOutput) -> Path:
        """Write one exposure's result file (atomically) and return its path."""
        path = self.result_path(record.id)

        def write(tmp: Path) -> None:
            with h5py.File(tmp, "w") as f:
                entry = nx_entry(f, title=record.id)
                entry["run"] = record.run
                entry["frame"] = record.frame
                write_nx_columns(nx_group(entry, "data", "NXdata"), output.columns)
                write_nx_process(entry, output.parameters)
                if "provenance" in output.extra:
                    entry["process"]["provenance"] = json.dumps(output.extra["provenance"], default=str)
                if output.rejected:
                    write_nx_columns(nx_group(entry, "rejected", "NXdata"), output.rejected)
                if output.curves is not None and output.curve_alpha is not None:
                    curves = nx_group(entry, "curves", "NXdata")
                    curves.attrs["signal"] = "brightness"
                    curves.attrs["axes"] = [".", "alpha"]
                    curves.create_dataset("brightness", data=np.asarray(output.curves, dtype=np.float32))
                    curves.create_dataset("alpha", data=np.asarray(output.curve_alpha, dtype=np.float64))
                if output.slices is not None and output.slice_alpha is not None:
                    slices = nx_group(entry, "slices", "NXdata")
                    slices.attrs["signal"] = "image"
                    slices.attrs["axes"] = ["alpha", ".", "."]
                    slices.attrs["binning"] = int(output.slice_binning)
                    slices.create_dataset("image", data=np.asarray(output.slices, dtype=np.uint8),
                                          chunks=(1, *output.slices.shape[1:]), compression="gzip",
                                          compression_opts=1)
                    slices.create_dataset("alpha", data=np.asarray(output.slice_alpha, dtype=np.float64))

        with atomic_path(path) as tmp:
            write(tmp)
        return path

    def index_result(self, conn: sqlite3.Connection, record: ExposureRecord, particles: int) -> None:
        """Record a result in the index inside the caller's transaction."""
        conn.execute(
            "INSERT INTO results (exposure_id, run, frame, particles, path, created_at) "
            "VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT (exposure_id) DO UPDATE SET "
            "particles = excluded.particles, path = excluded.path, created_at = excluded.created_at",
            (record.id, record.run, record.frame, particles,
             str(self.result_path(record.id).relative_to(self.data_dir)), time.time()))

    def has_result(self, exposure_id: str) -> bool:
        return bool(self.db.read("SELECT 1 FROM results WHERE exposure_id = ?", (exposure_id,)))

    def read_columns(self, exposure_id: str) -> dict[str, np.ndarray]:
        """The particle table of one exposure."""
        with h5py.File(self.result_path(exposure_id), "r") as f:
            return read_nx_columns(f["entry/data"])

    def read_parameters(self, exposure_id: str) -> dict:
        with h5py.File(self.result_path(exposure_id), "r") as f:
            return json.loads(decode_strings(f["entry/process/parameters"][()]))

    def read_provenance(self, exposure_id: str) -> dict:
        """Timings, warnings, calibration used: what the pipeline reported beside the table."""
        with h5py.File(self.result_path(exposure_id), "r") as f:
            if "entry/process/provenance" not in f:
                return {}
            return json.loads(decode_strings(f["entry/process/provenance"][()]))

    def read_rejected(self, exposure_id: str) -> dict[str, np.ndarray]:
        """The candidates that did not become particles, with their reasons (empty if none)."""
        with h5py.File(self.result_path(exposure_id), "r") as f:
            return read_nx_columns(f["entry/rejected"]) if "entry/rejected" in f else {}

    def read_curves(self, exposure_id: str) -> tuple[np.ndarray, np.ndarray] | None:
        """``(alpha, brightness)`` of shape (A,), (N, A), or None if not kept."""
        with h5py.File(self.result_path(exposure_id), "r") as f:
            if "entry/curves" not in f:
                return None
            return f["entry/curves/alpha"][()], f["entry/curves/brightness"][()]

    def slice_count(self, exposure_id: str) -> int:
        with h5py.File(self.result_path(exposure_id), "r") as f:
            return int(f["entry/slices/image"].shape[0]) if "entry/slices" in f else 0

    def slice_info(self, exposure_id: str) -> tuple[np.ndarray, int]:
        """The ``alpha`` of each kept slice and their binning (empty and 1 if none were kept)."""
        with h5py.File(self.result_path(exposure_id), "r") as f:
            if "entry/slices" not in f:
                return np.empty(0), 1
            return f["entry/slices/alpha"][()], int(f["entry/slices"].attrs.get("binning", 1))

    def read_slice(self, exposure_id: str, index: int) -> tuple[float, np.ndarray, int] | None:
        """``(alpha, image, binning)`` of one kept slice, or None; ``binning`` is output-image
        pixels per slice pixel."""
        with h5py.File(self.result_path(exposure_id), "r") as f:
            if "entry/slices" not in f or not 0 <= index < f["entry/slices/image"].shape[0]:
                return None
            slices = f["entry/slices"]
            return float(slices["alpha"][index]), slices["image"][index], int(slices.attrs.get("binning", 1))

    # -- run files -------------------------------------------------------------------

    def run_path(self, run: str) -> Path:
        return self.runs_dir / f"{run}.nxs"

    def _run_lock(self, run: str) -> threading.Lock:
        with self._locks_lock:
            return self._run_locks.setdefault(run, threading.Lock())

    @contextmanager
    def run_guard(self, run: str) -> Iterator[None]:
        """Hold a run file: a thread lock within this process, an ``flock`` across processes
        sharing the data folder (a run file is changed in place, so writers must not overlap)."""
        with self._run_lock(run):
            fd = os.open(self.runs_dir / f".{run}.lock", os.O_CREAT | os.O_RDWR, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX)
                yield
            finally:
                os.close(fd)  # releases the flock

    def update_run_file(self, record: ExposureRecord, output: JobOutput | None) -> str:
        """Put one exposure's rows into its run file (replacing earlier ones), or remove them.

        Idempotent: a job that runs again after a crash replaces its own rows. The next frame
        of a run is appended in place, at a cost that does not grow with the run; see
        :mod:`service.run_file` for the rest. Returns how the file was changed
        (``"in place"``, ``"rewritten"``, ``"rebuilt"``).
        """
        rows = None if output is None else with_track_columns(run_file.frame_rows(output.columns, record.frame))
        with self.run_guard(record.run):
            return run_file.put_frame(self.run_path(record.run), record.run, record.frame, record.id, rows,
                                      output.parameters if output is not None else {},
                                      lambda: self.rebuilt_run(record.run))

    @contextmanager
    def _repaired_run(self, run: str) -> Iterator[Path | None]:
        """Hold a run file, repaired first if a crash left it half-written or damaged; yields its
        path, or None if the run has no file."""
        path = self.run_path(run)
        if not path.exists() and not run_file.marker_path(path).exists():
            yield None
            return
        with self.run_guard(run):
            run_file.repair(path, run, lambda: self.rebuilt_run(run))
            yield path if path.exists() else None

    def read_run_columns(self, run: str) -> dict[str, np.ndarray] | None:
        """All particles of a run with a ``frame`` column, or None for an unknown run."""
        with self._repaired_run(run) as path:
            return None if path is None else run_file.read_run_table(path)

    def read_run_frames(self, run: str, first: int = 0, last: int | None = None) -> dict[str, np.ndarray] | None:
        """The rows of frames ``first`` ... ``last`` of a run (at the cost of those rows), or None
        for a run without a file."""
        with self._repaired_run(run) as path:
            return None if path is None else run_file.read_frames(path, first, last)

    def run_file_snapshot(self, run: str) -> Path | None:
        """A private copy of the run file for serving (appends change the file in place), or
        None if the run has none yet. The caller deletes it."""
        with self._repaired_run(run) as path:
            if path is None:
                return None
            fd, name = tempfile.mkstemp(prefix=f".{run}.", suffix=".nxs", dir=self.cache_dir)
            os.close(fd)
            copy = Path(name)
            try:
                run_file.copy_run_file(path, copy)
            except BaseException:
                copy.unlink(missing_ok=True)
                raise
            return copy

    def rebuilt_run(self, run: str) -> run_file.RunContents:
        """:meth:`run_from_results`, telling :attr:`on_run_rebuilt` (its trajectories must be linked again)."""
        contents = self.run_from_results(run)
        if self.on_run_rebuilt is not None:
            self.on_run_rebuilt(run)
        return contents

    def run_from_results(self, run: str) -> run_file.RunContents:
        """A run as its indexed result files record it: what a damaged run file is rebuilt from."""
        rows = self.db.read("SELECT exposure_id, frame FROM results WHERE run = ? ORDER BY frame", (run,))
        tables, exposures = [], []
        for row in rows:
            try:
                columns = self.read_columns(row["exposure_id"])
                parameters = self.read_parameters(row["exposure_id"])
            except (OSError, KeyError, ValueError) as exc:
                log.warning("run %s: the result of frame %d (%s) cannot be read (%s); the run file will "
                            "lack it until the exposure is processed again", run, row["frame"],
                            row["exposure_id"], exc)
                continue
            table = with_track_columns(run_file.frame_rows(columns, row["frame"]))
            tables.append(table)
            exposures.append({"id": row["exposure_id"], "frame": row["frame"], "particles": len(table["frame"]),
                              "parameters": parameters})
        return run_file.RunContents(run_file.concat_tables(tables), exposures)

    def runs(self) -> list[dict]:
        """Each run with its exposure count and job states."""
        rows = self.db.read(
            "SELECT e.run AS run, COUNT(*) AS exposures, "
            "SUM(j.state = 'done') AS done, SUM(j.state = 'failed') AS failed, "
            "SUM(j.state IN ('queued', 'running')) AS pending, MAX(e.created_at) AS last "
            "FROM exposures e LEFT JOIN jobs j ON j.exposure_id = e.id "
            "GROUP BY e.run ORDER BY last DESC")
        return [{"run": r["run"], "exposures": r["exposures"], "done": r["done"] or 0,
                 "failed": r["failed"] or 0, "pending": r["pending"] or 0, "last": r["last"]}
                for r in rows]

    def run_exposures(self, run: str, *, limit: int = 50, offset: int = 0,
                      newest_first: bool = False) -> tuple[list[dict], int]:
        """One page of a run's exposures with their latest job and particle count, by frame;
        and how many the run has."""
        total = self.db.read("SELECT COUNT(*) AS n FROM exposures WHERE run = ?", (run,))[0]["n"]
        order = "DESC" if newest_first else "ASC"
        rows = self.db.read(
            "SELECT e.id, e.frame, e.source, e.created_at, j.id AS job_id, j.state, j.progress, "
            "j.error, r.particles FROM exposures e "
            "LEFT JOIN jobs j ON j.seq = (SELECT MAX(seq) FROM jobs WHERE exposure_id = e.id) "
            f"LEFT JOIN results r ON r.exposure_id = e.id WHERE e.run = ? ORDER BY e.frame {order} "
            "LIMIT ? OFFSET ?", (run, limit, offset))
        return [dict(r) for r in rows], total

    # -- calibrations ----------------------------------------------------------------

    def calibration_dir(self, serial: str) -> Path:
        return self.calibrations_dir / _safe_name(serial)

    def calibration_serials(self) -> list[dict]:
        return [dict(r) for r in self.db.read("SELECT * FROM calibrations ORDER BY serial")]

    def has_calibration(self, serial: str) -> bool:
        return bool(self.db.read("SELECT 1 FROM calibrations WHERE serial = ?", (serial,)))

    def adopt_calibration(self, serial: str, folder: Path, *, source: str) -> Path:
        """Move the white-image files of ``folder`` (on the data disk) into the camera's folder."""
        target = self.calibration_dir(serial)
        target.mkdir(parents=True, exist_ok=True)
        # File by file, so a job reading white images already there never sees a gap.
        for path in sorted(Path(folder).iterdir()):
            if path.is_file():
                os.replace(path, target / _safe_name(path.name))
        self.index_calibration(serial, source=source)
        return target

    def index_calibration(self, serial: str, *, source: str) -> None:
        folder = self.calibration_dir(serial)
        count = sum(1 for p in folder.iterdir() if p.is_file() and not p.name.startswith("."))
        with self.db.write() as conn:
            conn.execute(
                "INSERT INTO calibrations (serial, path, images, source, created_at) VALUES (?, ?, ?, ?, ?) "
                "ON CONFLICT (serial) DO UPDATE SET path = excluded.path, images = excluded.images, "
                "source = excluded.source, created_at = excluded.created_at",
                (serial, str(folder.relative_to(self.data_dir)), count, source, time.time()))


#: Trajectory columns of a run file's rows before their frame is linked (service.tracking).
TRACK_COLUMNS = {"particle": (-1, np.int64), "t": (np.nan, np.float64), "vX": (np.nan, np.float64),
                 "vY": (np.nan, np.float64), "vZ": (np.nan, np.float64)}


def with_track_columns(rows: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A frame's rows with the trajectory columns (``particle`` -1, ``t`` and velocities NaN) where
    they lack them; a per-exposure table's own ``particle`` (the row number of older results) is
    its ``index``."""
    n = len(rows["frame"])
    out = dict(rows)
    if "particle" in out and "index" not in out:
        out["index"] = out.pop("particle")
    for name, (fill, dtype) in TRACK_COLUMNS.items():
        out.setdefault(name, np.full(n, fill, dtype))
    return out


def _safe_name(name: str) -> str:
    cleaned = "".join(c if c.isalnum() or c in "._-" else "_" for c in name)
    return cleaned.lstrip(".") or "unnamed"
