"""numba kernels of the refocus: arrays and scalars in, caller-allocated arrays out.

No validation here; :mod:`analysis.lightfield.refocus` checks shapes and dtypes and chooses the settings.
Lattice coordinates are relative: ``(ii, jj) = (i - i0, j - j0)``. Lens ``(ii, jj)`` is stored at
row ``jj``, column ``ii + jj // 2 + col_offset`` of the dense site grid (n_rows, n_cols) of a
:class:`analysis.lightfield.table.LightFieldTable`; so from site ``(ii, jj)``, ``(ii + 1, jj)`` is the
next column and ``(ii, jj + 1)`` is ``n_cols + (jj & 1)`` further on.

Triangles: the hexagonal lattice cell ``(i0, j0) ... (i0+1, j0+1)`` splits along the diagonal
``(i0+1, j0) - (i0, j0+1)`` into two equilateral triangles; barycentric weights in lattice
coordinates equal those in metres because the map between them is affine.
"""

from __future__ import annotations

import math
import os

# OpenMP threads that spin while waiting at barriers take the CPU from the thread still working
# when the machine is busy (2 shared cores, other workers): measured on the full pipeline under
# load, 343 ... 593 ms per exposure with passive waiting against 754 ... 1436 ms with the default,
# and 3 ... 4 times faster refocus calls. It must be set before numba starts its OpenMP threads
# (the first parallel kernel call); a value set by the user is kept.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np  # noqa: E402
from numba import njit, prange  # noqa: E402

# fastmath without nnan/ninf (the house rule): NaN checks must keep working.
FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@njit(cache=True)
def gather_subsample(image_flat, pixel_index, weight, black, stride):  # pragma: no cover - numba
    """``raw + dither - black`` and ``weight`` of every ``stride``-th sample (float32).

    The dither (a golden-ratio sequence over [-0.5, 0.5)) spreads each integer raw count over
    the interval it stands for, so that medians and MADs of 1 ... 3 DN noise are not rounded
    to whole DN.
    """
    n = (pixel_index.size + stride - 1) // stride
    values = np.empty(n, np.float32)
    weights = np.empty(n, np.float32)
    phase = 0.0
    for m in range(n):
        k = m * stride
        phase += 0.6180339887498949
        if phase >= 1.0:
            phase -= 1.0
        values[m] = image_flat[pixel_index[k]] + (phase - 0.5) - black
        weights[m] = weight[k]
    return values, weights


@njit(cache=True)
def value_histogram(values, weights, betas, divide, lo, inv_width, hist):  # pragma: no cover - numba
    """Histogram of ``values - betas * weights`` (divided by ``weights`` if ``divide``); bin ``b``
    is centred on ``lo + b / inv_width``, values outside go to the end bins."""
    n_bins = hist.size
    for k in range(values.size):
        val = values[k] - betas[k] * weights[k]
        if divide:
            val = val / weights[k]
        b = int(math.floor((val - lo) * inv_width + 0.5))
        if b < 0:
            b = 0
        elif b >= n_bins:
            b = n_bins - 1
        hist[b] += 1


