"""Accuracy, speed and memory of the pipeline on simulated scenarios (prints a report).

For each scenario and seed: simulate a full-size exposure (``plenodust simulate``'s
``write_scenario``), process it with a cached calibration after a warm-up, match the particles
found to the truth, and print recall, precision, depth and lateral errors as % of the mean 3D
nearest-neighbour distance (NN), the depth error by defocus, shadowing pairs separated, and
per-stage times and peak memory.

Usage::

    NUMBA_CACHE_DIR=.cache/numba .venv/bin/python bench/bench_pipeline.py [--size 3280]
        [--seeds 1 2 3] [--scenarios tilted-layer shadowing ball] [--work DIR] [--repeat 3]

Targets (issue): tilted layer and shadowing pairs: recall >= 98 %, precision >= 95 %, depth
(linear-fit RMS) <= 3.5 %, absolute depth RMS <= 5 %, lateral RMS <= 1.5 %, every pair
separated; ball: recall >= 95 %, precision >= 95 %, depth <= 7 %, lateral <= 3 %.
Speed: <= 1 s per full-size exposure with 40 slices on 2 cores, calibration cached; <= 600 MB.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path
from typing import Sequence

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
os.environ.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".cache" / "numba"))

import numpy as np  # noqa: E402
from _common import AnonPeak, check_free_disk, peak_rss_mb, work_folder  # noqa: E402

from analysis.simulation.scoring import BLUR_BINS, Score, blur_bin_label, depth_floor, score  # noqa: E402
from analysis.cache import Cache  # noqa: E402
from analysis.calibration.cache import load_calibration  # noqa: E402
from analysis.formats.exposure import read_exposure  # noqa: E402
from analysis.formats.particle_table import read_csv  # noqa: E402
from analysis.pipeline.params import PipelineParams
from analysis.pipeline.process import process, warm_up  # noqa: E402

TARGETS = {
    "tilted-layer": dict(recall=0.98, precision=0.95, depth_fit=0.035, depth_abs=0.05, lateral=0.015),
    "shadowing": dict(recall=0.98, precision=0.95, depth_fit=0.035, depth_abs=0.05, lateral=0.015, pairs=1.0),
    "ball": dict(recall=0.95, precision=0.95, depth_fit=0.07, depth_abs=None, lateral=0.03),
}

#: Score attributes the targets are checked against (pairs: the fraction of shadowing pairs separated).
SCORE_FIELDS = dict(recall="recall", precision="precision", depth_fit="depth_fit_rms_over_nn",
                    depth_abs="depth_abs_rms_over_nn", lateral="lateral_rms_over_nn")


def metric(s: Score, name: str) -> float:
    if name == "pairs":
        return s.pairs_separated / s.pairs_total if s.pairs_total else 1.0
    return getattr(s, SCORE_FIELDS[name])


def case_folder(work: Path, scenario: str, seed: int, size: int, centre_z: float | None = None,
                tag: str = "") -> Path:
    """Where a case's simulated files and caches live under ``work``."""
    return work / (f"{scenario}-{seed}-{size}" + ("" if centre_z is None else f"-z{centre_z:g}")
                   + (f"-{tag}" if tag else ""))


