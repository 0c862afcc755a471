"""Target calibration mappings on synthetic targets traced forward through known optics: the
physical model recovers the auxiliary lens, the distortion and where the target was; the better
mapping on held-back positions is kept; files round-trip; the right one is picked per camera."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from analysis.calibration.metric_files import (choose_metric_calibration, coordinates_for, read_metric_calibration,
                                               save_metric_calibration)
from analysis.camera.coordinates import ThinLensCalibration, coordinate_warnings, to_physical
from analysis.camera.front_optics import FrontOptics
from analysis.camera.image_grid import ImageGrid
from analysis.camera.mapping_fit import fit_physical, fit_target_mapping, metric_calibration, predict
from analysis.camera.target_mapping import CameraKey, PhysicalMapping
from analysis.errors import MetricCalibrationError, PositionMismatchError
from analysis.simulation.camera import DEFAULT_LENS, simulated_camera_metadata

from target_helpers import PAPER_FRONT, P_MM, between, main_lens, observations, seen, tilt_of

KEY = CameraKey("A202160042", DEFAULT_LENS.zoom_step, DEFAULT_LENS.focus_step)


def _rms_um(mapping, obs) -> np.ndarray:
    return np.sqrt(np.mean((predict(mapping, obs) - obs.world_mm) ** 2, axis=0)) * 1e3


def test_auxiliary_lens_images_as_a_thin_lens_and_distortion_is_one_percent_at_the_corner():
    front = FrontOptics.with_lens(174.0, 20.0, distortion=0.01, reference_tan=0.2)
    # Object 32.5 mm before a 174 mm lens: virtual image at 1 / (1/32.5 - 1/174) = 39.96 mm, x1.2296.
    x, y, z = front.apparent(np.array([0.0, 1e-6]), np.array([0.0, 0.0]), np.array([52.5, 52.5]))
    v = 1.0 / (1.0 / 32.5 - 1.0 / 174.0)
    assert z[0] == pytest.approx(20.0 + v, abs=1e-9)
    assert x[1] / 1e-6 == pytest.approx(v / 32.5, rel=1e-6)
    plain = FrontOptics(k1=0.01, reference_tan=0.2)
    x, _, _ = plain.apparent(np.array([0.2 * 60.0]), np.array([0.0]), np.array([60.0]))
    assert x[0] / (0.2 * 60.0) == pytest.approx(1.01, abs=1e-12)
    back = front.physical(*front.apparent(np.array([3.0]), np.array([-2.0]), np.array([50.0])))
    np.testing.assert_allclose(np.ravel(back), [3.0, -2.0, 50.0], atol=1e-9)


def test_physical_model_recovers_the_optics_and_the_targets_pose():
    obs = observations(rotation=(0.06, -0.03, 0.25), origin=(0.3, -0.2, 0.4), stage_slope=(0.015, -0.01))
    fit = fit_physical(obs, main_lens())
    assert fit.front.aux_focal_mm == pytest.approx(174.0, rel=1e-3)
    assert fit.front.aux_distance_mm == pytest.approx(20.0, abs=0.05)
    assert fit.front.k1 + fit.front.k2 == pytest.approx(0.01, abs=2e-4)
    np.testing.assert_allclose(fit.rotation, (0.06, -0.03, 0.25), atol=1e-4)
    np.testing.assert_allclose(fit.origin_mm, (0.3, -0.2, 0.4), atol=1e-3)
    np.testing.assert_allclose(fit.stage_slope, (0.015, -0.01), atol=1e-5)
    assert np.all(_rms_um(fit, between(rotation=(0.06, -0.03, 0.25), origin=(0.3, -0.2, 0.4),
                                       stage_slope=(0.015, -0.01))) < 0.5)


def test_noisy_target_predicts_positions_between_stage_positions_to_the_issue_targets():
    # The pipeline's scatter: about 0.5 um on the lens plane and 5e-5 in alpha per dot.
    obs = observations(noise_s_m=0.5e-6, noise_alpha=5e-5, seed=4)
    best, fitted, report = fit_target_mapping(obs, main_lens())
    assert report["chosen"] == "physical" and best is fitted["physical"]
    fov_mm, depth_mm = 12.0, 8.0
    held = report["comparison"]["physical"]["held_out_rms_um"]
    assert held["X"] <= 2.0 * fov_mm and held["Y"] <= 2.0 * fov_mm      # 0.2 % of the field, in um
    assert held["Z"] <= 10.0 * depth_mm                                  # 1 % of the depth range
    x, y, z = _rms_um(best, between(noise_s_m=0.0, noise_alpha=0.0))
    assert x < 3 and y < 3 and z < 15
    # Residuals per position and axis, fitted and held back, in micrometres.
    assert [r["position_mm"] for r in report["residuals"]["fit"]] == [48.5, 50.5, 52.5, 54.5, 56.5]
    assert [r["position_mm"] for r in report["residuals"]["held_out"]] == [50.5, 52.5, 54.5]
    assert set(report["residuals"]["fit"][0]["rms_um"]) == {"X", "Y", "Z"}


def test_the_mapping_that_predicts_held_back_positions_better_is_kept():
    plain = fit_target_mapping(observations(noise_alpha=2e-5), main_lens())
    assert plain[2]["chosen"] == "physical"
    # A field curvature no thin lens has: the polynomial follows it, the physical model cannot.
    curved = fit_target_mapping(observations(noise_alpha=2e-5, field_curvature_mm=0.4), main_lens())
    comparison = curved[2]["comparison"]
    assert curved[2]["chosen"] == "polynomial"
    assert comparison["polynomial"]["held_out_rms_um"]["3d"] < comparison["physical"]["held_out_rms_um"]["3d"]
    # Without a thin lens in the metadata only the polynomial can be fitted.
    assert fit_target_mapping(observations(), None)[2]["chosen"] == "polynomial"


def test_two_positions_are_too_few():
    with pytest.raises(PositionMismatchError, match="at least 3"):
        fit_target_mapping(observations(positions=(50.0, 54.0)), main_lens())


def _metric(tmp_path, *, focus_step=DEFAULT_LENS.focus_step, name="metric.json"):
    cal = metric_calibration(observations(), main_lens(), CameraKey(KEY.serial, KEY.zoom_step, focus_step),
                             margin_mm=0.5, created_utc="2024-01-01T00:00:00Z")
    return save_metric_calibration(cal, tmp_path / name), cal


def test_file_round_trip_predicts_the_same_and_refuses_other_formats(tmp_path):
    path, cal = _metric(tmp_path)
    back = read_metric_calibration(path)
    obs = between()
    np.testing.assert_array_equal(predict(back.mapping, obs), predict(cal.mapping, obs))
    assert back.sha1 and back.camera == KEY and set(back.alternatives) == {"physical", "polynomial"}
    doc = json.loads(path.read_text())
    assert doc["format"] == "plenodust.metric-calibration" and doc["version"] == 1
    doc["version"] = 2
    (tmp_path / "v2.json").write_text(json.dumps(doc))
    with pytest.raises(MetricCalibrationError, match="version"):
        read_metric_calibration(tmp_path / "v2.json")
    (tmp_path / "other.json").write_text("{}")
    with pytest.raises(MetricCalibrationError, match="calibrate-target"):
        read_metric_calibration(tmp_path / "other.json")


def test_the_calibration_of_the_pictures_camera_zoom_and_focus_is_picked(tmp_path):
    _metric(tmp_path, focus_step=DEFAULT_LENS.focus_step + 40, name="a.json")
    path, _ = _metric(tmp_path, name="b.json")
    (tmp_path / "notes.json").write_text('{"not": "a calibration"}')
    meta = simulated_camera_metadata()
    chosen = choose_metric_calibration(tmp_path, meta, serial=KEY.serial)
    assert chosen is not None and chosen.camera.focus_step == DEFAULT_LENS.focus_step
    assert choose_metric_calibration(tmp_path, meta, serial="A999999999") is None
    with pytest.raises(MetricCalibrationError, match="zoom and focus"):
        choose_metric_calibration(tmp_path / "a.json", meta, serial=KEY.serial)
    fallback = coordinates_for(tmp_path, meta, serial="A999999999")
    assert isinstance(fallback, ThinLensCalibration) and "A999999999" in fallback.fallback_reason
    assert "thin-lens" in coordinate_warnings(np.zeros(1), np.zeros(1), np.zeros(1), fallback)[0]
    assert "not a target calibration" in fallback.to_dict()["note"]


def test_particles_are_mapped_from_output_pixels_and_warned_about_outside_the_volume(tmp_path):
    path, _ = _metric(tmp_path)
    cal = read_metric_calibration(path)
    grid = ImageGrid(width=200, height=200, x0_m=-1e-3, y0_m=-1e-3, step_m=1e-5)
    truth = np.array([[1.0, -2.0, 51.0], [0.0, 0.0, 70.0]]).T           # the second far behind the volume
    sx, sy, alpha = seen(PAPER_FRONT, truth)
    col, row = grid.to_pixels(sx, sy)
    X, Y, Z = to_physical(col, row, alpha, grid, cal)
    np.testing.assert_allclose([X[0], Y[0], Z[0]], truth[:, 0], atol=2e-3)
    warnings = coordinate_warnings(X, Y, Z, cal)
    assert len(warnings) == 1 and warnings[0].startswith("1 of 2 particles lie outside")
    assert cal.to_dict()["kind"] == "target" and cal.to_dict()["sha1"] == cal.sha1
