"""The Cramér-Rao bound of a particle's position from its pixels (analysis.simulation.bound)."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.errors import ParameterError
from analysis.simulation.bound import position_bound


def test_the_bound_follows_the_shot_noise():
    # Four times the light, a quarter of the variance where shot noise dominates: half the error
    # (a little more: the faint rims of the blur are read-noise limited).
    faint, bright = (position_bound(np.array([57.4]), np.array([b]), size=384).sigma_z_mm[0] for b in (450.0, 1800.0))
    assert 1.9 < faint / bright < 2.4


def test_a_wider_blur_raises_the_bound_and_depth_is_the_weak_axis():
    z, b = np.array([57.0, 58.5]), np.full(2, 1800.0)
    bounds = [position_bound(z, b, blur_px=blur, size=384) for blur in (0.5, 0.8, 1.2)]
    sigma_z = np.array([r.sigma_z_mm for r in bounds])
    assert np.all(np.isfinite(sigma_z)) and np.all(np.diff(sigma_z, axis=0) > 0)
    # Off focus the blur disk's size carries depth, its place the lateral position: far better known.
    assert np.all(bounds[0].sigma_x_mm < 0.2 * bounds[0].sigma_z_mm)


def test_bad_input_is_refused():
    with pytest.raises(ParameterError):
        position_bound(np.array([57.0, 58.0]), np.array([1800.0]))
    with pytest.raises(ParameterError):
        position_bound(np.array([57.0]), np.array([-1.0]))
