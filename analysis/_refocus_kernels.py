"""numba kernels of the refocus: arrays and scalars in, caller-allocated arrays out.

No validation here; :mod:`analysis.refocus` checks shapes and dtypes and chooses the settings.
Lattice coordinates are "site" coordinates: column ``i - i0`` and row ``j - j0`` on the dense
lens-site grid of a :class:`analysis.lightfield.LightFieldTable`.

Triangles: the hexagonal lattice cell ``(i0, j0) ... (i0+1, j0+1)`` splits along the diagonal
``(i0+1, j0) - (i0, j0+1)`` into two equilateral triangles; barycentric weights in lattice
coordinates equal those in metres because the map between them is affine.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

# fastmath without nnan/ninf (the house rule): NaN checks must keep working.
FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@njit(cache=True)
def value_histogram(image_flat, pixel_index, weight, black, beta, divide, lo, inv_width, hist):  # pragma: no cover
    """Histogram of ``(raw + dither - black - beta * weight)`` (divided by ``weight`` if ``divide``)
    over all samples; bin ``b`` is centred on ``lo + b / inv_width``, values outside go to the
    end bins.

    The dither (a golden-ratio sequence over [-0.5, 0.5)) spreads each integer raw count over
    the interval it stands for, so that medians and MADs of 1 ... 3 DN noise are not rounded
    to whole DN.
    """
    n_bins = hist.size
    phase = 0.0
    for k in range(pixel_index.size):
        phase += 0.6180339887498949
        if phase >= 1.0:
            phase -= 1.0
        val = image_flat[pixel_index[k]] + (phase - 0.5) - black - beta * weight[k]
        if divide:
            val = val / weight[k]
        b = int(math.floor((val - lo) * inv_width + 0.5))
        if b < 0:
            b = 0
        elif b >= n_bins:
            b = n_bins - 1
        hist[b] += 1


@njit(parallel=True, cache=True)
def select_samples(image_flat, pixel_index, weight, keep, black, beta, threshold, n_chunks):  # pragma: no cover
    """Samples with ``raw - black - beta * weight > threshold`` (and ``keep``), as
    (ids int32, values float32); order is preserved. ``keep`` is a bool mask over samples."""
    n = pixel_index.size
    step = (n + n_chunks - 1) // n_chunks
    counts = np.zeros(n_chunks + 1, np.int64)
    for c in prange(n_chunks):
        cnt = 0
        for k in range(c * step, min(n, (c + 1) * step)):
            if keep[k] and image_flat[pixel_index[k]] - black - beta * weight[k] > threshold:
                cnt += 1
        counts[c + 1] = cnt
    starts = np.cumsum(counts)
    ids = np.empty(starts[-1], np.int32)
    values = np.empty(starts[-1], np.float32)
    for c in prange(n_chunks):
        pos = starts[c]
        for k in range(c * step, min(n, (c + 1) * step)):
            val = image_flat[pixel_index[k]] - black - beta * weight[k]
            if keep[k] and val > threshold:
                ids[pos] = k
                values[pos] = val
                pos += 1
    return ids, values


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def splat(ids, values, lens, lens_site, u, v, inv_basis, coeffs, n_i, n_j, acc):  # pragma: no cover
    """Shift-and-add every sample onto the 3 lens sites of its triangle, for every alpha.

    Sample ``ids[k]`` with value ``values[k]`` moves from its lens site by
    ``inv_basis @ (u, v) * coeffs[a]`` lattice steps (``coeffs = 1/alpha - 1``) and is split
    barycentrically. ``acc`` has shape (n_chunks, n_j * n_i, n_alpha), zeroed by the caller;
    chunk ``c`` of the samples adds into ``acc[c]`` only, so threads never share an output.
    Contributions whose triangle leaves the site grid are dropped (the normalisation drops the
    same ones).
    """
    n_chunks = acc.shape[0]
    n_alpha = coeffs.size
    n = ids.size
    step = (n + n_chunks - 1) // n_chunks
    b00 = np.float32(inv_basis[0, 0])
    b01 = np.float32(inv_basis[0, 1])
    b10 = np.float32(inv_basis[1, 0])
    b11 = np.float32(inv_basis[1, 1])
    for c in prange(n_chunks):
        out = acc[c]
        for k in range(c * step, min(n, (c + 1) * step)):
            s = ids[k]
            val = values[k]
            lk = lens[s]
            base_i = lens_site[lk, 0]
            base_j = lens_site[lk, 1]
            du = b00 * u[s] + b01 * v[s]
            dv = b10 * u[s] + b11 * v[s]
            for a in range(n_alpha):
                fi = base_i + du * coeffs[a]
                fj = base_j + dv * coeffs[a]
                i0 = int(math.floor(fi))
                j0 = int(math.floor(fj))
                if i0 < 0 or j0 < 0 or i0 + 1 >= n_i or j0 + 1 >= n_j:
                    continue
                wa = fi - i0
                wb = fj - j0
                site = j0 * n_i + i0
                if wa + wb < 1.0:
                    out[site, a] += val * (1.0 - wa - wb)
                    out[site + 1, a] += val * wa
                    out[site + n_i, a] += val * wb
                else:
                    out[site + n_i + 1, a] += val * (wa + wb - 1.0)
                    out[site + 1, a] += val * (1.0 - wb)
                    out[site + n_i, a] += val * (1.0 - wa)


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def reduce_chunks(acc, scale):  # pragma: no cover - numba
    """``acc[0] = sum(acc, axis=0) * scale`` (in place), in parallel over sites."""
    n_chunks, n_sites, n_alpha = acc.shape
    for s in prange(n_sites):
        for a in range(n_alpha):
            total = acc[0, s, a]
            for c in range(1, n_chunks):
                total += acc[c, s, a]
            acc[0, s, a] = total * scale[s, a]


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def interpolate_to_grid(site_values, valid, n_i, n_j, origin, d_col, d_row, out):  # pragma: no cover
    """Barycentric interpolation from the lens-site grid onto a regular image grid.

    Output pixel ``(col, row)`` sits at site coordinates ``origin + col * d_col + row * d_row``.
    ``site_values`` (n_sites, n_alpha); ``valid`` (n_sites, n_alpha) bool marks sites that
    received enough light to be trusted. Each pixel is the weighted mean of the valid corners
    of its triangle (0 where none is valid). ``out`` has shape (n_alpha, height, width).
    """
    n_alpha, height, width = out.shape
    for row in prange(height):
        for col in range(width):
            fi = origin[0] + col * d_col[0] + row * d_row[0]
            fj = origin[1] + col * d_col[1] + row * d_row[1]
            i0 = int(math.floor(fi))
            j0 = int(math.floor(fj))
            if i0 < 0 or j0 < 0 or i0 + 1 >= n_i or j0 + 1 >= n_j:
                for a in range(n_alpha):
                    out[a, row, col] = 0.0
                continue
            wa = fi - i0
            wb = fj - j0
            s0 = j0 * n_i + i0
            if wa + wb < 1.0:
                sa, sb, sc = s0, s0 + 1, s0 + n_i
                wx, wy, wz = 1.0 - wa - wb, wa, wb
            else:
                sa, sb, sc = s0 + n_i + 1, s0 + 1, s0 + n_i
                wx, wy, wz = wa + wb - 1.0, 1.0 - wb, 1.0 - wa
            for a in range(n_alpha):
                num = 0.0
                den = 0.0
                if valid[sa, a]:
                    num += wx * site_values[sa, a]
                    den += wx
                if valid[sb, a]:
                    num += wy * site_values[sb, a]
                    den += wy
                if valid[sc, a]:
                    num += wz * site_values[sc, a]
                    den += wz
                out[a, row, col] = num / den if den > 1e-6 else 0.0


@njit(parallel=True, fastmath=FASTMATH, cache=True)
def multiply_slices(stack, image, out):  # pragma: no cover - numba
    """``out[a] = stack[a] * image`` for every slice ``a``."""
    n_alpha, height, width = stack.shape
    for row in prange(height):
        for a in range(n_alpha):
            for col in range(width):
                out[a, row, col] = stack[a, row, col] * image[row, col]
