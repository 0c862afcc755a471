"""Cost of adding one exposure's particles to a run's NeXus file as the run grows.

For runs already holding 10 ... 5000 exposures of 100 particles, times
``Store.update_run_file`` for the next frames (the normal, in-order case), for the last
frame again (a job re-run after a crash), for a frame arriving just after the next one (two
workers finishing out of order) and for a frame in the middle again (the rare worst case).
At one shot per second the in-order figure must stay far below a second however long the run.
Last, the time to rebuild a run file from its result files (what a crash mid-append costs once).

    python bench/bench_run_file.py [--sizes 10 100 1000 5000] [--particles 100] [--rebuild 1000]
"""

from __future__ import annotations

import argparse
import logging
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.database import Database  # noqa: E402
from service.results import JobOutput  # noqa: E402
from service.store import ExposureRecord, Store  # noqa: E402

# As long as the pipeline's (about 700 characters of JSON): each exposure keeps a copy.
PARAMETERS = {"n_slices": 40, "alpha_min": 0.987, "alpha_max": 1.013,
              **{f"setting_{k:02d}": 0.1234567 * k for k in range(25)}}


def _columns(n: int, frame: int) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(frame)
    return {"index": np.arange(n), "x": rng.uniform(0, 3280, n), "y": rng.uniform(0, 3280, n),
            "alpha": rng.uniform(0.98, 1.02, n), "X": rng.normal(size=n), "Y": rng.normal(size=n),
            "Z": rng.normal(size=n), "brightness": rng.uniform(0, 1, n)}


def _record(run: str, frame: int) -> ExposureRecord:
    return ExposureRecord(id=f"{frame:040x}", run=run, frame=frame, kind="lfp", source="bench",
                          serial=None, created_at=0.0)


def _prefill(store: Store, run: str, exposures: int, particles: int) -> None:
    """A run file holding ``exposures`` frames, written in one go (as a rebuild would)."""
    columns = _columns(particles, 0)
    table = {name: np.tile(col, exposures) for name, col in columns.items()}
    table["frame"] = np.repeat(np.arange(exposures, dtype=np.int64), particles)
    listing = [{"id": _record(run, f).id, "frame": f, "particles": particles, "parameters": PARAMETERS}
               for f in range(exposures)]
    if hasattr(Store, "run_from_results"):
        from service import run_file
        run_file.write_run(store.run_path(run), run, run_file.RunContents(table, listing))
    else:  # the store before appending (git archive 896c96e), for comparison
        from service import store as old
        old._write_run(store.run_path(run), run, table, listing)


def _time(fn) -> float:
    t0 = time.perf_counter()
    fn()
    return time.perf_counter() - t0


def bench(sizes: list[int], particles: int, repeat: int) -> None:
    print(f"one exposure = {particles} particles x {len(_columns(1, 0)) + 1} columns; "
          f"median (min) of {repeat} calls, ms")
    print(f"{'exposures':>9} {'file MB':>8} {'append next':>16} {'re-add last':>16} {'one late':>16} "
          f"{'middle frame':>16}")
    for n in sizes:
        with tempfile.TemporaryDirectory() as tmp:
            db = Database(Path(tmp) / "data" / "plenodust.sqlite")
            store = Store(Path(tmp) / "data", db)
            _prefill(store, "r", n, particles)
            append = [_time(lambda f=f: store.update_run_file(_record("r", f), JobOutput(
                columns=_columns(particles, f), parameters=PARAMETERS))) for f in range(n, n + repeat)]
            last = n + repeat - 1
            again = [_time(lambda: store.update_run_file(_record("r", last), JobOutput(
                columns=_columns(particles, last + 1), parameters=PARAMETERS))) for _ in range(repeat)]
            late = []
            for k in range(repeat):  # a frame arriving after the next one (two workers finishing out of order)
                f = n + repeat + 2 * k
                store.update_run_file(_record("r", f + 1), JobOutput(columns=_columns(particles, f + 1),
                                                                     parameters=PARAMETERS))
                late.append(_time(lambda f=f: store.update_run_file(_record("r", f), JobOutput(
                    columns=_columns(particles, f), parameters=PARAMETERS))))
            early = [_time(lambda: store.update_run_file(_record("r", n // 2), JobOutput(
                columns=_columns(particles, n // 2), parameters=PARAMETERS))) for _ in range(min(repeat, 3))]
            size_mb = store.run_path("r").stat().st_size / 2**20
            rows = len(store.read_run_columns("r")["frame"])
            assert rows == (n + 3 * repeat) * particles, rows  # the bench must not time a broken store
            db.close()

        def fmt(times: list[float]) -> str:
            return f"{statistics.median(times) * 1e3:8.2f} ({min(times) * 1e3:6.2f})"
        print(f"{n:>9} {size_mb:>8.1f} {fmt(append):>16} {fmt(again):>16} {fmt(late):>16} {fmt(early):>16}",
              flush=True)


def bench_rebuild(exposures: int, particles: int) -> None:
    """Time a read after the run file was left half-written: it is rebuilt from the results."""
    if not hasattr(Store, "run_from_results"):
        print("rebuild: this version of the store has no rebuild")
        return
    from service.run_file import marker_path
    with tempfile.TemporaryDirectory() as tmp:
        db = Database(Path(tmp) / "data" / "plenodust.sqlite")
        store = Store(Path(tmp) / "data", db)
        for f in range(exposures):
            with db.write() as conn:
                record, _ = store.register(conn, f"{f:040x}", run="r", kind="lfp", source="bench", serial=None)
            output = JobOutput(columns=_columns(particles, f), parameters=PARAMETERS)
            store.write_result(record, output)
            store.update_run_file(record, output)
            with db.write() as conn:
                store.index_result(conn, record, particles)
        marker_path(store.run_path("r")).touch()
        seconds = _time(lambda: store.read_run_columns("r"))
        assert not marker_path(store.run_path("r")).exists()
        db.close()
    print(f"rebuild of a {exposures}-exposure run from its result files: {seconds:.2f} s "
          f"({seconds / exposures * 1e3:.2f} ms per exposure)")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[10, 100, 1000, 5000])
    parser.add_argument("--particles", type=int, default=100)
    parser.add_argument("--repeat", type=int, default=7)
    parser.add_argument("--rebuild", type=int, default=1000, help="exposures of the rebuilt run (0: skip)")
    args = parser.parse_args(argv)
    logging.disable(logging.WARNING)  # the rebuild's warning is expected here
    bench(args.sizes, args.particles, args.repeat)
    if args.rebuild:
        bench_rebuild(args.rebuild, args.particles)


if __name__ == "__main__":
    main()
