"""The look-up table of an exposure whose micro-lens lattice drifted from where the white image had it.

Each micro-image's pixels are now those about its moved centre: each sees another aperture point,
is lit differently (its weight), and near the rim some pixels come in and others fall out.

The weights are the white image as it would read with its micro-images moved. Reading the white
image between pixels (bilinear) cannot give that: a micro-image's rim falls from full light to
none within a pixel or so, and the Bayer neighbours a reading between green pixels mixes in answer
white light differently (a realistic white image, drifted by 0.29 px: rim weights off by 12-25 %,
and depth errors 1.4x those of the same scene without drift). Instead each green pixel's own white
value is corrected by how much the white image's pattern about a micro-image's centre changes
there when the micro-images move, scaled by the lens's gain.

That pattern is the white image's own: its micro-image centres fall at every sub-pixel phase, so
the green pixels of the lenses of one part of the sensor, placed by their offset from their
lens's centre (over its gain), sample it on a grid finer than the pixels
(:data:`PATTERN_STEP_PX`). It holds what the white image shows and a model of one micro-image
would have to be told: the neighbours' tails, the aperture's true shape and the pixel response,
and how vignetting by a second stop narrows the micro-images toward the corners
(:data:`PATTERN_REGIONS`, interpolated between them). Against the white rendered on the moved
lattice, the calibration's fitted profile moved with its six neighbours left the weights at 0.8-0.9
of the radius off by 3.1 % (rms; the white's own noise: 1.8 %) and beyond the radius by 9 %, with
biases of 0.5-1.5 %, on a layer with drift alone; the white's pattern leaves 1.9 and 4.5 %, no
bias. With every effect, at 0.8-0.9 of the radius: 5.0 % before, 3.2 % now (noise 2.4 %).
"""

from __future__ import annotations

import dataclasses
import uuid
from typing import NamedTuple

import numpy as np
from numba import njit, prange
from scipy.ndimage import uniform_filter

from analysis.formats.mapped_npz import release_pages

from .table import LightFieldTable

#: Lens ``(i, j)`` itself and its six neighbours, as index steps.
_NEIGHBOURS = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1], [1, -1], [-1, 1]], dtype=np.float64)
#: The white pattern about micro-image centres is sampled on offsets this far apart (pixels) ...
PATTERN_STEP_PX = 0.125
#: ... in each of up to this many parts of the sensor per side (its micro-images' shape changes over
#: the field: vignetting by a second stop narrows them toward the corners) ...
PATTERN_REGIONS = 8
#: ... each of at least this many lenses (their centres' phases then fill the grid: about 8 pixels
#: to a cell).
PATTERN_LENSES = 1000


