"""What a physicist met in the first hour (issue 12), over real HTTP against ``plenodust serve``.

Calibrations arriving after a job failed for want of them, paging, long URLs, no server paths
in errors, response models in the OpenAPI document, and a full data disk.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import time
from pathlib import Path

import httpx
import pytest

from analysis.simulation.scenario_files import write_scenario
from service_helpers import SIZE_PX, assert_problem, simulate, variant_lfp, wait_for_job
from service_server import ServiceProcess

OCTET = {"Content-Type": "application/octet-stream"}


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return simulate(tmp_path_factory.mktemp("sim"), seed=3, count=1)


@pytest.fixture(scope="module")
def other_camera(tmp_path_factory):
    # A second camera: same optics, another serial.
    return write_scenario(tmp_path_factory.mktemp("other"), "ball", 4, count=1, size=SIZE_PX, serial="A262000077",
                          progress=lambda line: None)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    service = ServiceProcess(tmp_path_factory.mktemp("data"))
    try:
        yield service.wait_ready()
    finally:
        service.stop()


def _whites(sim) -> list:
    return [("files", (p.name, p.read_bytes())) for p in sorted(sim.calibration_dir.iterdir())]


def test_white_images_of_a_second_camera_rerun_its_failed_job(server, sim, other_camera) -> None:
    assert httpx.post(server.url + "/api/v1/calibrations", files=_whites(sim), timeout=60).status_code == 201
    r = httpx.post(server.url + "/api/v1/exposures?run=second-camera", content=other_camera.lfp[0].read_bytes(),
                   headers=OCTET)
    assert r.status_code == 202, r.text
    job = wait_for_job(lambda p: httpx.get(server.url + p), r.json()["job_id"])
    # Only the first camera's white images are known: the analysis calls it a camera mismatch.
    assert job["state"] == "failed" and job["waits_for"] == "calibration"
    assert "POST /api/v1/calibrations" in job["error"] and "plenodust camera calibration" in job["error"]
    assert "A262000077" in job["error"]
    uploaded = httpx.post(server.url + "/api/v1/calibrations", files=_whites(other_camera), timeout=60)
    assert uploaded.status_code == 201 and uploaded.json()["serial"] == "A262000077"
    assert uploaded.json()["jobs_retried"] == [job["id"]]
    again = wait_for_job(lambda p: httpx.get(server.url + p), job["id"])
    assert again["state"] == "done" and again["waits_for"] is None and again["error"] is None
    table = httpx.get(server.url + f"/api/v1/exposures/{r.json()['exposure_id']}/particles").json()
    assert table["count"] > 0


def test_run_exposures_are_paged(server, sim) -> None:
    ids = []
    for k in range(3):
        r = httpx.post(server.url + "/api/v1/exposures?run=pages", content=variant_lfp(sim.lfp[0], 40 + k),
                       headers=OCTET)
        assert r.status_code == 202, r.text
        ids.append(r.json()["exposure_id"])
    page = httpx.get(server.url + "/api/v1/runs/pages/exposures?limit=2").json()
    assert [e["id"] for e in page["items"]] == ids[:2] and page["total"] == 3
    assert page["next"] == "/api/v1/runs/pages/exposures?offset=2&limit=2&order=asc"
    rest = httpx.get(server.url + page["next"]).json()
    assert [e["id"] for e in rest["items"]] == ids[2:] and rest["next"] is None
    newest = httpx.get(server.url + "/api/v1/runs/pages/exposures?limit=1&order=desc").json()
    assert [e["id"] for e in newest["items"]] == ids[-1:]
    assert_problem(httpx.get(server.url + "/api/v1/runs/pages/exposures?limit=0"), 422)


def _raw_get(url: str, target: bytes) -> tuple[int, dict, bytes]:
    """One GET over a plain socket (httpx refuses URLs over 64 kB): status, headers, body."""
    host, port = url.removeprefix("http://").split(":")
    with socket.create_connection((host, int(port)), timeout=30) as sock:
        sock.sendall(b"GET " + target + b" HTTP/1.1\r\nHost: " + host.encode() + b"\r\nConnection: close\r\n\r\n")
        reply = b""
        while chunk := sock.recv(65536):  # a reset connection raises here
            reply += chunk
    head, _, body = reply.partition(b"\r\n\r\n")
    status_line, *header_lines = head.decode().split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, v in (line.split(":", 1) for line in header_lines)}
    return int(status_line.split()[1]), headers, body


@pytest.mark.parametrize("length", [20_000, 100_000, 1_000_000])
def test_a_long_url_gets_414_not_a_reset(server, length) -> None:
    status, headers, body = _raw_get(server.url, b"/api/v1/jobs?state=" + b"x" * length)
    assert status == 414 and headers["content-type"] == "application/problem+json"
    problem = json.loads(body)
    assert problem["status"] == 414 and "8192" in problem["detail"]
    # The server is fine for the next client.
    assert httpx.get(server.url + "/healthz").status_code == 200


def test_a_junk_calibration_upload_names_no_server_path(server) -> None:
    r = httpx.post(server.url + "/api/v1/calibrations", files=[("files", ("MOD_0000.RAW", b"\0" * 10)),
                                                              ("files", ("MOD_0000.TXT", b"[]"))])
    body = assert_problem(r, 422)
    assert str(server.data_dir) not in r.text and ".upload-" not in r.text and "/tmp" not in r.text, body
    assert "MOD_0000" in body["detail"]


def test_openapi_documents_what_comes_back(server) -> None:
    spec = httpx.get(server.url + "/openapi.json").json()

    def schema(path: str, method: str, status: str) -> dict:
        content = spec["paths"][path][method]["responses"][status]["content"]
        return content.get("application/json") or content["application/problem+json"]

    for path, method, status, model in [
            ("/api/v1/exposures", "post", "202", "UploadAccepted"),
            ("/api/v1/jobs/{job_id}", "get", "200", "Job"),
            ("/api/v1/jobs", "get", "200", "JobPage"),
            ("/api/v1/runs/{run}/exposures", "get", "200", "RunExposurePage"),
            ("/api/v1/exposures/{exposure_id}/particles", "get", "200", "ParticleTable"),
            ("/api/v1/camera/shots", "post", "202", "QueuedShot"),
            ("/readyz", "get", "200", "Readiness"),
            ("/api/v1/exposures", "post", "507", "ProblemBody")]:
        assert schema(path, method, status)["schema"]["$ref"].endswith("/" + model), (path, status)
    assert "waits_for" in spec["components"]["schemas"]["Job"]["properties"]
    page = httpx.get(server.url + "/docs").text
    assert "/static/docs/swagger-ui-bundle.js" in page and "cdn" not in page.lower()
    assert httpx.get(server.url + "/static/docs/swagger-ui-bundle.js").status_code == 200


def _fill(path: Path, size: int) -> None:
    subprocess.run(["fallocate", "-l", str(size), str(path)], check=True)


def test_a_full_disk_answers_507_is_not_ready_and_jobs_run_again_when_space_returns(tmp_path, sim) -> None:
    # The margin is set just under today's free space; a real file then takes the disk below it.
    data = tmp_path / "data"
    data.mkdir()
    margin = shutil.disk_usage(data).free - 600_000_000
    env = {"PLENODUST_MIN_FREE_BYTES": str(margin), "PLENODUST_PIPELINE": json.dumps({"n_slices": 1000}),
           "PLENODUST_LEASE_S": "5", "PLENODUST_HEARTBEAT_S": "1"}
    server = ServiceProcess(data, env=env).wait_ready()
    filler = data.parent / "filler"
    try:
        url = server.url
        assert httpx.post(url + "/api/v1/calibrations", files=_whites(sim), timeout=60).status_code == 201
        assert "plenodust_data_free_bytes" in httpx.get(url + "/metrics").text
        r = httpx.post(url + "/api/v1/exposures?run=full", content=variant_lfp(sim.lfp[0], 70), headers=OCTET)
        job_id = r.json()["job_id"]
        wait_for_job(lambda p: httpx.get(url + p), job_id, states=("running", "done"))
        _fill(filler, 900_000_000)  # the disk fills up while the job runs
        failed = wait_for_job(lambda p: httpx.get(url + p), job_id)
        assert failed["state"] == "failed" and failed["waits_for"] == "space", failed
        ready = httpx.get(url + "/readyz")
        assert ready.status_code == 503 and not ready.json()["disk"]["ok"]
        free = next(line for line in httpx.get(url + "/metrics").text.splitlines()
                    if line.startswith("plenodust_data_free_bytes "))
        assert 0 < int(free.split()[1]) < margin
        refused = httpx.post(url + "/api/v1/exposures?run=full", content=variant_lfp(sim.lfp[0], 71), headers=OCTET)
        body = assert_problem(refused, 507)
        assert str(data) in body["detail"] and body["data_dir"] == str(data)
        assert body["needed_bytes"] > body["free_bytes"]
        assert httpx.get(url + "/api/v1/runs/full/exposures").json()["total"] == 1  # nothing half-kept
        os.unlink(filler)  # space returns
        again = wait_for_job(lambda p: httpx.get(url + p), job_id, states=("done",), timeout_s=120)
        assert again["waits_for"] is None
        assert httpx.get(url + "/readyz").status_code == 200
    finally:
        if filler.exists():
            filler.unlink()
        server.stop()
