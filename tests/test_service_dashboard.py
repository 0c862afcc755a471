"""The dashboard in headless Chromium against the real service: data arrives and is drawn, and
a physicist can read it (axes with units, colour bars, one Y orientation, the fitted depth
against the curve's peak, every slice, a 1000 px window); /docs works without internet.

Skipped only when Chromium is not installed (``make test`` installs Debian's ``chromium``
when it runs as root). Screenshots are kept under ``.cache/`` for a person to look at.
"""

from __future__ import annotations

import json
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

SHOTS = ROOT / ".cache"


@pytest.fixture(scope="module")
def chromium() -> str:
    path = chromium_path()
    if path is None:
        pytest.skip("headless Chromium is not installed (apt-get install chromium; `make test` does it as root)")
    return path


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return simulate(tmp_path_factory.mktemp("sim"), seed=4, count=2)


@pytest.fixture(scope="module")
def server(tmp_path_factory, sim):
    service = ServiceProcess(tmp_path_factory.mktemp("data")).wait_ready()
    try:
        files = [("files", (p.name, p.read_bytes())) for p in sorted(sim.calibration_dir.iterdir())]
        assert httpx.post(service.url + "/api/v1/calibrations", files=files, timeout=60).status_code == 201
        yield service
    finally:
        service.stop()


OCTET = {"Content-Type": "application/octet-stream"}


def _upload(server, data: bytes) -> dict:
    r = httpx.post(server.url + "/api/v1/exposures?run=dash", content=data, headers=OCTET)
    assert r.status_code in (200, 202), r.text
    wait_for_job(lambda p: httpx.get(server.url + p), r.json()["job_id"])
    return r.json()


def _plot(browser: Browser, plot_id: str, expression: str) -> object:
    """``expression`` evaluated with ``gd`` the plotly.js graph div ``plot_id``."""
    return browser.evaluate(f"(() => {{ const gd = document.getElementById('{plot_id}'); return {expression}; }})()")


