"""Storage under one data folder: raw exposures by SHA-1, results, NeXus run files, index.

Layout::

    DATA/plenodust.sqlite                 queue and index (see service.database)
    DATA/raw/ab/<sha1>.lfp                an uploaded .lfp, or
    DATA/raw/ab/<sha1>.RAW, .TXT          a camera .RAW + .TXT pair
    DATA/results/ab/<sha1>.h5             one exposure's particle table, curves, slices
    DATA/runs/<run>.nxs                   every exposure of a run (NeXus: NXentry/NXdata)
    DATA/calibrations/<serial>/MOD_*      white images per camera
    DATA/cache/                           calibration cache

Every file is written to a temporary name and renamed into place, so a crash leaves
either the old file or the new one.
"""

from __future__ import annotations

import json
import os
import sqlite3
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from analysis.atomic_write import atomic_path, write_all_atomic
from analysis.particle_table import UNITS
from service.database import Database
from service.results import JobOutput


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
        for folder in (self.raw_dir, self.results_dir, self.runs_dir, self.calibrations_dir, self.cache_dir):
            folder.mkdir(parents=True, exist_ok=True)
        # One writer per run file at a time within this process.
        self._run_locks: dict[str, threading.Lock] = {}
        self._locks_lock = threading.Lock()

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

    def register(self, conn: sqlite3.Connection, exposure_id: str, *, run: str, kind: str,
                 source: str, serial: str | None) -> tuple[ExposureRecord, bool]:
        """Index an exposure inside the caller's transaction; ``(record, created)``.

        An exposure already known keeps its run and frame (same bytes, same exposure).
        """
        row = conn.execute("SELECT * FROM exposures WHERE id = ?", (exposure_id,)).fetchone()
        if row is not None:
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
                f.attrs["default"] = "entry"
                f.attrs["creator"] = "plenodust"
                entry = nx_group(f, "entry", "NXentry")
                entry.attrs["default"] = "data"
                entry["title"] = record.id
                entry["run"] = record.run
                entry["frame"] = record.frame
                write_table(nx_group(entry, "data", "NXdata"), output.columns)
                _write_process(entry, output.parameters)
                if "provenance" in output.extra:
                    entry["process"]["provenance"] = json.dumps(output.extra["provenance"], default=str)
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
            return read_table(f["entry/data"])

    def read_parameters(self, exposure_id: str) -> dict:
        with h5py.File(self.result_path(exposure_id), "r") as f:
            return json.loads(f["entry/process/parameters"][()].decode())

    def read_provenance(self, exposure_id: str) -> dict:
        """Timings, warnings, calibration used: what the pipeline reported beside the table."""
        with h5py.File(self.result_path(exposure_id), "r") as f:
            if "entry/process/provenance" not in f:
                return {}
            return json.loads(f["entry/process/provenance"][()].decode())

    def read_curves(self, exposure_id: str) -> tuple[np.ndarray, np.ndarray] | None:
        """``(alpha, brightness)`` of shape (A,), (N, A), or None if not kept."""
        with h5py.File(self.result_path(exposure_id), "r") as f:
            if "entry/curves" not in f:
                return None
            return f["entry/curves/alpha"][()], f["entry/curves/brightness"][()]

    def slice_count(self, exposure_id: str) -> int:
        with h5py.File(self.result_path(exposure_id), "r") as f:
            return int(f["entry/slices/image"].shape[0]) if "entry/slices" in f else 0

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

    def update_run_file(self, record: ExposureRecord, output: JobOutput | None) -> None:
        """Put one exposure's rows into its run file (replacing earlier ones), or remove them.

        Idempotent: a job that runs again after a crash replaces its own rows.
        """
        with self._run_lock(record.run):
            path = self.run_path(record.run)
            table, exposures = _read_run(path) if path.exists() else ({}, [])
            keep = table.get("frame", np.zeros(0, np.int64)) != record.frame
            table = {name: column[keep] for name, column in table.items()}
            exposures = [e for e in exposures if e["frame"] != record.frame]
            if output is not None:
                rows = dict(output.columns)
                rows["frame"] = np.full(output.particles, record.frame, dtype=np.int64)
                table = _concat_tables(table, rows)
                exposures.append({"id": record.id, "frame": record.frame, "particles": output.particles,
                                  "parameters": output.parameters})
                exposures.sort(key=lambda e: e["frame"])
            order = np.argsort(table["frame"], kind="stable") if "frame" in table else None
            if order is not None:
                table = {name: column[order] for name, column in table.items()}
            with atomic_path(path) as tmp:
                _write_run(tmp, record.run, table, exposures)

    def read_run_columns(self, run: str) -> dict[str, np.ndarray] | None:
        """All particles of a run with a ``frame`` column, or None for an unknown run."""
        path = self.run_path(run)
        if not path.exists():
            return None
        with self._run_lock(run):
            return _read_run(path)[0]

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

    def run_exposures(self, run: str) -> list[dict]:
        """Exposures of a run with their latest job and particle count, by frame."""
        rows = self.db.read(
            "SELECT e.id, e.frame, e.source, e.created_at, j.id AS job_id, j.state, j.progress, "
            "j.error, r.particles FROM exposures e "
            "LEFT JOIN jobs j ON j.seq = (SELECT MAX(seq) FROM jobs WHERE exposure_id = e.id) "
            "LEFT JOIN results r ON r.exposure_id = e.id WHERE e.run = ? ORDER BY e.frame", (run,))
        return [dict(r) for r in rows]

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


