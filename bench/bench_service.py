"""Load benchmark of the lab service: sustained exposures per second and upload-to-result latency.

Starts ``plenodust serve`` in a subprocess, uploads simulated exposures over HTTP (each a
distinct exposure) at a fixed rate and then as fast as back-pressure allows, and times each
from the upload to the ``result`` event of the event stream. Target: keep up with one shot
per second on 2 cores, with upload-to-result under 2 s.

    python bench/bench_service.py [--size 3280] [--count 20] [--rate 1.0] [--workers 1]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))

from service_helpers import variant_lfp  # noqa: E402
from service_server import ServiceProcess  # noqa: E402

from analysis.simulation.scenario_files import write_scenario  # noqa: E402

OCTET = {"Content-Type": "application/octet-stream"}


class ResultTimes:
    """Arrival time of each exposure's ``result`` event."""

    def __init__(self, url: str) -> None:
        self.times: dict[str, float] = {}
        self.ready = threading.Event()
        threading.Thread(target=self._run, args=(url,), daemon=True).start()
        self.ready.wait(10)

    def _run(self, url: str) -> None:
        try:
            with httpx.stream("GET", url + "/api/v1/events", timeout=httpx.Timeout(5, read=None)) as r:
                kind = None
                for line in r.iter_lines():
                    if line.startswith("event:"):
                        kind = line.split(":", 1)[1].strip()
                    elif line.startswith("data:"):
                        if kind == "hello":
                            self.ready.set()
                        elif kind == "result":
                            self.times[json.loads(line[5:])["exposure_id"]] = time.perf_counter()
        except httpx.HTTPError:
            pass  # the service stopped at the end of the run

    def wait(self, ids: list[str], timeout_s: float) -> None:
        deadline = time.perf_counter() + timeout_s
        while not all(i in self.times for i in ids):
            if time.perf_counter() > deadline:
                raise TimeoutError(f"{sum(i in self.times for i in ids)} of {len(ids)} results arrived")
            time.sleep(0.01)


def _children(pid: int) -> list[int]:
    """Worker processes of the service (its resource tracker left out)."""
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        found += [int(c) for c in (task / "children").read_text().split()]
    return [c for c in found if b"resource_tracker" not in Path(f"/proc/{c}/cmdline").read_bytes()]


def _peak_rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def upload(client: httpx.Client, data: bytes, run: str) -> tuple[str, float, int]:
    """Upload until accepted (honouring Retry-After); returns id, start time, refusals."""
    start, refusals = time.perf_counter(), 0
    while True:
        r = client.post(f"/api/v1/exposures?run={run}", content=data, headers=OCTET)
        if r.status_code == 503:
            refusals += 1
            time.sleep(float(r.headers.get("retry-after", "1")))
            continue
        r.raise_for_status()
        return r.json()["exposure_id"], start, refusals


def report(name: str, ids: list[str], starts: list[float], times: ResultTimes) -> None:
    latency = np.array([times.times[i] - s for i, s in zip(ids, starts, strict=True)])
    span = max(times.times[i] for i in ids) - min(starts)
    print(f"{name}: {len(ids)} exposures in {span:.1f} s = {len(ids) / span:.2f} exposures/s; "
          f"upload-to-result median {np.median(latency):.2f} s, p90 {np.percentile(latency, 90):.2f} s, "
          f"max {latency.max():.2f} s")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=int, default=3280, help="sensor crop in px (3280 = full F01 frame)")
    parser.add_argument("--count", type=int, default=20, help="exposures per phase")
    parser.add_argument("--rate", type=float, default=1.0, help="shots per second in the paced phase")
    parser.add_argument("--workers", type=int, default=1)
    args = parser.parse_args()

    with tempfile.TemporaryDirectory(prefix="plenodust-bench-") as tmp:
        t = time.perf_counter()
        sim = write_scenario(Path(tmp) / "sim", "ball", 1, count=1, size=args.size, progress=lambda line: None)
        exposures = [variant_lfp(sim.lfp[0], k) for k in range(2 * args.count + 1)]
        print(f"simulated a {args.size} px exposure ({len(exposures[0]) / 1e6:.1f} MB .lfp) and "
              f"{len(exposures)} variants in {time.perf_counter() - t:.1f} s")
        server = ServiceProcess(Path(tmp) / "data", env={"PLENODUST_WORKERS": str(args.workers),
                                                        "PLENODUST_QUEUE_CAPACITY": "16"})
        try:
            t = time.perf_counter()
            server.wait_ready(timeout_s=300)
            print(f"service ready (workers warm) in {time.perf_counter() - t:.1f} s, {args.workers} worker(s)")
            files = [("files", (p.name, p.read_bytes())) for p in sorted(sim.calibration_dir.iterdir())]
            httpx.post(server.url + "/api/v1/calibrations", files=files, timeout=120).raise_for_status()
            times = ResultTimes(server.url)
            with httpx.Client(base_url=server.url, timeout=120) as client:
                # The first job of a camera fits its calibration: time it on its own.
                first, start, _ = upload(client, exposures[0], "bench-first")
                times.wait([first], 300)
                print(f"first exposure (calibration fit + look-up table): {times.times[first] - start:.2f} s")

                ids, starts = [], []
                t0 = time.perf_counter()
                for k in range(args.count):
                    # Paced like a camera: one shot every 1/rate seconds.
                    time.sleep(max(0.0, t0 + k / args.rate - time.perf_counter()))
                    exposure_id, start, _ = upload(client, exposures[1 + k], "bench-paced")
                    ids.append(exposure_id)
                    starts.append(start)
                times.wait(ids, 600)
                report(f"paced at {args.rate:g}/s", ids, starts, times)

            results: list[tuple[str, float, int]] = []
            lock = threading.Lock()

            def burst(data: bytes) -> None:
                with httpx.Client(base_url=server.url, timeout=120) as c:
                    out = upload(c, data, "bench-burst")
                with lock:
                    results.append(out)

            threads = [threading.Thread(target=burst, args=(d,)) for d in exposures[1 + args.count:]]
            for th in threads:
                th.start()
            for th in threads:
                th.join()
            times.wait([r[0] for r in results], 900)
            report("saturated", [r[0] for r in results], [r[1] for r in results], times)
            print(f"saturated: {sum(r[2] for r in results)} uploads refused with 503 first (queue capacity 16)")
            metrics = httpx.get(server.url + "/metrics").text
            line = next(m for m in metrics.splitlines() if m.startswith("plenodust_job_duration_seconds_sum"))
            count = next(m for m in metrics.splitlines() if m.startswith("plenodust_job_duration_seconds_count"))
            print(f"worker time per job: {float(line.split()[1]) / float(count.split()[1]):.2f} s (mean)")
            for name, pid in [("server", server.proc.pid), *(("worker", c) for c in _children(server.proc.pid))]:
                print(f"peak memory of {name} process {pid}: {_peak_rss_mb(pid):.0f} MB")
        finally:
            server.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
