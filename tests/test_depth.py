"""Linking across slices and sub-slice peak location on synthetic stacks with known depths."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.detection.curves import Peaks, Tracks, find_depth_peaks, link_tracks, merge_duplicates, unique_indices
from analysis.errors import ParameterError
from analysis.detection.moments import detect

ALPHAS = np.linspace(0.987, 1.013, 40)
STEP = ALPHAS[1] - ALPHAS[0]


def spot_stack(xs, ys, alpha0, width_alpha, rng, *, shape=(120, 120), sigma_px=1.3, noise=0.3, amp=40.0):
    """Slices where each spot's amplitude follows a Gaussian in alpha peaking at its alpha0."""
    h, w = shape
    yy, xx = np.mgrid[0:h, 0:w]
    stack = np.zeros((ALPHAS.size, h, w))
    for x, y, a0, wa in zip(xs, ys, alpha0, width_alpha):
        spot = np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / (2 * sigma_px**2))
        curve = amp * np.exp(-((ALPHAS - a0) ** 2) / (2 * wa**2))
        stack += curve[:, None, None] * spot[None]
    return stack + noise * rng.standard_normal(stack.shape)


def run(stack, **kw):
    dets = [detect(s, threshold=3.0) for s in stack]
    return find_depth_peaks(link_tracks(dets), ALPHAS, **kw)


def match(found_x, found_y, found_a, xs, ys):
    d = np.hypot(found_x[:, None] - xs[None], found_y[:, None] - ys[None])
    return d.argmin(axis=0), d.min(axis=0)


def test_sub_slice_depth_and_position_recovered():
    rng = np.random.default_rng(10)
    n = 25
    gx, gy = np.meshgrid(np.arange(5) * 22 + 15, np.arange(5) * 22 + 15)
    xs = gx.ravel() + rng.uniform(-0.5, 0.5, n)
    ys = gy.ravel() + rng.uniform(-0.5, 0.5, n)
    a0 = rng.uniform(ALPHAS[3], ALPHAS[-4], n)
    wa = rng.uniform(2.0, 4.0, n) * STEP
    peaks = run(spot_stack(xs, ys, a0, wa, rng))
    assert len(peaks) == n
    idx, dist = match(peaks.x, peaks.y, peaks.alpha, xs, ys)
    assert dist.max() < 0.2
    err = (peaks.alpha[idx] - a0) / STEP
    # A fitted peak, not the arg-max: errors well under a slice, and not piled on slice centres.
    assert np.sqrt(np.mean(err**2)) < 0.1
    frac = ((peaks.alpha[idx] - ALPHAS[0]) / STEP) % 1.0
    assert np.ptp(frac) > 0.5
    # Mean intensity per pixel varies more slowly than the spot amplitude: wider, but in step.
    ratio = peaks.peak_width[idx] / wa
    assert np.all((ratio > 1.0) & (ratio < 1.6)) and np.ptp(ratio) < 0.3
    assert np.all(peaks.residual[idx] < 0.1)


def test_shadowing_pair_gives_two_particles():
    rng = np.random.default_rng(11)
    xs = np.array([40.0, 40.4, 80.0])
    ys = np.array([50.0, 50.3, 80.0])
    a0 = np.array([ALPHAS[12] + 0.3 * STEP, ALPHAS[22] - 0.2 * STEP, ALPHAS[20]])
    wa = np.full(3, 3 * STEP)
    peaks = run(spot_stack(xs, ys, a0, wa, rng))
    assert len(peaks) == 3
    pair = np.flatnonzero(np.hypot(peaks.x - 40.2, peaks.y - 50.15) < 2)
    assert pair.size == 2
    assert peaks.track[pair[0]] == peaks.track[pair[1]]  # one curve, two maxima
    found = np.sort(peaks.alpha[pair])
    assert np.allclose(found, a0[:2], atol=0.5 * STEP)  # the blobs merge, so each lobe leans a little
    # (x, y) at each maximum follows the particle in focus there
    first = pair[np.argmin(peaks.alpha[pair])]
    assert abs(peaks.x[first] - 40.0) < 0.3


def test_small_bump_is_not_a_second_particle():
    b = 100 * np.exp(-((ALPHAS - ALPHAS[15]) ** 2) / (2 * (3 * STEP) ** 2)) + 5
    b[30] += 3  # a bump of 3 % of the peak over the tail
    tracks = Tracks(x=np.full((1, 40), 10.0), y=np.full((1, 40), 20.0), brightness=b[None])
    assert len(find_depth_peaks(tracks, ALPHAS, min_prominence=0.2)) == 1
    assert len(find_depth_peaks(tracks, ALPHAS, min_prominence=0.0)) == 2


def test_gap_inside_a_curve_does_not_split_the_peak():
    b = 100 * np.exp(-((ALPHAS - ALPHAS[20]) ** 2) / (2 * (4 * STEP) ** 2))
    b[18] = np.nan
    tracks = Tracks(x=np.full((1, 40), 10.0), y=np.full((1, 40), 20.0), brightness=b[None])
    peaks = find_depth_peaks(tracks, ALPHAS)
    assert len(peaks) == 1 and abs(peaks.alpha[0] - ALPHAS[20]) < 0.2 * STEP