class MicroImageTemplate(NamedTuple):
    """One micro-image of unit central response as each pixel records it, on a fine grid of offsets
    from its centre: ``values[n // 2 + iy, n // 2 + ix]`` is the pixel centred ``(ix, iy) * step_px``
    from it (:func:`analysis.calibration.profile.micro_image_template`); nothing beyond ``reach_px``."""

    values: np.ndarray
    step_px: float
    reach_px: float

    @classmethod
    def cropped(cls, values: np.ndarray, step_px: float, floor: float = 1e-4) -> "MicroImageTemplate":
        """``values`` (float32) cropped to the radius beyond which they stay below ``floor``."""
        n = values.shape[0]
        row = np.abs(values[n // 2, n // 2:])  # the micro-image is round: one radius tells
        above = np.flatnonzero(row >= floor)
        half = int(above[-1]) + 2 if above.size else 1
        lo, hi = max(n // 2 - half, 0), min(n // 2 + half, n)
        return cls(np.ascontiguousarray(values[lo:hi, lo:hi], dtype=np.float32), float(step_px),
                   float((half - 1) * step_px))


def shifted_table(table: LightFieldTable, devignetting: np.ndarray, shift_px: np.ndarray, *,
                  m_per_px: float, template: MicroImageTemplate, defects: np.ndarray | None = None,
                  min_weight: float = 0.05) -> LightFieldTable:
    """The table of an exposure whose micro-images moved by ``shift_px`` (per lens, (L, 2), sensor
    pixels) from where the white image had them: the lattice drifted (thermal, mechanical).

    Each lens of ``table`` keeps its number; its samples are the green pixels within the table's
    reach (``micro_image_radius_px - rim_px``) of its moved micro-image's centre, and nearer to it
    than to a neighbour's, as :func:`analysis.lightfield.table.build_table` picks them about the
    white image's centres, without ``defects`` (the camera's defective pixels, bool (H, W)) and
    those whose weight is below ``min_weight``. A sample's aperture point follows from its offset
    from the moved centre; its weight is its own white value (``devignetting``) plus the lens's
    gain (``template`` fitted to its core) times the change of the white pattern of its part of
    the sensor (:func:`white_pattern`) between its offsets from the moved and from the old centre,
    in the table's units. Lens centres move by ``shift * m_per_px`` on the lens plane
    (``pixel pitch / projection factor``).
    """
    shift_px = np.asarray(shift_px, dtype=np.float64)
    u_per_px = table.aperture_radius_m / table.micro_image_radius_px
    white = np.asarray(devignetting)
    # The table's weights are the white image over one normalising constant.
    every = max(1, table.n_samples // 10_000)
    norm = float(np.median(white.reshape(-1)[table.pixel_index[::every]] / np.maximum(table.weight[::every], 1e-6)))
    steps_px = (table.basis_m @ _NEIGHBOURS.T).T / m_per_px  # each neighbour's centre from the lens's
    # Each lens's micro-image centre: its first sample's pixel centre less that pixel's offset from it, -(u, v).
    old = np.column_stack(np.divmod(table.pixel_index[table.lens_start[:-1]], table.width)[::-1]).astype(np.float64)
    old += 0.5 + np.column_stack([table.u_m[table.lens_start[:-1]], table.v_m[table.lens_start[:-1]]]) / u_per_px
    gain = _lens_gains(white.reshape(-1), table.pixel_index, table.lens_start, table.u_m, table.v_m, 1.0 / u_per_px,
                       template.values, 1.0 / template.step_px, 0.5 * table.micro_image_radius_px)
    for column in (table.pixel_index, table.lens, table.u_m, table.v_m, table.weight):
        release_pages(column)  # not read again here (mapped from a cache file: 90 MB an F01's)
    reach = table.micro_image_radius_px - table.rim_px
    bad = np.zeros((0, 0), np.bool_) if defects is None else np.asarray(defects, dtype=np.bool_)
    centres = old + shift_px
    count = _count_samples(white.shape[0], white.shape[1], bad, centres, steps_px, reach)
    start = np.concatenate([[0], np.cumsum(count)]).astype(np.int64)
    n = int(start[-1])
    pixel_index = np.empty(n, dtype=np.int32)
    u_m, v_m, weight = (np.empty(n, dtype=np.float32) for _ in range(3))
    parts = _regions_per_side(len(old))
    pattern = white_pattern(white, bad, old, gain, _regions(old, white.shape, parts),
                            reach + float(np.abs(shift_px).max(initial=0.0)) + 1.0)
    near, share = _nearest_parts(old, white.shape, parts)
    _moved_samples(white, bad, centres, shift_px, gain, steps_px, pattern, near, share, 1.0 / PATTERN_STEP_PX, reach,
                   start, pixel_index, u_m, v_m, weight)
    lens = np.repeat(np.arange(table.n_lenses, dtype=np.int32), count)
    keep = weight >= min_weight  # as the table about the white image's centres leaves out the faintest
    if not keep.all():  # in place, one column at a time (a copy of all five: 90 MB more at the peak)
        m = int(keep.sum())
        columns = (pixel_index, lens, u_m, v_m, weight)
        pixel_index, lens, u_m, v_m, weight = (_kept(column, keep, m) for column in columns)
    u_m *= np.float32(u_per_px)
    v_m *= np.float32(u_per_px)
    weight *= np.float32(1.0 / norm)
    return dataclasses.replace(table, pixel_index=pixel_index, lens=lens, u_m=u_m, v_m=v_m, weight=weight,
                               lens_xy_m=table.lens_xy_m + shift_px * m_per_px, uid=uuid.uuid4().hex)


def _regions_per_side(n_lenses: int) -> int:
    """Parts of the sensor per side: of at least :data:`PATTERN_LENSES` lenses each, at most
    :data:`PATTERN_REGIONS`."""
    return int(np.clip(np.sqrt(n_lenses / PATTERN_LENSES), 1, PATTERN_REGIONS))


def _regions(centres: np.ndarray, shape: tuple[int, int], n: int) -> np.ndarray:
    """The part of the sensor of each lens centre (``n`` by ``n`` parts, row by row)."""
    h, w = shape
    ry = np.clip((centres[:, 1] * n / h).astype(np.int64), 0, n - 1)
    rx = np.clip((centres[:, 0] * n / w).astype(np.int64), 0, n - 1)
    return ry * n + rx


def _nearest_parts(centres: np.ndarray, shape: tuple[int, int], n: int) -> tuple[np.ndarray, np.ndarray]:
    """Per lens centre, the four parts of the sensor whose middles surround it and their bilinear
    shares (L, 4): the pattern changes smoothly across the field, not from part to part."""
    h, w = shape
    fx = np.clip(centres[:, 0] * n / w - 0.5, 0.0, n - 1.0)
    fy = np.clip(centres[:, 1] * n / h - 0.5, 0.0, n - 1.0)
    x0 = np.minimum(fx.astype(np.int64), max(n - 2, 0))
    y0 = np.minimum(fy.astype(np.int64), max(n - 2, 0))
    x1, y1 = np.minimum(x0 + 1, n - 1), np.minimum(y0 + 1, n - 1)
    ax, ay = fx - x0, fy - y0
    near = np.column_stack([y0 * n + x0, y0 * n + x1, y1 * n + x0, y1 * n + x1])
    share = np.column_stack([(1 - ay) * (1 - ax), (1 - ay) * ax, ay * (1 - ax), ay * ax])
    return near, share


def white_pattern(white: np.ndarray, defects: np.ndarray, centres: np.ndarray, gain: np.ndarray,
                  region: np.ndarray, radius_px: float) -> np.ndarray:
    """The white image's green pixels about the lens centres, over their lens's gain, averaged by
    their offset from the centre on a grid of :data:`PATTERN_STEP_PX` out to ``radius_px``, per part
    of the sensor (``region``: each lens's, of ``n`` of them): ndarray (n, m, m), float64, with the
    offset ``(x, y)`` at ``[r, m // 2 + round(y / step), m // 2 + round(x / step)]``. A cell no pixel
    fell in takes the mean of the pixels in the cells around it, or else the whole sensor's."""
    half = int(np.ceil(radius_px / PATTERN_STEP_PX))
    n_regions = int(region.max(initial=0)) + 1
    order = np.argsort(region, kind="stable")
    ptr = np.searchsorted(region[order], np.arange(n_regions + 1))
    sums = np.zeros((n_regions, 2 * half + 1, 2 * half + 1))
    counts = np.zeros_like(sums)
    _pool_pattern(white, defects, centres, gain, order, ptr, 1.0 / PATTERN_STEP_PX, half, radius_px, sums, counts)
    near_sums, near_counts = (uniform_filter(a, size=(1, 3, 3), mode="constant") for a in (sums, counts))
    everywhere = sums.sum(axis=0) / np.maximum(counts.sum(axis=0), 1.0)
    return np.where(counts > 0, sums / np.maximum(counts, 1.0),
                    np.where(near_counts > 0, near_sums / np.maximum(near_counts, 1e-12), everywhere))


def _kept(column: np.ndarray, keep: np.ndarray, m: int) -> np.ndarray:
    """The first ``m`` entries of ``column`` overwritten with its entries where ``keep`` holds; a view of them."""
    column[:m] = column[keep]
    return column[:m]


@njit(cache=True, inline="always")
def _bilinear(grid, fx, fy):  # pragma: no cover - numba
    # grid (n, n) at the fractional index (fx, fy), 0 <= fx, fy < n - 1.
    ix = int(fx)
    iy = int(fy)
    ax = fx - ix
    ay = fy - iy
    return ((1.0 - ay) * ((1.0 - ax) * grid[iy, ix] + ax * grid[iy, ix + 1])
            + ay * ((1.0 - ax) * grid[iy + 1, ix] + ax * grid[iy + 1, ix + 1]))


@njit(cache=True, inline="always")
def _template_at(template, per_step, x, y):  # pragma: no cover - numba
    # The template at offset (x, y) px, bilinear on its fine grid; 0 beyond it.
    n = template.shape[0]
    fx = x * per_step + n // 2
    fy = y * per_step + n // 2
    if fx < 0.0 or fy < 0.0 or fx >= n - 1 or fy >= n - 1:
        return 0.0
    return _bilinear(template, fx, fy)


@njit(cache=True, parallel=True)
def _pool_pattern(white, defects, centres, gain, order, ptr, per_step, half, radius, sums,
                  counts):  # pragma: no cover - numba
    # One part of the sensor per iteration (its lenses: order[ptr[r]:ptr[r + 1]]), so that no two
    # threads add to one cell.
    h, w = white.shape
    reach = int(radius) + 2
    for r in prange(ptr.size - 1):
        for k in range(ptr[r], ptr[r + 1]):
            lens = order[k]
            if gain[lens] <= 0.0:
                continue
            cx = centres[lens, 0]
            cy = centres[lens, 1]
            for row in range(max(int(cy) - reach, 0), min(int(cy) + reach + 1, h)):
                for col in range(max(int(cx) - reach, 0), min(int(cx) + reach + 1, w)):
                    if (row + col) % 2 == 0 or (defects.size and defects[row, col]):
                        continue  # BGGR: the green pixels only, as the table
                    x = col + 0.5 - cx
                    y = row + 0.5 - cy
                    if x * x + y * y > radius * radius:
                        continue
                    iy = half + int(np.floor(y * per_step + 0.5))
                    ix = half + int(np.floor(x * per_step + 0.5))
                    sums[r, iy, ix] += white[row, col] / gain[lens]
                    counts[r, iy, ix] += 1.0


@njit(cache=True, inline="always")
def _pattern_at(pattern, per_step, x, y):  # pragma: no cover - numba
    # One part's pattern (m, m) at offset (x, y) px, bilinear between its cells' centres.
    n = pattern.shape[0]
    half = n // 2
    return _bilinear(pattern, min(max(x * per_step + half, 0.0), n - 1.000001),
                     min(max(y * per_step + half, 0.0), n - 1.000001))


@njit(cache=True, parallel=True)
def _lens_gains(white, pixel_index, lens_start, u_m, v_m, px_per_u, template, per_step,
                core_px):  # pragma: no cover - numba
    # Per lens, the least-squares scale of the template to its samples' white values within core_px
    # of its centre (where the neighbours' light does not reach). A pixel's offset from its
    # micro-image's centre is -(u, v) / (aperture metres per pixel).
    n_lens = lens_start.size - 1
    gain = np.zeros(n_lens)
    for lens in prange(n_lens):
        s_wm = 0.0
        s_mm = 0.0
        for k in range(lens_start[lens], lens_start[lens + 1]):
            x = -u_m[k] * px_per_u
            y = -v_m[k] * px_per_u
            if x * x + y * y <= core_px * core_px:
                m = _template_at(template, per_step, x, y)
                s_wm += white[pixel_index[k]] * m
                s_mm += m * m
        gain[lens] = s_wm / s_mm if s_mm > 0.0 else 0.0
    return gain


@njit(cache=True, inline="always")
def _is_sample(defects, steps_px, reach, x, y, row, col):  # pragma: no cover - numba
    # Whether the pixel at (row, col), (x, y) px from a lens's centre, is a green one (BGGR: row +
    # col odd) of that lens's table: not defective, within reach, nearer to it than to a neighbour.
    if (row + col) % 2 == 0 or (defects.size and defects[row, col]):
        return False
    d2 = x * x + y * y
    if d2 > reach * reach:
        return False
    for n in range(1, steps_px.shape[0]):
        dx = x - steps_px[n, 0]
        dy = y - steps_px[n, 1]
        if dx * dx + dy * dy < d2:
            return False
    return True


@njit(cache=True, parallel=True)
def _count_samples(h, w, defects, centres, steps_px, reach):  # pragma: no cover - numba
    # Per lens, its samples about its (moved) centre.
    r = int(reach) + 2
    count = np.zeros(centres.shape[0], dtype=np.int64)
    for lens in prange(centres.shape[0]):
        cx = centres[lens, 0]
        cy = centres[lens, 1]
        for row in range(max(int(cy) - r, 0), min(int(cy) + r + 1, h)):
            for col in range(max(int(cx) - r, 0), min(int(cx) + r + 1, w)):
                if _is_sample(defects, steps_px, reach, col + 0.5 - cx, row + 0.5 - cy, row, col):
                    count[lens] += 1
    return count


@njit(cache=True, parallel=True)
def _moved_samples(white, defects, centres, shift_px, gain, steps_px, pattern, near, share, per_step, reach,
                   start, pixel_index, offset_x, offset_y, weight):  # pragma: no cover - numba
    # Per lens, from start[lens] on, its samples in row-major order: pixel, minus the offset from the
    # moved centre (px), and the weight (white units): its white value plus the change of the white
    # pattern between its offsets from the moved and the old centre, the patterns of the four parts
    # of the sensor about the lens (near[lens]) weighed by their shares.
    h, w = white.shape
    r = int(reach) + 2
    for lens in prange(centres.shape[0]):
        cx = centres[lens, 0]
        cy = centres[lens, 1]
        sx = shift_px[lens, 0]
        sy = shift_px[lens, 1]
        at = start[lens]
        for row in range(max(int(cy) - r, 0), min(int(cy) + r + 1, h)):
            for col in range(max(int(cx) - r, 0), min(int(cx) + r + 1, w)):
                x = col + 0.5 - cx
                y = row + 0.5 - cy
                if not _is_sample(defects, steps_px, reach, x, y, row, col):
                    continue
                pixel_index[at] = row * w + col
                offset_x[at] = -x
                offset_y[at] = -y
                change = 0.0
                for k in range(4):
                    if share[lens, k] > 0.0:
                        part = pattern[near[lens, k]]
                        change += share[lens, k] * (_pattern_at(part, per_step, x, y)
                                                    - _pattern_at(part, per_step, x + sx, y + sy))
                weight[at] = white[row, col] + gain[lens] * change
                at += 1