def prepare_case(work: Path, scenario: str, seed: int, size: int, centre_z: float | None = None,
                 simulate_args: Sequence[str] = (), tag: str = "") -> Path:
    """Simulate the case (once) and fill its calibration and look-up-table caches, in child processes.

    ``simulate_args`` are passed on to ``plenodust simulate`` (e.g. realism options); ``tag`` names
    the case's folder apart from the plain one."""
    place = [] if centre_z is None else ["--centre-z", str(centre_z)]
    folder = case_folder(work, scenario, seed, size, centre_z, tag)
    if not (folder / "scenario.json").is_file():  # written last: a killed simulation is done again
        # A full-frame case and its caches take about 0.6 + 0.5 GiB.
        check_free_disk(work, 1.1 * (size / 3280) ** 2, f"simulating {folder.name}")
        subprocess.run([sys.executable, "-m", "service.cli.main", "simulate", "--scenario", scenario,
                        "--seed", str(seed), "--size", str(size), "--out", str(folder), "--quiet", *place,
                        *simulate_args], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    if not (folder / "cache").is_dir():
        subprocess.run([sys.executable, "-m", "service.cli.main", "process", str(folder / "IMG_0001.lfp"),
                        "--calibration", str(folder / "calibration"), "--out", str(folder / "warm.csv"),
                        "--cache", str(folder / "cache"), "--quiet"], check=True, cwd=ROOT, stdout=subprocess.DEVNULL)
    return folder


def measure_case(folder: Path, params: PipelineParams, repeat: int, table_out: Path | None = None) -> dict:
    """In this (fresh) process: load the cached calibration, warm up, time ``repeat`` runs, score
    (and write the particle table to ``table_out`` when given)."""
    t0 = time.perf_counter()
    warm_up()
    warm_s = time.perf_counter() - t0
    meta = json.loads((folder / "scenario.json").read_text())
    nn = meta["exposures"][0]["mean_nn_distance_mm"]
    exposure = read_exposure(folder / "IMG_0001.lfp")
    cache = folder / "cache"
    t0 = time.perf_counter()
    calibration = load_calibration(folder / "calibration", exposure.metadata, serial=exposure.serial,
                                   cache_dir=cache)
    load_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    tables = Cache(directory=cache)
    process(exposure, calibration, params, cache=tables)  # first run: tables from the disk cache
    first_s = time.perf_counter() - t0
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = process(exposure, calibration, params, cache=tables)
        times.append(time.perf_counter() - t0)
    truth = read_csv(folder / "IMG_0001.truth.csv")
    if table_out is not None:
        result.to_csv(table_out)
    s = score(result.particles, truth, nn_mm=nn)
    return {"score": s.to_dict(), "floor": depth_floor(truth, exposure.model.lattice, nn_mm=nn),
            "timings": result.timings, "wall_s": min(times), "first_s": first_s,
            "calibration_load_s": load_s, "warm_up_s": warm_s, "warnings": result.warnings,
            "grid": [result.grid.width, result.grid.height], "peak_rss_mb": peak_rss_mb()}


def run_case(work: Path, scenario: str, seed: int, size: int, params_json: str, repeat: int,
             centre_z: float | None = None, simulate_args: Sequence[str] = (), tag: str = "",
             table_out: Path | None = None, keep_tables: bool = False) -> dict:
    """Prepare, measure (in a fresh process) and score one case. Its look-up tables (about 0.5 GiB
    per full-frame case) are deleted afterwards unless ``keep_tables``: a few dozen cases filled a
    shared disk; the next run builds them again in :func:`prepare_case`."""
    folder = prepare_case(work, scenario, seed, size, centre_z, simulate_args, tag)
    table = [] if table_out is None else ["--table-out", str(table_out)]
    command = [sys.executable, __file__, "--measure", str(folder), "--params", params_json, "--repeat", str(repeat),
               *table]
    try:
        worker = subprocess.Popen(command, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        with AnonPeak(worker.pid) as anon:
            stdout, stderr = worker.communicate()
        if worker.returncode:
            raise subprocess.CalledProcessError(worker.returncode, command, stdout, stderr)
    finally:
        if not keep_tables:
            shutil.rmtree(folder / "cache", ignore_errors=True)
    row = json.loads(stdout.strip().splitlines()[-1])
    row["peak_anon_mb"] = anon.peak_mb
    row["score"] = Score(**row["score"])
    row.update(scenario=scenario, seed=seed)
    return row


def pct(v: float) -> str:
    return "   -  " if v is None or not np.isfinite(v) else f"{100 * v:6.2f}"


def pooled(rms: list[float], counts: list[int]) -> str:
    """RMS over all particles of several cases, from each case's RMS and count, as :func:`pct`."""
    return pct(float(np.sqrt(np.average(np.square(rms), weights=counts))))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=3280)
    parser.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    parser.add_argument("--scenarios", nargs="+", default=["tilted-layer", "shadowing", "ball"])
    parser.add_argument("--work", type=Path, default=None,
                        help="keep simulated files here (default: a temporary folder, removed at the end)")
    parser.add_argument("--keep-tables", action="store_true",
                        help="keep each case's look-up tables under --work (0.5 GiB per full-frame case)")
    parser.add_argument("--repeat", type=int, default=3, help="timed runs per case (the fastest is shown)")
    parser.add_argument("--params", type=str, default="{}", help="PipelineParams overrides as JSON")
    parser.add_argument("--centre-z", type=float, default=None, metavar="MM",
                        help="place each cluster's centre this far from the lens (default: at focus); e.g. "
                             "57.4 with --params '{\"alpha_min\": 0.999, \"alpha_max\": 1.026}' keeps every "
                             "particle's blur above a lens pitch")
    parser.add_argument("--measure", type=Path, default=None, help=argparse.SUPPRESS)
    parser.add_argument("--table-out", type=Path, default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    params = PipelineParams.from_dict(json.loads(args.params))
    if args.measure is not None:
        print(json.dumps(measure_case(args.measure, params, args.repeat, args.table_out), default=float))
        return 0

    rows = []
    with work_folder(args.work, "plenodust-bench-") as work:
        for scenario in args.scenarios:
            for seed in args.seeds:
                rows.append(run_case(work, scenario, seed, args.size, args.params, args.repeat, args.centre_z,
                                     keep_tables=args.keep_tables))
                r = rows[-1]
                print(f"  done {scenario} seed {seed}: {r['score'].n_matched}/{r['score'].n_true} matched, "
                      f"{r['wall_s']:.3f} s", flush=True)

    span = (f"alpha {params.alpha_min} ... {params.alpha_max}" if params.alpha_min is not None
            else "the alpha range found from each exposure")
    print(f"\nsensor {args.size} px, {params.n_slices} slices over {span}; "
          f"errors in % of the mean 3D nearest-neighbour distance (NN)\n")
    head = (f"{'scenario':13s} {'seed':>4s} {'true':>5s} {'found':>5s} {'recall':>7s} {'precis':>7s} "
            f"{'depth':>7s} {'|dZ|':>7s} {'lateral':>7s} {'pairs':>6s} {'1-lens':>6s} {'floor':>6s}")
    print(head)
    print("-" * len(head))
    for r in rows:
        s = r["score"]
        pairs = f"{s.pairs_separated}/{s.pairs_total}" if s.pairs_total else "-"
        print(f"{r['scenario']:13s} {r['seed']:4d} {s.n_true:5d} {s.n_found:5d} {pct(s.recall)} {pct(s.precision)} "
              f"{pct(s.depth_fit_rms_over_nn)} {pct(s.depth_abs_rms_over_nn)} {pct(s.lateral_rms_over_nn)} "
              f"{pairs:>6s} {r['floor'][0]:6d} {pct(r['floor'][1])}")
    print("\npooled over seeds (RMS of all particles):")
    for scenario in args.scenarios:
        mine = [r for r in rows if r["scenario"] == scenario]
        if not mine:
            continue
        matched = [r["score"].n_matched for r in mine]
        print(f"  {scenario:13s} depth {pooled([r['score'].depth_fit_rms_over_nn for r in mine], matched)}  "
              f"|dZ| {pooled([r['score'].depth_abs_rms_over_nn for r in mine], matched)}  "
              f"floor {pooled([r['floor'][1] for r in mine], [r['score'].n_true for r in mine])}")
    print("\n1-lens: true particles whose blur fits in one micro-lens (their pixels allow any depth up to that "
          "blur,\nin front of focus or behind). floor: the |dZ| of the best estimate from the pixels alone "
          "(analysis.simulation.scoring.depth_floor:\nthe mean over all positions and depths that light the same pattern; "
          "blurs over an edge or a corner\nof a lens cell leave depth and position trading too). "
          "Scoring below it takes a prior (depth_prior).")
    print("\ntargets, against every seed:")
    for scenario in args.scenarios:
        mine = [r["score"] for r in rows if r["scenario"] == scenario]
        if not mine or scenario not in TARGETS:
            continue
        verdicts = []
        for name, target in TARGETS[scenario].items():
            if target is None:
                continue
            values = [metric(sc, name) for sc in mine]
            at_least = name in ("recall", "precision", "pairs")
            missed = sum(v < target if at_least else v > target for v in values)
            verdicts.append(f"{name} {'>=' if at_least else '<='} {100 * target:g} %: "
                            + ("met" if not missed else f"MISSED on {missed} of {len(values)}"))
        print(f"  {scenario:13s} " + "; ".join(verdicts))

    labels = [blur_bin_label(lo, hi) for lo, hi in BLUR_BINS]
    print("\nabsolute depth RMS (% NN) by defocus blur (lens pitches), particles in bin in brackets")
    print(f"{'scenario':13s} " + " ".join(f"{lab:>14s}" for lab in labels))
    for scenario in args.scenarios:
        cells = []
        for lab in labels:
            sq, n = 0.0, 0
            for r in rows:
                if r["scenario"] != scenario:
                    continue
                count, rms = r["score"].depth_by_blur.get(lab, (0, np.nan))
                if count:
                    sq += rms**2 * count
                    n += count
            cells.append(f"{100 * np.sqrt(sq / n):7.2f} ({n:4d})" if n else f"{'-':>14s}")
        print(f"{scenario:13s} " + " ".join(cells))

    stages = sorted({k for r in rows for k in r["timings"] if k != "total"},
                    key=lambda k: -np.median([r["timings"].get(k, 0) for r in rows]))
    print("\nper-stage times (median over cases, ms):")
    for k in stages:
        print(f"  {k:12s} {1e3 * np.median([r['timings'].get(k, 0.0) for r in rows]):8.1f}")
    walls = [r["wall_s"] for r in rows]
    print(f"  {'wall total':12s} {1e3 * np.median(walls):8.1f}  (min {1e3 * min(walls):.1f}, max {1e3 * max(walls):.1f}; "
          f"target <= 1000 ms)")
    print(f"  output grid  {rows[0]['grid'][0]} x {rows[0]['grid'][1]} px")
    rss = [r["peak_rss_mb"] for r in rows]
    anon = [r["peak_anon_mb"] for r in rows]
    print(f"  first run after loading the cache: median {1e3 * np.median([r['first_s'] for r in rows]):.0f} ms; "
          f"calibration load {1e3 * np.median([r['calibration_load_s'] for r in rows]):.0f} ms; "
          f"kernel warm-up {1e3 * np.median([r['warm_up_s'] for r in rows]):.0f} ms")
    print(f"\npeak RSS of a worker process (cached calibration, warm-up, {args.repeat + 1} exposures): "
          f"median {np.median(rss):.0f} MB, max {max(rss):.0f} MB (target <= 600 MB); of it anonymous (what the "
          f"process allocates, without the shared libraries' pages, see _common.AnonPeak): median "
          f"{np.median(anon):.0f} MB, max {max(anon):.0f} MB")
    warned = {w for r in rows for w in r["warnings"]}
    if warned:
        print("warnings seen:", *sorted(warned), sep="\n  ")
    return 0


if __name__ == "__main__":
    sys.exit(main())
