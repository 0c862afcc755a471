"""The crowded 3D ball: particles whose blobs merge in the product slices are still found."""

from __future__ import annotations


import numpy as np
import pytest

from analysis.simulation.scoring import depth_floor, score
from analysis.errors import ParameterError
from analysis.detection.maxima import find_maxima
from analysis.detection.moments import detect
from analysis.pipeline.params import PipelineParams
from analysis.pipeline.process import process
from simulated_case import simulated_case

# A sensor crop that holds most of the 150-particle ball (about 130 particles): a few seconds.
SIZE = 700


@pytest.fixture(scope="module")
def ball(tmp_path_factory):
    c = simulated_case(tmp_path_factory.mktemp("ball"), "ball", 1, size=SIZE)
    return c.exposure, c.calibration, c.truth, c.nn_mm, c.cache


def test_crowded_ball_found(ball):
    exposure, calibration, truth, nn, cache = ball
    assert truth["X"].size >= 100
    result = process(exposure, calibration, PipelineParams(), cache=cache)
    s = score(result.particles, truth, nn_mm=nn)
    # Connected components alone merge neighbours' blobs and find about 40 % of this crop.
    assert s.recall >= 0.9 and s.precision >= 0.93
    assert s.lateral_rms_over_nn < 0.03
    # Near focus the pixels leave depths open (analysis.simulation.scoring.depth_floor): the fit comes within
    # 30 % of the best that any estimate from them can do.
    floor = depth_floor(truth, exposure.model.lattice, nn_mm=nn)[1]
    assert 0.03 < floor < 0.15
    assert s.depth_abs_rms_over_nn < 1.3 * floor


def test_components_alone_merge_neighbours(ball):
    """The same crop without the stack's maxima: most particles are lost (what the maxima fix)."""
    exposure, calibration, truth, nn, cache = ball
    params = PipelineParams(maxima_half_slices=-1, merge_slices=2.0, max_fit_residual=0.6)
    s = score(process(exposure, calibration, params, cache=cache).particles, truth, nn_mm=nn)
    assert s.recall < 0.7


def test_maxima_split_touching_blobs():
    """Two particles whose blobs touch in one slice give two maxima with their own centroids."""
    stack = np.zeros((5, 12, 16), dtype=np.float32)
    spot = np.array([[1, 2, 1], [2, 5, 2], [1, 2, 1]], dtype=np.float32)
    stack[2, 4:7, 3:6] += spot  # centre (x, y) = (4, 5)
    stack[2, 4:7, 6:9] += 0.8 * spot  # centre (7, 5): shares an edge with the first blob
    stack[1] = 0.5 * stack[2]
    stack[3] = 0.25 * stack[2]
    assert len(detect(stack[2], threshold=0.5)) == 1  # one connected component
    m = find_maxima(stack, np.linspace(0.99, 1.01, 5), threshold=0.5)
    order = np.argsort(m.x)
    assert len(m) == 2
    assert np.all(m.slice == 2)
    # the centroid windows (3 x 3 around each maximum) hold each particle's own pixels
    assert np.allclose(m.x[order], [4.0, 7.0])
    assert np.allclose(m.y, 5.0)
    # sub-slice alpha: the window sums fall off faster above slice 2 than below
    assert np.all(m.alpha < 1.0) and np.all(m.alpha > 0.995)


def test_maxima_refuse_a_bad_footprint():
    stack = np.zeros((3, 5, 5), dtype=np.float32)
    with pytest.raises(ParameterError):
        find_maxima(stack, np.linspace(0.99, 1.01, 3), threshold=0.0, half_px=0)
    with pytest.raises(ParameterError):
        find_maxima(stack, np.linspace(0.99, 1.01, 4), threshold=0.0)
    with pytest.raises(ParameterError):
        find_maxima(stack[0], np.linspace(0.99, 1.01, 3), threshold=0.0)
