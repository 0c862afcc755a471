"""The service links each run's shots as they arrive: real service, real HTTP over loopback, real
SQLite, simulated shots with known truth (a moving ball, one shot a second on the metadata clock).

Checked against the simulator's truth: the trajectory ids the service gives follow the true
particles; t comes from the metadata clock; velocities agree with the true ones; the run's NeXus
file carries the trajectory columns; the per-shot summary is there; after a restart linking goes
on where it stopped (ids continue), and a failed shot in the middle does not stop it.
"""

from __future__ import annotations

import io
import time

import h5py
import httpx
import numpy as np
import pandas as pd
import pytest

from analysis.simulation.scenario_files import write_scenario
from analysis.simulation.scoring import match
from analysis.simulation.track_scoring import read_truth_run
from service_helpers import variant_lfp, wait_for_job
from service_server import ServiceProcess

OCTET = {"Content-Type": "application/octet-stream"}
SHOTS = 5


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    # A ball off focus on a 640 px crop: a few dozen particles, every one's blur over a lens pitch.
    return write_scenario(tmp_path_factory.mktemp("movie"), "ball", 11, count=SHOTS, size=640, centre_z_mm=57.4,
                          progress=lambda line: None)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("data")


def _start(data_dir) -> ServiceProcess:
    env = {"PLENODUST_PIPELINE": '{"alpha_min": 0.999, "alpha_max": 1.026}'}
    return ServiceProcess(data_dir, env=env).wait_ready()


def _upload(url: str, data: bytes, run: str = "movie") -> dict:
    r = httpx.post(url + f"/api/v1/exposures?run={run}", content=data, headers=OCTET, timeout=60)
    assert r.status_code in (200, 202), r.text
    return r.json()


def _linked(url: str, frames: list[int], *, timeout_s: float = 30.0) -> dict:
    """The run's trajectories once ``frames`` are linked (a job is done a moment before its shot
    is linked; the ``tracks`` event says when)."""
    deadline = time.monotonic() + timeout_s
    while True:
        body = httpx.get(url + "/api/v1/runs/movie/trajectories").json()
        if body.get("frames") == frames or time.monotonic() > deadline:
            return body
        time.sleep(0.1)


def _pair_with_truth(table: dict, truth: pd.DataFrame) -> np.ndarray:
    """The true particle of each row (-1 where none is within half a mean NN distance)."""
    out = np.full(len(table["frame"]), -1)
    frames = np.asarray(table["frame"])
    for f in np.unique(frames):
        rows = np.flatnonzero(frames == f)
        t = truth[truth["frame"] == f]
        r, c = match({k: np.asarray(table[k], float)[rows] for k in "XYZ"}, {k: t[k].to_numpy() for k in "XYZ"})
        out[rows[r]] = t["particle"].to_numpy()[c]
    return out


