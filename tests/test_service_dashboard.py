"""The dashboard in headless Chromium against the real service: data arrives and is drawn.

Skipped only when Chromium is not installed (``make test`` installs Debian's ``chromium``
when it runs as root). The screenshot is kept under ``.cache/`` for a person to look at.
"""

from __future__ import annotations

import time
from pathlib import Path

import cv2
import httpx
import numpy as np
import pytest

from headless_chromium import Browser, chromium_path
from service_helpers import simulate, variant_lfp, wait_for_job
from service_server import ROOT, ServiceProcess

pytestmark = pytest.mark.browser

SHOT = ROOT / ".cache" / "dashboard.png"


@pytest.fixture(scope="module")
def chromium() -> str:
    path = chromium_path()
    if path is None:
        pytest.skip("headless Chromium is not installed (apt-get install chromium; `make test` does it as root)")
    return path


def _canvas_pixels(browser: Browser, canvas_id: str) -> int:
    """Lit pixels of a canvas, counted in the page."""
    return browser.evaluate(f"""(() => {{
        const c = document.getElementById('{canvas_id}');
        const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
        let n = 0;
        for (let i = 0; i < d.length; i += 4) if (d[i] + d[i + 1] + d[i + 2] > 150) n++;
        return n; }})()""")


def test_dashboard_shows_new_results_live(tmp_path: Path, chromium: str) -> None:
    sim = simulate(tmp_path / "sim", seed=4, count=2)
    server = ServiceProcess(tmp_path / "data").wait_ready()
    try:
        files = [("files", (p.name, p.read_bytes())) for p in sorted(sim.calibration_dir.iterdir())]
        assert httpx.post(server.url + "/api/v1/calibrations", files=files).status_code == 201
        octet = {"Content-Type": "application/octet-stream"}
        first = httpx.post(server.url + "/api/v1/exposures?run=dash", content=sim.lfp[0].read_bytes(), headers=octet)
        wait_for_job(lambda p: httpx.get(server.url + p), first.json()["job_id"])
        with Browser(chromium) as browser:
            browser.goto(server.url + "/")
            browser.wait_for("document.getElementById('stream').textContent === 'live'")
            browser.wait_for("document.getElementById('status').textContent.includes('frame 0')")
            # A new result reaches the page through the event stream alone (no reload).
            second = httpx.post(server.url + "/api/v1/exposures?run=dash", content=variant_lfp(sim.lfp[1], 1),
                                headers=octet)
            wait_for_job(lambda p: httpx.get(server.url + p), second.json()["job_id"])
            status = browser.wait_for(
                "(() => { const t = document.getElementById('status').textContent;"
                " return t.includes('frame 1') && document.getElementById('slice-alpha').textContent && t; })()")
            count = httpx.get(server.url + f"/api/v1/exposures/{second.json()['exposure_id']}/particles").json()["count"]
            assert f"{count} particles" in status
            assert browser.evaluate("document.querySelectorAll('#exposures li').length") == 2
            assert browser.evaluate("document.getElementById('particle').options.length") == count
            time.sleep(0.3)
            for canvas in ("scatter", "top", "curve", "slice-view"):
                assert _canvas_pixels(browser, canvas) > 200, canvas
            SHOT.parent.mkdir(parents=True, exist_ok=True)
            browser.screenshot(SHOT)
    finally:
        server.stop()
    image = cv2.imread(str(SHOT))
    assert image.shape[:2] == (1000, 1500)
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 100  # drawn, not a blank page
