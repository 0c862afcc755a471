"""End to end over real HTTP: ``plenodust serve`` in a subprocess on loopback.

Upload -> job done -> particles vs the simulator's truth, announced on the event stream;
SIGKILL mid-job and restart -> every exposure done exactly once; 50 concurrent uploads
against a small queue -> none lost, 503 + Retry-After honoured; the API key and the body
limit over a real socket.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from datetime import datetime
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import h5py
import httpx
import numpy as np
import pytest

from service_helpers import assert_matches_truth, assert_problem, simulate, truth_xyz, variant_lfp, wait_for_job
from service_server import ROOT, ServiceProcess

KEY = "e2e-key"
AUTH = {"Authorization": f"Bearer {KEY}"}
OCTET = {**AUTH, "Content-Type": "application/octet-stream"}
CAPACITY = 5


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return simulate(tmp_path_factory.mktemp("sim"), seed=2, count=2)


def _calibrate(url: str, sim) -> None:
    files = [("files", (p.name, p.read_bytes())) for p in sorted(sim.calibration_dir.iterdir())]
    r = httpx.post(url + "/api/v1/calibrations", files=files, headers=AUTH, timeout=60)
    assert r.status_code == 201, r.text


@pytest.fixture(scope="module")
def server(tmp_path_factory, sim):
    service = ServiceProcess(tmp_path_factory.mktemp("data"), env={
        "PLENODUST_API_KEY": KEY, "PLENODUST_QUEUE_CAPACITY": str(CAPACITY), "PLENODUST_RETRY_AFTER_S": "1",
        "PLENODUST_MAX_BODY_BYTES": "4000000"})
    try:
        service.wait_ready()
        _calibrate(service.url, sim)
        yield service
    finally:
        service.stop()


class EventStream:
    """Reads ``/api/v1/events`` in a thread and keeps what arrives."""

    def __init__(self, url: str, *, last_event_id: int | None = None) -> None:
        self.events: list[tuple[str, dict]] = []
        self.last_id: int | None = None
        self.connected = threading.Event()
        self._stop = threading.Event()
        headers = {"Last-Event-ID": str(last_event_id)} if last_event_id is not None else {}
        self._thread = threading.Thread(target=self._run, args=(url, headers), daemon=True)
        self._thread.start()
        assert self.connected.wait(10), "event stream did not open"

    def _run(self, url: str, headers: dict) -> None:
        try:
            with httpx.stream("GET", url + "/api/v1/events", headers=headers,
                              timeout=httpx.Timeout(5, read=None)) as r:
                assert r.headers["content-type"].startswith("text/event-stream")
                kind = None
                for line in r.iter_lines():
                    if line.startswith("event:"):
                        kind = line.split(":", 1)[1].strip()
                    elif line.startswith("id:"):
                        self.last_id = int(line.split(":", 1)[1])
                    elif line.startswith("data:") and kind:
                        self.events.append((kind, json.loads(line.split(":", 1)[1])))
                        if kind == "hello":
                            self.connected.set()
                    if self._stop.is_set():
                        return
        except httpx.TransportError:
            if not self._stop.is_set():
                raise  # the stream broke while the test still listened

    def wait_for(self, predicate, timeout_s: float = 60.0) -> tuple[str, dict]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for event in list(self.events):
                if predicate(*event):
                    return event
            time.sleep(0.05)
        raise TimeoutError(f"no such event among {self.events}")

    def close(self) -> None:
        self._stop.set()


def test_upload_over_http_is_processed_matches_truth_and_is_announced(server, sim) -> None:
    stream = EventStream(server.url)
    try:
        r = httpx.post(server.url + "/api/v1/exposures?run=e2e", content=sim.lfp[0].read_bytes(), headers=OCTET)
        assert r.status_code == 202, r.text
        body = r.json()
        assert r.headers["location"] == f"/api/v1/jobs/{body['job_id']}"
        job = wait_for_job(lambda path: httpx.get(server.url + path), body["job_id"])
        assert job["state"] == "done"
        stream.wait_for(lambda kind, data: kind == "result" and data["exposure_id"] == body["exposure_id"])
        states = [d["state"] for k, d in stream.events if k == "job" and d.get("id") == body["job_id"]]
        assert states[0] == "queued" and states[-1] == "done" and "running" in states
        # Progress names the pipeline's stages as they run.
        stages = {d.get("stage") for k, d in stream.events if k == "job" and d.get("id") == body["job_id"]}
        assert {"refocus", "refine"} <= stages, stages
    finally:
        stream.close()
    table = httpx.get(server.url + f"/api/v1/exposures/{body['exposure_id']}/particles").json()
    assert_matches_truth(table["columns"], truth_xyz(sim.truth[0]))


def test_a_reconnecting_client_gets_the_events_it_missed(server, sim) -> None:
    first = EventStream(server.url)
    try:
        r = httpx.post(server.url + "/api/v1/exposures?run=replay", content=variant_lfp(sim.lfp[0], 900),
                       headers=OCTET)
        seen = r.json()["exposure_id"]
        first.wait_for(lambda kind, data: kind == "result" and data["exposure_id"] == seen)
        last_id = first.last_id
    finally:
        first.close()
    # While no one listens, another exposure is processed.
    r = httpx.post(server.url + "/api/v1/exposures?run=replay", content=variant_lfp(sim.lfp[0], 901), headers=OCTET)
    missed = r.json()
    wait_for_job(lambda path: httpx.get(server.url + path), missed["job_id"])
    again = EventStream(server.url, last_event_id=last_id)
    try:
        again.wait_for(lambda kind, data: kind == "result" and data["exposure_id"] == missed["exposure_id"],
                       timeout_s=10)
        assert not any(kind == "result" and data["exposure_id"] == seen for kind, data in again.events)
    finally:
        again.close()


def test_the_api_key_and_body_limit_hold_over_a_real_socket(server, sim) -> None:
    data = sim.lfp[1].read_bytes()
    r = httpx.post(server.url + "/api/v1/exposures", content=data, headers={"Content-Type": "application/octet-stream"})
    assert_problem(r, 401)
    r = httpx.post(server.url + "/api/v1/exposures", content=b"\0" * 4_000_001, headers=OCTET)
    assert_problem(r, 413)
    # A streamed body without Content-Length is cut off at the limit too.
    r = httpx.post(server.url + "/api/v1/exposures", content=iter([b"\0" * 1_000_000] * 5), headers=OCTET)
    assert_problem(r, 413)
    assert_problem(httpx.post(server.url + "/api/v1/exposures", content=b"junk" * 10, headers=OCTET), 422)


def test_50_concurrent_uploads_none_lost_and_back_pressure_honoured(server, sim) -> None:
    # Every tenth shot holds the ball; the others are shots with no particle in view, which keep
    # the queue's traffic and take the pipeline a fraction of the time.
    uploads = [variant_lfp(sim.lfp[1], 100 + k, dark=k % 10 != 0) for k in range(50)]
    refusals: list[str] = []

    def upload(data: bytes) -> dict:
        with httpx.Client(base_url=server.url, timeout=60) as client:
            while True:
                r = client.post("/api/v1/exposures?run=load", content=data, headers=OCTET)
                if r.status_code != 503:
                    assert r.status_code == 202, r.text
                    return r.json()
                assert_problem(r, 503)
                refusals.append(r.headers["retry-after"])
                time.sleep(float(r.headers["retry-after"]))  # what a well-behaved client does

    with ThreadPoolExecutor(50) as pool:
        accepted = list(pool.map(upload, uploads))
    assert refusals, "a queue of 5 should have refused some of 50 uploads at once"
    assert all(value == "1" for value in refusals)
    assert len({a["exposure_id"] for a in accepted}) == 50
    for a in accepted:
        assert wait_for_job(lambda path: httpx.get(server.url + path), a["job_id"], timeout_s=180)["state"] == "done"
    exposures = httpx.get(server.url + "/api/v1/runs/load/exposures").json()["items"]
    assert len(exposures) == 50 and all(e["state"] == "done" for e in exposures)
    assert sorted(e["frame"] for e in exposures) == list(range(50))
    found = {e["id"]: e["particles"] for e in exposures}
    assert all((found[a["exposure_id"]] > 0) == (k % 10 == 0) for k, a in enumerate(accepted)), found
    metrics = httpx.get(server.url + "/metrics").text
    assert f'plenodust_uploads_total{{result="rejected"}} {len(refusals)}' in metrics


def test_sigkill_mid_job_and_restart_finishes_every_exposure_exactly_once(tmp_path: Path, sim) -> None:
    # Many slices make each job last about a second, so the kill lands inside one.
    env = {"PLENODUST_API_KEY": KEY, "PLENODUST_PIPELINE": json.dumps({"n_slices": 1000}),
           "PLENODUST_LEASE_S": "5", "PLENODUST_HEARTBEAT_S": "1"}
    data_dir = tmp_path / "data"
    first = ServiceProcess(data_dir, env=env)
    try:
        first.wait_ready()
        _calibrate(first.url, sim)
        accepted = []
        for k in range(4):
            r = httpx.post(first.url + "/api/v1/exposures?run=crash", content=variant_lfp(sim.lfp[0], 500 + k),
                           headers=OCTET, timeout=60)
            assert r.status_code == 202
            accepted.append(r.json())
        deadline = time.monotonic() + 60
        while not (running := httpx.get(first.url + "/api/v1/jobs?state=running").json()["items"]):
            assert time.monotonic() < deadline, "no job ever ran"
            time.sleep(0.05)
        interrupted = running[0]["id"]
        workers = first.children()
        first.kill()  # the server only: its pool workers must notice and go
        deadline = time.monotonic() + 15
        while any(Path(f"/proc/{pid}").exists() for pid in workers):
            assert time.monotonic() < deadline, "worker processes outlived their server"
            time.sleep(0.1)
    finally:
        first.stop()

    second = ServiceProcess(data_dir, env=env)
    try:
        second.wait_ready()
        for a in accepted:
            job = wait_for_job(lambda path: httpx.get(second.url + path), a["job_id"], timeout_s=120)
            assert job["state"] == "done", job
        jobs = httpx.get(second.url + "/api/v1/jobs?limit=500").json()
        assert jobs["total"] == 4  # no second job for any exposure
        attempts = {j["id"]: j["attempts"] for j in jobs["items"]}
        assert attempts[interrupted] == 2  # it was running when killed, and ran again
        counts = {a["exposure_id"]: httpx.get(second.url + f"/api/v1/exposures/{a['exposure_id']}/particles")
                  .json()["count"] for a in accepted}
        run_file = httpx.get(second.url + "/api/v1/runs/crash/particles?format=h5")
    finally:
        second.stop()
    path = tmp_path / "crash.nxs"
    path.write_bytes(run_file.content)
    with h5py.File(path, "r") as f:
        frames = f["entry/data/frame"][()]
        ids = [i.decode() for i in f["entry/exposures/id"][()]]
    # Each exposure's rows are in the run file once.
    assert sorted(ids) == sorted(counts)
    assert [int(np.sum(frames == a["frame"])) for a in accepted] == [counts[a["exposure_id"]] for a in accepted]


def test_a_dead_worker_process_is_replaced_and_its_job_runs_again(tmp_path: Path, sim) -> None:
    env = {"PLENODUST_PIPELINE": json.dumps({"n_slices": 1000})}
    server = ServiceProcess(tmp_path / "data", env=env)
    try:
        server.wait_ready()
        _calibrate(server.url, sim)
        r = httpx.post(server.url + "/api/v1/exposures", content=sim.lfp[0].read_bytes(),
                       headers={"Content-Type": "application/octet-stream"})
        job_id = r.json()["job_id"]
        deadline = time.monotonic() + 60
        while httpx.get(server.url + f"/api/v1/jobs/{job_id}").json()["state"] != "running":
            assert time.monotonic() < deadline
            time.sleep(0.02)
        workers = [pid for pid in server.children()
                   if b"resource_tracker" not in Path(f"/proc/{pid}/cmdline").read_bytes()]
        assert len(workers) == 1
        os.kill(workers[0], signal.SIGKILL)  # as the kernel's OOM killer would
        job = wait_for_job(lambda path: httpx.get(server.url + path), job_id, timeout_s=120)
        assert job["state"] == "done" and job["attempts"] == 2
        assert httpx.get(server.url + "/readyz").json()["workers"] == "warm"
        assert "plenodust_job_retries_total 1" in httpx.get(server.url + "/metrics").text
    finally:
        server.stop()


def _zulu_times(camera_dir: Path) -> list[datetime]:
    times = []
    for txt in sorted(camera_dir.glob("IMG_*.TXT")):
        text = txt.read_text()
        zulu = text[text.index('"zuluTime"'):].split('"')[3]
        times.append(datetime.strptime(zulu, "%Y-%m-%dT%H:%M:%S.%fZ"))
    return times


def test_make_run_demo_shows_clusters_at_once_takes_shots_on_request_and_tidies_up(tmp_path: Path) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "NUMBA_CACHE_DIR": str(ROOT / ".cache" / "numba"), "TMPDIR": str(tmp_path)}
    demo = subprocess.Popen([sys.executable, "-m", "service.cli.main", "demo", "--port", str(port),
                             "--every", "1", "--size", "320", "--keep", "4"], cwd=ROOT, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True)
    base = f"http://127.0.0.1:{port}"
    lines: list[str] = []
    try:
        first_line = demo.stdout.readline()
        assert f"http://127.0.0.1:{port}/" in first_line  # the URL comes first
        lines.append(demo.stdout.readline())
        data_dir = Path(lines[-1].split("data in ", 1)[1].split(" ", 1)[0].rstrip(";"))
        assert data_dir.parent == tmp_path and "removed on exit" in lines[-1]
        threading.Thread(target=lambda: lines.extend(demo.stdout), daemon=True).start()
        deadline = time.monotonic() + 120
        done = []
        while len(done) < 2:
            assert demo.poll() is None and time.monotonic() < deadline, "demo produced no results"
            try:
                r = httpx.get(base + "/api/v1/runs/demo/exposures", timeout=5)
                done = [e for e in r.json().get("items", []) if e["state"] == "done"] if r.status_code == 200 else []
            except httpx.TransportError:
                pass
            time.sleep(0.3)
        assert {e["source"] for e in done} == {"camera"}
        assert min(e["frame"] for e in done) == 0  # the first shot is queued at once
        # The header's camera is the one the shots and white images are filed under.
        camera = httpx.get(base + "/api/v1/camera").json()
        exposure = httpx.get(base + f"/api/v1/exposures/{done[0]['id']}").json()
        calibrations = httpx.get(base + "/api/v1/calibrations").json()["items"]
        assert camera["serial"] == exposure["serial"] == calibrations[0]["serial"] == "A202160042"
        assert camera["can_take_shots"]
        # Experiment control: one call takes a shot; its job's result holds the particles.
        shot = httpx.post(base + "/api/v1/camera/shots", timeout=60)
        assert shot.status_code == 202, shot.text
        assert shot.headers["location"] == f"/api/v1/jobs/{shot.json()['job_id']}"
        job = wait_for_job(lambda path: httpx.get(base + path), shot.json()["job_id"])
        assert job["state"] == "done"
        table = httpx.get(base + f"/api/v1/exposures/{shot.json()['exposure_id']}/particles").json()
        assert table["count"] > 0 and table["run"] == "demo"
        # Shots come on the clock: each taken a whole number of --every seconds after the first,
        # the requested one aside; the card keeps the newest --keep.
        camera_dir = data_dir / "simulated-camera"
        while len(list(camera_dir.glob("IMG_*.RAW"))) < 4:
            assert time.monotonic() < deadline
            time.sleep(0.2)
        times = _zulu_times(camera_dir)
        assert len(list(camera_dir.glob("IMG_*.RAW"))) == 4
        # The shot taken on request may be the oldest left on the card: the clock is that of the
        # largest set of shots whole seconds apart.
        on_clock = max(([(b - a).total_seconds() for b in times
                         if abs((b - a).total_seconds() - round((b - a).total_seconds())) < 0.002] for a in times),
                       key=len)
        assert len(on_clock) >= len(times) - 1, times  # all but the shot taken on request
        assert len({round(step) for step in on_clock}) == len(on_clock)
    finally:
        os.killpg(demo.pid, signal.SIGINT)
        try:
            demo.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(demo.pid, signal.SIGKILL)
            demo.wait()
    time.sleep(0.2)
    output = "".join(lines)
    assert "Traceback" not in output, output
    # It said what it was doing while the first result was on its way.
    assert "loading the compiled analysis kernels" in output and "workers ready after" in output
    assert "first result: run demo frame" in output
    assert not data_dir.exists() and f"removed {data_dir}" in output  # a temporary demo leaves nothing behind


def test_ctrl_c_while_workers_warm_up_prints_no_traceback(tmp_path: Path) -> None:
    # A terminal's Ctrl-C reaches the whole process group: server and pool workers alike.
    server = ServiceProcess(tmp_path / "data")
    try:
        assert server._found.wait(60), server.log()
        time.sleep(0.5)  # the workers are importing and loading the kernels now
        os.killpg(server.proc.pid, signal.SIGINT)
        assert server.proc.wait(timeout=60) in (0, 130)  # 130: ended by SIGINT, as a shell reports it
    finally:
        server.stop()
    assert "Traceback" not in server.log() and "KeyboardInterrupt" not in server.log(), server.log()