def test_dashboard_shows_new_results_live_and_readably(server, sim, chromium) -> None:
    first = _upload(server, sim.lfp[0].read_bytes())
    with Browser(chromium, offline=True) as browser:
        browser.goto(server.url + "/")
        browser.wait_for("document.getElementById('stream').textContent === 'live'")
        browser.wait_for("document.getElementById('status').textContent.includes('frame 0')")
        # A new result reaches the page through the event stream alone (no reload).
        second = httpx.post(server.url + "/api/v1/exposures?run=dash", content=variant_lfp(sim.lfp[1], 1), headers=OCTET)
        wait_for_job(lambda p: httpx.get(server.url + p), second.json()["job_id"])
        status = browser.wait_for(
            "(() => { const t = document.getElementById('status').textContent;"
            " return t.includes('frame 1') && document.getElementById('slice-view').data && t; })()")
        exposure = second.json()["exposure_id"]
        count = httpx.get(server.url + f"/api/v1/exposures/{exposure}/particles").json()["count"]
        assert f"{count} particles" in status
        assert browser.evaluate("document.querySelectorAll('#exposures li').length") == 2
        # The header tells the run new shots go to from the run on view.
        current = httpx.get(server.url + "/api/v1/runs").json()["current"]
        assert browser.evaluate("document.getElementById('current-run').textContent") == current
        viewing = browser.evaluate("[document.getElementById('viewing').hidden,"
                                   " document.getElementById('viewing-run').textContent]")
        assert viewing == ([True, "dash"] if current == "dash" else [False, "dash"])
        assert browser.evaluate("document.getElementById('particle').options.length") == count
        time.sleep(0.5)

        # Trails: the two shots are linked as they arrive, and each view draws every trajectory's path.
        trails = httpx.get(server.url + "/api/v1/runs/dash/trajectories?frame_min=0&frame_max=1").json()
        linked = {p for p, f in zip(trails["columns"]["particle"], trails["columns"]["frame"]) if f == 1}
        browser.wait_for("document.getElementById('scatter').data.length === 3"
                         " && document.getElementById('scatter').data[2].x.length > 0")
        for plot_id in ("scatter", "top"):
            xs = _plot(browser, plot_id, "gd.data[2].x")
            assert _plot(browser, plot_id, "gd.data[2].mode") == "lines"
            # One line per trajectory seen in both shots, separated by gaps (null).
            points = [v for v in xs if v is not None]
            assert len(points) == trails["count"] and xs.count(None) == len(set(trails["columns"]["particle"])) - 1
        assert any("trajectory" in t for t in _plot(browser, "top", "gd.data[0].text")) and linked
        # The run over time: particles per shot, temperature with its error bars, against t in s.
        browser.wait_for("document.getElementById('timeline').data")
        summary = httpx.get(server.url + "/api/v1/runs/dash/summary").json()["columns"]
        assert _plot(browser, "timeline", "gd.data[0].y") == summary["count"]
        assert _plot(browser, "timeline", "gd.data.map(d => d.name)")[:3] == ["particles", "T lateral (X, Y)", "T (X, Y, Z)"]
        assert "t (s" in _plot(browser, "timeline", "gd._fullLayout.xaxis.title.text")
        assert _plot(browser, "timeline", "gd._fullLayout.yaxis2.title.text") == "T (eV)"
        assert "position noise" in browser.evaluate("document.getElementById('run-info').textContent")

        # 3D positions: named axes in mm with tick labels, a colour bar for Z, Y down.
        scene = _plot(browser, "scatter", "(a => ({x: a.xaxis.title.text, y: a.yaxis.title.text, z: a.zaxis.title.text,"
                                          " ticks: a.xaxis.showticklabels && a.zaxis.showticklabels,"
                                          " yDown: a.yaxis.autorange === 'reversed'}))(gd._fullLayout.scene)")
        assert scene == {"x": "X (mm)", "y": "Y (mm)", "z": "Z (mm)", "ticks": True, "yDown": True}
        assert _plot(browser, "scatter", "gd._fullData[0].marker.showscale && gd._fullData[0].marker.colorbar.title.text") \
            == "Z (mm)"
        assert _plot(browser, "scatter", "gd.querySelectorAll('.colorbar .cbaxis text, .colorbar text').length") > 3
        # Top view: Y down too, said on the axis; its colour bar names Z.
        assert _plot(browser, "top", "gd._fullLayout.yaxis.range[0] > gd._fullLayout.yaxis.range[1]")
        assert "down" in _plot(browser, "top", "gd._fullLayout.yaxis.title.text")
        assert _plot(browser, "top", "[...gd.querySelectorAll('.colorbar text')].map(t => t.textContent).join(' ')") \
            .count("Z (mm)") == 1
        # The slice image is in image coordinates: y down as well.
        assert _plot(browser, "slice-view", "gd._fullLayout.yaxis.range[0] > gd._fullLayout.yaxis.range[1]")

        # B(alpha): a named axis with its unit, plain tick labels; fitted alpha and the curve's peak both shown.
        assert _plot(browser, "curve", "gd._fullLayout.yaxis.title.text") == "B(α), DN² per pixel"
        ticks = _plot(browser, "curve", "[...gd.querySelectorAll('.ytick text')].map(t => t.textContent)")
        assert ticks and not any("e+" in t for t in ticks), ticks
        names = _plot(browser, "curve", "gd.data.map(d => d.name)")
        assert any(n.startswith("fitted α") for n in names) and any(n.startswith("curve peak") for n in names)
        info = browser.evaluate("document.getElementById('particle-info').textContent")
        assert "The table holds the fitted α" in info and "forward-model fit" in info
        # Particles whose depth their pixels leave open are flagged, in the top view and when picked.
        opened = browser.evaluate("view.table.columns.x.map((_, i) => depthOpen(i))")
        symbols = _plot(browser, "top", "gd.data[0].marker.symbol")
        assert [s == "circle-open" for s in symbols] == opened
        if any(opened):
            browser.evaluate(f"pickParticle({opened.index(True)}, {{jump: true}})")
            assert "Depth left open by its pixels" in browser.evaluate("document.getElementById('particle-info').textContent")

        # Every slice is kept; picking a particle shows the slice of its depth.
        info = httpx.get(server.url + f"/api/v1/exposures/{exposure}").json()
        assert info["slices"] == len(httpx.get(server.url + f"/api/v1/exposures/{exposure}/curves").json()["alpha"])
        assert browser.evaluate("+document.getElementById('slice').max") == info["slices"] - 1
        alphas = np.array(info["slice_alpha"])
        table = httpx.get(server.url + f"/api/v1/exposures/{exposure}/particles").json()["columns"]
        for particle in (0, count - 1):
            browser.evaluate(f"(() => {{ const s = document.getElementById('particle'); s.value = '{particle}';"
                             " s.dispatchEvent(new Event('change')); })()")
            expected = int(np.argmin(np.abs(alphas - table["alpha"][particle])))
            assert browser.evaluate("+document.getElementById('slice').value") == expected
            browser.wait_for(f"document.getElementById('slice-alpha').textContent.includes('({expected + 1} of')")
        time.sleep(0.5)
        shot = browser.screenshot(SHOTS / "dashboard.png")
    image = cv2.imread(str(shot))
    assert image.shape[:2] == (1000, 1500)
    assert len(np.unique(image.reshape(-1, 3), axis=0)) > 100  # drawn, not a blank page


