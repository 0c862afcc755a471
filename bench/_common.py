"""Helpers the benchmark scripts share: best-of timing, peak memory, and a check for disk space."""

from __future__ import annotations

import contextlib
import resource
import shutil
import tempfile
import threading
import time
from pathlib import Path
from typing import Callable, Iterator


def best_time(fn: Callable[[], object], repeat: int = 5, *, warmup: bool = False) -> float:
    """Fastest wall time in seconds of ``repeat`` calls (after one untimed call if ``warmup``)."""
    if warmup:
        fn()
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def _status_mb(pid: int | str, field: str) -> float | None:
    """A memory field (``VmHWM``, ``RssAnon``, ...) of ``/proc/PID/status`` in MiB; None where the
    process has ended or there is no ``/proc``."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith(f"{field}:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


def peak_rss_mb(pid: int | str = "self") -> float:
    """Peak resident memory in MiB of a process (VmHWM: unlike ru_maxrss, a child's figure is its
    own and not inherited from the parent across fork and exec)."""
    peak = _status_mb(pid, "VmHWM")
    if peak is not None:
        return peak
    if pid != "self":
        return float("nan")
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


class AnonPeak:
    """Peak of a process's anonymous resident memory (``RssAnon``), polled in a thread while the
    block runs; for a child process, as the bench's workers are: a process's own numba kernels hold
    its GIL, so a thread of its own would miss their temporaries.

    The peak RSS also counts the shared libraries' pages the process has mapped, and how many those
    are depends on the page cache, not on the pipeline: numba's LLVM library alone maps 40 MB after
    the caches are dropped and about 100 MB once a compilation has read all of it (same process,
    same exposure: a peak of 522 MB or of 620 MB). The anonymous part is what the process
    allocates itself. Polled every ``interval_s`` (reading ``/proc`` takes tens of microseconds),
    so a spike shorter than that can be missed.

    >>> with AnonPeak() as watch:
    ...     block = bytearray(50 * 2**20)
    >>> watch.peak_mb > 50
    True
    """

    def __init__(self, pid: int | str = "self", interval_s: float = 0.005) -> None:
        self.pid = pid
        self.interval_s = interval_s
        self.peak_mb = 0.0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._poll, daemon=True)

    def _poll(self) -> None:
        while True:
            self.peak_mb = max(self.peak_mb, _status_mb(self.pid, "RssAnon") or 0.0)
            if self._stop.wait(self.interval_s):
                return

    def __enter__(self) -> "AnonPeak":
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        self.peak_mb = max(self.peak_mb, _status_mb(self.pid, "RssAnon") or 0.0)


def check_free_disk(path: Path, needed_gb: float, what: str) -> None:
    """Stop with a clear message, before writing, when the file system of ``path`` (or of its
    nearest existing parent) has less than ``needed_gb`` GiB free: a bench that fills the disk
    halfway through leaves nothing useful, and other work on the machine fails with it."""
    where = Path(path)
    while not where.exists() and where != where.parent:
        where = where.parent
    free = shutil.disk_usage(where).free / 2 ** 30
    if free < needed_gb:
        raise SystemExit(f"{what} needs about {needed_gb:.2f} GiB free under {where}, but only {free:.2f} GiB are: "
                         "free some space, or give --work a folder on a larger disk")


@contextlib.contextmanager
def work_folder(path: Path | None, prefix: str) -> Iterator[Path]:
    """``path`` (created if needed, kept), or a temporary folder removed at the end: a bench's
    simulated cases take about 0.6 GiB each."""
    if path is not None:
        path.mkdir(parents=True, exist_ok=True)
        yield path
        return
    with tempfile.TemporaryDirectory(prefix=prefix) as tmp:
        yield Path(tmp)
