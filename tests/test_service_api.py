"""The REST API in process (``with TestClient(app)``): uploads, results, errors, key, camera.

One app for the module (its warm worker pool is the slow part), with an API key, a small
body limit and a simulated camera.
"""

from __future__ import annotations

import io
import shutil
import time
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest
from fastapi.testclient import TestClient

from analysis.calibration.cache import load_calibration
from analysis.formats.exposure import read_exposure
from analysis.pipeline.process import process
from driver import open_simulated
from driver.simulated import CameraFolder
from service.app import create_app
from service.settings import Settings
from service_helpers import (assert_matches_truth, assert_problem, simulate, truth_xyz, variant_lfp,
                             wait_for_job, wait_until_ready)

KEY = "test-key-123"
AUTH = {"Authorization": f"Bearer {KEY}"}
BODY_LIMIT = 2_000_000


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return simulate(tmp_path_factory.mktemp("sim"), seed=1, count=2)


@pytest.fixture(scope="module")
def camera_sim(tmp_path_factory):
    return simulate(tmp_path_factory.mktemp("camsim"), seed=5, count=2)


@pytest.fixture(scope="module")
def camera_dir(tmp_path_factory, camera_sim) -> Path:
    # The camera holds its white images and one old picture; the second shot comes later.
    folder = tmp_path_factory.mktemp("camera")
    shutil.copytree(camera_sim.calibration_dir, folder / "calibration")
    CameraFolder(folder).add_picture(camera_sim.raw[0].read_bytes(), camera_sim.txt[0].read_bytes())
    return folder


@pytest.fixture(scope="module")
def client(tmp_path_factory, camera_dir, sim):
    settings = Settings(data_dir=tmp_path_factory.mktemp("data"), api_key=KEY, max_body_bytes=BODY_LIMIT,
                        camera_poll_s=0.3, heartbeat_s=1.0, workers=1, run="default")
    camera = open_simulated(camera_dir)
    app = create_app(settings, camera=camera)
    with TestClient(app) as c:
        wait_until_ready(c.get)
        files = [("files", (p.name, p.read_bytes())) for p in sorted(sim.calibration_dir.iterdir())]
        r = c.post("/api/v1/calibrations", files=files, headers=AUTH)
        assert r.status_code == 201, r.text
        yield c


def upload_lfp(client: TestClient, data: bytes, run: str):
    return client.post(f"/api/v1/exposures?run={run}", content=data,
                       headers={**AUTH, "Content-Type": "application/octet-stream"})


def test_upload_is_processed_by_the_real_pipeline_and_matches_truth(client, sim) -> None:
    r = upload_lfp(client, sim.lfp[0].read_bytes(), "t1")
    assert r.status_code == 202, r.text
    body = r.json()
    assert r.headers["location"] == f"/api/v1/jobs/{body['job_id']}"
    assert body["frame"] == 0 and body["run"] == "t1" and len(body["exposure_id"]) == 40
    job = wait_for_job(client.get, body["job_id"])
    assert job["state"] == "done" and job["progress"] == 1.0 and job["error"] is None

    table = client.get(f"/api/v1/exposures/{body['exposure_id']}/particles").json()
    columns = table["columns"]
    for name in ("index", "x", "y", "alpha", "X", "Y", "Z", "brightness"):
        assert len(columns[name]) == table["count"]
    assert_matches_truth(columns, truth_xyz(sim.truth[0]))

    # The service serves exactly what the pipeline computes for this exposure.
    exposure = read_exposure(sim.lfp[0])
    direct = process(exposure, load_calibration(sim.calibration_dir, exposure.metadata, serial=exposure.serial))
    for name in ("x", "y", "alpha", "Z"):
        np.testing.assert_allclose(np.array(columns[name], dtype=float), direct.particles[name], rtol=1e-12)


def test_same_bytes_twice_give_the_same_exposure_and_no_second_job(client, sim) -> None:
    first = upload_lfp(client, sim.lfp[1].read_bytes(), "t2")
    again = upload_lfp(client, sim.lfp[1].read_bytes(), "t2")
    assert first.status_code == 202 and again.status_code == 200
    assert again.json()["exposure_id"] == first.json()["exposure_id"]
    assert again.json()["job_id"] == first.json()["job_id"]
    # The camera's .RAW + .TXT of the same picture is the same exposure too.
    pair = client.post("/api/v1/exposures?run=t2", headers=AUTH, files={
        "raw": ("IMG_0002.RAW", sim.raw[1].read_bytes()), "metadata": ("IMG_0002.TXT", sim.txt[1].read_bytes())})
    assert pair.status_code == 200 and pair.json()["exposure_id"] == first.json()["exposure_id"]
    jobs = client.get("/api/v1/jobs?limit=500").json()["items"]
    assert sum(j["exposure_id"] == first.json()["exposure_id"] for j in jobs) == 1


