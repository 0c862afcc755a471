"""The camera watcher against the driver's simulated cameras: first contact, callbacks,
back-pressure that leaves shots on the camera, and a camera that goes away."""

from __future__ import annotations

import asyncio
import shutil
import time
from pathlib import Path

import pytest

from driver import open_simulated, open_wifi
from driver.protocol import picture_id
from driver.simulated import CameraFolder
from driver.simulated_wifi import SimulatedWifiServer
from service.database import Database
from service.events import EventBus
from service.metrics import Metrics
from service.queue import JobQueue, QueueFull
from service.store import Store
from service.watcher import CameraUnavailable, CameraWatcher, open_camera
from service_helpers import simulate


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    return simulate(tmp_path_factory.mktemp("sim"), seed=6, count=3)


@pytest.fixture
def camera_dir(tmp_path: Path, sim) -> Path:
    folder = tmp_path / "camera"
    shutil.copytree(sim.calibration_dir, folder / "calibration")
    CameraFolder(folder).add_picture(sim.raw[0].read_bytes(), sim.txt[0].read_bytes())
    return folder


@pytest.fixture
def parts(tmp_path: Path):
    db = Database(tmp_path / "data" / "plenodust.sqlite")
    store = Store(tmp_path / "data", db)
    yield store, db
    db.close()


def _watcher(opener, store: Store, *, capacity: int = 64, poll_s: float = 30.0) -> CameraWatcher:
    queue = JobQueue(store.db, capacity=capacity)
    return CameraWatcher(opener, store, queue, EventBus(), Metrics(), current_run=lambda: "shots",
                         on_queued=lambda: None, poll_s=poll_s)


def test_first_contact_pulls_white_images_once_and_skips_old_pictures(camera_dir, parts) -> None:
    store, db = parts
    watcher = _watcher(lambda: open_simulated(camera_dir), store)
    assert watcher.poll_once() == []          # the picture already there belongs to earlier work
    [calibration] = store.calibration_serials()
    assert calibration["serial"] == "A202160042" and calibration["source"] == "camera"
    assert calibration["images"] == len(list((camera_dir / "calibration").iterdir()))
    # The camera reports the serial its white images (and shots) carry: the one they are filed under.
    assert watcher.status()["serial"] == "A202160042" and watcher.status()["calibrated"]
    watcher.close()


def test_a_wifi_announcement_pulls_the_shot_before_the_next_poll(camera_dir, parts, sim) -> None:
    store, db = parts
    with SimulatedWifiServer(camera_dir) as server:
        watcher = _watcher(lambda: open_wifi("127.0.0.1", server.port, callback_port=server.callback_port,
                                             timeout_s=5.0), store, poll_s=60.0)

        async def scenario() -> float:
            task = asyncio.create_task(watcher.run())
            try:
                while watcher.last_poll is None:
                    await asyncio.sleep(0.05)
                raw = sim.raw[1].read_bytes()
                CameraFolder(camera_dir).add_picture(raw, sim.txt[1].read_bytes())
                start = time.monotonic()
                server.announce(picture_id(raw))
                while not db.read("SELECT 1 FROM exposures WHERE run = 'shots'"):
                    assert time.monotonic() - start < 20, "the announcement was not acted on"
                    await asyncio.sleep(0.05)
                return time.monotonic() - start
            finally:
                task.cancel()
                await asyncio.gather(task, return_exceptions=True)

        waited = asyncio.run(scenario())
        watcher.close()
    assert waited < 10  # well before the 60 s poll
    [row] = db.read("SELECT source, frame, run FROM exposures WHERE run = 'shots'")
    assert (row["source"], row["frame"]) == ("camera", 0)


def test_a_full_queue_leaves_shots_on_the_camera_until_there_is_room(camera_dir, parts, sim) -> None:
    store, db = parts
    watcher = _watcher(lambda: open_simulated(camera_dir), store, capacity=1)
    watcher.poll_once()
    for k in (1, 2):
        CameraFolder(camera_dir).add_picture(sim.raw[k].read_bytes(), sim.txt[k].read_bytes())
    with pytest.raises(QueueFull):
        watcher.poll_once()                   # the first new shot is queued, the second waits
    assert len(db.read("SELECT * FROM exposures")) == 1
    job = watcher.queue.claim("w")
    with db.write() as conn:
        watcher.queue.complete(conn, job.id, "w")
    [queued] = watcher.poll_once()
    assert queued["frame"] == 1 and queued["created"]
    assert watcher.poll_once() == []          # and nothing twice
    watcher.close()


def test_a_camera_that_goes_away_is_reported_and_counted(camera_dir, parts) -> None:
    store, db = parts
    with SimulatedWifiServer(camera_dir) as server:
        watcher = _watcher(lambda: open_wifi("127.0.0.1", server.port, callback_port=server.callback_port,
                                             timeout_s=1.0), store)
        watcher.poll_once()
        assert watcher.status()["state"] == "connected"
    with pytest.raises(CameraUnavailable):
        watcher.poll_once()
    assert watcher.status()["state"] == "disconnected" and watcher.status()["last_error"]
    assert watcher.metrics.value("plenodust_usb_errors_total") == 1
    watcher.close()


def test_camera_specs_open_the_named_camera(camera_dir) -> None:
    with open_camera(f"simulated:{camera_dir}") as camera:
        assert camera.info().serial == "A202160042"
    with SimulatedWifiServer(camera_dir) as server, open_camera(f"wifi:127.0.0.1:{server.port}") as camera:
        assert [pic.name for pic in camera.pictures()] == ["IMG_0001"]
    for bad in ("usb2", "wifi:", "simulated:", "firewire:1"):
        with pytest.raises(CameraUnavailable, match="use usb, wifi:HOST"):
            open_camera(bad)
