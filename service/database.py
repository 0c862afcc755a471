"""The service's SQLite database: one file, WAL journal, one connection per thread.

The job queue (:mod:`service.queue`) and the storage index (:mod:`service.store`) share
this file so that "job done" and "result indexed" commit in one transaction.
"""

from __future__ import annotations

import sqlite3
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

SCHEMA = """
CREATE TABLE IF NOT EXISTS exposures (
    id          TEXT PRIMARY KEY,          -- SHA-1 of the uploaded bytes
    run         TEXT NOT NULL,
    frame       INTEGER NOT NULL,          -- order within the run, from 0
    kind        TEXT NOT NULL,             -- 'lfp' or 'raw'
    source      TEXT NOT NULL,             -- 'upload' or 'camera'
    serial      TEXT,                      -- camera serial from the metadata, if any
    created_at  REAL NOT NULL,
    UNIQUE (run, frame)
);
CREATE TABLE IF NOT EXISTS jobs (
    seq           INTEGER PRIMARY KEY AUTOINCREMENT,
    id            TEXT NOT NULL UNIQUE,
    exposure_id   TEXT NOT NULL REFERENCES exposures(id),
    state         TEXT NOT NULL CHECK (state IN ('queued', 'running', 'done', 'failed')),
    progress      REAL NOT NULL DEFAULT 0,
    error         TEXT,
    attempts      INTEGER NOT NULL DEFAULT 0,
    lease_owner   TEXT,
    lease_expires REAL,
    created_at    REAL NOT NULL,
    started_at    REAL,
    finished_at   REAL
);
CREATE INDEX IF NOT EXISTS jobs_state ON jobs (state, seq);
CREATE TABLE IF NOT EXISTS results (
    exposure_id  TEXT PRIMARY KEY REFERENCES exposures(id),
    run          TEXT NOT NULL,
    frame        INTEGER NOT NULL,
    particles    INTEGER NOT NULL,
    path         TEXT NOT NULL,
    created_at   REAL NOT NULL
);
CREATE INDEX IF NOT EXISTS results_run ON results (run, frame);
CREATE TABLE IF NOT EXISTS camera_pictures (
    serial       TEXT NOT NULL,
    picture      TEXT NOT NULL,
    exposure_id  TEXT,
    pulled_at    REAL NOT NULL,
    PRIMARY KEY (serial, picture)
);
CREATE TABLE IF NOT EXISTS calibrations (
    serial       TEXT PRIMARY KEY,
    path         TEXT NOT NULL,
    images       INTEGER NOT NULL,
    source       TEXT NOT NULL,            -- 'camera' or 'upload'
    created_at   REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS run_tracks (
    run          TEXT PRIMARY KEY,
    next_frame   INTEGER NOT NULL,         -- the first frame not linked yet
    next_id      INTEGER NOT NULL,         -- the next trajectory id
    t0           REAL,                     -- shot time (s since 1970) of the run's first linked frame
    last_t       REAL                      -- t (s since t0) of the last linked frame
);
CREATE TABLE IF NOT EXISTS frame_summaries (
    run          TEXT NOT NULL,
    frame        INTEGER NOT NULL,
    t            REAL,
    data         TEXT NOT NULL,            -- the shot's structure (JSON, analysis.tracking.summary)
    PRIMARY KEY (run, frame)
);
CREATE TABLE IF NOT EXISTS settings_kv (
    key    TEXT PRIMARY KEY,
    value  TEXT NOT NULL
);
"""

# Columns added after the first release: (table, column, declaration); see Database.__init__.
ADDED_COLUMNS = [
    # What a failed job waits for before it runs again by itself: 'calibration' (its camera's
    # white images) or 'space' (free space on the data disk); NULL for a failure of the input.
    ("jobs", "waits_for", "TEXT"),
    # The pipeline stage a running job is in, for the progress shown to users.
    ("jobs", "stage", "TEXT"),
    # When the raw files were removed under the raw retention setting (NULL: still kept).
    ("exposures", "raw_removed_at", "REAL"),
]


#: How long :meth:`Database.close` waits for the reads and writes under way.
CLOSE_WAIT_S = 30.0


class DatabaseClosed(sqlite3.ProgrammingError):
    """The database was used after :meth:`Database.close` (a thread outliving the service's stop)."""