def test_raw_and_txt_pair_upload_is_processed(client, sim) -> None:
    raw = bytearray(sim.raw[0].read_bytes())
    raw[0] ^= 0x10  # a different picture than the .lfp one, so it is a new exposure
    r = client.post("/api/v1/exposures?run=pairs", headers=AUTH, files={
        "raw": ("IMG_0001.RAW", bytes(raw)), "metadata": ("IMG_0001.TXT", sim.txt[0].read_bytes())})
    assert r.status_code == 202, r.text
    assert wait_for_job(client.get, r.json()["job_id"])["state"] == "done"


def test_particles_as_csv_and_hdf5_equal_the_json(client, sim) -> None:
    r = upload_lfp(client, sim.lfp[0].read_bytes(), "t1")
    exposure_id = r.json()["exposure_id"]
    wait_for_job(client.get, r.json()["job_id"])
    url = f"/api/v1/exposures/{exposure_id}/particles"
    as_json = client.get(url).json()["columns"]
    csv_text = client.get(url, headers={"Accept": "text/csv"})
    assert csv_text.headers["content-type"].startswith("text/csv")
    header, *rows = csv_text.text.strip().split("\n")
    assert header.split(",") == list(as_json)
    assert len(rows) == len(as_json["x"])
    np.testing.assert_allclose([float(row.split(",")[header.split(",").index("Z")]) for row in rows], as_json["Z"])
    h5 = client.get(url + "?format=h5")
    assert h5.headers["content-type"] == "application/x-hdf5"
    with h5py.File(io.BytesIO(h5.content), "r") as f:
        assert f["entry"].attrs["NX_class"] == "NXentry"
        np.testing.assert_allclose(f["entry/data/Z"][()], as_json["Z"])


def test_run_particles_have_a_frame_column(client, sim) -> None:
    ids = []
    for k in range(2):
        # New exposures (the plain ones belong to other runs already).
        r = upload_lfp(client, variant_lfp(sim.lfp[k], 10 + k), "frames")
        assert r.status_code == 202
        ids.append(r.json())
    for body in ids:
        wait_for_job(client.get, body["job_id"])
    run = client.get("/api/v1/runs/frames/particles").json()
    per_frame = [client.get(f"/api/v1/exposures/{b['exposure_id']}/particles").json()["count"] for b in ids]
    assert run["count"] == sum(per_frame)
    frames = run["columns"]["frame"]
    assert [frames.count(f) for f in (0, 1)] == per_frame
    nexus = client.get("/api/v1/runs/frames/particles?format=h5")
    with h5py.File(io.BytesIO(nexus.content), "r") as f:
        assert list(f["entry/data/frame"][()]) == frames
        assert f["entry/process"].attrs["NX_class"] == "NXprocess"
        assert b"n_slices" in f["entry/process/parameters"][()]
    listing = client.get("/api/v1/runs").json()["items"]
    assert any(r["run"] == "frames" and r["done"] == 2 for r in listing)


def test_curves_and_refocused_slices(client, sim) -> None:
    r = upload_lfp(client, sim.lfp[0].read_bytes(), "t1")
    exposure_id = r.json()["exposure_id"]
    wait_for_job(client.get, r.json()["job_id"])
    count = client.get(f"/api/v1/exposures/{exposure_id}/particles").json()["count"]
    curves = client.get(f"/api/v1/exposures/{exposure_id}/curves").json()
    assert len(curves["brightness"]) == count and len(curves["brightness"][0]) == len(curves["alpha"])
    one = client.get(f"/api/v1/exposures/{exposure_id}/curves?particle=0").json()
    assert one["brightness"] == curves["brightness"][:1]
    info = client.get(f"/api/v1/exposures/{exposure_id}").json()
    assert info["slices"] > 1 and info["job"]["state"] == "done"
    png = client.get(f"/api/v1/exposures/{exposure_id}/slices/0")
    assert png.headers["content-type"] == "image/png"
    image = cv2.imdecode(np.frombuffer(png.content, np.uint8), cv2.IMREAD_UNCHANGED)
    assert image.ndim == 2 and image.max() > 0
    assert min(curves["alpha"]) - 1e-6 <= float(png.headers["x-alpha"]) <= max(curves["alpha"]) + 1e-6  # 6 decimals