@njit(parallel=True, cache=True)
def select_samples(image_flat, pixel_index, weight, black, beta, centre, n_sigmas, noise_a, noise_b,
                   lens, lens_threshold, n_chunks):  # pragma: no cover
    """Samples with ``val = raw - black - beta * weight`` above ``centre + n_sigmas * sqrt(noise_a +
    noise_b * beta * weight)`` (``beta`` per sample: the noise grows with the background), or where
    ``lens_threshold`` is not empty, above their lens's (``lens``: each sample's), as (ids int32,
    values float32), in table order.

    One pass over the image: chunk ``c`` writes its hits from the start of its own stretch of
    a full-length buffer (only the touched pages of which are ever backed by memory), then the
    stretches are packed.
    """
    n = pixel_index.size
    step = (n + n_chunks - 1) // n_chunks
    all_ids = np.empty(n, np.int32)
    all_values = np.empty(n, np.float32)
    counts = np.zeros(n_chunks, np.int64)
    for c in prange(n_chunks):
        pos = c * step
        for k in range(c * step, min(n, (c + 1) * step)):
            signal = beta[k] * weight[k]
            val = image_flat[pixel_index[k]] - black - signal
            if lens_threshold.size:
                above = val > lens_threshold[lens[k]]
            else:
                above = val > centre + n_sigmas * math.sqrt(noise_a + noise_b * max(signal, 0.0))
            if above:
                all_ids[pos] = k
                all_values[pos] = val
                pos += 1
        counts[c] = pos - c * step
    total = 0
    for c in range(n_chunks):
        total += counts[c]
    ids = np.empty(total, np.int32)
    values = np.empty(total, np.float32)
    pos = 0
    for c in range(n_chunks):
        for m in range(counts[c]):
            ids[pos + m] = all_ids[c * step + m]
            values[pos + m] = all_values[c * step + m]
        pos += counts[c]
    return ids, values


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def splat(ids, values, lens, lens_site, u, v, inv_basis, coeffs, n_cols, n_rows, col_offset, band_start,
          acc):  # pragma: no cover
    """Shift-and-add samples onto the 3 lens sites of their triangle, for every alpha at once.

    Sample ``ids[k]`` with value ``values[k]`` moves from its lens site by
    ``inv_basis @ (u, v) * coeffs[a]`` lattice steps (``coeffs = 1/alpha - 1``) and is split
    barycentrically into ``acc`` (n_rows * n_cols, n_alpha), which this kernel zeroes first.

    Threads never write the same site: samples come ordered by lens row and are cut into bands
    of ``H`` site rows (``band_start[b]`` is the first sample of band ``b``), where the caller
    makes sure no sample moves more than ``(H - 1) // 2`` rows, so that bands two apart never
    touch the same row; even bands run in parallel, then odd ones. Contributions whose triangle leaves the site
    grid are dropped (the normalisation drops the same ones).
    """
    n_sites, n_alpha = acc.shape
    for row in prange(n_rows):
        for s in range(row * n_cols, (row + 1) * n_cols):
            for a in range(n_alpha):
                acc[s, a] = 0.0
    b00 = np.float32(inv_basis[0, 0])
    b01 = np.float32(inv_basis[0, 1])
    b10 = np.float32(inv_basis[1, 0])
    b11 = np.float32(inv_basis[1, 1])
    one = np.float32(1.0)
    n_bands = band_start.size - 1
    for parity in range(2):
        for q in prange((n_bands - parity + 1) // 2):
            band = 2 * q + parity
            for k in range(band_start[band], band_start[band + 1]):
                s = ids[k]
                val = values[k]
                lk = lens[s]
                base_i = lens_site[lk, 0]
                base_j = lens_site[lk, 1]
                du = b00 * u[s] + b01 * v[s]
                dv = b10 * u[s] + b11 * v[s]
                for a in range(n_alpha):
                    # float32 throughout: the weights need no more, and it keeps the loop lean.
                    fi = base_i + du * coeffs[a]
                    fj = base_j + dv * coeffs[a]
                    fi0 = np.floor(fi)
                    fj0 = np.floor(fj)
                    i0 = int(fi0)
                    j0 = int(fj0)
                    col = i0 + (j0 >> 1) + col_offset
                    up = n_cols + (j0 & 1)             # from (i0, j0) to (i0, j0 + 1)
                    if j0 < 0 or j0 + 1 >= n_rows or col < 0 or col + 1 + (j0 & 1) >= n_cols:
                        continue
                    wa = fi - fi0
                    wb = fj - fj0
                    va = val * wa
                    vb = val * wb
                    site = j0 * n_cols + col
                    if wa + wb < one:
                        acc[site, a] += val - va - vb
                        acc[site + 1, a] += va
                        acc[site + up, a] += vb
                    else:
                        acc[site + up + 1, a] += va + vb - val
                        acc[site + 1, a] += val - vb
                        acc[site + up, a] += val - va


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def interpolate_to_grid(site_sums, site_scale, n_cols, n_rows, col_offset, origin, d_col, d_row,
                        out):  # pragma: no cover
    """Barycentric interpolation of ``site_sums * site_scale`` from the lens-site grid onto a
    regular image grid.

    Output pixel ``(col, row)`` sits at relative lattice coordinates ``origin + col * d_col + row * d_row``.
    ``site_sums`` and ``site_scale`` have shape (n_sites, n_alpha); a site with
    ``site_scale == 0`` received too little light to be trusted and is left out: each pixel is
    the weighted mean of the valid corners of its triangle (0 where none is valid).
    ``out`` has shape (n_alpha, height, width).
    """
    n_alpha, height, width = out.shape
    for row in prange(height):
        for col in range(width):
            fi = origin[0] + col * d_col[0] + row * d_row[0]
            fj = origin[1] + col * d_col[1] + row * d_row[1]
            i0 = int(math.floor(fi))
            j0 = int(math.floor(fj))
            c0 = i0 + (j0 >> 1) + col_offset
            if j0 < 0 or j0 + 1 >= n_rows or c0 < 0 or c0 + 1 + (j0 & 1) >= n_cols:
                for a in range(n_alpha):
                    out[a, row, col] = 0.0
                continue
            wa = fi - i0
            wb = fj - j0
            s0 = j0 * n_cols + c0
            up = n_cols + (j0 & 1)
            if wa + wb < 1.0:
                sa, sb, sc = s0, s0 + 1, s0 + up
                wx, wy, wz = 1.0 - wa - wb, wa, wb
            else:
                sa, sb, sc = s0 + up + 1, s0 + 1, s0 + up
                wx, wy, wz = wa + wb - 1.0, 1.0 - wb, 1.0 - wa
            for a in range(n_alpha):
                num = 0.0
                den = 0.0
                ga = site_scale[sa, a]
                gb = site_scale[sb, a]
                gc = site_scale[sc, a]
                if ga > 0.0:
                    num += wx * site_sums[sa, a] * ga
                    den += wx
                if gb > 0.0:
                    num += wy * site_sums[sb, a] * gb
                    den += wy
                if gc > 0.0:
                    num += wz * site_sums[sc, a] * gc
                    den += wz
                out[a, row, col] = num / den if den > 1e-6 else 0.0


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def splat_bilinear(ids, values, lens, lens_px, u, v, inv_step, coeffs, band_start, out):  # pragma: no cover
    """Shift-and-add every sample straight onto the regular output grid, bilinearly, for all alphas.

    Sample ``ids[k]`` sits at output-pixel coordinates ``lens_px[lens]`` plus
    ``(u, v) * inv_step * coeffs[a]`` and is split over the 4 pixels around it in slice ``a``
    of ``out`` (n_alpha, height, width), which this kernel zeroes first. Contributions whose
    square leaves the grid are dropped (the normalisation drops the same ones). Bands of
    samples (``band_start``) are cut by the caller so that bands two apart never write the
    same row; even bands run in parallel, then odd ones.
    """
    n_alpha, height, width = out.shape
    for plane_row in prange(n_alpha * height):
        a = plane_row // height
        row = plane_row - a * height
        for col in range(width):
            out[a, row, col] = 0.0
    step = np.float32(inv_step)
    n_bands = band_start.size - 1
    for parity in range(2):
        for q in prange((n_bands - parity + 1) // 2):
            band = 2 * q + parity
            for k in range(band_start[band], band_start[band + 1]):
                s = ids[k]
                val = values[k]
                lk = lens[s]
                base_c = lens_px[lk, 0]
                base_r = lens_px[lk, 1]
                du = u[s] * step
                dv = v[s] * step
                for a in range(n_alpha):
                    fc = base_c + du * coeffs[a]
                    fr = base_r + dv * coeffs[a]
                    fc0 = np.floor(fc)
                    fr0 = np.floor(fr)
                    c0 = int(fc0)
                    r0 = int(fr0)
                    if c0 < 0 or r0 < 0 or c0 + 1 >= width or r0 + 1 >= height:
                        continue
                    wc = fc - fc0
                    wr = fr - fr0
                    top = val - val * wr           # val * (1 - wr)
                    bottom = val * wr
                    out[a, r0, c0] += top - top * wc
                    out[a, r0, c0 + 1] += top * wc
                    out[a, r0 + 1, c0] += bottom - bottom * wc
                    out[a, r0 + 1, c0 + 1] += bottom * wc


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def gaussian_blur(image, taps, out):  # pragma: no cover - numba
    """Separable blur of ``image`` (H, W) float32 with the odd-length kernel ``taps``, zero
    outside the image, into ``out``. (In numba rather than OpenCV so that one thread pool
    serves the whole refocus: two pools on two cores wait on each other.)"""
    height, width = image.shape
    half = taps.size // 2
    tmp = np.empty_like(image)
    for row in prange(height):
        for col in range(width):
            acc = np.float32(0.0)
            for k in range(taps.size):
                c = col + k - half
                if 0 <= c < width:
                    acc += taps[k] * image[row, c]
            tmp[row, col] = acc
    for row in prange(height):
        for col in range(width):
            acc = np.float32(0.0)
            for k in range(taps.size):
                r = row + k - half
                if 0 <= r < height:
                    acc += taps[k] * tmp[r, col]
            out[row, col] = acc


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def multiply_slices(stack, image, out):  # pragma: no cover - numba
    """``out[a] = stack[a] * image`` for every slice ``a``."""
    n_alpha, height, width = stack.shape
    for row in prange(height):
        for a in range(n_alpha):
            for col in range(width):
                out[a, row, col] = stack[a, row, col] * image[row, col]
