"""Slow, readable numpy version of the refocus, to check the numba kernels on small inputs.

It works in lens-plane metres throughout. For the "triangles" method it finds each point's
triangle among the six around its nearest lens site, with barycentric weights from a 3 x 3
solve; for "bilinear" it splats with ``np.add.at`` on the output grid. It shares no index
arithmetic with :mod:`analysis.lightfield.kernels`.
"""

from __future__ import annotations

import numpy as np

from analysis.camera.image_grid import ImageGrid
from .table import LightFieldTable


# Neighbours of a lens in lattice steps, in order of angle (0, 60, ..., 300 degrees).
_RING = np.array([(1, 0), (0, 1), (-1, 1), (-1, 0), (0, -1), (1, -1)])


def _triangles(table: LightFieldTable, sx: np.ndarray, sy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lattice indices (n, 3, 2) of the lattice triangle around each point (m) and its barycentric
    weights (n, 3).

    The nearest lens site is a corner of the containing triangle; of the 6 triangles around it,
    the one where no barycentric weight is negative is taken.
    """
    fi, fj = table.lattice_coordinates(sx, sy)
    base = np.stack([np.floor(fi), np.floor(fj)], axis=-1).astype(np.int64)
    offsets = np.array([(di, dj) for di in (-1, 0, 1, 2) for dj in (-1, 0, 1, 2)])
    cand = base[:, None, :] + offsets[None]                          # (n, 16, 2)
    pos = cand.astype(np.float64) @ table.basis_m.T
    dist = np.hypot(pos[..., 0] - sx[:, None], pos[..., 1] - sy[:, None])
    nearest = cand[np.arange(sx.size), np.argmin(dist, axis=1)]     # (n, 2)
    best_tri = np.zeros((sx.size, 3, 2), dtype=np.int64)
    best_w = np.zeros((sx.size, 3))
    best_min = np.full(sx.size, -np.inf)
    point = np.stack([sx, sy, np.ones_like(sx)], axis=1)[..., None]
    for m in range(6):
        tri = np.stack([nearest, nearest + _RING[m], nearest + _RING[(m + 1) % 6]], axis=1)
        corners = tri.astype(np.float64) @ table.basis_m.T            # (n, 3, 2)
        mat = np.stack([corners[..., 0], corners[..., 1], np.ones(corners.shape[:2])], axis=1)
        w = np.linalg.solve(mat, point)[..., 0]
        better = w.min(axis=1) > best_min
        best_tri[better], best_w[better], best_min[better] = tri[better], w[better], w.min(axis=1)[better]
    return best_tri, np.clip(best_w, 0.0, None)


def splat_reference(table: LightFieldTable, values: np.ndarray, alpha: float) -> dict[tuple[int, int], float]:
    """Sum of ``barycentric weight * value`` per lens site ``(i, j)`` for one alpha (all samples)."""
    c = 1.0 / alpha - 1.0
    sx = table.lens_xy_m[table.lens, 0] + table.u_m.astype(np.float64) * c
    sy = table.lens_xy_m[table.lens, 1] + table.v_m.astype(np.float64) * c
    tri, w = _triangles(table, sx, sy)
    sums: dict[tuple[int, int], float] = {}
    for n in range(values.size):
        if values[n] == 0:
            continue
        for k in range(3):
            key = (int(tri[n, k, 0]), int(tri[n, k, 1]))
            sums[key] = sums.get(key, 0.0) + w[n, k] * float(values[n])
    return sums


def splat_bilinear_reference(table: LightFieldTable, values: np.ndarray, alpha: float,
                             grid: ImageGrid) -> np.ndarray:
    """Sums (height, width) of every sample split over the 4 output pixels around its shifted
    position; samples whose 2 x 2 square is not wholly on the grid are dropped."""
    c = 1.0 / alpha - 1.0
    sx = table.lens_xy_m[table.lens, 0] + table.u_m.astype(np.float64) * c
    sy = table.lens_xy_m[table.lens, 1] + table.v_m.astype(np.float64) * c
    col, row = grid.to_pixels(sx, sy)
    c0, r0 = np.floor(col).astype(np.int64), np.floor(row).astype(np.int64)
    on = (c0 >= 0) & (r0 >= 0) & (c0 + 1 < grid.width) & (r0 + 1 < grid.height)
    fc, fr = (col - c0)[on], (row - r0)[on]
    c0, r0, val = c0[on], r0[on], values[on]
    sums = np.zeros((grid.height, grid.width))
    np.add.at(sums, (r0, c0), val * (1 - fc) * (1 - fr))
    np.add.at(sums, (r0, c0 + 1), val * fc * (1 - fr))
    np.add.at(sums, (r0 + 1, c0), val * (1 - fc) * fr)
    np.add.at(sums, (r0 + 1, c0 + 1), val * fc * fr)
    return sums


def refocus_reference(image: np.ndarray, table: LightFieldTable, alphas: np.ndarray, grid: ImageGrid, *,
                      black: float, background: float, threshold: float, min_coverage: float,
                      keep: np.ndarray | None = None, method: str = "triangles") -> np.ndarray:
    """Refocused stack (A, H, W) float64, by the recipe of :mod:`analysis.lightfield.refocus`.

    Each sample's value is ``raw - black - background * weight``; samples whose value is
    ``<= threshold`` are dropped from the numerator; ``keep`` (bool over samples) restricts both sums.
    """
    keep = np.ones(table.n_samples, dtype=bool) if keep is None else keep
    values = (image.reshape(-1)[table.pixel_index].astype(np.float64) - black
              - background * table.weight.astype(np.float64))
    numerator = np.where(keep & (values > threshold), values, 0.0)
    weights = np.where(keep, table.weight.astype(np.float64), 0.0)
    if method == "bilinear":
        out = np.zeros((len(alphas), grid.height, grid.width))
        for a, alpha in enumerate(alphas):
            num = splat_bilinear_reference(table, numerator, alpha, grid)
            den = splat_bilinear_reference(table, weights, alpha, grid)
            floor = min_coverage * np.median(den[den > 0])
            out[a] = np.where(den >= floor, num / np.where(den > 0, den, 1.0), 0.0)
        return out
    cols, rows = np.meshgrid(np.arange(grid.width), np.arange(grid.height))
    px, py = grid.to_lens_plane(cols.reshape(-1), rows.reshape(-1))
    tri, bary = _triangles(table, px, py)
    out = np.zeros((len(alphas), grid.height, grid.width))
    for a, alpha in enumerate(alphas):
        num = splat_reference(table, numerator, alpha)
        den = splat_reference(table, weights, alpha)
        positive = np.array([d for d in den.values() if d > 0])
        floor = min_coverage * np.median(positive)
        site_value = {key: num.get(key, 0.0) / d for key, d in den.items() if d >= floor}
        flat = np.zeros(px.size)
        for n in range(px.size):
            total, wsum = 0.0, 0.0
            for k in range(3):
                key = (int(tri[n, k, 0]), int(tri[n, k, 1]))
                if key in site_value:
                    total += bary[n, k] * site_value[key]
                    wsum += bary[n, k]
            flat[n] = total / wsum if wsum > 1e-6 else 0.0
        out[a] = flat.reshape(grid.height, grid.width)
    return out
