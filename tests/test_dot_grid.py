"""Grid identification of a dot target: every dot gets its true row and column, the dot nearest the
axis is (0, 0), and exposures at several stage positions are labelled alike."""

from __future__ import annotations

import math

import numpy as np
import pytest

from analysis.camera.dot_grid import align_grids, identify_grid
from analysis.errors import GridIdentificationError, TooFewDotsError


def _plate(*, half: int = 6, pitch: float = 1.0, turn_deg: float = 0.0, offset=(0.0, 0.0), scale: float = 1.0,
           distortion: float = 0.0, noise: float = 0.0, seed: int = 0):
    """Image positions of a square dot grid (x right, y down) with its true rows and columns."""
    rng = np.random.default_rng(seed)
    rows, cols = (a.ravel() for a in np.meshgrid(np.arange(-half, half + 1), np.arange(-half, half + 1),
                                                 indexing="ij"))
    t = math.radians(turn_deg)
    x = (cols * math.cos(t) - rows * math.sin(t)) * pitch + offset[0]
    y = (cols * math.sin(t) + rows * math.cos(t)) * pitch + offset[1]
    r2 = (x * x + y * y) / (half * pitch) ** 2
    k = scale * (1 + distortion * r2)
    pts = np.column_stack([x * k, y * k]) + rng.normal(0, noise, (rows.size, 2))
    return pts, rows, cols


def _labels(grid, rows, cols):
    return grid.rows, grid.cols, rows[grid.index], cols[grid.index]


def test_turned_distorted_noisy_grid_gets_its_true_rows_and_columns():
    pts, rows, cols = _plate(turn_deg=17.0, offset=(0.2, -0.3), distortion=0.04, noise=0.03)
    rng = np.random.default_rng(3)
    missing = rng.choice(len(pts), size=12, replace=False)
    keep = np.setdiff1d(np.arange(len(pts)), missing)
    # Faint duplicates beside some dots and stray detections between them.
    dup = rng.choice(keep, size=10, replace=False)
    stray = rng.uniform(-6, 6, (6, 2)) + 0.5
    all_pts = np.vstack([pts[keep], pts[dup] + 0.05, stray])
    brightness = np.r_[np.full(keep.size, 1000.0), np.full(dup.size, 100.0), np.full(len(stray), 300.0)]
    truth_rows = np.r_[rows[keep], np.full(dup.size + len(stray), -99)]
    truth_cols = np.r_[cols[keep], np.full(dup.size + len(stray), -99)]
    grid = identify_grid(all_pts, brightness=brightness)
    got_r, got_c, true_r, true_c = _labels(grid, truth_rows, truth_cols)
    assert len(grid) >= keep.size - 2
    assert np.array_equal(got_r, true_r) and np.array_equal(got_c, true_c)
    assert np.all(grid.index < keep.size), "a faint duplicate or a stray point was taken for a dot"


def test_columns_step_along_x_and_rows_down_y_and_zero_is_nearest_the_axis():
    pts, rows, cols = _plate(offset=(0.35, 0.2), turn_deg=-8.0)
    grid = identify_grid(pts, axis=(0.0, 0.0))
    origin = grid.index[(grid.rows == 0) & (grid.cols == 0)][0]
    assert origin == int(np.argmin(np.hypot(*pts.T)))
    assert grid.column_step[0] > 0.9 and grid.row_step[1] > 0.9
    # Off-axis elsewhere: the origin follows the axis.
    grid = identify_grid(pts, axis=(3.3, -2.1))
    origin = grid.index[(grid.rows == 0) & (grid.cols == 0)][0]
    assert (rows[origin], cols[origin]) == (-2, 3)
    assert np.array_equal(grid.rows - grid.rows[grid.index == origin], rows[grid.index] - rows[origin])


def test_exposures_at_several_positions_are_labelled_alike_when_another_dot_becomes_nearest_the_axis():
    # The stage drifts sideways, so the axis crosses from one dot's side to the next's; the image
    # grows with depth as through a lens.
    points, grids, truth = [], [], []
    for k, (ox, scale) in enumerate([(0.44, 1.0), (0.49, 1.04), (0.54, 1.08), (0.59, 1.12)]):
        pts, rows, cols = _plate(offset=(-ox, 0.1), scale=scale, noise=0.01, seed=k)
        points.append(pts)
        grids.append(identify_grid(pts))
        truth.append((rows, cols))
    raw_origins = [int(truth[k][1][g.index[(g.rows == 0) & (g.cols == 0)][0]]) for k, g in enumerate(grids)]
    assert len(set(raw_origins)) > 1, "setup: the dot nearest the axis should change between positions"
    aligned = align_grids(points, grids)
    # One physical dot, one label: the label minus the true row and column is the same everywhere.
    offsets = {(int(r) - int(rows[i]), int(c) - int(cols[i]))
               for g, (rows, cols) in zip(aligned, truth) for r, c, i in zip(g.rows, g.cols, g.index)}
    assert len(offsets) == 1, offsets


def test_a_dot_missed_on_the_axis_in_one_exposure_does_not_move_the_origin():
    points, grids, truth = [], [], []
    for k, scale in enumerate((1.0, 1.05, 1.1)):
        pts, rows, cols = _plate(offset=(0.05, -0.04), scale=scale, noise=0.01, seed=k)
        if k == 0:  # the dot on the axis is lost in the first exposure
            keep = ~((rows == 0) & (cols == 0))
            pts, rows, cols = pts[keep], rows[keep], cols[keep]
        points.append(pts)
        grids.append(identify_grid(pts))
        truth.append((rows, cols))
    for g, (rows, cols) in zip(align_grids(points, grids), truth):
        assert np.array_equal(g.rows, rows[g.index]) and np.array_equal(g.cols, cols[g.index])


def test_too_few_dots_and_no_grid_are_errors_that_say_what_to_do():
    pts, _, _ = _plate(half=1)
    with pytest.raises(TooFewDotsError, match="too few"):
        identify_grid(pts[:5])
    scatter = np.random.default_rng(1).uniform(-5, 5, (80, 2))
    with pytest.raises(GridIdentificationError, match="regular grid|square grid|spacing"):
        identify_grid(scatter)
