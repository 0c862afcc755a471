"""A simulated experiment for ``plenodust demo``: a camera folder that gets a new shot every few seconds.

The white images come from :func:`analysis.simulation.scenario_files.write_scenario`; every shot,
the first included, is the same cluster as much later as the clock says, moved physically
(:class:`analysis.simulation.dynamics.MovingCluster`: Langevin motion in cages, rotation, shell
hops; so the dashboard's trails and temperatures have something real to show), rendered
by the simulator's forward model and added to the simulated camera's file system as the
camera would store it (``IMG_nnnn.RAW`` + ``.TXT``). Shots are taken on a fixed clock (the
k-th at ``k * every_s`` after the start, its metadata saying so), whatever rendering takes,
and the card keeps the newest ``keep`` of them. The motion is :class:`Motion`'s played
``every_s / interval_s`` times slower (:meth:`Motion.slowed`), so a shot every few seconds sees
the steps a shot a second would (about 0.15 of the mean nearest-neighbour distance, which the
linker follows), and without drift, so the cluster stays in view however long the demo runs. :meth:`DemoShots.shutter` takes one at once
(the simulated camera's take-picture command).
"""

from __future__ import annotations

import logging
import shutil
import threading
import time
from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np

from analysis.camera.model import CameraModel
from analysis.formats.exposure import Exposure, txt_bytes
from analysis.simulation.dynamics import Motion, MovingCluster, moved_scenario
from analysis.simulation.scenarios import make_scenario
from analysis.simulation.camera import (DEFAULT_LENS, DEFAULT_SERIAL, simulated_camera_metadata,
    simulated_private_metadata)
from analysis.simulation.render import in_view, particle_truth, render_exposure
from analysis.simulation.scenario_files import write_scenario
from driver.simulated import CameraFolder

log = logging.getLogger(__name__)


class DemoShots:
    """Fills ``camera_dir`` with shots of one simulated cluster.

    Parameters
    ----------
    camera_dir : Path
        The simulated camera's folder (created); white images go to ``calibration/``.
    scenario : {"ball", "tilted-layer", "shadowing"}
    size : int
        Sensor crop in pixels (multiple of 4); 3280 is a full F01 frame.
    seed : int
    keep : int
        Pictures kept on the simulated card; older ones are deleted as new ones come.
    every_s : float
        The time between shots the motion is scaled to (also for shots on request).
    """

    def __init__(self, camera_dir: Path, *, scenario: str = "ball", size: int = 1024, seed: int = 1,
                 keep: int = 200, every_s: float = 4.0) -> None:
        self.camera_dir = Path(camera_dir)
        self.scenario_name = scenario
        self.size = size
        self.seed = seed
        self.metadata = simulated_camera_metadata(lens=DEFAULT_LENS, size=size)
        self.model = CameraModel.from_metadata(self.metadata)
        self.private = simulated_private_metadata(DEFAULT_SERIAL)
        self.scenario = make_scenario(scenario, seed)
        base = Motion(drift_mm_per_s=(0.0, 0.0, 0.0))
        self.motion = base.slowed((every_s if every_s > 0 else 4.0) / base.interval_s)
        self.cluster = MovingCluster(self.scenario, self.motion, seed=[seed, 0x40710])
        self._last_shot: datetime | None = None
        self.keep = keep
        self.shots = 0
        self.serial = DEFAULT_SERIAL  # the camera whose shots and white images these are
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._shooting = threading.Lock()  # the clock and the shutter may both shoot

    def prepare(self) -> None:
        """White images (through the simulator's own writer) and the first shot, taken now.

        The first shot goes through :meth:`shoot` like every later one, so its metadata's clock
        is today's too (the writer's exposure carries a fixed date years back, and a run's ``t``
        would jump by those years between its first and second shot).
        """
        staging = self.camera_dir.parent / ".demo-staging"
        if staging.exists():
            shutil.rmtree(staging)
        files = write_scenario(staging, self.scenario_name, self.seed, count=1, size=self.size)
        self.camera_dir.mkdir(parents=True, exist_ok=True)
        shutil.copytree(files.calibration_dir, self.camera_dir / "calibration", dirs_exist_ok=True)
        shutil.rmtree(staging)
        self.shoot()

    def shutter(self, folder: CameraFolder | None = None) -> str:
        """Take a shot now (the simulated camera calls this on its take-picture command)."""
        return self.shoot()

    def shoot(self, taken_at: datetime | None = None) -> str:
        """Render the next shot and put it on the camera; returns its name (``IMG_nnnn``).

        ``taken_at`` is the time its metadata records (default: now).
        """
        with self._shooting:
            return self._shoot(taken_at or datetime.now(timezone.utc))

    def _shoot(self, taken_at: datetime) -> str:
        rng = np.random.default_rng([self.seed, self.shots + 1])
        # The first shot is the scenario itself; later ones move on by the time since the last
        # (one motion interval per step, at least one, at most 60).
        if self._last_shot is not None:
            steps = (taken_at - self._last_shot).total_seconds() / self.motion.interval_s
            for _ in range(int(min(60, max(1, round(steps))))):
                self.cluster.advance()
        self._last_shot = taken_at
        self.scenario = moved_scenario(self.scenario, self.cluster.snapshot())
        particles = self.scenario.particles
        keep = np.flatnonzero(in_view(self.model, particle_truth(self.model, particles)))
        image = render_exposure(self.model, particles.subset(keep), seed=int(rng.integers(2 ** 63)),
                                background_dn=self.scenario.background_dn)
        zulu = taken_at.astimezone(timezone.utc).strftime("%Y-%m-%dT%H:%M:%S.") + \
            f"{taken_at.microsecond // 1000:03d}Z"
        metadata = simulated_camera_metadata(lens=DEFAULT_LENS, size=self.size, zulu_time=zulu)
        exposure = Exposure(image=image, metadata=metadata, private_metadata=self.private)
        folder = CameraFolder(self.camera_dir)
        name = folder.add_picture(exposure.raw_bytes(), txt_bytes(exposure))
        self.shots += 1
        folder.remove_oldest(keep=self.keep)
        return name

    def start(self, every_s: float) -> None:
        """Shoot every ``every_s`` seconds, on a fixed clock, in a background thread until :meth:`stop`.

        The k-th shot is due ``k * every_s`` after the start (the last shot taken, if any: the first
        shot :meth:`prepare` took) and its metadata records that time;
        rendering happens in between. If rendering takes longer than ``every_s``, due times are
        skipped (and said so once) rather than shots piling up.
        """
        def loop() -> None:
            # The clock starts at the shot taken last (prepare()'s first one), so that one is on it too.
            now = datetime.now(timezone.utc)
            start_wall = self._last_shot if self._last_shot is not None and self._last_shot <= now else now
            start_mono = time.monotonic() - (now - start_wall).total_seconds()
            k, warned = 1, False
            while not self._stop.wait(max(0.0, start_mono + k * every_s - time.monotonic())):
                try:
                    name = self.shoot(start_wall + timedelta(seconds=k * every_s))
                    log.debug("demo camera: new shot %s", name)
                except Exception:
                    log.exception("demo camera: rendering a shot failed")
                late = int((time.monotonic() - start_mono) // every_s) - k
                if late > 0 and not warned:
                    log.warning("demo camera: rendering a shot takes longer than --every %.1f s; shots come "
                                "every %.1f s", every_s, (late + 1) * every_s)
                    warned = True
                k += 1 + max(0, late)

        self._thread = threading.Thread(target=loop, name="demo-shots", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=10)
