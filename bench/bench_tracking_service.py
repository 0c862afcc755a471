"""The service's time per shot as a run grows: storing a result and linking it to its run.

    python bench/bench_tracking_service.py [--shots 1000] [--particles 150]

What a service worker's job costs besides the analysis, shot after shot of one run: the result
file, the run file's rows (appended in place), the index row, and linking the shot to the run
(``service.tracking.RunTracker.advance``: trajectory ids, velocities of the recent frames written
in place, the per-shot structure). The shots are the simulator's moving ball (truth plus position
noise of the size the pipeline reaches), so no rendering or processing is timed. Printed: the
mean time per shot over the first and the last 100 shots and their ratio (a cost that does not
grow with the run stays near 1), and the linking alone. Times are this process's CPU time, so
other work on a shared machine does not colour the ratio (file-system waits are left out).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from analysis.simulation.dynamics import Motion, simulate_motion  # noqa: E402
from analysis.simulation.scenarios import make_scenario  # noqa: E402
from service.database import Database  # noqa: E402
from service.results import JobOutput  # noqa: E402
from service.store import Store  # noqa: E402
from service.tracking import RunTracker  # noqa: E402

NOISE_MM = np.array([0.005, 0.005, 0.03])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--shots", type=int, default=1000)
    args = parser.parse_args()
    shots, _ = simulate_motion(make_scenario("ball", 1, centre_z_mm=57.4), Motion(), args.shots, seed=[1, 2])
    rng = np.random.default_rng(3)
    with tempfile.TemporaryDirectory() as tmp:
        db = Database(Path(tmp) / "plenodust.sqlite")
        store = Store(Path(tmp), db)
        tracker = RunTracker(store)
        total, linking = [], []
        for k, shot in enumerate(shots):
            keep = rng.random(len(shot.xyz_mm)) > 0.01
            xyz = shot.xyz_mm[keep] + rng.normal(0.0, 1.0, (keep.sum(), 3)) * NOISE_MM
            n = len(xyz)
            columns = {"index": np.arange(n), "x": xyz[:, 0] * 30, "y": xyz[:, 1] * 30, "alpha": np.full(n, 1.01),
                       "X": xyz[:, 0], "Y": xyz[:, 1], "Z": xyz[:, 2], "brightness": np.full(n, 1e4),
                       "alpha_std": np.full(n, 2e-4), "blur_pitches": np.full(n, 5.0)}
            output = JobOutput(columns=columns, parameters={"n_slices": 40})
            output.extra["provenance"] = {"shot_time": 1.6e9 + shot.t_s}
            start = time.process_time()
            with db.write() as conn:
                record, _ = store.register(conn, f"{k:040x}", run="bench", kind="lfp", source="upload", serial=None)
            store.write_result(record, output)
            store.update_run_file(record, output)
            with db.write() as conn:
                store.index_result(conn, record, output.particles)
            middle = time.process_time()
            assert tracker.advance("bench") == [k]
            end = time.process_time()
            total.append(end - start)
            linking.append(end - middle)
        first, last = slice(1, 101), slice(-100, None)
        report = {
            "shots": args.shots, "particles_per_shot": 150,
            "ms_per_shot_first_100": 1000 * float(np.mean(total[first])),
            "ms_per_shot_last_100": 1000 * float(np.mean(total[last])),
            "last_over_first": float(np.mean(total[last]) / np.mean(total[first])),
            "linking_ms_first_100": 1000 * float(np.mean(linking[first])),
            "linking_ms_last_100": 1000 * float(np.mean(linking[last])),
            "linking_last_over_first": float(np.mean(linking[last]) / np.mean(linking[first])),
            "run_file_mb": (Path(tmp) / "runs" / "bench.nxs").stat().st_size / 1e6,
        }
        print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
