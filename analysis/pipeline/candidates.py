"""Candidate particles from the product stack: detection per slice, brightness curves and their
peaks, and the stack's local maxima where neighbours' blobs merge (stages 5 and 6 of the design)."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from analysis.camera.image_grid import ImageGrid
from analysis.detection.curves import Peaks, Tracks, find_depth_peaks, link_tracks, merge_duplicates
from analysis.detection.maxima import find_maxima
from analysis.detection.moments import detect

from .params import PipelineParams
from .stages import StageClock

#: Where extended light raises the noise (the shot noise of a reflection or of bright glow, and
#: what the background model misses there), noise peaks of the product stand higher, in proportion
#: to the samples' noise variance. A candidate there must stand this fraction of the threshold times
#: that ratio. At 0.25 (set on the realistic scenes of seeds 1-2, where it dropped 300-1100
#: candidates per frame before their fit, none of them a particle) it dropped real particles on a
#: 2000 DN band (fresh seed 106: blurred over 5 pitches, 800-1300 DN, at 0.12 and 0.24 of it, where
#: the variance ratio is 25-54); the fits' own tests reject what the lower gate lets through: on the
#: realistic layers, shadowing scenes, off-focus balls and clouds of seeds 106-109 (16 frames) 0.1
#: found 5 more real particles, no false one, in about the same time.
LOCAL_NOISE_FRACTION = 0.1


def product_threshold(noise_dn: float, params: PipelineParams) -> float:
    """Detection threshold for the product images: ``params.threshold``, or
    ``(threshold_sigma * noise_dn)**2``.

    A product pixel is a refocused value times a sub-aperture value, both in DN per unit white
    weight; it passes when both factors stand ``threshold_sigma`` raw-noise sigmas above the
    background. (The product's own pixel statistics are no guide: most pixels are exactly zero
    once the refocus skips samples in the noise, and the rest are mostly particle light.)
    """
    if params.threshold is not None:
        return float(params.threshold)
    return (params.threshold_sigma * max(noise_dn, 0.5)) ** 2


def below_local_noise(peaks: Peaks, grid: ImageGrid, lenses: cKDTree, variance_ratio: np.ndarray,
                      threshold: float) -> np.ndarray:
    """Mask of the candidates whose peak height is below :data:`LOCAL_NOISE_FRACTION` of
    ``threshold`` times the noise variance ratio of the lens nearest them.

    ``lenses``: a tree of the lens centres (lens-plane metres) that ``variance_ratio`` (at least 1,
    :meth:`analysis.lightfield.samples.Samples.variance_ratio`) is given for, one value each.
    """
    low = np.zeros(len(peaks), dtype=bool)
    if len(peaks) == 0 or not np.any(variance_ratio > 1.0):
        return low
    sx, sy = grid.to_lens_plane(peaks.x, peaks.y)
    lens = lenses.query(np.column_stack([sx, sy]))[1]
    return peaks.peak_height < LOCAL_NOISE_FRACTION * threshold * variance_ratio[lens]


def locate(product: np.ndarray, alphas: np.ndarray, params: PipelineParams, *, threshold: float,
           clock: StageClock | None = None) -> tuple[Peaks, Tracks]:
    """Detection in every product slice, linking, and the brightness peaks (stages 5 and 6)."""
    clock = StageClock() if clock is None else clock
    with clock.stage("detect"):
        detections = [detect(s, threshold=threshold, min_pixels=params.min_pixels) for s in product]
    with clock.stage("link"):
        tracks = link_tracks(detections, radius_px=params.link_radius_px, max_gap=params.max_gap)
    with clock.stage("peaks"):
        peaks = find_depth_peaks(tracks, alphas, min_prominence=params.min_prominence,
                                 fit_half_width=params.fit_half_width)
        step = float(alphas[1] - alphas[0])
        peaks = merge_duplicates(peaks, radius_px=params.link_radius_px, alpha_tolerance=1.5 * step)
    with clock.stage("maxima"):
        if params.maxima_half_slices >= 0:
            peaks, tracks = _add_maxima(product, alphas, params, threshold, peaks, tracks)
    return peaks, tracks


def _add_maxima(product: np.ndarray, alphas: np.ndarray, params: PipelineParams, threshold: float,
                peaks: Peaks, tracks: Tracks) -> tuple[Peaks, Tracks]:
    """Add the local maxima of the product stack that no brightness-curve peak accounts for.

    In crowds the blobs of neighbours merge into one component per slice, and their tracks hold
    one peak for several particles; each particle still makes a maximum of its own over (alpha,
    y, x). Each new candidate gets a curve of its own: the product at its pixel, slice by slice.
    """
    m = find_maxima(product, alphas, threshold=threshold, half_slices=params.maxima_half_slices, half_px=1)
    if len(m) == 0:
        return peaks, tracks
    step = float(alphas[1] - alphas[0])
    new = np.ones(len(m), dtype=bool)
    if len(peaks):
        # Within the linking radius and two slices of a peak: the same particle.
        near = cKDTree(np.column_stack([peaks.x, peaks.y])).query_ball_point(
            np.column_stack([m.x, m.y]), r=params.link_radius_px)
        for i, js in enumerate(near):
            if js and np.min(np.abs(peaks.alpha[js] - m.alpha[i])) <= 2 * step:
                new[i] = False
    idx = np.flatnonzero(new)
    n = idx.size
    if n == 0:
        return peaks, tracks
    rows = np.clip(np.rint(m.y[idx]).astype(np.int64), 0, product.shape[1] - 1)
    cols = np.clip(np.rint(m.x[idx]).astype(np.int64), 0, product.shape[2] - 1)
    curve = product[:, rows, cols].T.astype(np.float64)
    curve[curve <= threshold] = np.nan
    extra = Tracks(x=np.repeat(m.x[idx, None], alphas.size, axis=1), y=np.repeat(m.y[idx, None], alphas.size, axis=1),
                   brightness=curve)
    cand = Peaks(track=len(tracks) + np.arange(n, dtype=np.int64), alpha=m.alpha[idx], x=m.x[idx], y=m.y[idx],
                 peak_height=m.brightness[idx], peak_width=np.full(n, np.nan), residual=np.full(n, np.nan),
                 prominence=np.ones(n))
    tracks = Tracks(x=np.vstack([tracks.x, extra.x]), y=np.vstack([tracks.y, extra.y]),
                    brightness=np.vstack([tracks.brightness, extra.brightness]))
    return Peaks.concat(peaks, cand), tracks
