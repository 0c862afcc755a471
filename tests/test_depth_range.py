"""The refocus range found from an exposure's survey (analysis.pipeline.depth_range)."""

from __future__ import annotations

import numpy as np

from analysis.pipeline.depth_range import LONE_GAP_STEPS, LONE_MAX, LONE_REST, apart

SURVEY = np.linspace(0.96, 1.0435, 48)
STEP = float(SURVEY[1] - SURVEY[0])


def _cluster(n: int, seed: int = 0) -> np.ndarray:
    """``n`` point fits' alphas, as close as a cluster's (under a survey step apart)."""
    return 1.0 + np.cumsum(np.random.default_rng(seed).uniform(0.1, 0.9, n)) * STEP


def test_a_lone_point_far_from_a_cluster_lies_apart_at_either_end():
    cluster = _cluster(40)
    front = cluster.min() - (LONE_GAP_STEPS + 1) * STEP
    back = cluster.max() + (LONE_GAP_STEPS + 3) * STEP
    alpha = np.r_[cluster[:20], back, front, front + 0.5 * STEP, cluster[20:]]
    assert np.array_equal(np.flatnonzero(apart(alpha, SURVEY)), [20, 21, 22])


def test_nothing_lies_apart_within_the_gap_or_where_the_rest_is_few_or_the_group_is_many():
    cluster = _cluster(LONE_REST)
    near = cluster.max() + (LONE_GAP_STEPS - 0.5) * STEP
    assert not apart(np.r_[cluster, near], SURVEY).any()
    far = cluster.max() + (LONE_GAP_STEPS + 1) * STEP
    assert not apart(np.r_[cluster[:-1], far], SURVEY).any()  # one fewer than LONE_REST left
    assert apart(np.r_[cluster, far], SURVEY).sum() == 1
    # A second layer of particles, however far, is part of the range.
    layer = far + np.arange(LONE_MAX + 1) * 0.5 * STEP
    assert not apart(np.r_[cluster, layer], SURVEY).any()
    assert not apart(np.empty(0), SURVEY).any()
