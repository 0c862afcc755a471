"""Exposures that arrive before their camera's white images run once the white images do."""

from __future__ import annotations

from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from service_helpers import assert_matches_truth, simulate, truth_xyz, wait_for_job, wait_until_ready


def test_jobs_waiting_for_white_images_run_when_they_are_uploaded(tmp_path) -> None:
    sim = simulate(tmp_path / "sim", seed=8, count=1)
    with TestClient(create_app(Settings(data_dir=tmp_path / "data"))) as client:
        wait_until_ready(client.get)
        r = client.post("/api/v1/exposures?run=early", content=sim.lfp[0].read_bytes(),
                        headers={"Content-Type": "application/octet-stream"})
        job = wait_for_job(client.get, r.json()["job_id"])
        assert job["state"] == "failed" and job["error"].startswith("NoWhiteImageError")
        assert "POST /api/v1/calibrations" in job["error"]  # the message says what to do

        files = [("files", (p.name, p.read_bytes())) for p in sorted(sim.calibration_dir.iterdir())]
        calibration = client.post("/api/v1/calibrations", files=files)
        assert calibration.status_code == 201 and calibration.json()["jobs_retried"] == [job["id"]]
        assert wait_for_job(client.get, job["id"])["state"] == "done"
        table = client.get(f"/api/v1/exposures/{r.json()['exposure_id']}/particles").json()
        assert_matches_truth(table["columns"], truth_xyz(sim.truth[0]))
