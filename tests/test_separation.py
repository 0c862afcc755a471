"""The separation prior: particles in a plasma repel, so two fits far closer than the cluster's
spacing are one particle's light fitted twice (``analysis.depth.quality.too_close``)."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.depth.quality import too_close
from analysis.errors import ParameterError
from analysis.pipeline.params import PipelineParams
from analysis.simulation.scenarios import make_scenario
from analysis.simulation.scoring import mean_nn_distance


def _cluster(name: str, seed: int) -> tuple[np.ndarray, np.ndarray, float]:
    p = make_scenario(name, seed).particles
    xyz = np.column_stack([p.x_mm, p.y_mm, p.z_mm])
    return xyz, np.asarray(p.brightness_dn, float), mean_nn_distance(p.x_mm, p.y_mm, p.z_mm)


@pytest.mark.parametrize("name", ["shadowing", "ball", "tilted-layer", "cloud"])
def test_the_fainter_of_a_particle_fitted_twice_goes_and_no_real_particle_does(name):
    xyz, bright, nn = _cluster(name, 4)
    # The shadowing partners stand on one line of sight 0.5-0.6 of the spacing apart: all kept.
    assert not too_close(xyz, bright, 0.3).any()
    rng = np.random.default_rng(4)
    hosts = rng.choice(len(xyz), 5, replace=False)
    offsets = rng.normal(size=(5, 3))
    offsets *= (rng.uniform(0.05, 0.25, 5) * nn / np.linalg.norm(offsets, axis=1))[:, None]
    both = np.vstack([xyz, xyz[hosts] + offsets])
    # A ghost carries a tenth of its host's light, or a quarter: the fainter of the two goes.
    light = np.r_[bright, bright[hosts] * np.array([0.1, 0.25, 0.1, 0.25, 0.1])]
    assert np.array_equal(np.flatnonzero(too_close(both, light, 0.3)), len(xyz) + np.arange(5))
    flipped = light.copy()
    flipped[hosts[0]] = 0.01 * light[len(xyz)]  # here the host is the fainter: it goes instead
    gone = np.flatnonzero(too_close(both, flipped, 0.3))
    assert hosts[0] in gone and len(xyz) not in gone and gone.size == 5


def test_without_coordinates_or_with_few_particles_nothing_is_dropped():
    xyz, bright, nn = _cluster("ball", 2)
    ghost = np.vstack([xyz, xyz[:1] + 0.05 * nn])
    light = np.r_[bright, 1.0]
    assert too_close(ghost, light, 0.3)[-1]
    ghost[-1, 2] = np.nan  # no depth model: no distance to judge by
    assert not too_close(ghost, light, 0.3).any()
    assert not too_close(ghost[[0, 1, -1]], light[[0, 1, -1]], 0.3).any()
    assert not too_close(np.vstack([xyz, xyz[:1] + 0.05 * nn]), light, 0.0).any()  # turned off


@pytest.mark.parametrize("value", [-0.1, 1.0])
def test_a_separation_out_of_range_is_refused(value):
    with pytest.raises(ParameterError, match="min_separation"):
        PipelineParams(min_separation=value)
