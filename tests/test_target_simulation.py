"""The simulated target and front optics: dots where the plate puts them, positions in the sidecar,
and every scene rendered where the main lens sees it while its truth keeps where it is."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest

from analysis.camera.model import CameraModel
from analysis.formats.exposure import read_exposure
from analysis.simulation.render import particle_truth
from analysis.simulation.scenario_files import write_scenario
from analysis.simulation.scenarios import Particles
from analysis.simulation.target import DotTarget, default_target, simulated_front_optics

FRONT = simulated_front_optics(174.0, 20.0, distortion=0.01)


def _truth(path):
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    return {k: np.array([float(r[k]) for r in rows]) for k in rows[0]}


def test_plate_geometry_tilt_turn_and_offset():
    plate = DotTarget(positions_mm=(50.0,), pitch_mm=0.5, extent_mm=2.0, tilt_deg=20.0, rotation_deg=90.0,
                      offset_mm=(0.3, -0.1))
    rows, cols = plate.dot_indices()
    assert rows.size == 25 and set(cols.tolist()) == {-2, -1, 0, 1, 2}
    xyz = plate.camera_positions(50.0)
    middle = np.flatnonzero((rows == 0) & (cols == 0))[0]
    np.testing.assert_allclose(xyz[:, middle], [0.3, -0.1, 50.0])
    # One column step along the plate's X: turned 90 degrees, it runs down the image.
    step = xyz[:, np.flatnonzero((rows == 0) & (cols == 1))[0]] - xyz[:, middle]
    np.testing.assert_allclose(step, [0.0, 0.5, 0.0], atol=1e-12)
    # One row step: tilted by 20 degrees out of the image plane (about the plate's rows).
    step = xyz[:, np.flatnonzero((rows == 1) & (cols == 0))[0]] - xyz[:, middle]
    assert math.degrees(math.atan2(step[2], math.hypot(step[0], step[1]))) == pytest.approx(20.0)
    np.testing.assert_allclose(plate.target_frame(50.0)[:, middle], [0.0, 0.0, 50.0])


def test_default_target_spans_8_mm_about_where_the_camera_focuses_through_the_auxiliary_lens():
    target = default_target(FRONT)
    assert len(target.positions_mm) == 5 and np.ptp(target.positions_mm) == pytest.approx(8.0)
    centre = float(np.mean(target.positions_mm))
    _, _, apparent = FRONT.apparent(np.zeros(1), np.zeros(1), np.array([centre]))
    assert apparent[0] == pytest.approx(60.0, abs=0.01)  # the simulated lens focuses at 60 mm


def test_target_exposures_and_sidecar(tmp_path):
    target = DotTarget(positions_mm=(51.0, 53.0, 55.0), pitch_mm=0.5, extent_mm=1.0, offset_mm=(0.1, 0.0))
    files = write_scenario(tmp_path, "target", 2, size=480, front_optics=FRONT, target=target,
                           progress=lambda line: None)
    side = json.loads(files.target_json.read_text())
    assert side["positions_mm"] == [51.0, 53.0, 55.0] and side["exposures"] == ["IMG_0001", "IMG_0002", "IMG_0003"]
    assert side["format"] == "plenodust.target-positions" and side["pitch_mm"] == 0.5
    model = CameraModel.from_metadata(read_exposure(files.lfp[0]).metadata)
    for k, z in enumerate(side["positions_mm"]):
        truth = _truth(files.truth[k])
        index = (truth["particle"] if "particle" in truth else truth["index"]).astype(int)
        np.testing.assert_allclose(truth["Z"], z, atol=1e-6)
        np.testing.assert_allclose(truth["X"], np.array(side["cols"])[index] * 0.5 + 0.1, atol=1e-6)
        # The truth's alpha is where the main lens sees the dot: through the auxiliary lens.
        seen = Particles(*FRONT.apparent(truth["X"], truth["Y"], truth["Z"]), truth["brightness"])
        np.testing.assert_allclose(truth["alpha"], particle_truth(model, seen).alpha, atol=1e-7)
    doc = json.loads(files.scenario_json.read_text())
    assert doc["front_optics"]["aux_focal_mm"] == pytest.approx(174.0) and doc["front_optics"]["k1"] == 0.01


def test_any_scene_can_sit_behind_the_same_optics(tmp_path):
    files = write_scenario(tmp_path, "ball", 1, size=480, front_optics=FRONT, progress=lambda line: None)
    truth = _truth(files.truth[0])
    centre = json.loads(files.scenario_json.read_text())["parameters"]["centre_mm"]
    assert centre[2] == pytest.approx(FRONT.object_distance_mm(60.0), abs=0.01)
    _, _, apparent = FRONT.apparent(truth["X"], truth["Y"], truth["Z"])
    assert np.all(np.abs(apparent - truth["Z"]) > 5.0)  # rendered 7 mm farther than it is
