"""Particles as local maxima of the product stack over (alpha, y, x).

Where particles crowd (a 3D ball), the blobs of neighbours merge in each thresholded product
slice, so the connected components of the moment method hold several particles and the
brightness curves of their tracks mix. Every particle still makes a local maximum of the
stack in its own slice; a maximum over a footprint tied to the spot size (about one output
pixel either side, a few slices in alpha) marks one particle, and the moment method of Feng
et al. (threshold-subtracted, intensity-weighted centroid) is applied to the pixels around
each maximum only, so merged blobs are split.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from analysis.errors import ParameterError

_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@dataclass(frozen=True)
class Maxima:
    """Local maxima of a stack; every array has shape ``(n,)``.

    Attributes
    ----------
    slice : int64
        Slice index of the maximum.
    alpha : float64
        Sub-slice position in alpha (parabola through the window sums of the slices either side).
    x, y : float64
        Moment centroid (threshold-subtracted, intensity-weighted) of the pixels above the
        threshold in the ``(2 r + 1)**2`` window around the maximum, index coordinates.
    height : float64
        Value of the maximum.
    brightness : float64
        Mean value per pixel above the threshold in the window (Feng et al.'s apparent brightness).
    """

    slice: np.ndarray
    alpha: np.ndarray
    x: np.ndarray
    y: np.ndarray
    height: np.ndarray
    brightness: np.ndarray

    def __len__(self) -> int:
        return int(self.x.shape[0])


def find_maxima(stack: np.ndarray, alphas: np.ndarray, *, threshold: float, half_slices: int = 2,
                half_px: int = 1, window_px: int = 1) -> Maxima:
    """Local maxima above ``threshold`` of a stack (A, H, W) and their moment centroids.

    Parameters
    ----------
    stack : ndarray of shape (A, H, W)
        Product images of the refocused slices (float32).
    alphas : ndarray of shape (A,)
        Refocus parameter of each slice (ascending, evenly spaced).
    threshold : float
        Values at or below it are background.
    half_slices, half_px : int
        The footprint: a voxel is a maximum when no voxel within ``half_slices`` slices and
        ``half_px`` pixels (a box) is higher (ties go to the first in memory order). Pixels on
        the image border are never maxima.
    window_px : int
        Half-width of the centroid window (pixels).

    Returns
    -------
    Maxima

    Raises
    ------
    ParameterError
        For a stack that is not 3-D, alphas that do not match it, or a footprint out of range.
    """
    stack = np.ascontiguousarray(stack, dtype=np.float32)
    if stack.ndim != 3:
        raise ParameterError(f"find_maxima needs a stack (A, H, W), got shape {stack.shape}")
    alphas = np.asarray(alphas, dtype=np.float64)
    if alphas.shape != (stack.shape[0],):
        raise ParameterError(f"need one alpha per slice: {alphas.shape[0]} alphas for {stack.shape[0]} slices")
    if half_slices < 0 or half_px < 1 or window_px < 0:
        raise ParameterError(f"need half_slices >= 0, half_px >= 1 and window_px >= 0, got {half_slices}, "
                             f"{half_px}, {window_px}")
    out = np.empty((_count_limit(stack, float(threshold)), 6))
    n = _maxima(stack, float(threshold), int(half_slices), int(half_px), int(window_px), out)
    out = out[:n]
    k = out[:, 0].astype(np.int64)
    step = float(alphas[1] - alphas[0]) if alphas.size > 1 else 0.0
    return Maxima(slice=k, alpha=alphas[k] + out[:, 1] * step, x=out[:, 2], y=out[:, 3], height=out[:, 4],
                  brightness=out[:, 5])


@numba.njit(cache=True)
def _count_limit(stack, threshold):
    # An upper bound on the maxima: voxels above the threshold that beat their 4 in-slice neighbours.
    a, h, w = stack.shape
    n = 0
    for k in range(a):
        for r in range(1, h - 1):
            for c in range(1, w - 1):
                v = stack[k, r, c]
                if v > threshold and v >= stack[k, r - 1, c] and v >= stack[k, r + 1, c] \
                        and v >= stack[k, r, c - 1] and v >= stack[k, r, c + 1]:
                    n += 1
    return n + 1


@numba.njit(cache=True, fastmath=_FASTMATH)
def _maxima(stack, threshold, hk, hp, win, out):
    a, h, w = stack.shape
    n = 0
    for k in range(a):
        for r in range(1, h - 1):
            for c in range(1, w - 1):
                v = stack[k, r, c]
                if v <= threshold:
                    continue
                best = True
                for kk in range(max(k - hk, 0), min(k + hk + 1, a)):
                    for rr in range(max(r - hp, 0), min(r + hp + 1, h)):
                        for cc in range(max(c - hp, 0), min(c + hp + 1, w)):
                            u = stack[kk, rr, cc]
                            # ties: the first in memory order wins, so a plateau gives one maximum
                            if u > v or (u == v and (kk, rr, cc) < (k, r, c)):
                                best = False
                                break
                        if not best:
                            break
                    if not best:
                        break
                if not best or n >= out.shape[0]:
                    continue
                # Feng et al.: threshold-subtracted intensity-weighted centroid over the window
                sw = 0.0
                sx = 0.0
                sy = 0.0
                si = 0.0
                m = 0
                for rr in range(max(r - win, 0), min(r + win + 1, h)):
                    for cc in range(max(c - win, 0), min(c + win + 1, w)):
                        u = stack[k, rr, cc]
                        if u > threshold:
                            wgt = u - threshold
                            sw += wgt
                            sx += wgt * cc
                            sy += wgt * rr
                            si += u
                            m += 1
                # sub-slice position: parabola through the window sums of slices k-1, k, k+1
                dk = 0.0
                if 0 < k < a - 1:
                    s0 = 0.0
                    s1 = 0.0
                    s2 = 0.0
                    for rr in range(max(r - win, 0), min(r + win + 1, h)):
                        for cc in range(max(c - win, 0), min(c + win + 1, w)):
                            s0 += stack[k - 1, rr, cc]
                            s1 += stack[k, rr, cc]
                            s2 += stack[k + 1, rr, cc]
                    den = s0 - 2.0 * s1 + s2
                    if den < 0.0:
                        dk = min(max(0.5 * (s0 - s2) / den, -0.5), 0.5)
                out[n, 0] = k
                out[n, 1] = dk
                out[n, 2] = sx / sw
                out[n, 3] = sy / sw
                out[n, 4] = v
                out[n, 5] = si / m
                n += 1
    return n