def _safe_name(name: str) -> str:
    cleaned = "".join(c if c.isalnum() or c in "._-" else "_" for c in name)
    return cleaned.lstrip(".") or "unnamed"


def nx_group(parent: h5py.Group, name: str, nx_class: str) -> h5py.Group:
    group = parent.create_group(name)
    group.attrs["NX_class"] = nx_class
    return group


def write_table(group: h5py.Group, columns: Mapping[str, np.ndarray]) -> None:
    names = list(columns)
    group.attrs["signal"] = "Z" if "Z" in columns else (names[0] if names else "")
    group.attrs["columns"] = json.dumps(names)
    for name in names:
        data = np.asarray(columns[name])
        if data.dtype.kind == "U":
            data = data.astype(object)
            ds = group.create_dataset(name, data=data, dtype=h5py.string_dtype())
        else:
            ds = group.create_dataset(name, data=data)
        if name in UNITS:
            ds.attrs["units"] = UNITS[name]


def read_table(group: h5py.Group) -> dict[str, np.ndarray]:
    names = json.loads(group.attrs["columns"])
    out = {}
    for name in names:
        data = group[name][()]
        if data.dtype.kind == "O":
            data = np.array([v.decode() if isinstance(v, bytes) else v for v in data], dtype=str)
        out[name] = data
    return out


def _write_process(entry: h5py.Group, parameters: dict) -> None:
    process = nx_group(entry, "process", "NXprocess")
    process["program"] = "plenodust"
    from importlib.metadata import PackageNotFoundError, version
    try:
        process["version"] = version("plenodust")
    except PackageNotFoundError:
        process["version"] = "unknown"
    process["parameters"] = json.dumps(parameters, sort_keys=True, default=str)


def _concat_tables(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    if not a:
        return {k: np.asarray(v) for k, v in b.items()}
    n_a = len(next(iter(a.values())))
    n_b = len(next(iter(b.values()))) if b else 0
    names = list(a) + [k for k in b if k not in a]
    out = {}
    for name in names:
        parts = []
        for table, n in ((a, n_a), (b, n_b)):
            if name in table:
                parts.append(np.asarray(table[name]))
            else:
                # A column one frame lacks is missing data there, not zero.
                parts.append(np.full(n, np.nan))
        out[name] = np.concatenate(parts)
    return out


def _write_run(path: Path, run: str, table: dict[str, np.ndarray], exposures: list[dict]) -> None:
    with h5py.File(path, "w") as f:
        f.attrs["default"] = "entry"
        f.attrs["creator"] = "plenodust"
        entry = nx_group(f, "entry", "NXentry")
        entry.attrs["default"] = "data"
        entry["title"] = run
        write_table(nx_group(entry, "data", "NXdata"), table)
        _write_process(entry, exposures[-1]["parameters"] if exposures else {})
        coll = nx_group(entry, "exposures", "NXcollection")
        coll.create_dataset("id", data=np.array([e["id"] for e in exposures], dtype="S40"))
        coll.create_dataset("frame", data=np.array([e["frame"] for e in exposures], dtype=np.int64))
        coll.create_dataset("particles", data=np.array([e["particles"] for e in exposures], dtype=np.int64))
        coll.create_dataset("parameters", data=np.array(
            [json.dumps(e["parameters"], sort_keys=True, default=str) for e in exposures], dtype=object),
            dtype=h5py.string_dtype())


def _read_run(path: Path) -> tuple[dict[str, np.ndarray], list[dict]]:
    with h5py.File(path, "r") as f:
        table = read_table(f["entry/data"])
        coll = f["entry/exposures"]
        exposures = [{"id": i.decode(), "frame": int(fr), "particles": int(n), "parameters": json.loads(p)}
                     for i, fr, n, p in zip(coll["id"][()], coll["frame"][()], coll["particles"][()],
                                            coll["parameters"][()], strict=True)]
    return table, exposures
