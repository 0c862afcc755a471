"""The depth fit's table of a drifted lattice: its weights are the white image as it would read with
the micro-images moved, against the simulated camera's white rendered on the drifted lattice."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.cache import Cache
from analysis.calibration.cache import load_calibration
from analysis.calibration.calibrate import calibrate
from analysis.calibration.drift import LatticeDrift
from analysis.camera.model import CameraModel
from analysis.formats.exposure import read_exposure
from analysis.formats.whites import WhiteImage
from analysis.lightfield.drifted_table import shifted_table
from analysis.lightfield.table import build_table_from_model
from analysis.pipeline.tables import FIT_TABLE_RIM_PX, MIN_WEIGHT, drift_template, drifted_fit_table, get_table
from analysis.simulation.camera import WHITE_RESPONSE, simulated_camera_metadata, simulated_private_metadata
from analysis.simulation.camera_effects import CameraEffects
from analysis.simulation.realism import Realism
from analysis.simulation.render import camera_coverage, channel_response_map, render_white_image
from analysis.simulation.scenario_files import write_scenario

SHIFT_PX, ROTATION_RAD = (0.29, -0.17), 3e-5


@pytest.fixture(scope="module", params=[0.5, 0.9], ids=["ideal-blur", "wide-blur"])
def drifted(request):
    """A calibration from a noise-free white of a camera with this blur and a rim response, its fit
    table drifted by the camera's drift, and that white rendered on the drifted lattice."""
    meta = simulated_camera_metadata(size=384)
    model = CameraModel.from_metadata(meta)
    realism = Realism(blur_px=request.param, rim_response=0.7, lens_transmission_spread=0.03,
                      lattice_drift_px=SHIFT_PX, lattice_drift_rad=ROTATION_RAD)
    camera = CameraEffects.build(realism, serial="A202160042")
    white = WhiteImage.from_image("MOD_0001", render_white_image(model, seed=7, noise=False, camera=camera), meta,
                                  simulated_private_metadata())
    calibration = calibrate(white)
    cache = Cache()
    base = get_table(calibration, cache, rim_px=FIT_TABLE_RIM_PX)
    table = drifted_fit_table(calibration, cache, LatticeDrift(SHIFT_PX, ROTATION_RAD, 0.0, 100))
    moved = camera_coverage(model, camera, lattice=camera.exposure_lattice(model.lattice))
    moved *= channel_response_map(model.height, model.width, WHITE_RESPONSE)
    scale = (model.white_level - model.black_level) / 2400.0  # render_white_image's default level
    return calibration, base, table, moved.reshape(-1) / scale


def _rim_error(table, moved, norm):
    """RMS error of the weights of the samples beyond 0.8 of the micro-image radius (white units)."""
    r = np.hypot(table.u_m, table.v_m) / table.aperture_radius_m
    rim = r > 0.8
    return float(np.sqrt(np.mean((table.weight[rim] * norm - moved[table.pixel_index[rim]]) ** 2)))


def test_a_drifted_tables_weights_are_the_white_read_where_the_micro_images_moved(drifted):
    calibration, base, table, moved = drifted
    norm = float(np.median(calibration.devignetting.reshape(-1)[base.pixel_index] / base.weight))
    error = _rim_error(table, moved, norm)
    # Reading the white image between pixels (bilinear) misses the rim's fall and mixes in the
    # Bayer neighbours, which answer white light differently.
    lens_shift = np.asarray(SHIFT_PX)  # the rotation moves this crop's lenses by < 0.01 px more
    rows, cols = np.divmod(base.pixel_index.astype(np.int64), base.width)
    between = _bilinear(calibration.devignetting, cols - lens_shift[0], rows - lens_shift[1])
    r = np.hypot(table.u_m, table.v_m) / table.aperture_radius_m
    rim = np.hypot(base.u_m, base.v_m) / base.aperture_radius_m > 0.8
    bilinear_error = float(np.sqrt(np.mean((between[rim] - moved[base.pixel_index[rim]]) ** 2)))
    # From the white image's own pattern about the micro-image centres: 0.005 and 0.003 (the fitted
    # profile moved with its six neighbours: 0.010 and 0.003).
    assert error < 0.006 and error < 0.5 * bilinear_error, (error, bilinear_error)
    # The pixels are those a table built about the moved centres takes (but for a few at the
    # smallest weight); the pixels about the white image's centres are not.
    lattice = calibration.model.lattice
    moved_lattice = lattice.with_changes(origin_x=lattice.origin_x + SHIFT_PX[0],
                                         origin_y=lattice.origin_y + SHIFT_PX[1],
                                         rotation_rad=lattice.rotation_rad + ROTATION_RAD)
    want = build_table_from_model(calibration.model.with_lattice(moved_lattice), moved.reshape(base.height, base.width),
                                  rim_px=FIT_TABLE_RIM_PX, min_weight=MIN_WEIGHT)
    assert np.setxor1d(table.pixel_index, want.pixel_index).size < 0.002 * want.n_samples
    assert np.setxor1d(base.pixel_index, want.pixel_index).size > 0.02 * want.n_samples
    reach = table.micro_image_radius_px - table.rim_px
    assert r.max() * table.micro_image_radius_px <= reach + 1e-3


def _bilinear(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    x0 = np.clip(np.floor(x).astype(int), 0, image.shape[1] - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, image.shape[0] - 2)
    fx, fy = x - x0, y - y0
    return ((1 - fx) * (1 - fy) * image[y0, x0] + fx * (1 - fy) * image[y0, x0 + 1]
            + (1 - fx) * fy * image[y0 + 1, x0] + fx * fy * image[y0 + 1, x0 + 1])


def test_an_undrifted_table_moved_by_nothing_is_the_same_table(case_with_defects):
    """Moved by zero, the table picks the same pixels with the same aperture points and weights as
    the table built about the white image's centres, and leaves the camera's defects out."""
    calibration, base = case_with_defects
    optics = calibration.model.optics
    same = shifted_table(base, calibration.devignetting, np.zeros((base.n_lenses, 2)),
                         m_per_px=optics.pixel_pitch_m / optics.projection_factor, template=drift_template(calibration),
                         defects=calibration.defect_mask, min_weight=MIN_WEIGHT)
    assert np.array_equal(same.pixel_index, base.pixel_index) and np.array_equal(same.lens, base.lens)
    np.testing.assert_allclose(same.u_m, base.u_m, atol=1e-6 * base.aperture_radius_m)
    np.testing.assert_allclose(same.v_m, base.v_m, atol=1e-6 * base.aperture_radius_m)
    np.testing.assert_allclose(same.weight, base.weight, rtol=1e-5)
    assert not calibration.defect_mask.reshape(-1)[same.pixel_index].any()


@pytest.fixture(scope="module")
def case_with_defects(tmp_path_factory):
    files = write_scenario(tmp_path_factory.mktemp("drifted"), "tilted-layer", 3, size=512,
                           realism=Realism.only("hot-pixels", "vignetting"))
    exposure = read_exposure(files.lfp[0])
    calibration = load_calibration(files.calibration_dir, exposure.metadata, serial=exposure.serial)
    assert calibration.defect_mask is not None and calibration.defect_mask.any()
    return calibration, get_table(calibration, Cache(), rim_px=FIT_TABLE_RIM_PX)
