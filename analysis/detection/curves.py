"""Depth from brightness curves: link detections across refocused slices, find the peaks.

Each particle is brightest in the slice refocused at its own depth (the paper's
``B_i(alpha)``). Detections of consecutive slices are linked into tracks by mutual nearest
neighbours, each track gives a curve of apparent brightness against the slice index, and
every prominent maximum of a curve becomes one particle: particles that shadow each other
(nearly the same image position, different depths) share one track and show as several
maxima. The maximum is located between slices by a Gaussian (a parabola in ``log B``)
fitted by least squares to the points around it, and ``(x, y)`` is interpolated there.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from analysis.errors import ParameterError
from .moments import Detections


@dataclass(frozen=True)
class Tracks:
    """Detections linked across slices; arrays of shape ``(n_tracks, n_slices)``, NaN where a
    track has no detection in a slice."""

    x: np.ndarray
    y: np.ndarray
    brightness: np.ndarray

    def __len__(self) -> int:
        return int(self.x.shape[0])

    @property
    def n_slices(self) -> int:
        return int(self.x.shape[1])


@dataclass(frozen=True)
class Peaks:
    """One entry per particle found; arrays of shape ``(n,)``.

    Attributes
    ----------
    track : int64
        Row of :class:`Tracks` whose curve holds the peak (shadowing particles share one).
    alpha : float64
        Refocus parameter at the fitted maximum.
    x, y : float64
        Image position interpolated to ``alpha`` (index coordinates of the product images).
    peak_height : float64
        Brightness at the fitted maximum.
    peak_width : float64
        Standard deviation of the fitted Gaussian, in units of alpha.
    residual : float64
        RMS of the fit residual in ``log B`` (0 for a perfect Gaussian; NaN for a 3-point fit).
    prominence : float64
        Height above the higher of the two valleys that separate it from higher maxima of its
        curve (or from the curve's ends), as a fraction of the curve's maximum.
    """

    track: np.ndarray
    alpha: np.ndarray
    x: np.ndarray
    y: np.ndarray
    peak_height: np.ndarray
    peak_width: np.ndarray
    residual: np.ndarray
    prominence: np.ndarray

    def __len__(self) -> int:
        return int(self.alpha.shape[0])

    def take(self, index: np.ndarray) -> "Peaks":
        """The peaks at ``index`` (integer array or mask)."""
        return Peaks(**{name: getattr(self, name)[index] for name in self.__dataclass_fields__})

    @staticmethod
    def concat(*peaks: "Peaks") -> "Peaks":
        """The peaks one after the other."""
        return Peaks(**{name: np.concatenate([getattr(p, name) for p in peaks]) for name in Peaks.__dataclass_fields__})


def link_tracks(detections: Sequence[Detections], *, radius_px: float = 1.5, max_gap: int = 1) -> Tracks:
    """Link the detections of consecutive slices into tracks.

    A detection joins the track whose last position is its mutual nearest neighbour within
    ``radius_px``; a track stays open across up to ``max_gap`` slices without a detection;
    every detection left over starts a new track.

    Parameters
    ----------
    detections : sequence of Detections
        One per slice, in the order of increasing alpha.
    radius_px : float
        Largest distance between a track's last position and its next detection. The product
        images of the pipeline share one magnification, so particles hardly move between
        slices; the radius only needs to cover the centroid noise.
    max_gap : int
        Slices a track may skip.

    Returns
    -------
    Tracks
    """
    if radius_px <= 0:
        raise ParameterError(f"radius_px must be positive, got {radius_px}")
    if max_gap < 0:
        raise ParameterError(f"max_gap must be 0 or more, got {max_gap}")
    n_slices = len(detections)
    last_x = np.empty(0)
    last_y = np.empty(0)
    last_seen = np.empty(0, dtype=np.int64)
    assignments: list[np.ndarray] = []
    n_tracks = 0
    for k, det in enumerate(detections):
        n = len(det)
        track_of = np.full(n, -1, dtype=np.int64)
        open_ = np.flatnonzero(last_seen >= k - 1 - max_gap)
        if n and open_.size:
            det_xy = np.column_stack([det.x, det.y])
            trk_xy = np.column_stack([last_x[open_], last_y[open_]])
            d_t, nearest_det = cKDTree(det_xy).query(trk_xy, distance_upper_bound=radius_px)
            d_d, nearest_trk = cKDTree(trk_xy).query(det_xy, distance_upper_bound=radius_px)
            hit = np.isfinite(d_d)
            # mutual nearest neighbours only: a blob between two tracks goes to neither
            mutual = hit.copy()
            mutual[hit] = nearest_det[nearest_trk[hit]] == np.flatnonzero(hit)
            track_of[mutual] = open_[nearest_trk[mutual]]
        new = track_of < 0
        track_of[new] = n_tracks + np.arange(int(new.sum()))
        n_tracks += int(new.sum())
        if new.any():
            last_x = np.concatenate([last_x, np.empty(int(new.sum()))])
            last_y = np.concatenate([last_y, np.empty(int(new.sum()))])
            last_seen = np.concatenate([last_seen, np.empty(int(new.sum()), dtype=np.int64)])
        last_x[track_of] = det.x
        last_y[track_of] = det.y
        last_seen[track_of] = k
        assignments.append(track_of)

    x = np.full((n_tracks, n_slices), np.nan)
    y = np.full((n_tracks, n_slices), np.nan)
    b = np.full((n_tracks, n_slices), np.nan)
    for k, (det, track_of) in enumerate(zip(detections, assignments)):
        x[track_of, k] = det.x
        y[track_of, k] = det.y
        b[track_of, k] = det.brightness
    return Tracks(x=x, y=y, brightness=b)


def _fill_gaps(values: np.ndarray) -> np.ndarray:
    """Linear interpolation along each row across interior NaNs; leading/trailing NaNs stay."""
    n_rows, n_cols = values.shape
    valid = np.isfinite(values)
    cols = np.broadcast_to(np.arange(n_cols), values.shape)
    prev_idx = np.maximum.accumulate(np.where(valid, cols, -1), axis=1)
    next_idx = np.minimum.accumulate(np.where(valid, cols, n_cols)[:, ::-1], axis=1)[:, ::-1]
    interior = ~valid & (prev_idx >= 0) & (next_idx < n_cols)
    if not interior.any():
        return values
    rows = np.broadcast_to(np.arange(n_rows)[:, None], values.shape)
    r, c = rows[interior], cols[interior]
    p, q = prev_idx[interior], next_idx[interior]
    t = (c - p) / (q - p)
    out = values.copy()
    out[r, c] = values[r, p] * (1 - t) + values[r, q] * t
    return out


def find_depth_peaks(tracks: Tracks, alphas: np.ndarray, *, min_prominence: float = 0.2,
                     fit_half_width: int = 4, min_points: int = 3) -> Peaks:
    """Locate the maxima of every brightness curve between slices.

    Parameters
    ----------
    tracks : Tracks
        From :func:`link_tracks`.
    alphas : ndarray of shape (n_slices,)
        Refocus parameter of each slice, increasing and evenly spaced.
    min_prominence : float
        A maximum counts as a particle when it stands this fraction of its curve's highest
        value above the valley separating it from any higher maximum of the same curve.
    fit_half_width : int
        The Gaussian is fitted to up to ``2 * fit_half_width + 1`` slices around the maximum,
        stopping at the valleys on either side and below 30 % of the maximum.
    min_points : int
        Tracks detected in fewer slices than this are ignored.

    Returns
    -------
    Peaks
        Maxima on the first or last slice are not returned: their true peak may lie outside
        the alpha range, so the range should be widened to find them.
    """
    alphas = np.asarray(alphas, dtype=np.float64)
    n_slices = tracks.n_slices
    if alphas.shape != (n_slices,):
        raise ParameterError(f"{alphas.size} alphas given for {n_slices} slices")
    if n_slices < 3:
        raise ParameterError(f"at least 3 slices are needed to locate a peak, got {n_slices}")
    step = np.diff(alphas)
    if np.any(step <= 0) or not np.allclose(step, step[0], rtol=1e-6, atol=0):
        raise ParameterError("alphas must increase in equal steps (use refocus.default_alphas)")
    if not 0.0 <= min_prominence < 1.0:
        raise ParameterError(f"min_prominence must be in [0, 1), got {min_prominence}")
    if fit_half_width < 1:
        raise ParameterError(f"fit_half_width must be at least 1, got {fit_half_width}")
    step = float(step[0])

    count = np.sum(np.isfinite(tracks.brightness), axis=1)
    rows = np.flatnonzero(count >= max(min_points, 3))
    if rows.size == 0:
        return _empty_peaks()
    b = _fill_gaps(tracks.brightness[rows])
    xs = _fill_gaps(tracks.x[rows])
    ys = _fill_gaps(tracks.y[rows])
    b = np.where(np.isfinite(b) & (b > 0), b, 0.0)

    # All curves in one 1-D signal separated by zeros, so one find_peaks call serves them all.
    width = n_slices + 1
    signal = np.zeros(rows.size * width + 1)
    flat_index = (np.arange(rows.size)[:, None] * width + 1 + np.arange(n_slices)).ravel()
    signal[flat_index] = b.ravel()
    peaks = local_maxima(signal)
    if peaks.size == 0:
        return _empty_peaks()
    row = (peaks - 1) // width
    k = (peaks - 1) % width
    prom = _prominence_within(b, row, k)
    curve_max = b.max(axis=1)[row]
    keep = (prom >= min_prominence * curve_max) & (k >= 1) & (k <= n_slices - 2)
    keep &= (signal[peaks - 1] > 0) & (signal[peaks + 1] > 0)
    peaks, row, k = peaks[keep], row[keep], k[keep]
    prom = prom[keep] / curve_max[keep]
    if peaks.size == 0:
        return _empty_peaks()

    offset, fit_height, sigma, residual = _fit_log_parabola(signal, peaks, fit_half_width)
    pos = k + offset
    k0 = np.clip(np.floor(pos).astype(np.int64), 0, n_slices - 2)
    t = pos - k0
    x = xs[row, k0] * (1 - t) + xs[row, k0 + 1] * t
    y = ys[row, k0] * (1 - t) + ys[row, k0 + 1] * t
    # A neighbour slice lacking a position (it was a gap at the track's end) falls back to the peak slice.
    bad = ~np.isfinite(x) | ~np.isfinite(y)
    x[bad], y[bad] = xs[row[bad], k[bad]], ys[row[bad], k[bad]]
    return Peaks(track=rows[row].astype(np.int64), alpha=alphas[0] + pos * step, x=x, y=y,
                 peak_height=fit_height, peak_width=sigma * step, residual=residual, prominence=prom)


# Points below this fraction of the maximum are left out of the fit: the tails of a brightness
# curve are not Gaussian (pixels drop below the threshold), and they would bias the location.
_FIT_LEVEL = 0.3


def _prominence_within(curves: np.ndarray, row: np.ndarray, col: np.ndarray) -> np.ndarray:
    """Prominence of maxima ``curves[row, col]`` measured within their own curve.

    As scipy's, but a curve's ends (and the zeros where it was not detected) are not valleys: a
    maximum must fall on both sides, before any higher point, to count. A curve still rising at
    the end of the alpha range, or flat, has no prominent maximum: its particle lies outside.
    """
    out = np.zeros(row.size)
    for n, (r, c) in enumerate(zip(row.tolist(), col.tolist())):
        curve = curves[r]
        top = curve[c]
        valid = np.flatnonzero(curve > 0)
        lo, hi = valid[0], valid[-1]
        left = curve[lo:c + 1][::-1]
        higher = np.flatnonzero(left > top)
        left_min = left[: higher[0] if higher.size else left.size].min()
        right = curve[c:hi + 1]
        higher = np.flatnonzero(right > top)
        right_min = right[: higher[0] if higher.size else right.size].min()
        out[n] = top - max(left_min, right_min)
    return out


def _fit_log_parabola(signal: np.ndarray, peaks: np.ndarray, half: int
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares parabola in ``log B`` around each peak, within its own lobe.

    Returns the sub-slice offset of the maximum (clamped to +-1 slice), the fitted height,
    the Gaussian sigma in slices, and the RMS residual in ``log B`` (NaN with 3 points).
    """
    offsets = np.arange(-half, half + 1)
    idx = peaks[:, None] + offsets[None, :]
    idx = np.clip(idx, 0, signal.size - 1)
    vals = signal[idx]
    # Walk outwards from the peak; stop where the curve rises again (a neighbouring peak) or ends.
    use = np.zeros(vals.shape, dtype=bool)
    use[:, half] = True
    for side in (1, -1):
        ok = np.ones(peaks.size, dtype=bool)
        for j in range(1, half + 1):
            c = half + side * j
            ok &= (vals[:, c] > 0) & (vals[:, c] <= vals[:, c - side]) & (idx[:, c] == peaks + side * j)
            ok &= vals[:, c] >= _FIT_LEVEL * vals[:, half]
            use[:, c] = ok
    logs = np.log(np.where(use, vals, 1.0))
    w = use.astype(np.float64)
    u = offsets.astype(np.float64)[None, :]
    # Normal equations of log B = c0 + c1 u + c2 u^2, batched over peaks.
    s = [np.sum(w * u**p, axis=1) for p in range(5)]
    a = np.stack([np.stack([s[0], s[1], s[2]], -1),
                  np.stack([s[1], s[2], s[3]], -1),
                  np.stack([s[2], s[3], s[4]], -1)], -2)
    rhs = np.stack([np.sum(w * logs * u**p, axis=1) for p in range(3)], -1)
    n_used = w.sum(axis=1)
    # A peak seen in fewer than three slices has no parabola (the system is singular): it keeps
    # its slice, its own height and no width.
    fit = n_used >= 3
    coef = np.zeros((peaks.size, 3))
    if fit.any():
        coef[fit] = np.linalg.solve(a[fit], rhs[fit][..., None])[..., 0]
    c0, c1, c2 = coef[:, 0], coef[:, 1], coef[:, 2]
    good = fit & (c2 < 0)
    offset = np.where(good, -c1 / np.where(good, 2 * c2, -1.0), 0.0)
    offset = np.clip(offset, -1.0, 1.0)
    log_height = c0 + c1 * offset + c2 * offset**2
    height = np.where(good, np.exp(log_height), signal[peaks])
    sigma = np.where(good, np.sqrt(-0.5 / np.where(good, c2, -1.0)), np.nan)
    fitted = c0[:, None] + c1[:, None] * u + c2[:, None] * u**2
    sq = np.sum(w * (logs - fitted) ** 2, axis=1)
    residual = np.where(n_used > 3, np.sqrt(sq / np.maximum(n_used - 3, 1)), np.nan)
    return offset, height, sigma, residual


def merge_duplicates(peaks: Peaks, *, radius_px: float = 1.5, alpha_tolerance: float) -> Peaks:
    """Keep the highest of peaks closer than ``radius_px`` in the image and ``alpha_tolerance`` in alpha.

    A track broken by a longer gap, or a blob split in one slice, can report one particle twice.
    """
    return peaks.take(unique_indices(peaks, radius_px=radius_px, alpha_tolerance=alpha_tolerance))


def unique_indices(peaks: Peaks, *, radius_px: float, alpha_tolerance: float,
                   priority: np.ndarray | None = None, settled: int = 0,
                   alpha_sigma: np.ndarray | None = None, max_sigmas: float = np.inf,
                   apart: Callable[[int, int], bool] | None = None) -> np.ndarray:
    """Indices of the peaks to keep when near-duplicates are merged, in their original order.

    Of peaks within ``radius_px`` (image) and ``alpha_tolerance`` (alpha) of each other, the one
    with the highest ``priority`` (default ``peak_height``) is kept; the first ``settled`` peaks
    (particles already accepted) win over the others whatever their priority. With
    ``alpha_sigma`` (each peak's alpha uncertainty), a pair must also lie within ``max_sigmas``
    of their combined uncertainty in alpha; pairs for which ``apart(i, j)`` holds are never merged.
    """
    n = len(peaks)
    if n < 2:
        return np.arange(n)
    priority = peaks.peak_height if priority is None else np.asarray(priority)
    tree = cKDTree(np.column_stack([peaks.x, peaks.y]))
    removed = np.zeros(n, dtype=bool)
    newcomer = np.arange(n) >= settled
    for i in np.lexsort((-priority, newcomer)):
        if removed[i]:
            continue
        for j in tree.query_ball_point([peaks.x[i], peaks.y[i]], r=radius_px):
            if j == i or removed[j]:
                continue
            gap = abs(peaks.alpha[j] - peaks.alpha[i])
            if (gap <= alpha_tolerance
                    and (alpha_sigma is None or gap <= max_sigmas * np.hypot(alpha_sigma[i], alpha_sigma[j]))
                    and (apart is None or not apart(i, j))):
                removed[j] = True
    return np.flatnonzero(~removed)


def _empty_peaks() -> Peaks:
    f = np.empty(0)
    return Peaks(track=np.empty(0, dtype=np.int64), alpha=f, x=f.copy(), y=f.copy(), peak_height=f.copy(),
                 peak_width=f.copy(), residual=f.copy(), prominence=f.copy())


def local_maxima(x: np.ndarray) -> np.ndarray:
    """Indices of the local maxima of a 1-D signal, a flat top at its middle (rounded down): what
    ``scipy.signal.find_peaks(x)`` gives, whose import (scipy.signal pulls in scipy.stats and more)
    holds 25 MB of every worker's memory for this one call.

    >>> local_maxima(np.array([0.0, 2.0, 1.0, 3.0, 3.0, 0.0, 5.0]))
    array([1, 3])
    """
    return _local_maxima(np.ascontiguousarray(x, dtype=np.float64))


@njit(cache=True)
def _local_maxima(x):  # pragma: no cover - numba
    # scipy.signal._peak_finding_utils._local_maxima_1d: the ends are never maxima; a rise, then a
    # run of equal values, then a fall is one maximum at the run's middle.
    out = np.empty(x.size // 2 + 1, dtype=np.int64)
    m = 0
    i = 1
    i_max = x.size - 1
    while i < i_max:
        if x[i - 1] < x[i]:
            i_ahead = i + 1
            while i_ahead < i_max and x[i_ahead] == x[i]:
                i_ahead += 1
            if x[i_ahead] < x[i]:
                out[m] = (i + i_ahead - 1) // 2
                m += 1
                i = i_ahead
        i += 1
    return out[:m]
