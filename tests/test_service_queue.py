"""The SQLite job queue: atomic claims under threads, leases, heartbeats, re-queueing, capacity."""

from __future__ import annotations

import subprocess
import sys
import threading
from pathlib import Path

import pytest

from service.database import Database
from service.queue import JobQueue, QueueFull, make_owner


class Clock:
    """A settable clock, so lease expiry is tested without waiting."""

    def __init__(self) -> None:
        self.now = 1_000_000.0

    def __call__(self) -> float:
        return self.now


def _exposure(db: Database, exposure_id: str) -> None:
    with db.write() as conn:
        conn.execute("INSERT INTO exposures (id, run, frame, kind, source, created_at) VALUES (?, 'r', "
                     "(SELECT COALESCE(MAX(frame) + 1, 0) FROM exposures), 'lfp', 'upload', 0)", (exposure_id,))


def _enqueue(queue: JobQueue, exposure_id: str):
    _exposure(queue.db, exposure_id)
    with queue.db.write() as conn:
        return queue.enqueue(conn, exposure_id)


@pytest.fixture
def db(tmp_path: Path) -> Database:
    database = Database(tmp_path / "q.sqlite")
    yield database
    database.close()


def test_database_uses_wal(db: Database) -> None:
    assert db.read("PRAGMA journal_mode")[0][0] == "wal"
    assert db.writable()