def test_peak_at_range_edge_is_not_reported():
    rng = np.random.default_rng(12)
    xs, ys = np.array([30.0, 70.0]), np.array([30.0, 70.0])
    a0 = np.array([ALPHAS[0] - 5 * STEP, ALPHAS[-1] + 5 * STEP])
    peaks = run(spot_stack(xs, ys, a0, np.full(2, 3 * STEP), rng))
    assert len(peaks) == 0


def test_linking_follows_slow_drift_and_keeps_neighbours_apart():
    rng = np.random.default_rng(13)
    stack = np.zeros((40, 60, 60))
    yy, xx = np.mgrid[0:60, 0:60]
    for k in range(40):
        for x0, y0 in ((20.0, 20.0), (26.0, 20.0)):
            x = x0 + 0.05 * k  # drifts 2 px over the stack, 0.05 px per slice
            stack[k] += 30 * np.exp(-((xx - x) ** 2 + (yy - y0) ** 2) / 2)
    stack += 0.2 * rng.standard_normal(stack.shape)
    tracks = link_tracks([detect(s, threshold=3.0) for s in stack])
    assert len(tracks) == 2
    assert np.all(np.isfinite(tracks.x))
    assert np.all(np.abs(np.diff(tracks.x, axis=1)) < 0.3)


def test_merge_duplicates_keeps_highest():
    b = np.vstack([100 * np.exp(-((ALPHAS - ALPHAS[20]) ** 2) / (2 * (3 * STEP) ** 2)),
                   60 * np.exp(-((ALPHAS - ALPHAS[20]) ** 2) / (2 * (3 * STEP) ** 2))])
    tracks = Tracks(x=np.full((2, 40), 10.0) + [[0.0], [0.5]], y=np.full((2, 40), 20.0), brightness=b)
    peaks = find_depth_peaks(tracks, ALPHAS)
    assert len(peaks) == 2
    merged = merge_duplicates(peaks, radius_px=1.5, alpha_tolerance=STEP)
    assert len(merged) == 1 and merged.track[0] == 0


def test_merge_with_depth_uncertainty_keeps_pairs_their_fits_tell_apart():
    # Three pairs 0.8 px apart, all within the alpha tolerance: the first's depths differ by one
    # combined standard deviation (one particle's light split between two fits), the second's by
    # five (two particles on nearly one line of sight), the third's by two with wide spreads.
    sigma = np.array([3e-4, 4e-4, 3e-4, 4e-4, 1e-3, 1e-3])
    gap = np.array([1.0, 5.0, 2.0]) * np.hypot(sigma[0::2], sigma[1::2])
    alpha = np.ravel(np.column_stack([np.full(3, 1.01), 1.01 + gap]))
    n = alpha.size
    peaks = Peaks(track=np.arange(n), alpha=alpha, x=np.repeat([10.0, 40.0, 70.0], 2) + np.tile([0.0, 0.8], 3),
                  y=np.full(n, 20.0), peak_height=np.ones(n), peak_width=np.ones(n), residual=np.zeros(n),
                  prominence=np.ones(n))
    brightness = np.array([1.0, 2.0, 1.0, 2.0, 2.0, 1.0])
    kept = unique_indices(peaks, radius_px=1.5, alpha_tolerance=0.01, priority=brightness, alpha_sigma=sigma,
                          max_sigmas=3.0)
    assert kept.tolist() == [1, 2, 3, 4]  # the brighter of the first and third pairs, both of the second
    # Without the uncertainties every pair within the tolerance is one particle.
    assert unique_indices(peaks, radius_px=1.5, alpha_tolerance=0.01, priority=brightness).tolist() == [1, 3, 4]


def test_bad_alphas_rejected():
    tracks = Tracks(x=np.zeros((1, 5)), y=np.zeros((1, 5)), brightness=np.ones((1, 5)))
    with pytest.raises(ParameterError, match="equal steps"):
        find_depth_peaks(tracks, np.array([1.0, 1.1, 1.3, 1.4, 1.5]))
    with pytest.raises(ParameterError, match="slices"):
        find_depth_peaks(tracks, ALPHAS)


def test_empty_input_gives_empty_peaks():
    tracks = link_tracks([detect(np.zeros((10, 10)), threshold=1.0) for _ in ALPHAS])
    assert len(tracks) == 0
    assert len(find_depth_peaks(tracks, ALPHAS)) == 0


def test_peak_in_one_slice_keeps_its_slice():
    # Neighbours under the fit level leave one point: no parabola can be fitted (singular).
    b = np.zeros(40)
    b[19:22] = [10.0, 100.0, 10.0]
    tracks = Tracks(x=np.full((1, 40), 10.0), y=np.full((1, 40), 20.0), brightness=b[None])
    peaks = find_depth_peaks(tracks, ALPHAS)
    assert len(peaks) == 1
    assert peaks.alpha[0] == pytest.approx(ALPHAS[20])
    assert peaks.peak_height[0] == pytest.approx(100.0) and np.isnan(peaks.peak_width[0])


def test_local_maxima_are_scipys_find_peaks():
    """The curves' peak finder replaces scipy.signal.find_peaks (whose import costs 25 MB): same
    indices, flat tops and ties included."""
    from scipy.signal import find_peaks

    from analysis.detection.curves import local_maxima

    rng = np.random.default_rng(3)
    for trial in range(500):
        n = int(rng.integers(0, 50))
        x = rng.integers(0, 4, n).astype(float) if trial % 2 else rng.random(n)  # integers: plateaus
        np.testing.assert_array_equal(local_maxima(x), find_peaks(x)[0])
