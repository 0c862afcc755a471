"""Scale-out: jobs sent to a Dask distributed cluster while the queue stays in SQLite."""

from __future__ import annotations

import time

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from service_helpers import assert_matches_truth, simulate, truth_xyz, wait_for_job

distributed = pytest.importorskip("distributed")


@pytest.fixture(scope="module")
def cluster():
    # TCP, as a real scheduler is reached (an in-process cluster would default to inproc://).
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp",
                                  dashboard_address=None) as local:
        yield local


def test_jobs_run_on_a_dask_cluster(tmp_path, cluster) -> None:
    sim = simulate(tmp_path / "sim", seed=3, count=1)
    address = cluster.scheduler_address.replace("tcp://", "dask://")
    settings = Settings(data_dir=tmp_path / "data", executor=address)
    with TestClient(create_app(settings)) as client:
        deadline = time.monotonic() + 120
        while (ready := client.get("/readyz").json())["workers"] != "warm":
            assert time.monotonic() < deadline, ready
            time.sleep(0.2)
        assert ready["executor"] == "dask"
        files = [("files", (p.name, p.read_bytes())) for p in sorted(sim.calibration_dir.iterdir())]
        assert client.post("/api/v1/calibrations", files=files).status_code == 201
        r = client.post("/api/v1/exposures?run=dask", content=sim.lfp[0].read_bytes(),
                        headers={"Content-Type": "application/octet-stream"})
        assert r.status_code == 202
        job = wait_for_job(client.get, r.json()["job_id"])
        assert job["state"] == "done", job
        # The queue and the index stay in SQLite even though the work ran on the cluster.
        assert client.get("/api/v1/jobs?state=done").json()["total"] == 1
        table = client.get(f"/api/v1/exposures/{r.json()['exposure_id']}/particles").json()
        assert_matches_truth(table["columns"], truth_xyz(sim.truth[0]))
    # The task really went through the scheduler (its prefix outlives the finished task).
    assert "plenodust" in cluster.scheduler.task_prefixes


def test_dask_workers_report_progress_stage_by_stage(tmp_path, cluster) -> None:
    import asyncio

    from service.executors import DaskExecutor
    from service.results import JobTask

    sim = simulate(tmp_path / "sim", seed=4, count=1)
    task = JobTask(exposure_id="0" * 40, raw_paths=(str(sim.lfp[0]),), calibration_dir=str(sim.calibration_dir),
                   calibration_cache_dir=str(tmp_path / "cache"))
    seen: list[float] = []
    stages: list[str] = []

    def report(fraction: float, stage: str | None) -> None:
        seen.append(fraction)
        stages.append(stage)

    async def go():
        executor = DaskExecutor(cluster.scheduler_address, warm_up=False)
        await executor.start()
        try:
            output = await executor.run(task, report)
            # Events travel through the scheduler: give the last ones a moment.
            deadline = time.monotonic() + 10
            while (not seen or seen[-1] < 1.0) and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            return output
        finally:
            await executor.close()

    output = asyncio.run(go())
    assert output.particles > 0
    assert any(0.0 < f < 1.0 for f in seen), seen  # stages in between, not just start and end
    assert seen == sorted(seen) and seen[-1] == 1.0
    assert "refocus" in stages and "refine" in stages  # each report names its stage
