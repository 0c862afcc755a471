"""The job runner: claims jobs from the queue, runs them on the executor, stores results.

One asyncio task per worker slot, plus a reaper that puts expired leases back. A job's
result is written (result file, then run file, both idempotent) before the job is
marked done together with its index row, so a crash at any point either leaves the job
to run again or has recorded it exactly once.
"""

from __future__ import annotations

import asyncio
import logging
import time
from dataclasses import dataclass

from analysis.errors import AnalysisError, CalibrationError, CameraMismatchError
from service.disk import DiskGuard, NoSpace, is_out_of_space
from service.events import EventBus
from service.executors import Executor, WorkerLost
from service.metrics import Metrics
from service.queue import Job, JobQueue, make_owner
from service.results import JobOutput, JobTask
from service.store import ExposureRecord, Store
from service.tracking import RunTracker

log = logging.getLogger(__name__)


@dataclass
class RunnerConfig:
    slots: int = 1
    heartbeat_s: float = 5.0
    idle_poll_s: float = 0.5
    keep_slices: bool = True
    parameters: dict | None = None
    # Keep the raw files of the newest N exposures only (0: all); see Settings.raw_retention.
    raw_retention: int = 0


# Room a result needs on the data disk (table, curves, slices, run-file rows), checked first.
RESULT_BYTES = 8_000_000


def calibration_hint(serial: str | None) -> str:
    """How a user supplies a camera's white images (said in the error of a job that lacks them)."""
    camera = f"camera {serial}" if serial else "the exposure's camera"
    return (f"supply the white images of {camera}: upload them with POST /api/v1/calibrations (multipart "
            "MOD_nnnn.RAW + MOD_nnnn.TXT, or data.C.N), or connect the camera to the service (--camera "
            "usb|wifi:HOST) so it pulls them; `plenodust camera calibration --out DIR` copies them from "
            "the camera to a folder. This job runs again by itself when they arrive")