def test_each_job_is_claimed_by_exactly_one_of_many_threads(db: Database) -> None:
    queue = JobQueue(db, capacity=1000)
    ids = {_enqueue(queue, f"e{i:03d}").id for i in range(120)}
    claimed: list[tuple[str, str]] = []
    lock = threading.Lock()
    start = threading.Barrier(8)

    def worker() -> None:
        owner = make_owner()
        start.wait()
        while (job := queue.claim(owner)) is not None:
            with lock:
                claimed.append((job.id, owner))

    threads = [threading.Thread(target=worker) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sorted(j for j, _ in claimed) == sorted(ids)  # every job once, none twice
    assert len({owner for _, owner in claimed}) > 1
    assert queue.depth()["running"] == 120


def test_claim_takes_the_oldest_job_first(db: Database) -> None:
    queue = JobQueue(db)
    first = _enqueue(queue, "a")
    _enqueue(queue, "b")
    assert queue.claim("o").id == first.id


def test_expired_lease_goes_back_to_the_queue_and_the_old_owner_cannot_finish(db: Database) -> None:
    clock = Clock()
    queue = JobQueue(db, lease_s=10, clock=clock)
    job = _enqueue(queue, "a")
    assert queue.claim("dead-worker").id == job.id
    clock.now += 5
    assert queue.requeue_expired() == []          # lease still valid
    clock.now += 6
    [back] = queue.requeue_expired()
    assert back.state == "queued" and back.attempts == 1
    assert not queue.heartbeat(job.id, "dead-worker")
    again = queue.claim("live-worker")
    assert again.id == job.id and again.attempts == 2
    with db.write() as conn:
        assert not queue.complete(conn, job.id, "dead-worker")
    with db.write() as conn:
        assert queue.complete(conn, job.id, "live-worker")
    assert queue.get(job.id).state == "done"


def test_heartbeats_keep_a_lease_alive(db: Database) -> None:
    clock = Clock()
    queue = JobQueue(db, lease_s=10, clock=clock)
    job = _enqueue(queue, "a")
    queue.claim("w")
    for _ in range(5):
        clock.now += 8
        assert queue.heartbeat(job.id, "w", progress=0.5)
        assert queue.requeue_expired() == []
    assert queue.get(job.id).progress == 0.5


def test_a_job_that_keeps_losing_its_worker_fails_after_max_attempts(db: Database) -> None:
    clock = Clock()
    queue = JobQueue(db, lease_s=1, max_attempts=2, clock=clock)
    job = _enqueue(queue, "a")
    for expected in ("queued", "failed"):
        queue.claim("w")
        clock.now += 2
        [changed] = queue.requeue_expired()
        assert changed.state == expected
    assert "2 attempts" in queue.get(job.id).error
    assert queue.claim("w") is None


def test_release_requeues_then_fails(db: Database) -> None:
    queue = JobQueue(db, max_attempts=2)
    job = _enqueue(queue, "a")
    queue.claim("w")
    assert queue.release(job.id, "w", "disk full") == "queued"
    queue.claim("w")
    assert queue.release(job.id, "w", "disk full") == "failed"
    assert queue.release(job.id, "w", "again") is None  # no lease any more


def test_a_lease_of_a_dead_local_process_is_taken_back_at_once(db: Database) -> None:
    queue = JobQueue(db, lease_s=3600)
    job = _enqueue(queue, "a")
    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child.wait()
    host = make_owner().split(":")[0]
    queue.claim(f"{host}:{child.pid}:deadbeef")
    [back] = queue.requeue_expired()
    assert back.id == job.id and back.state == "queued"
    # A live process keeps its lease.
    queue.claim(make_owner())
    assert queue.requeue_expired() == []


def test_full_queue_refuses_and_says_when_to_retry(db: Database) -> None:
    queue = JobQueue(db, capacity=2, retry_after_s=7)
    _enqueue(queue, "a")
    _enqueue(queue, "b")
    _exposure(db, "c")
    with pytest.raises(QueueFull):
        queue.check_room()
    with pytest.raises(QueueFull) as info, db.write() as conn:
        queue.enqueue(conn, "c")
    assert info.value.retry_after_s == 7
    # A finished job frees its place.
    job = queue.claim("w")
    with db.write() as conn:
        queue.complete(conn, job.id, "w")
    queue.check_room()
    with db.write() as conn:
        assert queue.enqueue(conn, "c").state == "queued"


def test_list_pages_and_filters(db: Database) -> None:
    queue = JobQueue(db)
    for i in range(5):
        _enqueue(queue, f"e{i}")
    queue.claim("w")
    page, total = queue.list(limit=2, offset=0)
    assert total == 5 and len(page) == 2
    running, n = queue.list(state="running")
    assert n == 1 and running[0].state == "running"
    assert queue.depth() == {"queued": 4, "running": 1, "done": 0, "failed": 0}


def test_a_failed_job_can_be_queued_again(db: Database) -> None:
    queue = JobQueue(db, capacity=1)
    job = _enqueue(queue, "a")
    queue.claim("w")
    queue.fail(job.id, "w", "NoWhiteImageError: no white images for camera A1")
    with db.write() as conn:
        assert queue.retry(conn, job.id).state == "queued"
    with db.write() as conn:
        assert queue.retry(conn, job.id) is None  # only failed jobs
    again = queue.claim("w")
    assert again.id == job.id and again.attempts == 1 and again.error is None
    queue.fail(job.id, "w", "NoWhiteImageError: still none")
    _enqueue(queue, "b")  # the queue is full now ...
    with pytest.raises(QueueFull), db.write() as conn:
        queue.retry(conn, job.id)
    # ... but jobs waiting for white images go back regardless, as accepted data.
    assert [j.id for j in queue.retry_waiting("calibration")] == [job.id]
    assert queue.retry_waiting("calibration") == []


def test_jobs_waiting_for_a_calibration_or_space_run_again_when_it_arrives(db: Database) -> None:
    queue = JobQueue(db, capacity=10)
    mismatch, wrong_input, full = (_enqueue(queue, name) for name in ("a", "b", "c"))
    with db.write() as conn:
        conn.execute("UPDATE exposures SET serial = 'A1' WHERE id = 'a'")
    for job, error, waits in ((mismatch, "CameraMismatchError: none of the white images is of camera", "calibration"),
                              (wrong_input, "FormatError: not a picture", None),
                              (full, "NoSpace: the data disk is full", "space")):
        queue.claim("w")
        assert queue.fail(job.id, "w", error, waits_for=waits)
    assert queue.get(mismatch.id).public()["waits_for"] == "calibration"
    assert queue.waiting("space") == 1
    # The white images of one camera re-run the jobs of that camera (or of none known), whatever
    # the analysis' error class was; never a job whose input was at fault.
    assert queue.retry_waiting("calibration", serial="OTHER") == []
    assert [j.id for j in queue.retry_waiting("calibration", serial="A1")] == [mismatch.id]
    assert [j.id for j in queue.retry_waiting("space")] == [full.id]
    assert queue.get(wrong_input.id).state == "failed"
    assert queue.get(full.id).waits_for is None
