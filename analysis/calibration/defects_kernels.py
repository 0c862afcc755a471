"""numba kernels of the defect search (:mod:`analysis.calibration.defects`): arrays and scalars in,
caller-allocated outputs filled."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from analysis.camera.lattice_kernels import nearest_lens
from analysis.order_statistics import median_in_place

# fastmath without nnan/ninf (style guide): NaN marks pixels and lenses without a value.
_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@njit(cache=True, parallel=True, fastmath=_FASTMATH)
def lens_levels(image: np.ndarray, origin_x: float, origin_y: float, basis: np.ndarray, i0: int, j0: int,
                r_inner: float, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """``out[b, a]``: median of the finite pixels of ``image`` within ``r_inner`` of the micro-image
    centre of lens ``(i0 + a, j0 + b)``; NaN where none is."""
    h, w = image.shape
    nb, na = out.shape
    reach = int(math.ceil(r_inner)) + 1
    r2 = r_inner * r_inner
    size = (2 * reach + 1) * (2 * reach + 1)
    for b in prange(nb):
        buf = np.empty(size)
        for a in range(na):
            i = i0 + a
            j = j0 + b
            x0 = origin_x + basis[0, 0] * i + basis[0, 1] * j
            y0 = origin_y + basis[1, 0] * i + basis[1, 1] * j
            n = 0
            for r in range(max(int(y0) - reach, 0), min(int(y0) + reach + 1, h)):
                dy = r + 0.5 - y0
                for c in range(max(int(x0) - reach, 0), min(int(x0) + reach + 1, w)):
                    dx = c + 0.5 - x0
                    if dx * dx + dy * dy <= r2:
                        v = image[r, c]
                        if math.isfinite(v):
                            buf[n] = v
                            n += 1
            out[b, a] = median_in_place(buf, n) if n > 0 else np.nan


@njit(cache=True, parallel=True, fastmath=_FASTMATH)
def predict_from_neighbours(image: np.ndarray, origin_x: float, origin_y: float, basis: np.ndarray,
                            inverse: np.ndarray, levels: np.ndarray, i0: int, j0: int, steps: np.ndarray,
                            shifts: np.ndarray, n_use: int, out_pred: np.ndarray,
                            out_spread: np.ndarray) -> None:  # pragma: no cover - compiled
    """Each pixel as the micro-images around show the same place, without interpolating.

    ``shifts[m]`` (whole pixels ``(dx, dy)``) is nearly the lattice step ``steps[m] = (si, sj)``, so
    the pixel that far away sits at nearly the same place in lens ``(i + si, j + sj)`` as this pixel
    in its own lens ``(i, j)`` (the one nearest to it): a witness, scaled by the ratio of the two
    lenses' ``levels`` (``levels[b, a]`` of lens ``(i0 + a, j0 + b)``; a NaN or non-positive level
    counts as the same). The first ``n_use`` witnesses on the sensor (steps in order of preference)
    are used: ``out_pred`` is their median (NaN with fewer than three), ``out_spread`` 1.4826 times
    their median absolute deviation.
    """
    h, w = image.shape
    nb, na = levels.shape
    n_steps = steps.shape[0]
    for r in prange(h):
        val = np.empty(n_steps)
        dev = np.empty(n_steps)
        dy0 = r + 0.5 - origin_y
        for c in range(w):
            dx0 = c + 0.5 - origin_x
            bi, bj, _, _, _ = nearest_lens(dx0, dy0, basis, inverse)
            own = np.nan
            if 0 <= bi - i0 < na and 0 <= bj - j0 < nb:
                own = levels[bj - j0, bi - i0]
            n = 0
            for m in range(n_steps):
                if n == n_use:
                    break
                cc = c + shifts[m, 0]
                rr = r + shifts[m, 1]
                if cc < 0 or rr < 0 or cc >= w or rr >= h:
                    continue
                v = image[rr, cc]
                if not math.isfinite(v):
                    continue
                a = bi + steps[m, 0] - i0
                b = bj + steps[m, 1] - j0
                if math.isfinite(own) and own > 0.0 and 0 <= a < na and 0 <= b < nb:
                    other = levels[b, a]
                    if math.isfinite(other) and other > 0.0:
                        v *= own / other
                val[n] = v
                n += 1
            if n < 3:
                out_pred[r, c] = np.nan
                out_spread[r, c] = np.nan
                continue
            mid = median_in_place(val, n)
            for q in range(n):
                dev[q] = abs(val[q] - mid)
            out_pred[r, c] = mid
            out_spread[r, c] = 1.4826 * median_in_place(dev, n)


def lattice_steps(rings: int) -> np.ndarray:
    """The lattice steps ``(si, sj)`` to every lens within ``rings`` hexagonal rings, (N, 2) int64."""
    out = []
    for sj in range(-rings, rings + 1):
        for si in range(-rings, rings + 1):
            if (si, sj) != (0, 0) and max(abs(si), abs(sj), abs(si + sj)) <= rings:
                out.append((si, sj))
    return np.array(out, dtype=np.int64)


@njit(cache=True, fastmath=_FASTMATH)
def _noise_at(level: float, noise_level: np.ndarray, noise_sigma: np.ndarray) -> float:  # pragma: no cover
    """``noise_sigma`` interpolated at ``level`` in the table ``(noise_level, noise_sigma)`` (levels
    increasing), held constant beyond its ends."""
    n = noise_level.size
    if level <= noise_level[0]:
        return noise_sigma[0]
    if level >= noise_level[n - 1]:
        return noise_sigma[n - 1]
    k = np.searchsorted(noise_level, level) - 1
    t = (level - noise_level[k]) / (noise_level[k + 1] - noise_level[k])
    return noise_sigma[k] * (1.0 - t) + noise_sigma[k + 1] * t


@njit(cache=True, parallel=True, fastmath=_FASTMATH)
def residual_and_sigma(balanced: np.ndarray, pred: np.ndarray, spread: np.ndarray, means: np.ndarray,
                       noise_level: np.ndarray, noise_sigma: np.ndarray, sigma_scale: float, out_residual: np.ndarray,
                       out_sigma: np.ndarray) -> None:  # pragma: no cover - compiled
    """Residual ``(balanced - pred) * mean`` and its sigma ``sigma_scale * sqrt(noise(pred * mean)^2 +
    (spread * mean)^2)`` in DN, ``mean = means[row % 2, col % 2]`` (the Bayer channel's mean), ``noise``
    interpolated in the table ``(noise_level, noise_sigma)`` (levels increasing, DN)."""
    h, w = balanced.shape
    for r in prange(h):
        for c in range(w):
            x, s = _residual_at(balanced, pred, spread, means, noise_level, noise_sigma, sigma_scale, r, c)
            out_residual[r, c] = x
            out_sigma[r, c] = s


@njit(cache=True, fastmath=_FASTMATH)
def _residual_at(balanced: np.ndarray, pred: np.ndarray, spread: np.ndarray, means: np.ndarray,
                 noise_level: np.ndarray, noise_sigma: np.ndarray, sigma_scale: float, r: int,
                 c: int) -> tuple[float, float]:  # pragma: no cover - compiled
    """Pixel ``(r, c)``'s residual and sigma (DN) as :func:`residual_and_sigma` gives them; NaN, NaN
    where the pixel or its prediction is missing."""
    m = means[r % 2, c % 2]
    p = pred[r, c] * m
    x = balanced[r, c] * m - p
    if not (math.isfinite(p) and math.isfinite(x)):
        return np.nan, np.nan
    noise = _noise_at(p, noise_level, noise_sigma)
    sp = spread[r, c] * m
    return x, sigma_scale * math.sqrt(noise * noise + sp * sp)


@njit(cache=True, parallel=True, fastmath=_FASTMATH)
def accumulate_frame(balanced: np.ndarray, pred: np.ndarray, spread: np.ndarray, means: np.ndarray,
                     noise_level: np.ndarray, noise_sigma: np.ndarray, sigma_scale: float, dark: bool,
                     lit_level: float, dead_fraction: float, agree: float, dark_sigmas: float, sum_w: np.ndarray,
                     sum_wr: np.ndarray, n_up: np.ndarray, n_down: np.ndarray, dark_hot: np.ndarray,
                     n_dead: np.ndarray) -> None:  # pragma: no cover - compiled
    """Add one frame's evidence per pixel, with its residual and sigma as :func:`residual_and_sigma`
    gives them: ``1 / sigma^2`` and ``residual / sigma^2`` to the sums; one to ``n_up`` (``n_down``)
    where ``z = residual / sigma`` exceeds ``agree`` (is below ``-agree``); ``dark_hot`` where a
    ``dark`` frame shows ``z > dark_sigmas``; one to ``n_dead`` where a bright frame's lit pixel
    (``pred >= lit_level``) reads under ``dead_fraction`` of its prediction."""
    h, w = balanced.shape
    for r in prange(h):
        for c in range(w):
            x, s = _residual_at(balanced, pred, spread, means, noise_level, noise_sigma, sigma_scale, r, c)
            if not s > 0.0:  # missing (NaN) or no noise
                continue
            inv = 1.0 / (s * s)
            sum_w[r, c] += inv
            sum_wr[r, c] += x * inv
            z = x / s
            if z > agree:
                n_up[r, c] += 1
            elif z < -agree:
                n_down[r, c] += 1
            if dark:
                if z > dark_sigmas:
                    dark_hot[r, c] = True
            elif pred[r, c] >= lit_level and balanced[r, c] < dead_fraction * pred[r, c]:
                n_dead[r, c] += 1