def test_an_exposure_of_another_camera_fails_with_a_reason(client, sim) -> None:
    r = upload_lfp(client, variant_lfp(sim.lfp[0], 3, serial="A999999999"), "other-camera")
    assert r.status_code == 202
    job = wait_for_job(client.get, r.json()["job_id"])
    assert job["state"] == "failed" and "CameraMismatchError" in job["error"]
    assert job["attempts"] == 1  # the input's fault: not retried
    assert_problem(client.get(f"/api/v1/exposures/{r.json()['exposure_id']}/particles"), 409)
    # Sending it again queues the same job again (the user may have fixed the cause).
    again = upload_lfp(client, variant_lfp(sim.lfp[0], 3, serial="A999999999"), "other-camera")
    assert again.status_code == 202 and again.json()["retried"] and again.json()["job_id"] == job["id"]
    rerun = wait_for_job(client.get, job["id"])
    assert rerun["state"] == "failed" and rerun["started_at"] > job["started_at"]


@pytest.mark.parametrize("case", ["text/plain", "empty", "garbage", "truncated-real", "too-large", "no-metadata",
                                  "bad-txt", "bad-run", "bad-format", "not-acceptable", "unknown-exposure",
                                  "unknown-job", "unknown-run", "calibration-junk", "calibration-type",
                                  "bad-state"])
def test_every_bad_input_gets_a_problem_body(client, real_fixtures, case) -> None:
    post = lambda url, **kw: client.post(url, **{"headers": AUTH, **kw})  # noqa: E731
    octet = {**AUTH, "Content-Type": "application/octet-stream"}
    if case == "text/plain":
        assert_problem(post("/api/v1/exposures", content=b"x", headers={**AUTH, "Content-Type": "text/plain"}), 415)
    elif case == "empty":
        assert_problem(post("/api/v1/exposures", content=b"", headers=octet), 400)
    elif case == "garbage":
        assert_problem(post("/api/v1/exposures", content=b"not a picture" * 100, headers=octet), 422)
    elif case == "truncated-real":
        data = (real_fixtures / "f01-raw-image-section-stripped.lfp").read_bytes()
        body = assert_problem(post("/api/v1/exposures", content=data, headers=octet), 422)
        assert "0360f825e6eed3c7c470fb79a755a54df07fae84" in body["detail"]
    elif case == "too-large":
        body = assert_problem(post("/api/v1/exposures", content=b"\0" * (BODY_LIMIT + 1), headers=octet), 413)
        assert str(BODY_LIMIT) in body["detail"]
    elif case == "no-metadata":
        assert_problem(post("/api/v1/exposures", files={"raw": ("a.RAW", b"\1" * 100)}), 400)
    elif case == "bad-txt":
        assert_problem(post("/api/v1/exposures", files={"raw": ("a.RAW", b"\1" * 100),
                                                        "metadata": ("a.TXT", b"{not json")}), 422)
    elif case == "bad-run":
        assert_problem(post("/api/v1/exposures?run=../../etc", content=b"x", headers=octet), 422)
    elif case == "bad-format":
        assert_problem(client.get("/api/v1/runs/t1/particles?format=xml"), 422)
    elif case == "not-acceptable":
        assert_problem(client.get("/api/v1/runs/t1/particles", headers={"Accept": "image/png"}), 406)
    elif case == "unknown-exposure":
        assert_problem(client.get(f"/api/v1/exposures/{'0' * 40}/particles"), 404)
    elif case == "unknown-job":
        assert_problem(client.get("/api/v1/jobs/nope"), 404)
    elif case == "unknown-run":
        assert_problem(client.get("/api/v1/runs/never/particles"), 404)
    elif case == "calibration-junk":
        assert_problem(post("/api/v1/calibrations", files=[("files", ("MOD_0000.RAW", b"\0" * 10)),
                                                          ("files", ("MOD_0000.TXT", b"[]"))]), 422)
    elif case == "calibration-type":
        assert_problem(post("/api/v1/calibrations", content=b"x", headers=octet), 415)
    elif case == "bad-state":
        assert_problem(client.get("/api/v1/jobs?state=sleeping"), 422)


