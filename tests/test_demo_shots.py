"""The demo's simulated experiment: a run whose clock is continuous from its first shot and whose
cluster stays in view and moves by linkable steps however long the demo runs."""

from __future__ import annotations

from datetime import datetime, timedelta, timezone
from pathlib import Path

import numpy as np
import pytest

from analysis.formats.exposure import read_exposure
from analysis.formats.frame_metadata import shot_time_s
from analysis.simulation.dynamics import Motion, MovingCluster
from analysis.simulation.scenarios import make_scenario
from service.demo_shots import DemoShots


def test_the_first_shot_is_on_the_same_clock_as_the_next(tmp_path) -> None:
    shots = DemoShots(tmp_path / "camera", size=256, every_s=4.0)
    shots.prepare()
    first = shot_time_s(read_exposure(next((tmp_path / "camera").rglob("IMG_*.RAW"))).metadata)
    assert abs(first - datetime.now(timezone.utc).timestamp()) < 120  # today, not the writer's fixed date
    shots.shoot(datetime.fromtimestamp(first, timezone.utc) + timedelta(seconds=4))
    raws = sorted((tmp_path / "camera").rglob("IMG_*.RAW"))
    assert len(raws) == 2
    times = [shot_time_s(read_exposure(r).metadata) for r in raws]
    assert times[1] - times[0] == pytest.approx(4.0, abs=0.01)


def test_the_demo_cluster_stays_in_view_and_steps_as_a_shot_a_second_would() -> None:
    scenario = make_scenario("ball", 1)
    demo = DemoShots(Path("/nonexistent"), every_s=4.0)  # only its motion: nothing is written
    slow = MovingCluster(scenario, demo.motion, seed=[1, 2])
    fast = MovingCluster(scenario, Motion(drift_mm_per_s=(0.0, 0.0, 0.0)), seed=[1, 2])
    start = slow.xyz.mean(axis=0)
    steps_slow, steps_fast = [], []
    for _ in range(300):  # 20 minutes of demo
        a, b = slow.xyz.copy(), fast.xyz.copy()
        slow.advance()
        fast.advance()
        steps_slow.append(np.linalg.norm(slow.xyz - a, axis=1))
        steps_fast.append(np.linalg.norm(fast.xyz - b, axis=1))
    assert np.linalg.norm(slow.xyz.mean(axis=0) - start) < 0.3
    assert slow.t == pytest.approx(300 * 4.0)
    assert np.median(steps_slow) == pytest.approx(np.median(steps_fast), rel=0.15)
