"""Timing and progress of the pipeline's stages."""

from __future__ import annotations

import ctypes
import ctypes.util
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

#: Typical share of each stage in the time of one exposure (bench/bench_pipeline.py, median over
#: its scenarios, calibration cached): progress advances by these, not by the count of stages.
STAGE_COST: dict[str, float] = {
    "table": 2.0, "samples": 10.0, "refocus": 10.0, "subaperture": 3.0, "products": 3.0, "detect": 36.0,
    "link": 8.0, "peaks": 4.0, "maxima": 23.0, "refine": 162.0, "more_passes": 133.0, "deblend": 147.0,
    "split": 37.0, "late_pass": 200.0, "depth_prior": 86.0, "refit": 40.0, "quality": 10.0, "sharpen": 40.0,
    "coordinates": 1.0, "survey": 60.0, "drift": 25.0, "glints": 10.0, "glints_behind": 30.0,
}

#: ``progress(fraction, stage)``: fraction of the work done (0 ... 1), the stage now running.
Progress = Callable[[float, str], None]


class StageClock:
    """Times the stages of one exposure and reports progress weighted by their typical cost.

    >>> clock = StageClock()
    >>> with clock.stage("refocus"):
    ...     pass
    >>> sorted(clock.timings)
    ['refocus']
    """

    def __init__(self, progress: Progress | None = None) -> None:
        self.timings: dict[str, float] = {}
        self._progress = progress
        self._done = 0.0
        self._total = sum(STAGE_COST.values())
        self._start = time.perf_counter()

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the block as stage ``name`` (times of a stage run twice add up)."""
        self._report(name)
        t = time.perf_counter()
        try:
            yield
        finally:
            self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - t
            self._done += STAGE_COST.get(name, 0.0)

    def skip(self, *names: str) -> None:
        """Stages that will not run: their share counts as done."""
        self._done += sum(STAGE_COST.get(n, 0.0) for n in names)

    def finish(self) -> dict[str, float]:
        """The timings, with the ``total``; reports completion."""
        self.timings["total"] = time.perf_counter() - self._start
        if self._progress is not None:
            self._progress(1.0, "done")
        return self.timings

    def _report(self, name: str) -> None:
        if self._progress is not None:
            self._progress(min(self._done / self._total, 0.99), name)


def _malloc_trim() -> Callable[[int], int] | None:
    try:
        return ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").malloc_trim
    except (OSError, AttributeError):  # not glibc: its allocator has its own policy
        return None


_TRIM = _malloc_trim()


def trim_heap() -> None:
    """Give the heap memory freed so far back to the system.

    glibc's malloc keeps freed blocks below its (self-raising) mmap threshold for reuse: between an
    F01's refocus stages and its depth fits that is ~100 MB of stacks, samples and index arrays
    that stay resident through every later stage. About 2 ms; call it where a stage's
    temporaries are gone, not in loops (memory reused after it is faulted in again)."""
    if _TRIM is not None:
        _TRIM(0)
