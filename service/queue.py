"""A durable job queue in SQLite: atomic claims, leases with heartbeats, re-queueing.

A job is claimed by one owner at a time: the claim is one ``UPDATE ... RETURNING`` in a
``BEGIN IMMEDIATE`` transaction, so two workers can never claim the same job. The owner
keeps the lease alive with heartbeats; when a lease expires (its process died), the job
goes back to the queue. A job only becomes ``done`` through the owner that holds its
lease, so a result is recorded exactly once even if a job ran twice.
"""

from __future__ import annotations

import os
import socket
import sqlite3
import time
import uuid
from collections.abc import Callable
from dataclasses import dataclass

from service.database import Database

STATES = ("queued", "running", "done", "failed")
_HOST = socket.gethostname()


class QueueFull(Exception):
    """The queue holds as many unfinished jobs as it may; try again later."""

    def __init__(self, depth: int, capacity: int, retry_after_s: int) -> None:
        super().__init__(f"the queue is full ({depth} of {capacity} jobs waiting or running); "
                         f"retry after {retry_after_s} s")
        self.depth = depth
        self.capacity = capacity
        self.retry_after_s = retry_after_s


@dataclass(frozen=True)
class Job:
    """One row of the queue."""

    id: str
    exposure_id: str
    state: str
    progress: float
    error: str | None
    attempts: int
    lease_owner: str | None
    lease_expires: float | None
    created_at: float
    started_at: float | None
    finished_at: float | None
    waits_for: str | None = None
    stage: str | None = None

    @classmethod
    def from_row(cls, row: sqlite3.Row) -> Job:
        return cls(**{name: row[name] for name in cls.__dataclass_fields__})

    def public(self) -> dict:
        """The fields the API shows (:class:`service.models.Job`)."""
        return {"id": self.id, "exposure_id": self.exposure_id, "state": self.state,
                "progress": self.progress, "stage": self.stage, "error": self.error,
                "waits_for": self.waits_for, "attempts": self.attempts,
                "created_at": self.created_at, "started_at": self.started_at,
                "finished_at": self.finished_at}


def make_owner(tag: str = "") -> str:
    """A lease owner name: host, process id and a random part (``host:pid:hex``)."""
    return f"{_HOST}:{os.getpid()}:{uuid.uuid4().hex[:8]}{tag}"


def _owner_is_dead_local_process(owner: str) -> bool:
    # A lease held by a process of this host that no longer exists can be taken back
    # at once instead of waiting for it to expire (the SIGKILL-and-restart case).
    host, _, rest = owner.partition(":")
    pid_text = rest.partition(":")[0]
    if host != _HOST or not pid_text.isdigit():
        return False
    pid = int(pid_text)
    if pid == os.getpid():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return True
    except PermissionError:
        return False
    return False