def test_shots_are_linked_as_they_arrive_and_served(sim, data_dir) -> None:
    truth = read_truth_run(sim.out_dir)
    service = _start(data_dir)
    try:
        url = service.url
        files = [("files", (p.name, p.read_bytes())) for p in sorted(sim.calibration_dir.iterdir())]
        assert httpx.post(url + "/api/v1/calibrations", files=files, timeout=60).status_code == 201
        # Not linked before the first result.
        first = _upload(url, sim.lfp[0].read_bytes())
        assert httpx.get(url + "/api/v1/runs/movie/summary").status_code == 409
        wait_for_job(lambda p: httpx.get(url + p), first["job_id"])
        for path in sim.lfp[1:SHOTS - 1]:
            wait_for_job(lambda p: httpx.get(url + p), _upload(url, path.read_bytes())["job_id"])

        body = _linked(url, list(range(SHOTS - 1)))
        table = body["columns"]
        assert body["frames"] == list(range(SHOTS - 1)) and body["count"] > 10 * (SHOTS - 1)
        assert list(table)[:13] == ["frame", "t", "particle", "index", "x", "y", "alpha", "X", "Y", "Z", "vX", "vY", "vZ"]
        # t is the metadata clock: one shot a second from the first.
        assert sorted(set(table["t"])) == pytest.approx([0.0, 1.0, 2.0, 3.0], abs=1e-3)
        # The service's trajectory ids follow the true particles.
        true_id = _pair_with_truth(table, truth)
        frame, particle = np.asarray(table["frame"]), np.asarray(table["particle"])
        order = np.lexsort((frame, particle))
        p, tid = particle[order], true_id[order]
        link = (p[1:] == p[:-1]) & (tid[1:] >= 0) & (tid[:-1] >= 0)
        # (A shadowed pair seen as one particle in one shot may cost a link: not more.)
        assert link.sum() > 20 and np.mean(tid[1:][link] == tid[:-1][link]) >= 0.97
        # Velocities: central between shots, close to the true ones (mm/s).
        merged = pd.DataFrame({"frame": frame, "truth": true_id, "vX": table["vX"], "vY": table["vY"]})
        merged = merged.merge(truth[["frame", "particle", "vX", "vY"]], left_on=["frame", "truth"],
                              right_on=["frame", "particle"], suffixes=("", "_true"))
        inner = merged[(merged["frame"] > 0) & (merged["frame"] < SHOTS - 2)].dropna()
        assert len(inner) > 10
        err = np.hypot(inner["vX"] - inner["vX_true"], inner["vY"] - inner["vY_true"])
        speed = np.hypot(inner["vX_true"], inner["vY_true"])
        assert np.median(err) < 0.5 * np.median(speed), (np.median(err), np.median(speed))

        # The same table as CSV and HDF5; a trail of the last two frames only.
        csv = pd.read_csv(io.StringIO(httpx.get(url + "/api/v1/runs/movie/trajectories?format=csv").text))
        assert list(csv["particle"]) == table["particle"]
        h5 = httpx.get(url + "/api/v1/runs/movie/trajectories?format=h5").content
        with h5py.File(io.BytesIO(h5), "r") as f:
            assert f["entry/data/particle"][()].tolist() == table["particle"]
            assert f["entry/data/vX"].attrs.get("units") in (None, "mm/s")
        trail = httpx.get(url + "/api/v1/runs/movie/trajectories?frame_min=2&frame_max=3").json()
        assert trail["frames"] == [2, 3]
        # The run's NeXus file has the trajectory columns.
        with h5py.File(io.BytesIO(httpx.get(url + "/api/v1/runs/movie/particles?format=h5").content), "r") as f:
            names = set(f["entry/data"].keys())
            assert {"particle", "t", "vX", "vY", "vZ", "index"} <= names
            assert np.all(f["entry/data/particle"][()] >= 0)

        summary = httpx.get(url + "/api/v1/runs/movie/summary").json()
        s = summary["columns"]
        assert s["frame"] == list(range(SHOTS - 1)) and summary["particle_mass_kg"] == pytest.approx(6.0766e-13, rel=1e-3)
        assert s["count"] == [int(np.sum(frame == f)) for f in range(SHOTS - 1)]
        assert all(v is not None and v > 0 for v in s["T_xy_eV"][1:-1])
        assert "noise_Z_mm" in s and "shells" in s
    finally:
        service.stop()

    # A restart: linking goes on from the run file and the database; a failed shot is bridged.
    service = _start(data_dir)
    try:
        url = service.url
        # Frame 4 is another camera's shot, whose white images the service lacks: its job fails ...
        broken = _upload(url, variant_lfp(sim.lfp[SHOTS - 1], 1, serial="A262000077"))
        assert wait_for_job(lambda p: httpx.get(url + p), broken["job_id"])["state"] == "failed"
        last = _upload(url, sim.lfp[SHOTS - 1].read_bytes())  # ... frame 5 is linked across it
        wait_for_job(lambda p: httpx.get(url + p), last["job_id"])
        body = _linked(url, [0, 1, 2, 3, 5])
        table = body["columns"]
        assert body["frames"] == [0, 1, 2, 3, 5]
        true_id = _pair_with_truth({**table, "frame": [f if f < 4 else 4 for f in table["frame"]]}, truth)
        frame, particle = np.asarray(table["frame"]), np.asarray(table["particle"])
        before = dict(zip(true_id[(frame == 3) & (true_id >= 0)], particle[(frame == 3) & (true_id >= 0)]))
        after = dict(zip(true_id[(frame == 5) & (true_id >= 0)], particle[(frame == 5) & (true_id >= 0)]))
        common = set(before) & set(after)
        assert len(common) > 10 and np.mean([before[k] == after[k] for k in common]) >= 0.95
    finally:
        service.stop()
