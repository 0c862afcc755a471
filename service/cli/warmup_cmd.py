"""``plenodust warm-up``: compile the numba kernels into their cache now, saying what happens.

The analysis is numba code: compiled on first use (about two minutes on two cores), then
loaded from ``NUMBA_CACHE_DIR`` in a second or two. ``make setup`` (so ``make run`` and
``make test``) runs this once after an install or a change to ``analysis/``, so that no
first job, first ``plenodust process`` or first demo shot waits for the compiler.

It simulates a small cluster, calibrates it and processes it the way a service job does
(:func:`service.pipeline_task.run_task`), so every kernel is compiled for the types a real
job uses, not just some.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

# A crop big enough to hold particles, small enough to render in a moment.
WARM_UP_SIZE_PX = 320


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "warm-up", help="compile the analysis kernels into the numba cache (make setup runs it)",
        description=__doc__.split("\n\n", 1)[1])
    parser.add_argument("--quiet", action="store_true", help="print only the summary line")
    parser.set_defaults(func=run)


@contextmanager
def still_working(say: Callable[[str], None], what: str, *, every_s: float = 10.0) -> Iterator[None]:
    """Say ``what`` now and, while the block runs, every ``every_s`` seconds how long it has taken."""
    start = time.perf_counter()
    done = threading.Event()
    say(f"{what} ...")

    def tick() -> None:
        while not done.wait(every_s):
            say(f"  ... {time.perf_counter() - start:.0f} s so far")

    ticker = threading.Thread(target=tick, name="still-working", daemon=True)
    ticker.start()
    try:
        yield
    finally:
        done.set()
        ticker.join()


def cache_dir() -> str:
    """Where numba keeps compiled kernels (``NUMBA_CACHE_DIR``, else beside the sources)."""
    return os.environ.get("NUMBA_CACHE_DIR") or "__pycache__ beside the analysis sources"


def warm_up_kernels(say: Callable[[str], None]) -> float:
    """Compile (or load) every kernel a job and the demo use; returns the seconds it took."""
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="plenodust-warm-up-") as tmp:
        with still_working(say, "compiling the simulator's kernels (rendering a small cluster)"):
            from analysis.simulation.scenario_files import write_scenario

            files = write_scenario(Path(tmp) / "sim", "ball", 1, count=1, size=WARM_UP_SIZE_PX,
                                   progress=lambda line: None)
        say(f"  simulator ready ({time.perf_counter() - start:.1f} s)")
        t = time.perf_counter()
        stages: list[str] = []

        def progress(fraction: float, stage: str | None = None) -> None:
            if stage and (not stages or stages[-1] != stage):
                stages.append(stage)
                say(f"  {stage} ({time.perf_counter() - t:.1f} s)")

        with still_working(say, "compiling the analysis kernels (calibration, refocus, detection, ray fit)"):
            from service.pipeline_task import run_task
            from service.results import JobTask

            task = JobTask(exposure_id="warm-up", raw_paths=(str(files.lfp[0]),),
                           calibration_dir=str(files.calibration_dir),
                           calibration_cache_dir=str(Path(tmp) / "cache"), keep_slices=True)
            output = run_task(task, progress)
        say(f"  analysis ready ({time.perf_counter() - t:.1f} s, {output.particles} particles found)")
        # What each service worker runs at start, so its types are in the cache as well.
        from service.pipeline_task import warm_up

        with still_working(say, "compiling what a service worker loads at start"):
            warm_up()
    return time.perf_counter() - start


def run(args: argparse.Namespace) -> int:
    def say(line: str) -> None:
        if not args.quiet:
            print(f"plenodust warm-up: {line}", file=sys.stderr, flush=True)

    say(f"numba cache: {cache_dir()}; the first time after an install this takes about two minutes")
    seconds = warm_up_kernels(say)
    print(f"plenodust warm-up: kernels ready in {seconds:.1f} s", file=sys.stderr, flush=True)
    return 0
