"""The look-up table of an exposure whose micro-lens lattice drifted from where the white image had it.

Each micro-image's pixels are now those about its moved centre: each sees another aperture point,
is lit differently (its weight), and near the rim some pixels come in and others fall out.

The weights are the white image as it would read with its micro-images moved. Reading the white
image between pixels (bilinear) cannot give that: a micro-image's rim falls from full light to
none within a pixel or so, and the Bayer neighbours a reading between green pixels mixes in answer
white light differently (a realistic white image, drifted by 0.29 px: rim weights off by 12-25 %,
and depth errors 1.4x those of the same scene without drift). Instead each green pixel's own white
value is corrected by how much the model of a micro-image (the calibration's fitted profile: the
aperture's disk with its rim response, integrated over a pixel and blurred) changes there when it
and its six neighbours move, scaled by the lens's gain.
"""

from __future__ import annotations

import dataclasses
import uuid
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from analysis.formats.mapped_npz import release_pages

from .table import LightFieldTable

#: Lens ``(i, j)`` itself and its six neighbours (whose micro-images' tails reach its rim), as index steps.
_NEIGHBOURS = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1], [1, -1], [-1, 1]], dtype=np.float64)


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
    gain times the change of ``template`` over the lens and its six neighbours (see the module's
    doc), in the table's units. Lens centres move by ``shift * m_per_px`` on the lens plane
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
    _moved_samples(white, bad, centres, shift_px, gain, steps_px, template.values, 1.0 / template.step_px,
                   template.reach_px ** 2, reach, start, pixel_index, u_m, v_m, weight)
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


def _kept(column: np.ndarray, keep: np.ndarray, m: int) -> np.ndarray:
    """The first ``m`` entries of ``column`` overwritten with its entries where ``keep`` holds; a view of them."""
    column[:m] = column[keep]
    return column[:m]


@njit(cache=True, inline="always")
def _template_at(template, per_step, x, y):  # pragma: no cover - numba
    # The template at offset (x, y) px, bilinear on its fine grid; 0 beyond it.
    n = template.shape[0]
    fx = x * per_step + n // 2
    fy = y * per_step + n // 2
    if fx < 0.0 or fy < 0.0 or fx >= n - 1 or fy >= n - 1:
        return 0.0
    ix = int(fx)
    iy = int(fy)
    ax = fx - ix
    ay = fy - iy
    return ((1.0 - ay) * ((1.0 - ax) * template[iy, ix] + ax * template[iy, ix + 1])
            + ay * ((1.0 - ax) * template[iy + 1, ix] + ax * template[iy + 1, ix + 1]))


@njit(cache=True, inline="always")
def _model_change(template, per_step, reach2, steps_px, x, y, sx, sy):  # pragma: no cover - numba
    # How the light of a lens's micro-image and its six neighbours' at offset (x, y) px from the
    # lens's centre changed when they moved by (sx, sy) to there; only templates that reach the pixel count.
    total = 0.0
    for n in range(steps_px.shape[0]):
        nx = x - steps_px[n, 0]  # from the neighbour's moved centre ...
        ny = y - steps_px[n, 1]
        if nx * nx + ny * ny <= reach2:
            total += _template_at(template, per_step, nx, ny)
        nx += sx  # ... and from where it was
        ny += sy
        if nx * nx + ny * ny <= reach2:
            total -= _template_at(template, per_step, nx, ny)
    return total


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
def _moved_samples(white, defects, centres, shift_px, gain, steps_px, template, per_step, reach2_template, reach,
                   start, pixel_index, offset_x, offset_y, weight):  # pragma: no cover - numba
    # Per lens, from start[lens] on, its samples in row-major order: pixel, minus the offset from the
    # moved centre (px), and the weight (white units): its white value plus the model's change.
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
                weight[at] = white[row, col] + gain[lens] * _model_change(template, per_step, reach2_template, steps_px,
                                                                          x, y, sx, sy)
                at += 1