def test_mutating_routes_need_the_api_key(client, sim) -> None:
    data = sim.lfp[0].read_bytes()
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": KEY}):
        r = client.post("/api/v1/exposures", content=data, headers={**headers, "Content-Type": "application/octet-stream"})
        assert_problem(r, 401)
        assert r.headers["www-authenticate"].startswith("Bearer")
    assert_problem(client.post("/api/v1/camera/pull"), 401)
    assert_problem(client.post("/api/v1/calibrations", files={"files": ("a", b"x")}), 401)
    assert_problem(client.put("/api/v1/runs/current", json={"name": "x"}), 401)
    # Reading needs no key.
    assert client.get("/api/v1/jobs").status_code == 200
    assert client.get("/api/v1/runs").status_code == 200


def test_jobs_are_listed_in_pages_and_by_state(client, sim) -> None:
    upload_lfp(client, sim.lfp[0].read_bytes(), "t1")
    page = client.get("/api/v1/jobs?limit=1").json()
    assert len(page["items"]) == 1 and page["total"] >= 1
    if page["total"] > 1:
        assert page["next"] == "/api/v1/jobs?offset=1&limit=1"
    done = client.get("/api/v1/jobs?state=done&limit=500").json()
    assert done["items"] and all(j["state"] == "done" for j in done["items"])


def test_health_readiness_and_metrics(client) -> None:
    assert client.get("/healthz").json() == {"status": "ok"}
    ready = client.get("/readyz").json()
    assert ready["ready"] and ready["database"] == "writable" and ready["workers"] == "warm"
    text = client.get("/metrics").text
    for name in ("plenodust_queue_depth{state=\"queued\"}", "plenodust_job_duration_seconds_bucket",
                 "plenodust_usb_errors_total", "plenodust_jobs_total", "plenodust_upload_to_result_seconds_count"):
        assert name in text


def test_the_camera_watcher_queues_each_new_shot_under_the_current_run(client, camera_dir, camera_sim) -> None:
    deadline = time.monotonic() + 30
    while (cam := client.get("/api/v1/camera").json())["state"] != "connected" or not cam["calibrated"]:
        assert time.monotonic() < deadline, cam
        time.sleep(0.2)
    assert cam["serial"] == "A202160042" and cam["battery"] == pytest.approx(87.5)
    assert client.put("/api/v1/runs/current", json={"name": "shots"}, headers=AUTH).json() == {"name": "shots"}
    # The picture already on the camera at first contact is not queued; a new shot is.
    CameraFolder(camera_dir).add_picture(camera_sim.raw[1].read_bytes(), camera_sim.txt[1].read_bytes())
    deadline = time.monotonic() + 60
    while True:
        r = client.get("/api/v1/runs/shots/exposures")
        items = r.json()["items"] if r.status_code == 200 else []
        if items and items[0]["state"] == "done":
            break
        assert time.monotonic() < deadline, items
        time.sleep(0.2)
    assert len(items) == 1 and items[0]["source"] == "camera" and items[0]["frame"] == 0
    assert_matches_truth(client.get(f"/api/v1/exposures/{items[0]['id']}/particles").json()["columns"],
                         truth_xyz(camera_sim.truth[1]))
    # Pulling now finds nothing new, and queues nothing twice.
    pulled = client.post("/api/v1/camera/pull", headers=AUTH).json()
    assert pulled["queued"] == []
    assert client.get("/api/v1/calibrations").json()["items"][0]["serial"] == "A202160042"
    assert 'plenodust_camera_pulls_total 1' in client.get("/metrics").text


def test_docs_and_dashboard_are_served(client) -> None:
    assert client.get("/docs").status_code == 200
    paths = client.get("/openapi.json").json()["paths"]
    for path in ("/api/v1/exposures", "/api/v1/jobs/{job_id}", "/api/v1/exposures/{exposure_id}/particles",
                 "/api/v1/runs/{run}/particles", "/api/v1/events", "/api/v1/camera/pull", "/api/v1/calibrations"):
        assert path in paths
    assert "multipart/form-data" in paths["/api/v1/exposures"]["post"]["requestBody"]["content"]
    page = client.get("/")
    assert page.headers["content-type"].startswith("text/html") and "/static/app.js" in page.text
    assert client.get("/static/app.js").status_code == 200
    plotly = client.get("/static/vendor/plotly.min.js")  # the dashboard's plots, from the service itself
    assert plotly.status_code == 200 and len(plotly.content) > 1_000_000
