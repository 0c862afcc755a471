"""Scoring a particle table against the simulator's truth: matches, and recall by defocus blur."""

from __future__ import annotations

import numpy as np

from analysis.simulation.scoring import RECALL_BLUR_BINS, blur_bin_label, score


def _truth() -> dict[str, np.ndarray]:
    """Ten particles 1 mm apart on a slanted line, blurred over 1, 3, 5, 7, 9, 10, 11, 13, 15 and 20
    pitches."""
    x = np.arange(10, dtype=float)
    return {"X": x, "Y": np.zeros(10), "Z": 50.0 + 0.3 * x,
            "blur_pitches": np.array([1.0, 3.0, 5.0, 7.0, 9.0, 10.0, 11.0, 13.0, 15.0, 20.0])}


def test_recall_by_blur_counts_each_bins_true_and_matched_particles():
    truth = _truth()
    # Found: particles 0, 2, 3, 5 and 9 (each 0.05 mm off), and one far from every true one.
    found_idx = np.array([0, 2, 3, 5, 9])
    found = {"X": np.r_[truth["X"][found_idx] + 0.05, 30.0], "Y": np.zeros(6),
             "Z": np.r_[truth["Z"][found_idx], 50.0]}
    s = score(found, truth, nn_mm=1.0)
    assert (s.n_true, s.n_found, s.n_matched) == (10, 6, 5)
    labels = [blur_bin_label(lo, hi) for lo, hi in RECALL_BLUR_BINS]
    assert labels == ["0-4", "4-8", "8-12", ">12"]
    # Blurs per bin: [1*, 3], [5*, 7*], [9, 10*, 11], [13, 15, 20*] (* found).
    assert s.recall_by_blur == {"0-4": (2, 1), "4-8": (2, 2), "8-12": (3, 1), ">12": (3, 1)}
    assert sum(t for t, _ in s.recall_by_blur.values()) == s.n_true
    assert sum(m for _, m in s.recall_by_blur.values()) == s.n_matched


def test_no_blur_column_no_breakdown_and_nothing_found_counts_every_true_particle():
    truth = _truth()
    plain = {c: truth[c] for c in "XYZ"}
    assert score(plain, plain, nn_mm=1.0).recall_by_blur == {}
    empty = {c: np.empty(0) for c in "XYZ"}
    s = score(empty, truth, nn_mm=1.0)
    assert s.n_matched == 0 and s.depth_by_blur == {}
    assert s.recall_by_blur == {"0-4": (2, 0), "4-8": (2, 0), "8-12": (3, 0), ">12": (3, 0)}
