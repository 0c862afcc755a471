"""Light that does not come from particles: plasma glow and out-of-focus reflections.

Seen through one aperture point, that is in one sub-aperture image (one sample per lens, the
samples at the same place in every micro-image), a particle is a point: the ray from that
aperture point toward it enters one lens. Glow, and light from sources far out of focus (a laser
band reflected by an electrode, glints), is extended there and changes slowly from lens to lens.
So a median over a lens's neighbours, taken at the same aperture point, gives the extended light
behind each sample and leaves the particles out, however crowded or defocused they are.

Working that out for every sample costs too much, and most of the sensor sees only glow, which
lights whole micro-images alike: there each lens's median value, a median over its neighbours,
gives its level. Only where that level stands out from the glow (reflections, glints, and their
surroundings) is the background taken sample by sample.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange
from scipy.ndimage import binary_dilation, median_filter

from analysis.order_statistics import median_in_place

from .table import LightFieldTable

#: Neighbourhood of the medians over lenses, in lenses (a square in lattice indices, 25 lenses).
NEIGHBOURHOOD_LENSES = 5
#: Samples nearer the micro-image centre than this fraction of its radius measure a lens's level
#: (the rims carry the neighbours' cross-talk and the vignetting's steepest slope).
CENTRAL_FRACTION = 0.8
#: Lenses whose level stands this many noise sigmas (of one sample) above the typical one hold
#: structured extended light (a lens's median over its ~50 central samples is 5 times less noisy):
#: their background is taken sample by sample, and that of the lenses around them ...
STRUCTURED_SIGMAS = 1.0
#: ... up to this many lenses away (the soft edges of out-of-focus sources).
STRUCTURED_MARGIN_LENSES = 5


@dataclass(frozen=True)
class BackgroundMap:
    """Extended light, in devignetted DN (per unit white-image weight).

    Attributes
    ----------
    level : ndarray of shape (n_j, n_i), float64
        Level of lens ``(i, j)`` at ``level[j - j0, i - i0]``.
    i0, j0 : int
        Lattice index of ``level[0, 0]``.
    pixels : ndarray of int64, sorted
        Flat sensor indices of the samples whose background was taken one by one ...
    values : ndarray of float32
        ... and their background (replacing their lens's level).
    """

    level: np.ndarray
    i0: int
    j0: int
    pixels: np.ndarray
    values: np.ndarray

    @staticmethod
    def uniform(level: float) -> "BackgroundMap":
        """One level everywhere (a diffuse glow)."""
        return BackgroundMap(np.full((1, 1), float(level)), 0, 0, np.empty(0, np.int64), np.empty(0, np.float32))

    @property
    def median(self) -> float:
        """The typical level: what a single number would say."""
        return float(np.median(self.level))

    def per_lens(self, table: LightFieldTable) -> np.ndarray:
        """The level behind each lens of ``table`` (float64, ``table.n_lenses``); lenses beyond
        the map take its nearest edge's."""
        if self.level.size == 1:
            return np.full(table.n_lenses, float(self.level[0, 0]))
        jj = np.clip(table.lens_ij[:, 1] - self.j0, 0, self.level.shape[0] - 1)
        ii = np.clip(table.lens_ij[:, 0] - self.i0, 0, self.level.shape[1] - 1)
        return np.ascontiguousarray(self.level[jj, ii], dtype=np.float64)

    def per_sample(self, table: LightFieldTable) -> np.ndarray:
        """The background behind each sample of ``table`` (float32, ``table.n_samples``)."""
        out = self.per_lens(table).astype(np.float32)[table.lens]
        if self.pixels.size:
            # Only the samples of lenses with structured light can be among the pixels.
            lo, hi = self.pixels[0], self.pixels[-1]
            maybe = np.flatnonzero((table.pixel_index >= lo) & (table.pixel_index <= hi))
            at = np.searchsorted(self.pixels, table.pixel_index[maybe])
            inside = at < self.pixels.size
            maybe, at = maybe[inside], at[inside]
            hit = self.pixels[at] == table.pixel_index[maybe]
            out[maybe[hit]] = self.values[at[hit]]
        return out


def estimate_background(image: np.ndarray, table: LightFieldTable, *, noise_dn: float,
                        neighbourhood: int = NEIGHBOURHOOD_LENSES) -> BackgroundMap:
    """The extended light behind each sample of a raw exposure (see the module docstring).

    Parameters
    ----------
    image : ndarray of shape (H, W), uint16
        Raw sensor counts.
    table : LightFieldTable
        Any table of the exposure's camera; the one with the micro-image rims (the depth fit's)
        covers every sample the others use.
    noise_dn : float
        Noise of one background sample (DN): how far above the typical level a lens must stand
        to have its background taken sample by sample.
    neighbourhood : int
        Side, in lenses, of the medians over neighbours.

    Returns
    -------
    BackgroundMap
    """
    flat = np.ascontiguousarray(image).reshape(-1)
    start = np.searchsorted(table.lens, np.arange(table.n_lenses + 1)).astype(np.int64)
    r_max = np.float32(CENTRAL_FRACTION * table.aperture_radius_m)
    medians = _lens_medians(flat, table.pixel_index, table.weight, table.u_m, table.v_m, start,
                            float(table.black_level), float(r_max * r_max))
    i0, j0 = (int(v) for v in table.lens_ij.min(axis=0))
    n_i, n_j = (int(v) + 1 for v in table.lens_ij.max(axis=0) - (i0, j0))
    grid = np.full((n_j, n_i), np.nan)
    jj, ii = table.lens_ij[:, 1] - j0, table.lens_ij[:, 0] - i0
    grid[jj, ii] = medians
    typical = float(np.nanmedian(medians)) if np.isfinite(medians).any() else 0.0
    # Cells of the index rectangle with no lens (the sensor's parallelogram corners, lenses with no
    # central sample) take the typical level before the spatial median.
    level = median_filter(np.where(np.isfinite(grid), grid, typical), size=neighbourhood, mode="nearest")
    # Where extended light stands out, sample by sample, over the lenses around those.
    structured = binary_dilation(level > typical + STRUCTURED_SIGMAS * max(noise_dn, 0.5),
                                 iterations=STRUCTURED_MARGIN_LENSES)
    marked = structured[jj, ii]
    if not marked.any():
        return BackgroundMap(level, i0, j0, np.empty(0, np.int64), np.empty(0, np.float32))
    lens_at = np.full((n_j, n_i), -1, dtype=np.int64)
    lens_at[jj, ii] = np.arange(table.n_lenses)
    u_per_px = table.aperture_radius_m / table.micro_image_radius_px
    half = int(np.ceil(table.micro_image_radius_px + 1.0))
    ids, values = _structured_background(flat, table.pixel_index, table.weight, table.u_m, table.v_m, start,
                                         table.lens_ij.astype(np.int64) - np.array([i0, j0]), lens_at,
                                         marked, float(table.black_level), float(u_per_px), half,
                                         neighbourhood // 2)
    lens_level = level[jj, ii]
    values = np.where(np.isnan(values), lens_level[table.lens[ids]], values).astype(np.float32)
    pixels = table.pixel_index[ids].astype(np.int64)
    order = np.argsort(pixels)
    return BackgroundMap(level, i0, j0, pixels[order], values[order])


@njit(cache=True, parallel=True)
def _lens_medians(flat, pixel_index, weight, u_m, v_m, start, black, r2_max):  # pragma: no cover - numba
    # Median devignetted value of each lens's central samples; NaN for a lens without any. Each
    # lens writes its own entry.
    n = start.size - 1
    out = np.empty(n)
    most = 0
    for k in range(n):
        most = max(most, start[k + 1] - start[k])
    for k in prange(n):
        buf = np.empty(most, dtype=np.float32)
        m = 0
        for j in range(start[k], start[k + 1]):
            if u_m[j] * u_m[j] + v_m[j] * v_m[j] <= r2_max:
                buf[m] = (np.float64(flat[pixel_index[j]]) - black) / max(np.float64(weight[j]), 1e-6)
                m += 1
        out[k] = median_in_place(buf, m) if m > 0 else np.nan
    return out


@njit(cache=True, parallel=True)
def _structured_background(flat, pixel_index, weight, u_m, v_m, start, lens_ij, lens_at, marked, black, u_per_px,
                           half, reach):  # pragma: no cover - numba
    # For every sample of a marked lens: the median over the lenses within `reach` lattice steps of
    # their samples at the same place in the micro-image (the same aperture point, to the pixel),
    # taken as a median along j of medians along i (separable: 2 x 5 values instead of 25, and
    # as sure to leave out a particle, which takes one lens, or two at a cell edge). Returns
    # (sample ids, background), marked lenses' samples in table order.
    n_lens = start.size - 1
    side = 2 * half + 1
    n_j, n_i = lens_at.shape
    # Lenses whose cells are needed (the marked ones' neighbourhoods), and whose row medians are.
    need = np.zeros(n_lens, dtype=np.bool_)
    rows = np.zeros(n_lens, dtype=np.bool_)
    for k in range(n_lens):
        if marked[k]:
            for dj in range(-reach, reach + 1):
                j = lens_ij[k, 1] + dj
                for di in range(-reach, reach + 1):
                    i = lens_ij[k, 0] + di
                    if 0 <= j < n_j and 0 <= i < n_i and lens_at[j, i] >= 0:
                        need[lens_at[j, i]] = True
                        if di == 0:
                            rows[lens_at[j, i]] = True
    slot = np.full(n_lens, -1, dtype=np.int64)
    n_slots = 0
    for k in range(n_lens):
        if need[k]:
            slot[k] = n_slots
            n_slots += 1
    cells = np.full((n_slots, side * side), np.nan, dtype=np.float32)
    for k in prange(n_lens):
        if slot[k] < 0:
            continue
        for j in range(start[k], start[k + 1]):
            cx = int(np.floor(-u_m[j] / u_per_px + 0.5)) + half
            cy = int(np.floor(-v_m[j] / u_per_px + 0.5)) + half
            if 0 <= cx < side and 0 <= cy < side:
                cells[slot[k], cy * side + cx] = (np.float64(flat[pixel_index[j]]) - black) / max(
                    np.float64(weight[j]), 1e-6)
    # Medians along i, per lens and cell.
    along_i = np.full((n_slots, side * side), np.nan, dtype=np.float32)
    for k in prange(n_lens):
        if not rows[k]:
            continue
        buf = np.empty(2 * reach + 1, dtype=np.float32)
        for c in range(side * side):
            m = 0
            for di in range(-reach, reach + 1):
                i = lens_ij[k, 0] + di
                if 0 <= i < n_i and lens_at[lens_ij[k, 1], i] >= 0:
                    v = cells[slot[lens_at[lens_ij[k, 1], i]], c]
                    if not np.isnan(v):
                        buf[m] = v
                        m += 1
            if m > 0:
                along_i[slot[k], c] = median_in_place(buf, m)
    # Sample ids of the marked lenses, in table order, and where each lens's begin.
    first = np.zeros(n_lens + 1, dtype=np.int64)
    for k in range(n_lens):
        first[k + 1] = first[k] + (start[k + 1] - start[k] if marked[k] else 0)
    ids = np.empty(first[n_lens], dtype=np.int64)
    out = np.empty(first[n_lens], dtype=np.float32)
    for k in prange(n_lens):
        if not marked[k]:
            continue
        buf = np.empty(2 * reach + 1, dtype=np.float32)
        for j in range(start[k], start[k + 1]):
            cx = int(np.floor(-u_m[j] / u_per_px + 0.5)) + half
            cy = int(np.floor(-v_m[j] / u_per_px + 0.5)) + half
            m = 0
            if 0 <= cx < side and 0 <= cy < side:
                c = cy * side + cx
                for dj in range(-reach, reach + 1):
                    jj = lens_ij[k, 1] + dj
                    if 0 <= jj < n_j and lens_at[jj, lens_ij[k, 0]] >= 0:
                        v = along_i[slot[lens_at[jj, lens_ij[k, 0]]], c]
                        if not np.isnan(v):
                            buf[m] = v
                            m += 1
            pos = first[k] + j - start[k]
            ids[pos] = j
            out[pos] = median_in_place(buf, m) if m > 0 else np.nan
    return ids, out
