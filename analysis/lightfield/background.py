"""Light that does not come from particles: plasma glow and out-of-focus reflections.

Seen through one aperture point, that is in one sub-aperture image (one sample per lens, the
samples at the same place in every micro-image), a particle is a point: the ray from that
aperture point toward it enters one lens. Glow, and light from sources far out of focus (a laser
band reflected by an electrode, glints), is extended there and changes slowly from lens to lens.
So a median over a lens's neighbours, taken at the same aperture point, gives the extended light
behind each sample and leaves the particles out. Not quite all of them: far from focus a
particle's spot moves by under a pixel from one lens to the next, and with the sensor's blur
its sub-aperture image spans two to four lenses, so that the median takes a third to two thirds
of the light of a particle blurred over 7-12 pitches (as it takes compact glints, which look
alike there).

Working that out for every sample costs too much, and most of the sensor sees only glow, which
lights whole micro-images alike: there each lens's median value, a median over its neighbours,
gives its level. Only where the light stands out from the glow in all of a lens's samples
(reflections, glints, and their surroundings), judged by their lower percentile which particles'
spots leave alone, is the background taken sample by sample.

How far a sample must stand above that background to be light of its own depends on where it
is: over glow, the shot and read noise of a few DN; over a reflection, tens of DN more of what
the background misses of its structure. :func:`local_noise` measures that, lens by lens.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit, prange
from scipy.ndimage import binary_dilation, median_filter

from analysis.order_statistics import median_in_place, median_of_5

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
#: Whether a lens stands out is judged by this quantile of its central samples (the spots of
#: particles light some of them, extended light all).
LOW_QUANTILE = 0.3


@dataclass(frozen=True)
class BackgroundMap:
    """Extended light, in devignetted DN (per unit white-image weight).

    Attributes
    ----------
    level : ndarray of shape (n_j, n_i), float64
        Level of lens ``(i, j)`` at ``level[j - j0, i - i0]``.
    i0, j0 : int
        Lattice index of ``level[0, 0]``.
    pixels : ndarray of int64
        Flat sensor indices of the samples whose background was taken one by one, lens by lens
        (in the order of ``level.ravel()``), ascending within each lens ...
    values : ndarray of float32
        ... and their background (replacing their lens's level).
    first : ndarray of shape (n_j * n_i + 1,), int64
        The samples of lens ``(i, j)`` are ``pixels[first[c]:first[c + 1]]``, ``c = (j - j0) * n_i + i - i0``.
    """

    level: np.ndarray
    i0: int
    j0: int
    pixels: np.ndarray
    values: np.ndarray
    first: np.ndarray

    @staticmethod
    def uniform(level: float) -> "BackgroundMap":
        """One level everywhere (a diffuse glow)."""
        return BackgroundMap(np.full((1, 1), float(level)), 0, 0, np.empty(0, np.int64), np.empty(0, np.float32),
                             np.zeros(2, np.int64))

    @property
    def median(self) -> float:
        """The typical level: what a single number would say."""
        return float(np.median(self.level))

    def per_lens(self, table: LightFieldTable) -> np.ndarray:
        """The level behind each lens of ``table`` (float64, ``table.n_lenses``); lenses beyond
        the map take its nearest edge's."""
        if self.level.size == 1:
            return np.full(table.n_lenses, float(self.level[0, 0]))
        return _on_lenses(self.level, self.i0, self.j0, table)

    def per_sample(self, table: LightFieldTable) -> np.ndarray:
        """The background behind each sample of ``table`` (float32, ``table.n_samples``): any table on
        the map's lattice (the refocus's or the depth fit's, drifted or not), whose lenses hold the
        same pixels."""
        if self.level.size == 1:
            return np.full(table.n_samples, self.level[0, 0], dtype=np.float32)
        # Lens by lens, in place: index arrays over the ~5 million samples of the depth fit's table
        # took 130 MB and 0.15 s where reflections cover much of the sensor.
        out = np.empty(table.n_samples, dtype=np.float32)
        _fill_per_sample(self.level.astype(np.float32), self.i0, self.j0, self.first, self.pixels, self.values,
                         table.lens_ij, table.lens_start, table.pixel_index, out)
        return out


@dataclass(frozen=True)
class NoiseMap:
    """How the samples of each lens scatter about the background (:func:`local_noise`).

    Attributes
    ----------
    offset, spread : ndarray of shape (n_j, n_i), float64
        Middle and standard deviation of the central samples of lens ``(i, j)`` about the
        background (raw DN: ``raw - black - level * weight``), at ``[j - j0, i - i0]``, read from
        their lower percentiles (particles only add light) and each a median over the lens's
        neighbours, so that particles' light hardly counts.
    i0, j0 : int
        Lattice index of ``offset[0, 0]``.
    """

    offset: np.ndarray
    spread: np.ndarray
    i0: int
    j0: int

    def per_lens(self, table: LightFieldTable) -> tuple[np.ndarray, np.ndarray]:
        """``(offset, spread)`` at each lens of ``table`` (any table on the map's lattice)."""
        return (_on_lenses(self.offset, self.i0, self.j0, table), _on_lenses(self.spread, self.i0, self.j0, table))


def local_noise(image: np.ndarray, table: LightFieldTable, background: np.ndarray, *,
                neighbourhood: int = NEIGHBOURHOOD_LENSES) -> NoiseMap:
    """How the central samples of each lens of ``table`` scatter about their ``background`` (one
    level per sample, devignetted DN, as :meth:`BackgroundMap.per_sample` gives it): their middle
    and spread, from their lower percentiles, each a median over the lens's neighbours.

    Over glow, the spread is the shot and read noise; over reflections and glints it adds what the
    background misses of their structure, there several times more (and where the table's weights
    miss the exposure's micro-images, a drifted lattice, the more so the brighter the light)."""
    flat = np.ascontiguousarray(image).reshape(-1)
    r_max = CENTRAL_FRACTION * table.aperture_radius_m
    offset, spread = _lens_scatter(flat, table.pixel_index, table.weight, table.u_m, table.v_m, table.lens_start,
                                   float(table.black_level), float(r_max * r_max), background)
    i0, j0, jj, ii, shape = _lattice_cells(table)
    # In float32, as the lens medians of the background are, for the quick exact median filter.
    return NoiseMap(_neighbour_median(offset.astype(np.float32), jj, ii, shape, neighbourhood)[0],
                    _neighbour_median(spread.astype(np.float32), jj, ii, shape, neighbourhood)[0], i0, j0)


def _lattice_cells(table: LightFieldTable) -> tuple[int, int, np.ndarray, np.ndarray, tuple[int, int]]:
    """``i0, j0`` (the lattice index of a map's first cell), each lens's row and column in the map
    (``jj, ii``), and the map's shape ``(n_j, n_i)``: a map over the lattice indices of ``table``'s lenses."""
    i0, j0 = (int(v) for v in table.lens_ij.min(axis=0))
    n_i, n_j = (int(v) + 1 for v in table.lens_ij.max(axis=0) - (i0, j0))
    return i0, j0, table.lens_ij[:, 1] - j0, table.lens_ij[:, 0] - i0, (n_j, n_i)


def _neighbour_median(values: np.ndarray, jj: np.ndarray, ii: np.ndarray, shape: tuple[int, int],
                      size: int) -> tuple[np.ndarray, float]:
    """One value per lens (float32 values: NaN where a lens has none), as a map, each replaced by the
    median over its ``size`` x ``size`` neighbours; and the typical value (their median)."""
    grid = np.full(shape, np.nan)
    grid[jj, ii] = values
    # Rounded to float32 like the values, so that the spatial median may run in float32 and still
    # return exactly the values it was given.
    typical = float(np.float32(np.nanmedian(values))) if np.isfinite(values).any() else 0.0
    # Cells of the index rectangle with no lens (the sensor's parallelogram corners, lenses with no
    # central sample) take the typical value before the spatial median.
    return _median_filter(np.where(np.isfinite(grid), grid, typical), size), typical


def _on_lenses(grid: np.ndarray, i0: int, j0: int, table: LightFieldTable) -> np.ndarray:
    """``grid`` (a map over lattice indices from ``(i0, j0)``) at each lens of ``table``; lenses
    beyond it take its nearest edge's."""
    jj = np.clip(table.lens_ij[:, 1] - j0, 0, grid.shape[0] - 1)
    ii = np.clip(table.lens_ij[:, 0] - i0, 0, grid.shape[1] - 1)
    return np.ascontiguousarray(grid[jj, ii], dtype=np.float64)


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
    start = table.lens_start
    r_max = np.float32(CENTRAL_FRACTION * table.aperture_radius_m)
    medians, lows = _lens_levels(flat, table.pixel_index, table.weight, table.u_m, table.v_m, start,
                                 float(table.black_level), float(r_max * r_max))
    i0, j0, jj, ii, shape = _lattice_cells(table)
    n_j, n_i = shape
    level, typical = _neighbour_median(medians, jj, ii, shape, neighbourhood)
    # Where extended light stands out, sample by sample, over the lenses around those. Judged by
    # each lens's lower percentile: crowded particles' spots raise its median too (110 of the 400
    # particles of realistic cloud 27 sat in lenses so marked, off its reflections), and there the
    # medians over lenses would take much of the light of the faint ones blurred over many pitches.
    # In float32, for the quick exact median filter (the quantiles are interpolated in float64: SciPy's
    # filter took 50 ms of a frame's every estimate; they only mark where light stands out).
    low, low_typical = _neighbour_median(lows.astype(np.float32), jj, ii, shape, neighbourhood)
    structured = binary_dilation(low > low_typical + STRUCTURED_SIGMAS * max(noise_dn, 0.5),
                                 iterations=STRUCTURED_MARGIN_LENSES)
    marked = structured[jj, ii]
    if not marked.any():
        return BackgroundMap(level, i0, j0, np.empty(0, np.int64), np.empty(0, np.float32),
                             np.zeros(n_j * n_i + 1, np.int64))
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
    # Grouped by lens in the order of the level map's cells, ascending within each lens: the table
    # lists them so already (the stable sort, timsort, then costs one pass over them).
    cell = (jj * n_i + ii)[table.lens[ids]]
    pixels = table.pixel_index[ids].astype(np.int64)
    order = np.argsort(cell * np.int64(flat.size) + pixels, kind="stable")
    cell, pixels, values = cell[order], pixels[order], values[order]
    first = np.concatenate([[0], np.cumsum(np.bincount(cell, minlength=n_j * n_i))]).astype(np.int64)
    return BackgroundMap(level, i0, j0, pixels, values, first)


def _median_filter(grid: np.ndarray, size: int) -> np.ndarray:
    """Median over ``size x size`` cells, edges repeated (float64 out). OpenCV's 3 x 3 and 5 x 5
    medians take float32, 30x quicker than SciPy's; exact where the grid holds float32 values."""
    if size in (3, 5) and np.array_equal(grid.astype(np.float32), grid):
        return cv2.medianBlur(np.ascontiguousarray(grid, dtype=np.float32), size).astype(np.float64)
    return median_filter(grid, size=size, mode="nearest")


@njit(cache=True, parallel=True)
def _fill_per_sample(level, i0, j0, first, pixels, values, lens_ij, lens_start, pixel_index,
                     out):  # pragma: no cover - numba
    # Each sample takes its lens's level (the nearest edge's beyond the map), or its own value where
    # its lens's pixels were taken one by one: found by bisection among that lens's. Each lens
    # writes its own samples.
    n_j, n_i = level.shape
    for k in prange(lens_ij.shape[0]):
        j = lens_ij[k, 1] - j0
        i = lens_ij[k, 0] - i0
        inside = 0 <= j < n_j and 0 <= i < n_i
        v = level[min(max(j, 0), n_j - 1), min(max(i, 0), n_i - 1)]
        lo = hi = 0
        if inside:
            lo, hi = first[j * n_i + i], first[j * n_i + i + 1]
        for s in range(lens_start[k], lens_start[k + 1]):
            out[s] = v
            if hi > lo:
                at = lo + np.searchsorted(pixels[lo:hi], pixel_index[s])
                if at < hi and pixels[at] == pixel_index[s]:
                    out[s] = values[at]


@njit(cache=True, parallel=True)
def _lens_levels(flat, pixel_index, weight, u_m, v_m, start, black, r2_max):  # pragma: no cover - numba
    # Median and LOW_QUANTILE of the devignetted values of each lens's central samples; NaN for a
    # lens without any. Each lens writes its own entries.
    n = start.size - 1
    out = np.empty(n)
    low = np.empty(n)
    most = _most_samples(start)
    for k in prange(n):
        buf = np.empty(most, dtype=np.float32)
        m = _central_values(flat, pixel_index, weight, u_m, v_m, start[k], start[k + 1], black, r2_max,
                            np.empty(0, np.float32), buf)
        out[k] = median_in_place(buf, m) if m > 0 else np.nan  # sorts buf[:m]
        low[k] = _sorted_quantile(buf, m, LOW_QUANTILE) if m > 0 else np.nan
    return out, low


@njit(cache=True)
def _most_samples(start):  # pragma: no cover - numba
    # The most samples of one lens (``start``: each lens's first sample, then the end): a lens's buffer.
    most = 0
    for k in range(start.size - 1):
        most = max(most, start[k + 1] - start[k])
    return most


@njit(cache=True, inline="always")
def _central_values(flat, pixel_index, weight, u_m, v_m, j0, j1, black, r2_max, background, buf):  # pragma: no cover
    # Samples j0:j1 (one lens's) within r2_max of the aperture centre into buf, how many returned:
    # devignetted, (raw - black) / weight, with an empty background; else about it, in raw DN,
    # raw - black - background * weight.
    m = 0
    for j in range(j0, j1):
        if u_m[j] * u_m[j] + v_m[j] * v_m[j] <= r2_max:
            if background.size:
                buf[m] = np.float64(flat[pixel_index[j]]) - black - background[j] * weight[j]
            else:
                buf[m] = (np.float64(flat[pixel_index[j]]) - black) / max(np.float64(weight[j]), 1e-6)
            m += 1
    return m


@njit(cache=True, parallel=True)
def _lens_scatter(flat, pixel_index, weight, u_m, v_m, start, black, r2_max, background):  # pragma: no cover
    # Middle and spread of each lens's central samples about the background (raw DN), from their
    # 10th and 30th percentiles as a normal distribution has them; NaN for a lens without any.
    # Particles only add light, and in the core of a blurred cluster they light a good part of
    # every lens's samples: the lower percentiles hardly move (a third of the samples lit raises
    # the spread read by a sixth), where the median absolute deviation grew several times.
    # Each lens writes its own entries.
    n = start.size - 1
    offset = np.empty(n)
    spread = np.empty(n)
    most = _most_samples(start)
    for k in prange(n):
        buf = np.empty(most, dtype=np.float32)
        m = _central_values(flat, pixel_index, weight, u_m, v_m, start[k], start[k + 1], black, r2_max, background,
                            buf)
        if m < 2:
            offset[k] = np.nan
            spread[k] = np.nan
            continue
        median_in_place(buf, m)  # sorts buf[:m]
        q10 = _sorted_quantile(buf, m, 0.1)
        q30 = _sorted_quantile(buf, m, 0.3)
        spread[k] = (q30 - q10) / (_Z30 - _Z10)
        offset[k] = q30 - _Z30 * spread[k]
    return offset, spread


#: Standard normal quantiles at 10 % and 30 %.
_Z10 = -1.2815515655446004
_Z30 = -0.5244005127080407


@njit(cache=True, inline="always")
def _sorted_quantile(values, n, q):  # pragma: no cover - numba
    # Quantile q of values[:n] (sorted), linear between order statistics.
    at = q * (n - 1)
    lo = int(at)
    hi = min(lo + 1, n - 1)
    return values[lo] + (at - lo) * (values[hi] - values[lo])


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
    # Each needed lens's samples by their place in the micro-image (a cell of a side x side grid
    # centred on it; -1 outside), worked out once for the three passes below.
    cell_of = np.empty(pixel_index.size, dtype=np.int16)
    cells = np.full((n_slots, side * side), np.nan, dtype=np.float32)
    for k in prange(n_lens):
        if slot[k] < 0:
            continue
        for j in range(start[k], start[k + 1]):
            cx = int(np.floor(-u_m[j] / u_per_px + 0.5)) + half
            cy = int(np.floor(-v_m[j] / u_per_px + 0.5)) + half
            cell_of[j] = -1
            if 0 <= cx < side and 0 <= cy < side:
                cell_of[j] = cy * side + cx
                cells[slot[k], cy * side + cx] = (np.float64(flat[pixel_index[j]]) - black) / max(
                    np.float64(weight[j]), 1e-6)
    # Medians along i, per lens and cell: only at the cells that the marked lenses within reach
    # along j look up (about half of a lens's cells).
    along_i = np.full((n_slots, side * side), np.nan, dtype=np.float32)
    for k in prange(n_lens):
        if not rows[k]:
            continue
        want = np.zeros(side * side, dtype=np.bool_)
        for dj in range(-reach, reach + 1):
            jj = lens_ij[k, 1] + dj
            if 0 <= jj < n_j and lens_at[jj, lens_ij[k, 0]] >= 0 and marked[lens_at[jj, lens_ij[k, 0]]]:
                q = lens_at[jj, lens_ij[k, 0]]
                for j in range(start[q], start[q + 1]):
                    if cell_of[j] >= 0:
                        want[cell_of[j]] = True
        near = _slots_along(k, 1, 0, lens_ij, lens_at, slot, reach)
        buf = np.empty(2 * reach + 1, dtype=np.float32)
        for c in range(side * side):
            if want[c]:
                along_i[slot[k], c] = _median_of_cells(cells, near, c, buf)
    # Sample ids of the marked lenses, in table order, and where each lens's begin.
    first = np.zeros(n_lens + 1, dtype=np.int64)
    for k in range(n_lens):
        first[k + 1] = first[k] + (start[k + 1] - start[k] if marked[k] else 0)
    ids = np.empty(first[n_lens], dtype=np.int64)
    out = np.empty(first[n_lens], dtype=np.float32)
    for k in prange(n_lens):
        if not marked[k]:
            continue
        near = _slots_along(k, 0, 1, lens_ij, lens_at, slot, reach)
        buf = np.empty(2 * reach + 1, dtype=np.float32)
        for j in range(start[k], start[k + 1]):
            pos = first[k] + j - start[k]
            ids[pos] = j
            out[pos] = _median_of_cells(along_i, near, cell_of[j], buf) if cell_of[j] >= 0 else np.nan
    return ids, out


@njit(cache=True, inline="always")
def _slots_along(k, di, dj, lens_ij, lens_at, slot, reach):  # pragma: no cover - numba
    # Slots of the lenses within `reach` steps of lens k along (di, dj) that exist (-1 past the end).
    near = np.full(2 * reach + 1, -1, dtype=np.int64)
    n_j, n_i = lens_at.shape
    m = 0
    for step in range(-reach, reach + 1):
        i = lens_ij[k, 0] + step * di
        j = lens_ij[k, 1] + step * dj
        if 0 <= j < n_j and 0 <= i < n_i and lens_at[j, i] >= 0:
            near[m] = slot[lens_at[j, i]]
            m += 1
    return near


@njit(cache=True, inline="always")
def _median_of_cells(cells, near, c, buf):  # pragma: no cover - numba
    # Median of cells[near[r], c] over the lenses listed in near (up to the first -1), NaN skipped;
    # NaN when all are.
    m = 0
    for r in range(near.size):
        if near[r] < 0:
            break
        v = cells[near[r], c]
        if not np.isnan(v):
            buf[m] = v
            m += 1
    if m == 5:
        return median_of_5(buf[0], buf[1], buf[2], buf[3], buf[4])
    return median_in_place(buf, m) if m > 0 else np.nan
