"""Where jobs run: a warm local process pool, or an existing Dask distributed cluster.

Either way the queue stays in SQLite; an executor only turns a :class:`JobTask` into a
:class:`JobOutput`. A worker that dies mid-job raises :class:`WorkerLost`, so the runner
gives the job back to the queue instead of failing it.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
import queue as queue_mod
import signal
import threading
import time
import uuid
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Protocol

from service.pipeline_task import run_task, warm_up
from service.results import JobOutput, JobTask

log = logging.getLogger(__name__)

# Called with the fraction done (weighted by the stages' cost) and, when the pipeline names
# it, the stage running now.
ProgressCallback = Callable[[float, "str | None"], None]


class WorkerLost(Exception):
    """The process running a job went away; the job should run again elsewhere."""


class Executor(Protocol):
    """What the runner needs from an executor."""

    name: str

    @property
    def warm(self) -> bool: ...

    async def start(self) -> None: ...

    async def run(self, task: JobTask, progress: ProgressCallback | None = None) -> JobOutput: ...

    async def close(self) -> None: ...


# -- local pool ------------------------------------------------------------------------

_progress_queue: multiprocessing.Queue | None = None


def _exit_with_parent(parent: int) -> None:
    # A server killed with SIGKILL cannot stop its pool; its workers would live on as orphans
    # holding a gigabyte each. The job they were on is re-queued by the next server.
    while os.getppid() == parent:
        time.sleep(1.0)
    os._exit(1)


def _init_worker(progress_queue: multiprocessing.Queue, do_warm: bool, threads: int) -> None:
    global _progress_queue
    # Ctrl-C in a terminal reaches the whole process group: the server stops its workers
    # itself, so a worker ignores it (rather than print a KeyboardInterrupt traceback). The
    # server spawned it with SIGINT blocked, so none arrived before this line.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    _progress_queue = progress_queue
    threading.Thread(target=_exit_with_parent, args=(os.getppid(),), name="parent-watch", daemon=True).start()
    # Share the cores between the pool's processes instead of each numba kernel using all.
    import numba

    numba.set_num_threads(max(1, min(threads, numba.config.NUMBA_NUM_THREADS)))
    if do_warm:
        warm_up()


def _pool_run(task: JobTask, key: str) -> JobOutput:
    queue = _progress_queue

    def report(fraction: float, stage: str | None = None) -> None:
        if queue is not None:
            queue.put((key, float(fraction), stage))

    return run_task(task, report)


def _pool_ping() -> int:
    return os.getpid()


def _submit_with_sigint_blocked(pool: ProcessPoolExecutor, count: int) -> list:
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        return [pool.submit(_pool_ping) for _ in range(count)]
    finally:
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})


class LocalPoolExecutor:
    """A pool of ``workers`` processes that import the analysis and compile it at start.

    Processes are spawned (not forked) so they never inherit the server's threads.
    """

    name = "local"

    def __init__(self, workers: int = 1, *, warm_up: bool = True) -> None:
        self.workers = workers
        self.do_warm = warm_up
        self._ctx = multiprocessing.get_context("spawn")
        self._progress_queue: multiprocessing.Queue | None = self._ctx.Queue()
        self._callbacks: dict[str, ProgressCallback] = {}
        self._pool: ProcessPoolExecutor | None = None
        self._warm = False
        self._stop = threading.Event()
        self._reader: threading.Thread | None = None

    @property
    def warm(self) -> bool:
        return self._warm

    def _new_pool(self) -> ProcessPoolExecutor:
        threads = max(1, (os.cpu_count() or 1) // self.workers)
        return ProcessPoolExecutor(self.workers, mp_context=self._ctx, initializer=_init_worker,
                                   initargs=(self._progress_queue, self.do_warm, threads))

    async def start(self) -> None:
        if self._pool is not None:  # a start that failed before: begin again with a fresh pool
            self._pool.shutdown(wait=False, cancel_futures=True)
        self._pool = self._new_pool()
        if self._reader is None:
            self._reader = threading.Thread(target=self._read_progress, name="pool-progress", daemon=True)
            self._reader.start()
        await self._warm_pool()

    async def _warm_pool(self) -> None:
        # One ping per worker: each submit while none is idle starts another process,
        # whose initializer imports and compiles the analysis. They are submitted (and so the
        # processes spawned) from a thread that blocks SIGINT: the children start with it
        # blocked and ignore it from their first line on (see _init_worker).
        pool = self._pool
        futures = await asyncio.to_thread(_submit_with_sigint_blocked, pool, self.workers)
        await asyncio.gather(*(asyncio.wrap_future(f) for f in futures))
        self._warm = True

    def _read_progress(self) -> None:
        queue = self._progress_queue
        while queue is not None and not self._stop.is_set():
            try:
                key, fraction, stage = queue.get(timeout=0.2)
            except queue_mod.Empty:
                continue
            except (EOFError, OSError, ValueError):
                return
            callback = self._callbacks.get(key)
            if callback is not None:
                try:
                    callback(fraction, stage)
                except Exception:  # a progress report must never stop the reader
                    log.exception("progress callback failed")

    async def run(self, task: JobTask, progress: ProgressCallback | None = None) -> JobOutput:
        if self._pool is None:
            raise RuntimeError("executor not started")
        key = uuid.uuid4().hex
        if progress is not None:
            self._callbacks[key] = progress
        loop = asyncio.get_running_loop()
        try:
            return await loop.run_in_executor(self._pool, _pool_run, task, key)
        except BrokenProcessPool as exc:
            await self._replace_pool()
            raise WorkerLost(f"a worker process died while processing {task.exposure_id}") from exc
        finally:
            self._callbacks.pop(key, None)

    async def _replace_pool(self) -> None:
        old = self._pool
        self._warm = False
        self._pool = self._new_pool()
        if old is not None:
            old.shutdown(wait=False, cancel_futures=True)
        await self._warm_pool()

    async def close(self) -> None:
        self._stop.set()
        if self._pool is not None:
            pool, self._pool = self._pool, None
            await asyncio.to_thread(pool.shutdown, wait=True, cancel_futures=True)
        if self._reader is not None:
            self._reader.join(timeout=2)
        self._progress_queue.close()
        self._progress_queue.join_thread()
        # Drop it now so its semaphores are released before interpreter exit.
        self._progress_queue = None
        self._warm = False


# -- Dask ------------------------------------------------------------------------------

#: Event-log topic on which Dask workers report each job's progress (``(key, fraction)``).
DASK_PROGRESS_TOPIC = "plenodust-progress"


def _dask_run(task: JobTask, key: str) -> JobOutput:
    """``run_task`` on a Dask worker, reporting progress through the scheduler's event log."""
    from distributed import get_worker

    worker = get_worker()
    return run_task(task, lambda fraction, stage=None: worker.log_event(DASK_PROGRESS_TOPIC,
                                                                       (key, float(fraction), stage)))


