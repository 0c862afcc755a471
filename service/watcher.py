"""Automatic processing: pull every new shot from the camera and queue it under the current run.

The watcher keeps which pictures it has pulled in SQLite (``camera_pictures``), so a
restart neither loses a shot nor queues one twice. On first contact with a camera it
pulls the camera's white images (once per serial) for calibration. When the queue is
full it stops the round and tries again at the next poll: a shot stays on the camera
until it is accepted.
"""

from __future__ import annotations

import asyncio
import logging
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import driver
from analysis.errors import AnalysisError
from analysis.formats.whites import load_white_images
from service.disk import DiskGuard, NoSpace
from service.events import EventBus
from service.ingest import NotAnExposure, ingest, parse_exposure
from service.metrics import Metrics
from service.queue import JobQueue, QueueFull
from service.store import Store

log = logging.getLogger(__name__)


class CameraUnavailable(Exception):
    """No camera is configured, or it cannot be reached now."""


class ShotsNotSupported(Exception):
    """This camera cannot be told to take a picture over this connection."""


class ShotNotSeen(Exception):
    """The camera took no new picture (none appeared in its list in time)."""


def open_camera(spec: str) -> Any:
    """Open the camera a ``--camera`` value names: ``usb``, ``wifi:HOST[:PORT]`` or ``simulated:DIR``.

    Raises
    ------
    CameraUnavailable
        For any other value.
    """
    kind, _, arg = spec.partition(":")
    if kind == "usb":
        return driver.open_usb()
    if kind == "wifi" and arg:
        host, _, port = arg.partition(":")
        return driver.open_wifi(host, int(port)) if port else driver.open_wifi(host)
    if kind == "simulated" and arg:
        return driver.open_simulated(arg)
    raise CameraUnavailable(f"camera {spec!r}: use usb, wifi:HOST[:PORT] or simulated:DIR")


