"""The lattice's drift between white images and an exposure, found from the exposure and undone."""

from __future__ import annotations

import json

import numpy as np
import pytest

from analysis.cache import Cache
from analysis.calibration.cache import load_calibration
from analysis.calibration.drift import block_phases, estimate_drift
from analysis.formats.exposure import read_exposure
from analysis.formats.particle_table import read_csv
from analysis.pipeline.params import PipelineParams
from analysis.pipeline.process import process
from analysis.simulation.realism import Realism
from analysis.simulation.scenario_files import write_scenario
from analysis.simulation.scoring import score

SIZE = 1024


def _case(folder, realism):
    files = write_scenario(folder, "tilted-layer", 2, size=SIZE, realism=realism)
    exposure = read_exposure(files.lfp[0])
    calibration = load_calibration(files.calibration_dir, exposure.metadata, serial=exposure.serial,
                                   cache_dir=folder / "cache")
    nn = json.loads(files.scenario_json.read_text())["exposures"][0]["mean_nn_distance_mm"]
    return exposure, calibration, read_csv(files.truth[0]), nn


@pytest.mark.parametrize("shift, rotation", [((0.3, -0.2), 5e-5), ((-0.12, 0.07), -3e-5), ((0.0, 0.0), 0.0)])
def test_drift_is_found_from_the_exposure_within_two_hundredths_of_a_pixel(tmp_path, shift, rotation):
    exposure, calibration, _, _ = _case(tmp_path, Realism(lattice_drift_px=shift, lattice_drift_rad=rotation))
    lattice = calibration.model.lattice
    drift = estimate_drift(exposure.image, lattice, block_phases(calibration.devignetting, lattice), noise_dn=3.0)
    assert drift is not None and drift.n_blocks >= 20
    # Over the crop, the displacement of every micro-image within 0.02 px of the truth.
    corners = np.array([[0, 0], [SIZE, 0], [0, SIZE], [SIZE, SIZE]], float)
    for x, y in corners:
        dx, dy = drift.displacement(x, y, lattice)
        tx = shift[0] - rotation * (y - lattice.origin_y)
        ty = shift[1] + rotation * (x - lattice.origin_x)
        assert abs(dx - tx) < 0.02 and abs(dy - ty) < 0.02, (dx, dy, tx, ty)


def test_a_drifted_exposure_is_fitted_as_well_as_one_that_did_not_drift(tmp_path):
    """The fit takes the exposure's micro-images where they are: lateral and depth errors stay those
    of the same layer without drift."""
    cases = {}
    for name, realism in [("still", Realism()), ("drifted", Realism(lattice_drift_px=(0.35, -0.25)))]:
        exposure, calibration, truth, nn = _case(tmp_path / name, realism)
        result = process(exposure, calibration, PipelineParams(), cache=Cache())
        cases[name] = (score(result.particles, truth, nn_mm=nn), result)
    still, drifted = cases["still"][0], cases["drifted"][0]
    assert cases["drifted"][1].drift is not None and abs(cases["drifted"][1].drift["shift_px"][0] - 0.35) < 0.02
    assert drifted.recall >= still.recall - 0.05 and drifted.precision >= 0.95
    assert drifted.lateral_rms_over_nn < 1.3 * still.lateral_rms_over_nn + 0.002
    assert drifted.depth_abs_rms_over_nn < 1.3 * still.depth_abs_rms_over_nn + 0.005
