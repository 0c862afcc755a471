"""Shared set-up for the service tests: simulated exposures and waiting for jobs."""

from __future__ import annotations

import csv
import time
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from analysis.formats.exposure import Exposure, lfp_bytes, read_exposure
from analysis.simulation.scenario_files import write_scenario

# Small crops keep the tests fast on two cores; the pipeline still finds particles there.
SIZE_PX = 480


def simulate(folder: Path, *, scenario: str = "ball", seed: int = 1, count: int = 2):
    """Simulated camera files with truth (see docs/interfaces.md)."""
    return write_scenario(folder, scenario, seed, count=count, size=SIZE_PX, progress=lambda line: None)


def truth_xyz(path: Path) -> np.ndarray:
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return np.array([[float(r["X"]), float(r["Y"]), float(r["Z"])] for r in rows])


def assert_matches_truth(columns: dict, truth: np.ndarray) -> None:
    """Every particle found lies near a true one, and enough are found."""
    found = np.stack([np.asarray(columns[k], dtype=float) for k in ("X", "Y", "Z")], axis=1)
    assert len(found) >= 3, f"only {len(found)} particles found"
    dist, _ = cKDTree(truth).query(found)
    lateral, _ = cKDTree(truth[:, :2]).query(found[:, :2])
    # X, Y to a fraction of the cluster's 0.3-0.5 mm spacing; Z is the hard coordinate.
    assert np.median(lateral) < 0.05, lateral
    assert np.median(dist) < 0.35 and dist.max() < 0.8, dist


def variant_lfp(path: Path, k: int, *, serial: str | None = None, dark: bool = False) -> bytes:
    """A different but valid exposure: the picture with one raw pixel changed (and maybe its serial);
    ``dark``: the picture replaced by its background level first (a shot with no particle in view,
    which the pipeline gets through in a fraction of the time)."""
    original = read_exposure(path)
    image = np.full_like(original.image, np.median(original.image)) if dark else original.image.copy()
    image[1, k % image.shape[1]] += 1
    private = dict(original.private_metadata)
    if serial is not None:
        private["camera"] = {**private.get("camera", {}), "serialNumber": serial}
    exposure = Exposure(image=image, metadata=original.metadata, private_metadata=private)
    return lfp_bytes(exposure)


def wait_for_job(get, job_id: str, *, timeout_s: float = 180.0, states=("done", "failed")) -> dict:
    """Poll ``GET /api/v1/jobs/{id}`` until the job reaches one of ``states``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        job = get(f"/api/v1/jobs/{job_id}").json()
        if job["state"] in states:
            return job
        time.sleep(0.1)
    raise TimeoutError(f"job {job_id} still {job['state']} after {timeout_s} s")


def wait_until_ready(get, *, timeout_s: float = 120.0) -> None:
    """Poll ``GET /readyz`` until it answers 200; a timeout says what it last answered (workers
    still warming, a data disk below the free-space margin, ...)."""
    deadline = time.monotonic() + timeout_s
    while (r := get("/readyz")).status_code != 200:
        if time.monotonic() > deadline:
            raise TimeoutError(f"service not ready after {timeout_s} s: /readyz said {r.text}")
        time.sleep(0.2)


def assert_problem(response, status: int) -> dict:
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/problem+json")
    body = response.json()
    assert body["status"] == status and body["title"] and body["detail"] and body["type"]
    return body
