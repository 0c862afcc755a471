"""Accept an exposure: check it is one, store its bytes, index it and queue a job, at once."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from analysis.errors import AnalysisError
from analysis.formats.exposure import Exposure, exposure_from_lfp_bytes, exposure_from_raw_pair
from service.disk import DiskGuard
from service.queue import Job, JobQueue
from service.store import ExposureRecord, Store


# Room left for an exposure's result (table, curves, slices) besides its raw bytes.
RESULT_ALLOWANCE_BYTES = 8_000_000


class NotAnExposure(Exception):
    """The uploaded bytes are not an F01 exposure the analysis can read."""


@dataclass(frozen=True)
class Accepted:
    """The outcome of :func:`ingest`."""

    exposure: ExposureRecord
    job: Job
    created: bool
    retried: bool = False


def parse_exposure(files: Mapping[str, bytes], *, name: str | None = None) -> Exposure:
    """The exposure in ``files`` (``.lfp``, or ``.RAW`` + ``.TXT``).

    Raises
    ------
    NotAnExposure
        With the analysis' reason, when the bytes are not a readable exposure.
    """
    try:
        if ".lfp" in files:
            return exposure_from_lfp_bytes(files[".lfp"], name=name)
        return exposure_from_raw_pair(files[".RAW"], files[".TXT"], name=name)
    except AnalysisError as exc:
        raise NotAnExposure(str(exc)) from exc


def ingest(store: Store, queue: JobQueue, files: Mapping[str, bytes], *, run: str, source: str,
           serial: str | None = None, exposure: Exposure | None = None,
           guard: DiskGuard | None = None) -> Accepted:
    """Store an exposure and queue its job; the same exposure twice gives the first one back.

    Parameters
    ----------
    files : mapping
        ``{".lfp": bytes}`` or ``{".RAW": bytes, ".TXT": bytes}``.
    run : str
        Run the exposure belongs to (its frame number is its order in the run).
    source : {"upload", "camera"}
        Where it came from.
    serial : str, optional
        Camera serial when the metadata does not carry it (camera ``.TXT`` files do not).
    exposure : Exposure, optional
        The already parsed exposure, to skip parsing again.
    guard : DiskGuard, optional
        Refuses the bytes (before writing any) when they would not fit with the free-space margin.

    An exposure whose job failed is queued again (same job) when it is sent again.

    Raises
    ------
    NotAnExposure
        If the bytes are not an exposure.
    service.queue.QueueFull
        If the queue is full; nothing is indexed then (the bytes may stay on disk, keyed
        by their SHA-1, ready for the retry).
    service.disk.NoSpace
        If the data disk lacks room; nothing is written then.
    """
    exposure = exposure or parse_exposure(files)
    if guard is not None:
        # The result file and the run file's rows come later; a few MB more than the raw bytes.
        guard.require(sum(len(data) for data in files.values()) + RESULT_ALLOWANCE_BYTES, what="this exposure")
    kind = store.put_raw(exposure.sha1, files)
    retried = False
    with store.db.write() as conn:
        record, created = store.register(conn, exposure.sha1, run=run, kind=kind, source=source,
                                         serial=exposure.serial or serial)
        if created:
            job = queue.enqueue(conn, record.id)
        else:
            row = conn.execute("SELECT * FROM jobs WHERE exposure_id = ? ORDER BY seq DESC LIMIT 1",
                               (record.id,)).fetchone()
            job = Job.from_row(row)
            if job.state == "failed":
                # Sent again after a failure (e.g. once its white images are there): try again.
                job = queue.retry(conn, job.id) or job
                retried = job.state == "queued"
    return Accepted(record, job, created, retried)
