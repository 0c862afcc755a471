"""Target calibrations in the service, over real HTTP: given at start (``serve --metric-calibration``)
or uploaded next to the white images, picked for each exposure's camera, zoom and focus, used for
its X, Y, Z (an exposure through an auxiliary lens comes out where its particles truly are) and
recorded with the result."""

from __future__ import annotations

import json

import httpx
import numpy as np
import pytest
from scipy.spatial import cKDTree

from analysis.calibration.metric_files import save_metric_calibration
from analysis.camera.mapping_fit import metric_calibration
from analysis.camera.target_mapping import CameraKey
from analysis.simulation.camera import DEFAULT_LENS, DEFAULT_SERIAL
from analysis.simulation.scenario_files import write_scenario
from service_helpers import assert_problem, truth_xyz, wait_for_job
from service_server import ServiceProcess
from target_helpers import PAPER_FRONT, main_lens, observations


def _metric_file(folder, *, focus_step=DEFAULT_LENS.focus_step):
    key = CameraKey(DEFAULT_SERIAL, DEFAULT_LENS.zoom_step, focus_step)
    cal = metric_calibration(observations(noise_alpha=1e-5), main_lens(), key, margin_mm=0.5,
                             created_utc="2024-05-01T00:00:00Z")
    return save_metric_calibration(cal, folder / f"metric-{focus_step}.json")


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    files = tmp_path_factory.mktemp("files")
    sim = write_scenario(files / "sim", "ball", 3, count=1, size=800, front_optics=PAPER_FRONT,
                         progress=lambda line: None)
    metric = _metric_file(files)
    service = ServiceProcess(tmp_path_factory.mktemp("data"), args=["--metric-calibration", str(metric)])
    try:
        service.wait_ready()
        whites = [("files", (p.name, p.read_bytes())) for p in sorted(sim.calibration_dir.iterdir())]
        r = httpx.post(service.url + "/api/v1/calibrations", files=whites, timeout=60)
        assert r.status_code == 201, r.text
        yield service, sim, metric
    finally:
        service.stop()


def test_an_exposure_through_an_auxiliary_lens_is_measured_with_the_cameras_target_calibration(setup):
    service, sim, metric = setup
    client = httpx.Client(base_url=service.url, timeout=60)
    listed = client.get("/api/v1/calibrations/metric").json()["items"]
    assert [(c["serial"], c["zoom_step"], c["focus_step"]) for c in listed] == [
        (DEFAULT_SERIAL, DEFAULT_LENS.zoom_step, DEFAULT_LENS.focus_step)]
    r = client.post("/api/v1/exposures?run=target", content=sim.lfp[0].read_bytes(),
                    headers={"Content-Type": "application/octet-stream"})
    assert r.status_code == 202, r.text
    ids = r.json()
    job = wait_for_job(client.get, ids["job_id"])
    assert job["state"] == "done", job
    info = client.get(f"/api/v1/exposures/{ids['exposure_id']}").json()
    assert info["coordinates"]["kind"] == "target"
    assert info["coordinates"]["sha1"] == listed[0]["sha1"]
    table = client.get(f"/api/v1/exposures/{ids['exposure_id']}/particles").json()
    found = np.stack([np.asarray(table["columns"][k], float) for k in ("X", "Y", "Z")], axis=1)
    truth = truth_xyz(sim.truth[0])
    assert len(found) >= 5
    dist, _ = cKDTree(truth).query(found)
    # The metadata's thin lens would put them 7 mm farther (where the main lens sees them).
    assert np.median(dist) < 0.1, dist


def test_calibrations_are_uploaded_next_to_the_white_images_and_checked(setup, tmp_path):
    service, _, _ = setup
    client = httpx.Client(base_url=service.url, timeout=60)
    other = _metric_file(tmp_path, focus_step=DEFAULT_LENS.focus_step + 120)
    r = client.post("/api/v1/calibrations/metric", content=other.read_bytes(),
                    headers={"Content-Type": "application/json"})
    assert r.status_code == 201, r.text
    assert r.json()["focus_step"] == DEFAULT_LENS.focus_step + 120 and r.json()["model"] in ("physical", "polynomial")
    assert len(client.get("/api/v1/calibrations/metric").json()["items"]) == 2
    body = assert_problem(client.post("/api/v1/calibrations/metric", content=json.dumps({"format": "other"}),
                                      headers={"Content-Type": "application/json"}), 422)
    assert "calibrate-target" in body["detail"]
    assert_problem(client.post("/api/v1/calibrations/metric", content=b"x", headers={"Content-Type": "text/plain"}),
                   415)