class JobRunner:
    """Runs queued jobs until stopped."""

    def __init__(self, queue: JobQueue, store: Store, executor: Executor, bus: EventBus, metrics: Metrics,
                 config: RunnerConfig | None = None, *, guard: DiskGuard | None = None,
                 tracker: RunTracker | None = None) -> None:
        self.queue = queue
        self.store = store
        self.executor = executor
        self.bus = bus
        self.metrics = metrics
        self.config = config or RunnerConfig()
        self.guard = guard
        self.tracker = tracker
        self._wake = asyncio.Event()
        self._tasks: list[asyncio.Task] = []

    def wake(self) -> None:
        """A job was queued: let an idle slot look now rather than at its next poll."""
        self._wake.set()

    def start(self) -> list[asyncio.Task]:
        self._tasks = [asyncio.create_task(self._slot(i), name=f"job-slot-{i}")
                       for i in range(self.config.slots)]
        self._tasks.append(asyncio.create_task(self._reaper(), name="lease-reaper"))
        return self._tasks

    async def stop(self) -> None:
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks = []

    async def _reaper(self) -> None:
        interval = max(0.2, self.queue.lease_s / 3)
        while True:
            try:
                for job in await asyncio.to_thread(self.queue.requeue_expired):
                    log.warning("job %s of %s: lease lost, now %s", job.id, job.exposure_id, job.state)
                    self.metrics.inc("plenodust_job_retries_total")
                    self._publish_job(job)
                    if job.state == "queued":
                        self.wake()
                await self._retry_when_space_returned()
            except Exception:
                log.exception("re-queueing expired leases failed")
            await asyncio.sleep(interval)

    async def _retry_when_space_returned(self) -> None:
        if self.guard is None or not await asyncio.to_thread(self.queue.waiting, "space"):
            return
        if not await asyncio.to_thread(self.guard.ok):
            return
        for job in await asyncio.to_thread(self.queue.retry_waiting, "space"):
            log.info("job %s: space on the data disk again, queued again", job.id)
            self._publish_job(job)
            self.wake()

    def _space_low(self) -> bool:
        return self.guard is not None and not self.guard.ok()

    async def _slot(self, index: int) -> None:
        owner = make_owner(f"/{index}")
        while True:
            try:
                # With the data disk below its margin no job starts: its result could not be kept.
                low = await asyncio.to_thread(self._space_low)
                job = None if low else await asyncio.to_thread(self.queue.claim, owner)
            except Exception:
                log.exception("claiming a job failed")
                job = None
                await asyncio.sleep(1.0)
            if job is None:
                self._wake.clear()
                try:
                    await asyncio.wait_for(self._wake.wait(), self.config.idle_poll_s)
                except TimeoutError:
                    pass
                continue
            try:
                await self._run(job, owner)
            except asyncio.CancelledError:
                raise
            except Exception:
                # Keep the slot alive; the job's lease runs out and the reaper re-queues it.
                log.exception("job %s: the runner failed around it", job.id)

    async def _run(self, job: Job, owner: str) -> None:
        record = await asyncio.to_thread(self.store.exposure, job.exposure_id)
        if record is None:  # cannot happen through ingest; guard against a damaged index
            await asyncio.to_thread(self.queue.fail, job.id, owner, "exposure not in the index")
            return
        self._publish_job(job, record)
        task = self._task_for(record)
        progress: dict = {"value": 0.0, "stage": None, "sent": 0.0, "at": 0.0}

        def on_progress(fraction: float, stage: str | None = None) -> None:
            changed = stage is not None and stage != progress["stage"]
            progress["value"] = fraction
            if stage is not None:
                progress["stage"] = stage
            now = time.monotonic()
            # Throttle: the event stream needs a few updates per job (and each new stage), not one per slice.
            if changed or fraction - progress["sent"] >= 0.1 or now - progress["at"] >= 0.5:
                progress["sent"], progress["at"] = fraction, now
                self.bus.publish("job", {"id": job.id, "exposure_id": job.exposure_id, "state": "running",
                                         "progress": fraction, "stage": progress["stage"], "run": record.run,
                                         "frame": record.frame})

        heartbeat = asyncio.create_task(self._heartbeat(job, owner, progress))
        try:
            output = await self.executor.run(task, on_progress)
        except WorkerLost as exc:
            await self._give_back(job, owner, record, str(exc))
            return
        except (CalibrationError, CameraMismatchError) as exc:
            # For want of this camera's white images (none, or another camera's): runs again
            # when they arrive, whatever the analysis called it.
            await self._fail(job, owner, record, f"{type(exc).__name__}: {exc}. {calibration_hint(record.serial)}",
                             waits_for="calibration")
            return
        except AnalysisError as exc:
            await self._fail(job, owner, record, f"{type(exc).__name__}: {exc}")
            return
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # not the input's fault as far as we know: try again
            if is_out_of_space(exc):
                await self._fail(job, owner, record, f"NoSpace: {exc}", waits_for="space")
                return
            log.exception("job %s failed unexpectedly", job.id)
            await self._give_back(job, owner, record, f"{type(exc).__name__}: {exc}")
            return
        finally:
            heartbeat.cancel()
        await self._finish(job, owner, record, output)

    def _task_for(self, record: ExposureRecord) -> JobTask:
        serial = record.serial
        calibration = None
        known = self.store.calibration_serials()
        if serial and self.store.has_calibration(serial):
            calibration = self.store.calibration_dir(serial)
        elif len(known) == 1:
            # A camera .TXT may not name its camera; with one camera known, use it (the
            # analysis refuses white images of another camera with CameraMismatchError).
            calibration = self.store.calibration_dir(known[0]["serial"])
        return JobTask(exposure_id=record.id,
                       raw_paths=tuple(str(p) for p in self.store.raw_paths(record.id, record.kind)),
                       calibration_dir=str(calibration) if calibration else None,
                       calibration_cache_dir=str(self.store.cache_dir),
                       metric_calibration_dir=str(self.store.metric_dir),
                       parameters=self.config.parameters or None,
                       keep_slices=self.config.keep_slices)

    async def _heartbeat(self, job: Job, owner: str, progress: dict) -> None:
        while True:
            await asyncio.sleep(self.config.heartbeat_s)
            try:
                alive = await asyncio.to_thread(self.queue.heartbeat, job.id, owner, progress=progress["value"],
                                                stage=progress["stage"])
            except Exception:
                log.exception("heartbeat for job %s failed", job.id)
                continue
            if not alive:
                log.warning("job %s: lease lost to another worker; its result will be discarded", job.id)
                return

    async def _finish(self, job: Job, owner: str, record: ExposureRecord, output: JobOutput) -> None:
        def store_it() -> bool:
            if self.guard is not None:
                self.guard.require(RESULT_BYTES, what="the result of this job")
            self.store.write_result(record, output)
            self.store.update_run_file(record, output)
            with self.store.db.write() as conn:
                if not self.queue.complete(conn, job.id, owner):
                    return False
                self.store.index_result(conn, record, output.particles)
            return True

        try:
            recorded = await asyncio.to_thread(store_it)
        except Exception as exc:
            if is_out_of_space(exc):
                # Nothing half-written is left (files are renamed into place); run it again later.
                log.warning("job %s: no space to store its result (%s); it runs again when there is", job.id, exc)
                message = str(exc) if isinstance(exc, NoSpace) else f"{type(exc).__name__}: {exc}"
                await self._fail(job, owner, record, f"NoSpace: {message}", waits_for="space")
                return
            log.exception("storing the result of job %s failed", job.id)
            await self._give_back(job, owner, record, f"storing the result failed: {exc}")
            return
        if not recorded:
            log.warning("job %s finished after its lease was lost; another run records it", job.id)
            return
        now = time.time()
        if not self.metrics.value("plenodust_jobs_total", outcome="done"):
            log.info("first result: run %s frame %d, %d particles", record.run, record.frame, output.particles)
        self.metrics.inc("plenodust_jobs_total", outcome="done")
        self.metrics.observe_job(output.seconds, now - record.created_at)
        # Linked before the result is announced, so a page that reloads on it sees the trajectories.
        await self._track(record.run)
        done = self.queue.get(job.id)
        if done is not None:
            self._publish_job(done, record)
        self.bus.publish("result", {"exposure_id": record.id, "run": record.run, "frame": record.frame,
                                    "particles": output.particles, "job_id": job.id})
        if self.config.raw_retention:
            try:
                await asyncio.to_thread(self.store.prune_raw, keep=self.config.raw_retention)
            except OSError:
                log.exception("removing raw files beyond the retention failed")

    async def _track(self, run: str) -> None:
        """Link the run's frames that can be linked now (a failure to link never fails the job)."""
        if self.tracker is None:
            return
        try:
            frames = await asyncio.to_thread(self.tracker.advance, run)
        except Exception:
            log.exception("linking run %s failed; its trajectories wait for the next result", run)
            return
        if frames:
            self.bus.publish("tracks", {"run": run, "frames": frames})

    async def _fail(self, job: Job, owner: str, record: ExposureRecord, error: str, *,
                    waits_for: str | None = None) -> None:
        if await asyncio.to_thread(self.queue.fail, job.id, owner, error, waits_for=waits_for):
            self.metrics.inc("plenodust_jobs_total", outcome="failed")
            self.metrics.inc("plenodust_job_failures_total")
            if job.attempts > 1:  # an earlier attempt may have reached the run file
                await asyncio.to_thread(self.store.update_run_file, record, None)
        failed = self.queue.get(job.id)
        if failed is not None:
            self._publish_job(failed, record)
        await self._track(record.run)  # frames after a failed one need not wait for it

    async def _give_back(self, job: Job, owner: str, record: ExposureRecord, error: str) -> None:
        state = await asyncio.to_thread(self.queue.release, job.id, owner, error)
        if state == "queued":
            self.metrics.inc("plenodust_job_retries_total")
            self.wake()
        elif state == "failed":
            self.metrics.inc("plenodust_jobs_total", outcome="failed")
            self.metrics.inc("plenodust_job_failures_total")
        changed = self.queue.get(job.id)
        if changed is not None:
            self._publish_job(changed, record)

    def _publish_job(self, job: Job, record: ExposureRecord | None = None) -> None:
        data = job.public()
        if record is not None:
            data.update(run=record.run, frame=record.frame)
        self.bus.publish("job", data)
