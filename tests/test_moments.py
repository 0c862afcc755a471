"""Moment-method detection on synthetic spots with known sub-pixel centres."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from analysis.errors import ParameterError
from analysis.detection.moments import detect, estimate_noise


def gaussian_spots(shape, xs, ys, amps, sigma, noise, rng):
    """Pixel-integrated Gaussian spots (erf differences) plus Gaussian noise."""
    from scipy.special import erf

    h, w = shape
    img = np.zeros(shape)
    edges_x = np.arange(w + 1) - 0.5
    edges_y = np.arange(h + 1) - 0.5
    s = sigma * np.sqrt(2)
    for x, y, a in zip(xs, ys, amps):
        gx = np.diff(erf((edges_x - x) / s)) / 2
        gy = np.diff(erf((edges_y - y) / s)) / 2
        img += a * np.outer(gy, gx) * 2 * np.pi * sigma**2
    return img + noise * rng.standard_normal(shape)


def spot_grid(n_side, spacing, rng):
    centres = (np.arange(n_side) + 1) * spacing
    gx, gy = np.meshgrid(centres, centres)
    xs = gx.ravel() + rng.uniform(-0.5, 0.5, gx.size)
    ys = gy.ravel() + rng.uniform(-0.5, 0.5, gy.size)
    return xs, ys, (n_side + 1) * spacing


def match(d, xs, ys):
    dist = np.hypot(d.x[:, None] - xs[None, :], d.y[:, None] - ys[None, :])
    return dist.argmin(axis=0), dist.min(axis=0)


def test_subpixel_centres_recovered():
    rng = np.random.default_rng(1)
    xs, ys, size = spot_grid(12, 14, rng)
    img = gaussian_spots((size, size), xs, ys, np.full(xs.size, 100.0), 1.3, 1.0, rng)
    d = detect(img, threshold_sigma=5)
    assert len(d) == xs.size
    idx, dist = match(d, xs, ys)
    assert dist.max() < 0.15
    assert np.sqrt(np.mean(dist**2)) < 0.06
    assert np.all(d.npix >= 5)


def test_no_pixel_locking():
    rng = np.random.default_rng(2)
    xs, ys, size = spot_grid(20, 12, rng)
    img = gaussian_spots((size, size), xs, ys, np.full(xs.size, 60.0), 1.2, 0.5, rng)
    d = detect(img, threshold_sigma=5)
    idx, dist = match(d, xs, ys)
    assert dist.max() < 0.2
    frac = np.concatenate([d.x[idx] % 1.0, d.y[idx] % 1.0])
    # Pixel locking piles the fractional parts up near 0 (pixel centres); a flat histogram passes.
    assert stats.kstest(frac, "uniform").pvalue > 0.01
    hist, _ = np.histogram(frac, bins=10, range=(0, 1))
    assert stats.chisquare(hist).pvalue > 0.01


def test_plain_centroid_would_lock_so_the_test_can_fail():
    """The same histogram test catches locking: round the centres and it fails."""
    rng = np.random.default_rng(2)
    xs, ys, size = spot_grid(20, 12, rng)
    img = gaussian_spots((size, size), xs, ys, np.full(xs.size, 60.0), 1.2, 0.5, rng)
    d = detect(img, threshold_sigma=5)
    locked = np.round(d.x * 2) / 2 + 0.01 * (d.x - np.round(d.x * 2) / 2)
    hist, _ = np.histogram(locked % 1.0, bins=10, range=(0, 1))
    assert stats.chisquare(hist).pvalue < 0.01


def test_brightness_is_mean_intensity_per_pixel_and_threshold_explicit():
    img = np.zeros((12, 12))
    img[2:4, 2:5] = 10.0                       # 6 pixels of 10
    img[2, 6] = 5.0                            # at the threshold, not above: not a blob
    img[8, 8], img[8, 9], img[9, 8] = 30, 20, 10
    d = detect(img, threshold=5.0, min_pixels=1)
    order = np.argsort(d.y)
    assert np.allclose(d.brightness[order], [10.0, 20.0])
    assert np.allclose(d.npix[order], [6, 3])
    # Weights are intensity minus threshold: 25, 15, 5.
    assert np.isclose(d.x[order][1], (25 * 8 + 15 * 9 + 5 * 8) / 45)
    assert np.isclose(d.y[order][1], (25 * 8 + 15 * 8 + 5 * 9) / 45)
    assert d.threshold == 5.0


def test_min_pixels_drops_isolated_pixels():
    img = np.zeros((10, 10))
    img[2, 2] = 50
    img[6:8, 6:8] = 50
    assert len(detect(img, threshold=1.0, min_pixels=2)) == 1
    assert len(detect(img, threshold=1.0, min_pixels=1)) == 2


def test_dilation_grows_blobs_without_moving_symmetric_centre():
    img = np.zeros((15, 15))
    img[6:9, 6:9] = 1.0
    img[7, 7] = 5.0
    d0 = detect(img, threshold=2.0, min_pixels=1)
    d1 = detect(img, threshold=2.0, min_pixels=1, dilate_px=1)
    assert d0.npix[0] == 1 and d1.npix[0] == 9
    assert (d1.x[0], d1.y[0]) == (7.0, 7.0)
    assert np.isclose(d1.brightness[0], 13 / 9)


def test_empty_and_constant_images_give_no_detections():
    assert len(detect(np.zeros((20, 30)))) == 0
    assert len(detect(np.full((20, 30), 7.0))) == 0
    rng = np.random.default_rng(3)
    noise_only = rng.standard_normal((200, 200))
    assert len(detect(noise_only, threshold_sigma=6)) == 0


def test_noise_estimate_ignores_sparse_spots_and_zero_padding():
    rng = np.random.default_rng(4)
    img = 5 + 0.5 * rng.standard_normal((300, 300))
    img[::25, ::25] = 500
    level = estimate_noise(img)
    assert abs(level.background - 5) < 0.05 and abs(level.sigma - 0.5) < 0.05
    padded = np.zeros((300, 300))
    padded[:100] = img[:100]
    assert estimate_noise(padded).sigma > 0


def test_float32_input_accepted_and_bad_shape_rejected():
    img = np.zeros((10, 10), np.float32)
    img[4:6, 4:6] = 3
    assert detect(img, threshold=1.0).x.dtype == np.float64
    with pytest.raises(ParameterError, match="2-D"):
        detect(np.zeros((2, 10, 10)))