class JobQueue:
    """Jobs in the ``jobs`` table of a :class:`Database`.

    Parameters
    ----------
    db : Database
        Where the jobs live.
    capacity : int
        Most jobs queued or running at once; :meth:`enqueue` raises :class:`QueueFull` beyond.
    lease_s : float
        How long a claim lasts without a heartbeat.
    max_attempts : int
        Claims a job may have before a lost lease marks it failed instead of queued.
    retry_after_s : int
        What :class:`QueueFull` tells clients to wait.
    """

    def __init__(self, db: Database, *, capacity: int = 64, lease_s: float = 30.0,
                 max_attempts: int = 3, retry_after_s: int = 2,
                 clock: Callable[[], float] = time.time) -> None:
        self.db = db
        self.capacity = capacity
        self.lease_s = lease_s
        self.max_attempts = max_attempts
        self.retry_after_s = retry_after_s
        self.clock = clock

    # -- producers -------------------------------------------------------------------

    def enqueue(self, conn: sqlite3.Connection, exposure_id: str) -> Job:
        """Add a job for ``exposure_id`` inside the caller's write transaction.

        Raises
        ------
        QueueFull
            When ``capacity`` jobs are already queued or running.
        """
        depth = conn.execute("SELECT COUNT(*) FROM jobs WHERE state IN ('queued', 'running')").fetchone()[0]
        if depth >= self.capacity:
            raise QueueFull(depth, self.capacity, self.retry_after_s)
        job_id = uuid.uuid4().hex[:16]
        row = conn.execute(
            "INSERT INTO jobs (id, exposure_id, state, created_at) VALUES (?, ?, 'queued', ?) RETURNING *",
            (job_id, exposure_id, self.clock())).fetchone()
        return Job.from_row(row)

    def retry(self, conn: sqlite3.Connection, job_id: str, *, check_room: bool = True) -> Job | None:
        """Queue a failed job again, inside the caller's transaction; None if it had not failed.

        Raises
        ------
        QueueFull
            When ``check_room`` and ``capacity`` jobs are already queued or running.
        """
        state = conn.execute("SELECT state FROM jobs WHERE id = ?", (job_id,)).fetchone()
        if state is None or state["state"] != "failed":
            return None
        if check_room:
            depth = conn.execute("SELECT COUNT(*) FROM jobs WHERE state IN ('queued', 'running')").fetchone()[0]
            if depth >= self.capacity:
                raise QueueFull(depth, self.capacity, self.retry_after_s)
        row = conn.execute(
            "UPDATE jobs SET state = 'queued', attempts = 0, error = NULL, waits_for = NULL, stage = NULL, "
            "progress = 0, started_at = NULL, finished_at = NULL WHERE id = ? AND state = 'failed' RETURNING *",
            (job_id,)).fetchone()
        return Job.from_row(row) if row is not None else None

    def retry_waiting(self, waits_for: str, *, serial: str | None = None) -> list[Job]:
        """Queue again every failed job that waits for ``waits_for`` (``calibration`` or ``space``).

        With ``serial``, only the jobs of exposures of that camera, or of no known camera, run
        again (the white images of one camera help no other). Jobs that failed for want of white
        images before failures were classified (their error names the analysis' exception)
        count too.
        """
        where = "j.waits_for = ?"
        params: list = [waits_for]
        if waits_for == "calibration":
            where = ("(j.waits_for = ? OR j.error LIKE 'NoWhiteImageError%' OR j.error LIKE "
                     "'CameraMismatchError%')")
            if serial is not None:
                where += " AND (e.serial IS NULL OR e.serial = ?)"
                params.append(serial)
        with self.db.write() as conn:
            ids = [r["id"] for r in conn.execute(
                f"SELECT j.id FROM jobs j JOIN exposures e ON e.id = j.exposure_id "
                f"WHERE j.state = 'failed' AND {where} ORDER BY j.seq", params)]
            return [job for job_id in ids if (job := self.retry(conn, job_id, check_room=False))]

    def waiting(self, waits_for: str) -> int:
        """How many failed jobs wait for ``waits_for``."""
        return self.db.read("SELECT COUNT(*) AS n FROM jobs WHERE state = 'failed' AND waits_for = ?",
                            (waits_for,))[0]["n"]

    # -- consumers -------------------------------------------------------------------

    def claim(self, owner: str) -> Job | None:
        """Take the oldest queued job for ``owner``, or None when there is none."""
        now = self.clock()
        with self.db.write() as conn:
            row = conn.execute(
                "UPDATE jobs SET state = 'running', lease_owner = ?, lease_expires = ?, "
                "attempts = attempts + 1, started_at = ?, progress = 0, stage = NULL, error = NULL, "
                "waits_for = NULL "
                "WHERE id = (SELECT id FROM jobs WHERE state = 'queued' ORDER BY seq LIMIT 1) "
                "RETURNING *", (owner, now + self.lease_s, now)).fetchone()
        return Job.from_row(row) if row is not None else None

    def heartbeat(self, job_id: str, owner: str, *, progress: float | None = None,
                  stage: str | None = None) -> bool:
        """Extend the lease (and record progress and stage); False when the lease was lost."""
        with self.db.write() as conn:
            if progress is None:
                cur = conn.execute(
                    "UPDATE jobs SET lease_expires = ? WHERE id = ? AND lease_owner = ? AND state = 'running'",
                    (self.clock() + self.lease_s, job_id, owner))
            else:
                cur = conn.execute(
                    "UPDATE jobs SET lease_expires = ?, progress = ?, stage = COALESCE(?, stage) "
                    "WHERE id = ? AND lease_owner = ? AND state = 'running'",
                    (self.clock() + self.lease_s, float(progress), stage, job_id, owner))
            return cur.rowcount == 1

    def complete(self, conn: sqlite3.Connection, job_id: str, owner: str) -> bool:
        """Mark the job done inside the caller's transaction; False if ``owner`` lost the lease."""
        cur = conn.execute(
            "UPDATE jobs SET state = 'done', progress = 1, lease_owner = NULL, lease_expires = NULL, "
            "finished_at = ? WHERE id = ? AND lease_owner = ? AND state = 'running'",
            (self.clock(), job_id, owner))
        return cur.rowcount == 1

    def fail(self, job_id: str, owner: str, error: str, *, waits_for: str | None = None) -> bool:
        """Mark the job failed; False if the lease was lost.

        ``waits_for`` names what would let it run (``calibration``, ``space``): such a job is
        queued again by :meth:`retry_waiting` when that arrives. Without it the input is at fault.
        """
        with self.db.write() as conn:
            cur = conn.execute(
                "UPDATE jobs SET state = 'failed', error = ?, waits_for = ?, lease_owner = NULL, "
                "lease_expires = NULL, finished_at = ? WHERE id = ? AND lease_owner = ? AND state = 'running'",
                (error, waits_for, self.clock(), job_id, owner))
            return cur.rowcount == 1

    def release(self, job_id: str, owner: str, error: str) -> str | None:
        """Give a job back after a failure that was not its input's fault.

        Returns the new state (``queued``, or ``failed`` after ``max_attempts``), or None
        when ``owner`` no longer held the lease.
        """
        with self.db.write() as conn:
            row = conn.execute(
                "UPDATE jobs SET state = CASE WHEN attempts >= ? THEN 'failed' ELSE 'queued' END, "
                "error = ?, lease_owner = NULL, lease_expires = NULL, "
                "finished_at = CASE WHEN attempts >= ? THEN ? ELSE NULL END "
                "WHERE id = ? AND lease_owner = ? AND state = 'running' RETURNING state",
                (self.max_attempts, error, self.max_attempts, self.clock(), job_id, owner)).fetchone()
        return row["state"] if row is not None else None

    def requeue_expired(self) -> list[Job]:
        """Put back every running job whose lease expired or whose local owner died.

        Jobs already claimed ``max_attempts`` times are marked failed instead, so an
        exposure that kills its worker cannot loop forever. Returns the jobs changed.
        """
        now = self.clock()
        changed: list[Job] = []
        with self.db.write() as conn:
            rows = conn.execute("SELECT id, lease_owner, lease_expires, attempts FROM jobs "
                                "WHERE state = 'running'").fetchall()
            for row in rows:
                expired = row["lease_expires"] is None or row["lease_expires"] < now
                if not expired and not _owner_is_dead_local_process(row["lease_owner"] or ""):
                    continue
                if row["attempts"] >= self.max_attempts:
                    new = conn.execute(
                        "UPDATE jobs SET state = 'failed', lease_owner = NULL, lease_expires = NULL, "
                        "finished_at = ?, error = ? WHERE id = ? RETURNING *",
                        (now, f"gave up after {row['attempts']} attempts: the worker stopped "
                              "without finishing each time", row["id"])).fetchone()
                else:
                    new = conn.execute(
                        "UPDATE jobs SET state = 'queued', lease_owner = NULL, lease_expires = NULL, "
                        "progress = 0 WHERE id = ? RETURNING *", (row["id"],)).fetchone()
                changed.append(Job.from_row(new))
        return changed

    # -- readers ---------------------------------------------------------------------

    def get(self, job_id: str) -> Job | None:
        rows = self.db.read("SELECT * FROM jobs WHERE id = ?", (job_id,))
        return Job.from_row(rows[0]) if rows else None

    def for_exposure(self, exposure_id: str) -> Job | None:
        """The latest job of an exposure."""
        rows = self.db.read("SELECT * FROM jobs WHERE exposure_id = ? ORDER BY seq DESC LIMIT 1",
                            (exposure_id,))
        return Job.from_row(rows[0]) if rows else None

    def list(self, *, state: str | None = None, limit: int = 50, offset: int = 0) -> tuple[list[Job], int]:
        """One page of jobs, newest first, and the total count."""
        where, params = ("WHERE state = ?", (state,)) if state else ("", ())
        total = self.db.read(f"SELECT COUNT(*) AS n FROM jobs {where}", params)[0]["n"]
        rows = self.db.read(f"SELECT * FROM jobs {where} ORDER BY seq DESC LIMIT ? OFFSET ?",
                            (*params, limit, offset))
        return [Job.from_row(r) for r in rows], total

    def check_room(self) -> None:
        """Raise :class:`QueueFull` now if the queue is full (a cheap early answer; the
        authoritative check is in :meth:`enqueue`)."""
        depth = self.db.read("SELECT COUNT(*) AS n FROM jobs WHERE state IN ('queued', 'running')")[0]["n"]
        if depth >= self.capacity:
            raise QueueFull(depth, self.capacity, self.retry_after_s)

    def depth(self) -> dict[str, int]:
        """Number of jobs in each state."""
        counts = dict.fromkeys(STATES, 0)
        for row in self.db.read("SELECT state, COUNT(*) AS n FROM jobs GROUP BY state"):
            counts[row["state"]] = row["n"]
        return counts