class CameraWatcher:
    """Polls a camera, pulls new pictures and queues them.

    Parameters
    ----------
    opener : callable
        Returns an open camera (``info()``, ``pictures()``, ``pull()``, ``pull_calibration()``,
        ``battery()``, ``close()``); called again after the camera goes away.
    current_run : callable
        The run new shots are filed under.
    pull_existing : bool
        On first contact with a camera, also queue the pictures already on it.
    """

    def __init__(self, opener: Callable[[], Any], store: Store, queue: JobQueue, bus: EventBus,
                 metrics: Metrics, *, current_run: Callable[[], str], on_queued: Callable[[], None],
                 poll_s: float = 2.0, pull_existing: bool = False, guard: DiskGuard | None = None) -> None:
        self.opener = opener
        self.store = store
        self.queue = queue
        self.bus = bus
        self.metrics = metrics
        self.current_run = current_run
        self.on_queued = on_queued
        self.poll_s = poll_s
        self.pull_existing = pull_existing
        self.guard = guard
        self.camera: Any = None
        self.state = "connecting"
        self.serial: str | None = None
        self.firmware: str | None = None
        self.battery: float | None = None
        self.last_error: str | None = None
        self.last_poll: float | None = None
        self.calibration_serial: str | None = None
        self._lock = threading.Lock()

    # -- status ----------------------------------------------------------------------

    def status(self) -> dict:
        return {"configured": True, "state": self.state, "serial": self.serial, "firmware": self.firmware,
                "battery": self.battery, "last_error": self.last_error, "last_poll": self.last_poll,
                "calibrated": bool(self.calibration_serial or (self.serial and self.store.has_calibration(self.serial))),
                "can_take_shots": bool(getattr(self.camera, "can_take_pictures", False))}

    def _set_state(self, state: str, error: str | None = None) -> None:
        changed = state != self.state or error != self.last_error
        self.state, self.last_error = state, error
        if changed:
            self.bus.publish("camera", self.status())

    # -- blocking work (runs in a thread) ----------------------------------------------

    def _connect(self) -> None:
        if self.camera is not None:
            return
        camera = self.opener()
        info = camera.info()
        self.camera = camera
        self.serial = info.serial
        self.firmware = getattr(info, "software", None)
        self._first_contact()

    def _first_contact(self) -> None:
        assert self.serial is not None
        if self.store.db.get_value(f"calibration_pulled:{self.serial}") is None:
            self._pull_calibration()
        marker = f"camera_seen:{self.serial}"
        if self.store.db.get_value(marker) is None:
            if not self.pull_existing:
                # Pictures already on a camera we meet for the first time belong to earlier work.
                now = time.time()
                with self.store.db.write() as conn:
                    for pic in self.camera.pictures():
                        conn.execute("INSERT OR IGNORE INTO camera_pictures (serial, picture, exposure_id, "
                                     "pulled_at) VALUES (?, ?, NULL, ?)", (self.serial, pic.id, now))
            self.store.db.set_value(marker, "1")

    def _pull_calibration(self) -> None:
        # Pull into a side folder, then file the white images under the serial they carry
        # (what the exposures' metadata will name), falling back to the camera's own.
        incoming = self.store.calibrations_dir / f".incoming-{self.serial}"
        if incoming.exists():
            shutil.rmtree(incoming)
        pulled = self.camera.pull_calibration(incoming)
        log.info("pulled %d calibration files from camera %s", len(pulled), self.serial)
        if pulled:
            try:
                serials = {w.serial for w in load_white_images(incoming) if w.serial}
            except AnalysisError as exc:
                log.error("white images pulled from camera %s are not usable: %s", self.serial, exc)
                serials = set()
            serial = serials.pop() if len(serials) == 1 else self.serial
            self.store.adopt_calibration(serial, incoming, source="camera")
            shutil.rmtree(incoming)
            self.calibration_serial = serial
            self.bus.publish("calibration", {"serial": serial, "camera": self.serial, "files": len(pulled)})
            # Uploads that came before the camera's white images run now.
            for job in self.queue.retry_waiting("calibration", serial=serial):
                self.bus.publish("job", job.public())
                self.on_queued()
        self.store.db.set_value(f"calibration_pulled:{self.serial}", "1")

    def _disconnect(self, error: Exception) -> None:
        self.metrics.inc("plenodust_usb_errors_total")
        camera, self.camera = self.camera, None
        if camera is not None:
            try:
                camera.close()
            except Exception:
                pass
        self._set_state("disconnected", f"{type(error).__name__}: {error}")

    def poll_once(self) -> list[dict]:
        """Connect if needed, pull every picture not pulled yet, queue each; returns what was queued.

        Raises
        ------
        CameraUnavailable
            If the camera cannot be reached (the error is also kept in :meth:`status`).
        """
        with self._lock:
            try:
                self._connect()
                self._set_state("connected")
                try:
                    self.battery = float(self.camera.battery())
                except Exception as exc:  # battery is nice to have; a failing query is not fatal
                    log.debug("battery query failed: %s", exc)
                queued = self._pull_new()
            except (QueueFull, NoSpace, CameraUnavailable):
                raise
            except Exception as exc:
                log.warning("camera: %s", exc)
                self._disconnect(exc)
                raise CameraUnavailable(f"the camera cannot be reached: {exc}") from exc
            finally:
                self.last_poll = time.time()
            return queued

    def _pull_new(self, only: set[str] | None = None) -> list[dict]:
        announced = getattr(self.camera, "new_picture", None)
        if announced is not None:
            announced.clear()  # whatever it announced is in the list read below
        seen = {r["picture"] for r in self.store.db.read(
            "SELECT picture FROM camera_pictures WHERE serial = ?", (self.serial,))}
        queued = []
        for pic in self.camera.pictures():
            if pic.id in seen or (only is not None and pic.id not in only):
                continue
            with tempfile.TemporaryDirectory(prefix="plenodust-pull-") as tmp:
                paths = self.camera.pull(pic, Path(tmp))
                by_suffix = {p.suffix.upper(): p.read_bytes() for p in paths}
            files = {".RAW": by_suffix[".RAW"], ".TXT": by_suffix[".TXT"]}
            self.metrics.inc("plenodust_camera_pulls_total")
            try:
                exposure = parse_exposure(files, name=pic.name)
            except NotAnExposure as exc:
                log.error("camera picture %s is not a readable exposure: %s; skipped", pic.name, exc)
                self._mark(pic.id, None)
                continue
            # QueueFull and NoSpace propagate: this picture is not marked, so a later poll tries again.
            accepted = ingest(self.store, self.queue, files, run=self.current_run(), source="camera",
                              serial=self.serial, exposure=exposure, guard=self.guard)
            self._mark(pic.id, accepted.exposure.id)
            if accepted.created:
                self.on_queued()
                self.bus.publish("job", {**accepted.job.public(), "run": accepted.exposure.run,
                                         "frame": accepted.exposure.frame})
            queued.append({"picture": pic.name, "exposure_id": accepted.exposure.id,
                           "job_id": accepted.job.id, "run": accepted.exposure.run,
                           "frame": accepted.exposure.frame, "created": accepted.created})
        return queued

    def take_shot(self, *, timeout_s: float = 30.0) -> dict:
        """Take a picture, pull it and queue it; returns what was queued (as :meth:`poll_once`).

        Raises
        ------
        ShotsNotSupported
            Over USB, where the F01's take-picture command is not known to work.
        ShotNotSeen
            If no new picture appears in the camera's list within ``timeout_s``.
        CameraUnavailable
            If the camera cannot be reached.
        """
        with self._lock:
            try:
                self._connect()
                if not getattr(self.camera, "can_take_pictures", False):
                    raise ShotsNotSupported(
                        "this camera cannot be told to take a picture: over USB the F01's take-picture "
                        "command is not known to work (lytro-f01.md, section 6), and a simulated camera needs "
                        "a shutter (plenodust demo has one). Connect the camera over Wi-Fi (--camera "
                        "wifi:HOST), or press its shutter and POST /api/v1/camera/pull")
                # Pictures there before are either pulled already or left alone (first contact).
                before = {pic.id for pic in self.camera.pictures()}
                self.camera.take_picture()
                deadline = time.monotonic() + timeout_s
                while True:
                    new = [pic for pic in self.camera.pictures() if pic.id not in before]
                    if new:
                        break
                    if time.monotonic() > deadline:
                        raise ShotNotSeen(f"the camera took no new picture within {timeout_s:.0f} s")
                    time.sleep(0.1)
                queued = self._pull_new(only={pic.id for pic in new})
            except (QueueFull, NoSpace, ShotsNotSupported, ShotNotSeen):
                raise
            except Exception as exc:
                log.warning("camera: %s", exc)
                self._disconnect(exc)
                raise CameraUnavailable(f"the camera cannot be reached: {exc}") from exc
            if not queued:
                raise ShotNotSeen("the new picture is not a readable exposure (see the service log)")
            return queued[-1]

    def _mark(self, picture_id: str, exposure_id: str | None) -> None:
        with self.store.db.write() as conn:
            conn.execute("INSERT OR REPLACE INTO camera_pictures (serial, picture, exposure_id, pulled_at) "
                         "VALUES (?, ?, ?, ?)", (self.serial, picture_id, exposure_id, time.time()))

    def close(self) -> None:
        with self._lock:
            if self.camera is not None:
                try:
                    self.camera.close()
                finally:
                    self.camera = None

    # -- async loop --------------------------------------------------------------------

    async def shoot_now(self) -> dict:
        """Take a picture and queue it (``POST /api/v1/camera/shots``)."""
        return await asyncio.to_thread(self.take_shot)

    async def pull_now(self) -> list[dict]:
        """Poll at once (``POST /api/v1/camera/pull``)."""
        return await asyncio.to_thread(self.poll_once)

    async def run(self) -> None:
        """Poll until cancelled, backing off while the camera is away."""
        backoff = self.poll_s
        while True:
            try:
                await asyncio.to_thread(self.poll_once)
                backoff = self.poll_s
            except QueueFull:
                log.info("queue full; camera shots wait on the camera")
            except NoSpace as exc:
                log.warning("camera shots wait on the camera: %s", exc)
            except CameraUnavailable:
                backoff = min(backoff * 2, 30.0)
            except Exception:
                log.exception("camera watcher round failed")
            await self._pause(backoff)

    async def _pause(self, seconds: float) -> None:
        # A Wi-Fi camera announces new pictures (driver.Camera.new_picture): pull at once
        # then; over USB there is no announcement and the poll interval decides.
        announced = getattr(self.camera, "new_picture", None)
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            if announced is not None and announced.is_set():
                return
            await asyncio.sleep(min(0.05, max(0.0, deadline - time.monotonic())))