class Database:
    """A SQLite file opened in WAL mode, with one connection per thread.

    Parameters
    ----------
    path : Path
        The database file; its folder is created when missing.
    busy_timeout_ms : int
        How long a writer waits for another writer's lock before giving up.
    """

    def __init__(self, path: Path, *, busy_timeout_ms: int = 10_000) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.busy_timeout_ms = busy_timeout_ms
        self._local = threading.local()
        self._all: list[sqlite3.Connection] = []
        self._lock = threading.Lock()
        self._idle = threading.Condition()  # guards _busy and _closed
        self._busy = 0                      # threads inside read() or write() now
        self._closed = False
        # executescript commits on its own; the statements are idempotent.
        self.connection().executescript(SCHEMA)
        self._add_missing_columns()

    def _add_missing_columns(self) -> None:
        # Databases made by an older version lack the columns added since; add them in place.
        conn = self.connection()
        for table, column, declaration in ADDED_COLUMNS:
            present = {row["name"] for row in conn.execute(f"PRAGMA table_info({table})")}
            if column not in present:
                conn.execute(f"ALTER TABLE {table} ADD COLUMN {column} {declaration}")

    def connection(self) -> sqlite3.Connection:
        """This thread's connection (autocommit; transactions are explicit)."""
        conn = getattr(self._local, "conn", None)
        if conn is None:
            conn = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False,
                                   timeout=self.busy_timeout_ms / 1000)
            conn.row_factory = sqlite3.Row
            conn.execute("PRAGMA journal_mode=WAL")
            # NORMAL is durable across process crashes in WAL mode; only power loss
            # can lose the last transactions.
            conn.execute("PRAGMA synchronous=NORMAL")
            conn.execute(f"PRAGMA busy_timeout={int(self.busy_timeout_ms)}")
            conn.execute("PRAGMA foreign_keys=ON")
            self._local.conn = conn
            with self._lock:
                self._all.append(conn)
        return conn

    @contextmanager
    def _in_use(self) -> Iterator[sqlite3.Connection]:
        """This thread's connection, counted as in use until the block ends (see :meth:`close`)."""
        with self._idle:
            if self._closed:
                raise DatabaseClosed(f"{self.path} is closed (the service is stopping)")
            self._busy += 1
        try:
            yield self.connection()
        finally:
            with self._idle:
                self._busy -= 1
                self._idle.notify_all()

    @contextmanager
    def write(self) -> Iterator[sqlite3.Connection]:
        """A write transaction, taken at once (``BEGIN IMMEDIATE``) so it cannot deadlock."""
        with self._in_use() as conn:
            conn.execute("BEGIN IMMEDIATE")
            try:
                yield conn
            except BaseException:
                conn.execute("ROLLBACK")
                raise
            conn.execute("COMMIT")

    def read(self, sql: str, params: tuple | dict = ()) -> list[sqlite3.Row]:
        """Rows of one query."""
        with self._in_use() as conn:
            return conn.execute(sql, params).fetchall()

    def writable(self) -> bool:
        """Whether a write transaction can be committed now (for ``/readyz``)."""
        try:
            with self.write() as conn:
                conn.execute("INSERT INTO settings_kv (key, value) VALUES ('ready_probe', '1') "
                             "ON CONFLICT (key) DO UPDATE SET value = excluded.value")
        except sqlite3.Error:
            return False
        return True

    def get_value(self, key: str) -> str | None:
        rows = self.read("SELECT value FROM settings_kv WHERE key = ?", (key,))
        return rows[0]["value"] if rows else None

    def set_value(self, key: str, value: str) -> None:
        with self.write() as conn:
            conn.execute("INSERT INTO settings_kv (key, value) VALUES (?, ?) "
                         "ON CONFLICT (key) DO UPDATE SET value = excluded.value", (key, value))

    def close(self, *, wait_s: float = CLOSE_WAIT_S) -> None:
        """Close every thread's connection, once the reads and writes under way have ended (at most
        ``wait_s``); later ones raise :class:`DatabaseClosed`.

        A thread left running by a cancelled task (a job's last write, the tracker saving a run) may
        still be inside a statement when the service stops: closing its connection under it crashed
        the process (a segmentation fault in SQLite)."""
        with self._idle:
            self._closed = True
            self._idle.wait_for(lambda: self._busy == 0, timeout=wait_s)
        with self._lock:
            for conn in self._all:
                try:
                    conn.close()
                except sqlite3.Error:
                    pass
            self._all.clear()
        self._local = threading.local()
