"""``service.client`` against the real service over loopback: uploads, shots, waits, errors,
and the README's experiment-control loop as written."""

from __future__ import annotations

import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from service.client import Accepted, Client, ClientError, JobFailed, ProblemError
from service_helpers import assert_matches_truth, simulate, truth_xyz, variant_lfp
from service_server import ROOT, ServiceProcess

KEY = "client-key"


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return simulate(tmp_path_factory.mktemp("sim"), seed=6, count=1)


@pytest.fixture(scope="module")
def server(tmp_path_factory, sim):
    service = ServiceProcess(tmp_path_factory.mktemp("data"), env={"PLENODUST_API_KEY": KEY})
    try:
        service.wait_ready()
        files = [("files", (p.name, p.read_bytes())) for p in sorted(sim.calibration_dir.iterdir())]
        assert httpx.post(service.url + "/api/v1/calibrations", files=files,
                          headers={"Authorization": f"Bearer {KEY}"}, timeout=60).status_code == 201
        yield service
    finally:
        service.stop()


def test_upload_wait_by_events_and_fetch_the_table(server, sim) -> None:
    client = Client(server.url, api_key=KEY)
    accepted = client.upload(sim.lfp[0], run="client")
    assert isinstance(accepted, Accepted) and accepted.run == "client" and accepted.frame == 0
    job = client.wait(accepted.job_id, timeout_s=120)
    assert job.state == "done" and job.progress == 1.0
    table = client.particles(accepted.exposure_id)
    assert_matches_truth(table, truth_xyz(sim.truth[0]))
    assert client.run_particles("client")["frame"] == [0] * len(table["Z"])


def test_a_raw_pair_by_polling(server, sim) -> None:
    client = Client(server.url, api_key=KEY)
    raw = bytearray(sim.raw[0].read_bytes())
    raw[5] ^= 1
    accepted = client.upload(bytes(raw), metadata=sim.txt[0], run="client-raw")
    assert client.wait(accepted.job_id, poll=True, timeout_s=120).state == "done"


def test_errors_carry_the_problem_document(server, sim) -> None:
    client = Client(server.url, api_key=KEY)
    with pytest.raises(ProblemError) as caught:
        client.job("no-such-job")
    assert caught.value.status == 404 and caught.value.problem["type"].endswith("job-not-found")
    with pytest.raises(ProblemError) as caught:
        client.upload(b"not a picture" * 10)
    assert caught.value.status == 422 and caught.value.detail
    with pytest.raises(ProblemError) as caught:
        Client(server.url).upload(sim.lfp[0])  # no key
    assert caught.value.status == 401
    with pytest.raises(ProblemError) as caught:
        client.take_shot()
    assert caught.value.status == 409 and "--camera" in caught.value.detail
    # A job that fails says why.
    other = client.upload(variant_lfp(sim.lfp[0], 5, serial="A999999999"), run="client-fail")
    with pytest.raises(JobFailed) as failed:
        client.wait(other.job_id, timeout_s=120)
    assert failed.value.job.waits_for == "calibration" and "CameraMismatchError" in failed.value.job.error
    with pytest.raises(ClientError):
        Client("http://127.0.0.1:9").job("x")  # nothing listens there


def test_the_readme_loop_runs_against_the_demo(tmp_path: Path) -> None:
    readme = (ROOT / "README.md").read_text()
    block = readme.split("### Experiment control from Python", 1)[1].split("```python\n", 1)[1].split("```", 1)[0]
    assert len(block.strip().splitlines()) <= 12
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "NUMBA_CACHE_DIR": str(ROOT / ".cache" / "numba")}
    demo = subprocess.Popen([sys.executable, "-m", "service.cli.main", "demo", "--port", str(port), "--every", "0",
                             "--size", "320", "--data", str(tmp_path)], cwd=ROOT, env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    try:
        url = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 120
        while True:
            try:
                if httpx.get(url + "/readyz", timeout=5).status_code == 200:
                    break
            except httpx.TransportError:
                pass
            assert demo.poll() is None and time.monotonic() < deadline, "the demo never became ready"
            time.sleep(0.3)
        printed: list[str] = []
        code = re.sub(r"http://127\.0\.0\.1:8000", url, block)
        exec(compile(code, "README.md", "exec"), {"print": lambda *a: printed.append(" ".join(map(str, a)))})
        assert len(printed) == 3 and all("particles, mean Z" in line for line in printed)
        runs = httpx.get(url + "/api/v1/runs/rf-scan/exposures").json()
        assert runs["total"] == 3 and all(e["state"] == "done" for e in runs["items"])
    finally:
        os.killpg(demo.pid, signal.SIGINT)
        try:
            demo.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(demo.pid, signal.SIGKILL)
            demo.wait()
