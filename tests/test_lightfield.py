"""The look-up table against the camera model's forward model (docs/camera-model.md)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from analysis.calibration.calibrate import Calibration
from analysis.camera.model import CameraModel, green_mask
from analysis.errors import CalibrationError, ParameterError
from analysis.camera.image_grid import ImageGrid
from analysis.cache import Cache
from analysis.formats.mapped_npz import is_mapped, release_pages
from analysis.lightfield.table import build_table, build_table_from_model, load_table, save_table
from analysis.simulation.camera import simulated_camera_metadata
from analysis.simulation.render import render_white_image


@pytest.fixture(scope="module")
def model() -> CameraModel:
    return CameraModel.from_metadata(simulated_camera_metadata(size=240))


@pytest.fixture(scope="module")
def table(model):
    return build_table_from_model(model, rim_px=1.0)


def test_every_green_pixel_inside_a_micro_image_is_listed_once(model, table):
    rows, cols = np.mgrid[0:model.height, 0:model.width]
    # Brute force: distance to every lens centre near the sensor.
    ij, centres = model.lattice.centres(model.width, model.height, margin_px=-20)
    px = cols.reshape(-1) + 0.5
    py = rows.reshape(-1) + 0.5
    d2 = (px[:, None] - centres[None, :, 0]) ** 2 + (py[:, None] - centres[None, :, 1]) ** 2
    nearest = d2.argmin(axis=1)
    inside = d2.min(axis=1) <= (model.optics.micro_image_radius_px - 1.0) ** 2
    expected = np.flatnonzero(inside & green_mask(model.height, model.width).reshape(-1))
    assert np.array_equal(np.sort(table.pixel_index), expected)
    # Each sample's lens is the nearest lens.
    lens_of_pixel = ij[nearest[table.pixel_index]]
    assert np.array_equal(table.lens_ij[table.lens], lens_of_pixel)
    # Samples are grouped by lens, lenses ordered by row then column (the refocus relies on it).
    assert np.all(np.diff(table.lens) >= 0)
    key = table.lens_ij[:, 1].astype(np.int64) * 10_000 + table.lens_ij[:, 0]
    assert np.all(np.diff(key) > 0)


def test_aperture_coordinate_sends_the_ray_to_that_pixel(model, table):
    """Forward model step 3: the ray through (u, v) and lens k lands at c_k + (c_k - u) d / P."""
    optics = model.optics
    s = table.lens_xy_m[table.lens]
    u = np.stack([table.u_m, table.v_m], axis=1).astype(np.float64)
    q = s + (s - u) * optics.mla_to_sensor_m / optics.exit_pupil_m
    qx = model.lattice.origin_x + q[:, 0] / optics.pixel_pitch_m
    qy = model.lattice.origin_y + q[:, 1] / optics.pixel_pitch_m
    row, col = np.divmod(table.pixel_index, model.width)
    assert np.all(np.abs(qx - (col + 0.5)) < 1e-3)
    assert np.all(np.abs(qy - (row + 0.5)) < 1e-3)
    # The aperture is filled: |u| reaches (but does not pass) D/2 minus the rim.
    r = np.hypot(table.u_m, table.v_m)
    assert r.max() <= table.aperture_radius_m * 1.0001
    assert r.max() > 0.6 * table.aperture_radius_m
    assert table.aperture_radius_m == pytest.approx(optics.aperture_diameter_m / 2, rel=1e-6)


def test_lens_positions_follow_the_lattice(model, table):
    sx, sy = model.lens_plane_position_m(table.lens_ij[:, 0], table.lens_ij[:, 1])
    assert np.allclose(table.lens_xy_m, np.stack([sx, sy], axis=1), atol=1e-12)
    assert np.allclose(table.lens_ij @ table.basis_m.T, table.lens_xy_m, atol=1e-12)
    fi, fj = table.lattice_coordinates(table.lens_xy_m[:, 0], table.lens_xy_m[:, 1])
    assert np.allclose(fi, table.lens_ij[:, 0]) and np.allclose(fj, table.lens_ij[:, 1])


def test_cos4_weights_fall_off_away_from_the_axis(model, table):
    assert table.weight.dtype == np.float32
    assert np.median(table.weight) == pytest.approx(1.0, rel=1e-6)
    s = table.lens_xy_m[table.lens]
    off_axis = np.hypot(s[:, 0] - table.u_m, s[:, 1] - table.v_m)
    order = np.argsort(off_axis)
    assert np.all(np.diff(table.weight[order].astype(np.float64)) <= 1e-6)


def test_white_image_becomes_the_weights(model):
    white = render_white_image(model, noise=False)
    dev = ((white.astype(np.float32) - model.black_level) / (model.white_level - model.black_level))
    dev[100, 101] = 0.0  # a dead green pixel inside a micro-image is left out
    calibration = Calibration(serial="A1", white_name="MOD_0001", white_sha1="0" * 40, zoom_step=None,
                              focus_step=None, model=model, devignetting=dev, fit_rms_px=0.0,
                              fit_n_lenses=0, fit_centroid_rms_px=0.0)
    table = build_table(calibration)
    assert 100 * model.width + 101 not in set(table.pixel_index.tolist())
    ratio = table.weight / dev.reshape(-1)[table.pixel_index]
    assert np.allclose(ratio, ratio[0], rtol=1e-5)


def test_save_and_load_round_trip(tmp_path, table):
    cache = Cache()
    cache.put(("normalisation", table.uid, b"key"), np.arange(6, dtype=np.float32).reshape(3, 2))
    cache.put(("normalisation", "another table", b"key"), np.ones(3, dtype=np.float32))
    path = save_table(table, tmp_path / "lot.npz", cache=cache)
    fresh = Cache()
    back = load_table(path, cache=fresh)
    for name in ("pixel_index", "lens", "u_m", "v_m", "weight", "lens_ij", "lens_xy_m", "basis_m"):
        assert np.array_equal(getattr(back, name), getattr(table, name)), name
        assert getattr(back, name).dtype == getattr(table, name).dtype, name
    for name in ("width", "height", "aperture_radius_m", "micro_image_radius_px", "rim_px", "black_level", "uid"):
        assert getattr(back, name) == getattr(table, name), name
    assert back.grid == table.grid
    # The per-sample columns are mapped from the file, aligned and writable (what numba compiles for).
    for name in ("pixel_index", "lens", "u_m", "v_m", "weight"):
        column = getattr(back, name)
        assert is_mapped(column) and column.flags.aligned and column.flags.writeable, name
        release_pages(column)
        assert np.array_equal(column, getattr(table, name)), name  # read back from the file
    assert len(fresh) == 1   # this table's normalisation only
    assert np.array_equal(fresh.get(("normalisation", table.uid, b"key")), np.arange(6).reshape(3, 2))


def test_broken_cache_says_rebuild(tmp_path):
    bad = tmp_path / "lot.npz"
    bad.write_bytes(b"not a table")
    with pytest.raises(CalibrationError, match="rebuilt"):
        load_table(bad)


def test_bad_settings_are_refused(model):
    with pytest.raises(ParameterError, match="rim_px"):
        build_table_from_model(model, rim_px=5.0)
    with pytest.raises(ParameterError, match="white image"):
        build_table_from_model(model, np.ones((10, 10), np.float32))


def test_default_grid_covers_the_lenses(table):
    g = table.grid
    cols, rows = g.to_pixels(table.lens_xy_m[:, 0], table.lens_xy_m[:, 1])
    assert cols.min() >= -0.5 and cols.max() <= g.width - 0.5
    assert rows.min() >= -0.5 and rows.max() <= g.height - 0.5
    assert g.step_m == pytest.approx(abs(table.basis_m[1, 1]))


def test_image_grid_round_trip():
    g = ImageGrid(width=50, height=40, x0_m=-1e-3, y0_m=-2e-3, step_m=1.2e-5)
    x, y = g.to_lens_plane(np.array([0.0, 3.25]), np.array([0.0, 7.5]))
    assert x[0] == -1e-3 and y[0] == -2e-3
    c, r = g.to_pixels(x, y)
    assert np.allclose(c, [0.0, 3.25]) and np.allclose(r, [0.0, 7.5])
    fine = g.scaled(2)
    assert (fine.width, fine.height) == (100, 80)
    # Same outer edge: left edge of pixel 0 stays put.
    assert fine.x0_m - fine.step_m / 2 == pytest.approx(g.x0_m - g.step_m / 2)


def test_real_f01_metadata_builds_a_telecentric_table(real_fixtures):
    """Firmware 1.0.2 writes exitPupilOffset.z = 10000: micro-images fill the pitch, weights are 1."""
    meta = json.loads((real_fixtures / "f01-frame-metadata.json").read_text())
    full = CameraModel.from_metadata(meta)
    # A 240 x 240 crop around the sensor centre (even offset keeps the Bayer phase).
    lat = full.lattice.with_changes(origin_x=full.lattice.origin_x - 1520, origin_y=full.lattice.origin_y - 1520)
    model = dataclasses.replace(full, width=240, height=240, lattice=lat)
    table = build_table_from_model(model, rim_px=1.0)
    assert model.optics.telecentric
    assert np.all(table.weight == 1.0)
    assert table.aperture_radius_m == pytest.approx(model.optics.aperture_diameter_m / 2)
    # Aperture sign: pixels right of / below their micro-image centre see the left / top of the aperture.
    row, col = np.divmod(table.pixel_index, model.width)
    cx, cy = model.lattice.centre(table.lens_ij[table.lens, 0], table.lens_ij[table.lens, 1])
    dx, dy = col + 0.5 - cx, row + 0.5 - cy
    assert np.all(np.sign(table.u_m[np.abs(dx) > 0.1]) == -np.sign(dx[np.abs(dx) > 0.1]))
    assert np.all(np.sign(table.v_m[np.abs(dy) > 0.1]) == -np.sign(dy[np.abs(dy) > 0.1]))
    # About 9 x 9 useful pixels per lens, half of them green (lytro-f01.md 1.7).
    per_lens = table.n_samples / table.n_lenses
    assert 15 < per_lens < 40