def test_a_1000_px_window_shows_all_four_panels(server, sim, chromium) -> None:
    _upload(server, sim.lfp[0].read_bytes())
    with Browser(chromium, width=1000, height=900, offline=True) as browser:
        browser.goto(server.url + "/")
        browser.wait_for("document.getElementById('slice-view').data && document.getElementById('curve').data")
        time.sleep(0.5)
        boxes = browser.evaluate("JSON.stringify([...document.querySelectorAll('.panel')].map(p => {"
                                 " const r = p.getBoundingClientRect(); return [r.left, r.top, r.right, r.bottom]; }))")
        panels = json.loads(boxes)
        assert len(panels) == 5  # the four views, and the run over time in a row below them (scrolled to)
        for left, top, right, bottom in panels[:4]:
            assert 0 <= left and right <= 1000 and 0 <= top and bottom <= 900, panels
            assert right - left > 300 and bottom - top > 300, panels
        # Each plot fills its panel (no empty area under the curve), and the curve's note is in view.
        for plot_id in ("scatter", "top", "curve", "slice-view"):
            size = _plot(browser, plot_id, "[gd.clientHeight, gd._fullLayout.height]")
            assert size[0] > 180 and abs(size[0] - size[1]) <= 2, (plot_id, size)
        note = json.loads(browser.evaluate("JSON.stringify(document.getElementById('particle-info').getBoundingClientRect())"))
        curve_panel = panels[2]
        assert note["height"] > 10 and note["bottom"] <= curve_panel[3] + 1
        browser.screenshot(SHOTS / "dashboard-1000.png")
        # The run's time plots fill the row below, a scroll away.
        browser.evaluate("document.querySelector('.panel.wide').scrollIntoView()")
        wide = json.loads(browser.evaluate("JSON.stringify(document.querySelector('.panel.wide').getBoundingClientRect())"))
        assert wide["width"] > 700 and wide["height"] >= 300 and wide["bottom"] <= 901, wide
        time.sleep(0.5)
        browser.screenshot(SHOTS / "dashboard-1000-timeline.png")


def test_api_docs_load_without_internet(server, chromium) -> None:
    with Browser(chromium, offline=True) as browser:
        browser.goto(server.url + "/docs")
        operations = browser.wait_for("document.querySelectorAll('.swagger-ui .opblock').length", timeout_s=60)
        assert operations >= 15
        assert "plenodust API" in browser.evaluate("document.title")
        # The response models are there to read.
        schemas = browser.wait_for("document.querySelector('.swagger-ui section.models') &&"
                                   " document.querySelector('.swagger-ui section.models').innerText")
        for model in ("Job", "UploadAccepted", "ParticleTable", "ProblemBody", "Readiness"):
            assert model in schemas
