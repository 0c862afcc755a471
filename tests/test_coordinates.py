"""Physical coordinates: thin-lens projection, user calibrations, tilted-layer fit, plane check."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from analysis.camera.model import CameraModel
from analysis.camera.coordinates import (ThinLensCalibration, UserCalibration, fit_tilted_layer, to_physical,
    validate_plane)
from analysis.errors import MetadataError, ParameterError
from analysis.camera.image_grid import ImageGrid


@pytest.fixture(scope="module")
def real_model(real_fixtures):
    return CameraModel.from_metadata(json.loads((real_fixtures / "f01-frame-metadata.json").read_text()))


def thin_lens_optics(real_model):
    # The real file writes an absurd exit pupil (10000 m); give it a finite one like the simulator.
    from dataclasses import replace
    return replace(real_model.optics, exit_pupil_m=0.0075)


GRID = ImageGrid(width=380, height=330, x0_m=-190 * 14e-6, y0_m=-165 * 14e-6, step_m=14e-6)


def test_thin_lens_inverts_the_forward_projection(real_model):
    optics = thin_lens_optics(real_model)
    f, p = optics.focal_length_m * 1e3, optics.exit_pupil_m * 1e3
    rng = np.random.default_rng(0)
    z = rng.uniform(40, 60, 50)
    x = rng.uniform(-5, 5, 50)
    y = rng.uniform(-5, 5, 50)
    # Forward, written out from camera-model.md: image distance, alpha, lens-plane position.
    fp = 1 / (1 / f - 1 / z)
    alpha = fp / p
    col = (x * p / z * 1e-3 - GRID.x0_m) / GRID.step_m
    row = (y * p / z * 1e-3 - GRID.y0_m) / GRID.step_m
    X, Y, Z = to_physical(col, row, alpha, GRID, ThinLensCalibration(optics))
    assert np.allclose(Z, z, rtol=1e-9) and np.allclose(X, x, atol=1e-9) and np.allclose(Y, y, atol=1e-9)
    # Right and below the axis in the image is +X, +Y; a larger alpha focuses nearer.
    X, Y, Z = to_physical(np.array([300.0, 50.0]), np.array([300.0, 10.0]), np.array([1.0, 1.01]), GRID,
                          ThinLensCalibration(optics))
    assert X[0] > 0 and Y[0] > 0 and X[1] < 0 and Y[1] < 0 and Z[1] < Z[0]


def test_thin_lens_without_exit_pupil_asks_for_user_calibration(real_model):
    with pytest.raises(MetadataError, match="user calibration"):
        to_physical(np.zeros(1), np.zeros(1), np.ones(1), GRID, ThinLensCalibration(real_model.optics))


def test_user_calibration_is_linear_about_the_reference():
    cal = UserCalibration(pixel_size_mm=0.05, depth_per_alpha_mm=-800.0, reference_alpha=1.0,
                          reference_z_mm=100.0, centre_x_px=190.0, centre_y_px=165.0)
    X, Y, Z = to_physical(np.array([190.0, 210.0]), np.array([165.0, 145.0]), np.array([1.0, 1.005]), GRID, cal)
    assert np.allclose(X, [0, 1.0]) and np.allclose(Y, [0, -1.0]) and np.allclose(Z, [100, 96])
    with pytest.raises(ParameterError, match="pixel_size_mm"):
        UserCalibration(pixel_size_mm=0, depth_per_alpha_mm=1)


def test_tilted_layer_fit_recovers_depth_scale_and_plane_check_reads_the_tilt():
    rng = np.random.default_rng(1)
    true = UserCalibration(pixel_size_mm=0.04, depth_per_alpha_mm=-600.0)
    tilt = 13.0
    n = 60
    X = rng.uniform(-7, 7, n)
    Y = rng.uniform(-7, 7, n)
    Z = np.tan(np.radians(tilt)) * Y + 0.02 * rng.standard_normal(n)  # layer tilted about the x axis
    x_px = X / true.pixel_size_mm + (GRID.width - 1) / 2
    y_px = Y / true.pixel_size_mm + (GRID.height - 1) / 2
    alpha = 1.0 + Z / true.depth_per_alpha_mm
    cal = fit_tilted_layer(x_px, y_px, alpha, tilt_deg=tilt, pixel_size_mm=0.04)
    assert cal.depth_per_alpha_mm == pytest.approx(-600.0, rel=0.03)
    X2, Y2, Z2 = to_physical(x_px, y_px, alpha, GRID, cal)
    report = validate_plane(X2, Y2, Z2)
    assert report.tilt_deg == pytest.approx(13.0, abs=0.5)
    assert report.rms_mm == pytest.approx(0.02, rel=0.3)
    assert report.normal[2] > 0.9
    nn = np.sort(np.hypot(X[:, None] - X, Y[:, None] - Y) + np.eye(n) * 1e9, axis=1)[:, 0]
    assert report.nn_mean_mm == pytest.approx(nn.mean(), rel=0.05)
    assert report.rms_over_nn == pytest.approx(report.rms_mm / report.nn_mean_mm)


def test_plane_check_sees_a_bumpy_layer():
    rng = np.random.default_rng(2)
    X, Y = rng.uniform(-5, 5, (2, 80))
    flat = validate_plane(X, Y, 50 + 0.01 * rng.standard_normal(80))
    bumpy = validate_plane(X, Y, 50 + 0.5 * rng.standard_normal(80))
    assert flat.tilt_deg < 1 and flat.rms_over_nn < 0.02 and bumpy.rms_over_nn > 0.3


def test_fit_rejects_flat_or_tiny_input():
    with pytest.raises(ParameterError, match="gradient"):
        fit_tilted_layer(np.arange(5.0), np.arange(5.0) ** 2, np.ones(5), tilt_deg=13, pixel_size_mm=0.04)
    with pytest.raises(ParameterError, match="at least 3"):
        fit_tilted_layer(np.arange(2.0), np.arange(2.0), np.ones(2), tilt_deg=13, pixel_size_mm=0.04)
    with pytest.raises(ParameterError, match="at least 4"):
        validate_plane(np.zeros(3), np.zeros(3), np.zeros(3))
    assert math.isfinite(validate_plane(*np.random.default_rng(3).uniform(size=(3, 10))).tilt_deg)
