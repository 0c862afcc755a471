"""Trajectories from `plenodust track` on simulated runs, against the truth; linking speed.

    python bench/bench_tracking.py run [--shots 100] [--size 3280] [--realism] [--seed 1] [--work DIR]
                                       [--temperature-ev 0.004]
    python bench/bench_tracking.py speed [--particles 1000] [--shots 30]

``run``: a ball of 150 particles 2.6 mm in front of focus (``--centre-z 57.4``) moving as
``analysis.simulation.dynamics.Motion()`` says (rotation, drift, Langevin at 0.004 eV, shell hops),
one shot a second (``--temperature-ev``: another temperature; steps scale with its square root,
the position noise's share of the apparent temperature inversely); simulated (ideal camera, or
``--realism``), processed and linked as ``plenodust track`` does (``--alpha-min 0.999 --alpha-max 1.026``), then scored: links right
(target >= 99 %), missed shots bridged, trajectories per true particle, velocity errors, the
position noise the run measured against the true position errors, and the temperature with
the noise taken out against the truth (target within 10 %). trackpy's ``link`` on the same
detections is scored beside ours. ``--work DIR`` keeps the simulated files and the processed
table, so a second call only links and scores (minutes instead of a quarter of an hour).

``speed``: linking alone, on the simulator's truth plus measured-size position noise, for a
cluster of ``--particles`` (target <= 50 ms a shot for 1000), both engines.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _common import check_free_disk  # noqa: E402
from analysis.simulation.dynamics import Motion, simulate_motion  # noqa: E402
from analysis.simulation.scenarios import Particles, Scenario, make_scenario  # noqa: E402

NOISE_MM = (0.005, 0.005, 0.03)  # about what the pipeline reaches off focus (README)


def run(args: argparse.Namespace) -> None:
    import pandas as pd

    from analysis.pipeline.params import PipelineParams
    from analysis.simulation.realism import Realism
    from analysis.simulation.scenario_files import write_scenario
    from analysis.simulation.track_scoring import (read_truth_run, score_tracks, truth_temperature_axes_ev,
                                                   truth_temperature_ev)
    from analysis.simulation.scoring import match
    from analysis.tracking.run import track
    from analysis.tracking.summary import summarize
    from analysis.tracking.trajectories import link, prepare

    work = Path(args.work or tempfile.mkdtemp(prefix="bench-tracking-"))
    sim = work / "sim"
    motion = Motion(temperature_ev=args.temperature_ev)
    if not (sim / "scenario.json").exists():
        # A full-frame shot takes 31 MiB, its calibration caches 80 MiB more.
        check_free_disk(work, (args.shots * 0.031 + 0.1) * (args.size / 3280) ** 2, f"simulating {args.shots} shots")
        start = time.perf_counter()
        write_scenario(sim, "ball", args.seed, count=args.shots, size=args.size, centre_z_mm=57.4,
                       realism=Realism.typical() if args.realism else None, motion=motion, progress=lambda s: None)
        print(f"simulated {args.shots} shots in {time.perf_counter() - start:.0f} s", flush=True)
    table_path = work / "detections.pkl"
    if table_path.exists():
        linked = pd.read_pickle(table_path)
    else:
        start = time.perf_counter()
        linked = track(sim, sim / "calibration", PipelineParams(alpha_min=0.999, alpha_max=1.026))
        took = time.perf_counter() - start
        print(f"processed and linked {args.shots} shots in {took:.0f} s ({took / args.shots:.2f} s a shot)", flush=True)
        linked.to_pickle(table_path)
    truth = read_truth_run(sim)
    doc = json.loads((sim / "scenario.json").read_text())
    nn = float(np.mean([e["mean_nn_distance_mm"] for e in doc["exposures"]]))
    steps = _true_steps(truth) / nn
    detections = prepare(linked.drop(columns=["particle", "vX", "vY", "vZ"]))
    report = {"shots": args.shots, "realism": bool(args.realism), "mean_nn_mm": nn,
              "true_step_over_nn": {"median": float(np.median(steps)), "p99": float(np.percentile(steps, 99)),
                                    "max": float(steps.max())},
              "hops": len(doc.get("motion", {}).get("hops", [])),
              "detections_per_shot": float(linked.groupby("frame").size().mean())}
    ours = None
    for engine in ("plenodust", "trackpy"):
        start = time.perf_counter()
        out = link(detections, engine=engine)
        if engine == "plenodust":
            ours = out
        took = time.perf_counter() - start
        score = score_tracks(out, truth)
        score["link_ms_per_shot"] = 1000 * took / args.shots
        report[engine] = score
    # Position errors against the truth, per axis: what the noise estimate should find.
    errors = []
    for f, rows in linked.groupby("frame").indices.items():
        t = truth[truth["frame"] == f]
        r, c = match({k: linked[k].to_numpy()[rows] for k in "XYZ"}, {k: t[k].to_numpy() for k in "XYZ"})
        errors.append(linked[["X", "Y", "Z"]].to_numpy()[rows[r]] - t[["X", "Y", "Z"]].to_numpy()[c])
    err = np.vstack(errors)
    # The temperature of this tree's linking (the saved table's links may be an older linker's).
    summary = summarize(ours)
    temperature, temperature_err = summary.temperature_ev()
    raw = summarize(ours, noise=summary.noise.__class__(np.zeros(3), np.zeros(3), summary.noise.speed2_mm2_s2,
                                                           np.zeros(3)))
    truth_t = truth_temperature_ev(truth)
    report["position_error_rms_mm"] = [float(v) for v in np.sqrt(np.mean((err - err.mean(0)) ** 2, axis=0))]
    report["position_noise_estimate_mm"] = summary.noise.to_dict()["sigma_mm"]
    report["temperature"] = {
        "set_ev": motion.temperature_ev, "truth_velocities_ev": truth_t,
        "recovered_ev": temperature, "recovered_err_ev": temperature_err,
        "recovered_over_truth": temperature / truth_t, "recovered_over_set": temperature / motion.temperature_ev,
        "without_noise_removal_over_truth": raw.temperature_ev()[0] / truth_t,
        # Each axis against its own truth (they differ by several % in one run).
        "per_axis_over_truth": [float(np.nanmean(summary.table[f"T_{a}_eV"]) / t)
                                for a, t in zip("XYZ", truth_temperature_axes_ev(truth))]}
    shells = summary.to_dataframe()
    if "shell0_n" in shells:
        report["shells_mean_count"] = [float(np.nanmean(shells[f"shell{s}_n"])) for s in range(int(shells["shells"].max()))]
    print(json.dumps(report, indent=2))


def _true_steps(truth) -> np.ndarray:
    t = truth.sort_values(["particle", "frame"])
    same = (t["particle"].to_numpy()[1:] == t["particle"].to_numpy()[:-1]) & (np.diff(t["frame"].to_numpy()) == 1)
    d = np.diff(t[["X", "Y", "Z"]].to_numpy(), axis=0)
    return np.linalg.norm(d[same], axis=1)


def cluster(n: int, seed: int) -> Scenario:
    """``n`` particles filling a ball at the mean spacing of the simulated 150-particle ball."""
    rng = np.random.default_rng(seed)
    spacing = 0.64
    radius = spacing * (n / (4 / 3 * math.pi) / 0.74) ** (1 / 3) * 0.9
    side = int(math.ceil(2 * radius / spacing)) + 1
    grid = (np.stack(np.meshgrid(*[np.arange(side)] * 3, indexing="ij"), -1).reshape(-1, 3) - side / 2) * spacing
    grid = grid[np.argsort(np.linalg.norm(grid, axis=1))][:n] + rng.normal(0, 0.05, (n, 3))
    xyz = grid + np.array([0.0, 0.0, 57.4])
    return Scenario("cluster", seed, Particles(xyz[:, 0], xyz[:, 1], xyz[:, 2], np.full(n, 1800.0)), 40.0, {})


def speed(args: argparse.Namespace) -> None:
    import pandas as pd

    from analysis.tracking.linking import Linker
    from analysis.tracking.trajectories import link

    shots, _ = simulate_motion(cluster(args.particles, 3), Motion(), args.shots, seed=[3, 1])
    rng = np.random.default_rng(4)
    frames = []
    for k, s in enumerate(shots):
        keep = rng.random(len(s.xyz_mm)) > 0.01
        xyz = s.xyz_mm[keep] + rng.normal(0, 1, (keep.sum(), 3)) * np.array(NOISE_MM)
        frames.append(pd.DataFrame({"frame": k, "t": s.t_s, "X": xyz[:, 0], "Y": xyz[:, 1], "Z": xyz[:, 2],
                                    "truth": np.flatnonzero(keep)}))
    table = pd.concat(frames, ignore_index=True)
    linker = Linker()
    times, cpu = [], []
    for k, part in table.groupby("frame"):
        start, start_cpu = time.perf_counter(), time.process_time()
        linker.add(int(k), float(part["t"].iloc[0]), {c: part[c].to_numpy() for c in ("X", "Y", "Z")})
        times.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    # Wall time, and this process's CPU time (other work on a shared machine stretches the former).
    out = {"particles": args.particles, "shots": args.shots,
           "plenodust_ms_per_shot": {"median": 1000 * float(np.median(times[1:])), "max": 1000 * float(np.max(times[1:])),
                                     "first_pair": 1000 * times[1]},
           "plenodust_cpu_ms_per_shot": {"median": 1000 * float(np.median(cpu[1:])), "max": 1000 * float(np.max(cpu[1:])),
                                         "first_pair": 1000 * cpu[1]}}
    for engine in ("plenodust", "trackpy"):
        start = time.perf_counter()
        linked = link(table, engine=engine)
        took = time.perf_counter() - start
        o = linked.sort_values(["particle", "frame"])
        same = o["particle"].to_numpy()[1:] == o["particle"].to_numpy()[:-1]
        right = o["truth"].to_numpy()[1:][same] == o["truth"].to_numpy()[:-1][same]
        out[engine] = {"link_ms_per_shot_with_velocities": 1000 * took / args.shots,
                       "links_right": float(right.mean()), "trajectories": int(linked["particle"].nunique())}
    print(json.dumps(out, indent=2))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="what", required=True)
    p = sub.add_parser("run")
    p.add_argument("--shots", type=int, default=100)
    p.add_argument("--size", type=int, default=3280)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--realism", action="store_true")
    p.add_argument("--work", type=Path, default=None)
    p.add_argument("--temperature-ev", type=float, default=Motion().temperature_ev)
    p.set_defaults(func=run)
    p = sub.add_parser("speed")
    p.add_argument("--particles", type=int, default=1000)
    p.add_argument("--shots", type=int, default=30)
    p.set_defaults(func=speed)
    args = parser.parse_args()
    args.func(args)


if __name__ == "__main__":
    main()