def _dask_address(spec: str) -> str:
    if spec.startswith("dask://"):
        return "tcp://" + spec[len("dask://"):]
    return spec


class DaskExecutor:
    """Sends each job to an existing Dask distributed scheduler.

    Workers must be able to import ``plenodust`` and read the data folder at the same path
    (a shared file system), since tasks carry paths, not bytes. Workers report each stage's
    progress as events on :data:`DASK_PROGRESS_TOPIC`, which the scheduler relays here.
    """

    name = "dask"

    def __init__(self, address: str, *, warm_up: bool = True) -> None:
        self.address = _dask_address(address)
        self.do_warm = warm_up
        self._client = None
        self._warm = False
        self._callbacks: dict[str, ProgressCallback] = {}

    @property
    def warm(self) -> bool:
        return self._warm

    def _on_progress(self, event: tuple) -> None:
        _, (key, fraction, *rest) = event
        callback = self._callbacks.get(key)
        if callback is not None:
            try:
                callback(fraction, rest[0] if rest else None)
            except Exception:  # a progress report must never break the client's event loop
                log.exception("progress callback failed")

    async def start(self) -> None:
        from distributed import Client

        self._client = await Client(self.address, asynchronous=True, timeout=10)
        self._client.subscribe_topic(DASK_PROGRESS_TOPIC, self._on_progress)
        if self.do_warm:
            await self._client.run(warm_up)
        self._warm = True

    async def run(self, task: JobTask, progress: ProgressCallback | None = None) -> JobOutput:
        from distributed import KilledWorker

        if self._client is None:
            raise RuntimeError("executor not started")
        key = f"plenodust-{task.exposure_id[:12]}-{uuid.uuid4().hex[:8]}"
        if progress is not None:
            self._callbacks[key] = progress
        try:
            return await self._client.submit(_dask_run, task, key, pure=False, key=key)
        except KilledWorker as exc:
            raise WorkerLost(f"Dask workers died while processing {task.exposure_id}") from exc
        finally:
            self._callbacks.pop(key, None)

    async def close(self) -> None:
        if self._client is not None:
            client, self._client = self._client, None
            await client.close()
        self._warm = False


def make_executor(spec: str, *, workers: int = 1, warm_up: bool = True) -> Executor:
    """The executor a ``--executor`` value names: ``local`` or ``dask://HOST:PORT``."""
    if spec == "local":
        return LocalPoolExecutor(workers, warm_up=warm_up)
    return DaskExecutor(spec, warm_up=warm_up)
