"""Light that does not come from particles: plasma glow and out-of-focus reflections, lens by lens.

A dust particle lights a small patch of each micro-image it reaches (the part of the aperture
whose rays enter that lens), or one micro-image when it is near focus. Glow, and light from
sources far out of focus (a laser band reflected by an electrode, glints), lights whole
micro-images alike and changes slowly from lens to lens. So each lens's median devignetted value
measures the extended light behind it, and a median over its neighbours removes the few lenses
that a near-focus particle fills. What is left after subtracting that map, ``level[lens] *
weight`` per sample, is particle light (and the edges of extended sources, which the fit then
rejects: they converge to no point).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit, prange
from scipy.ndimage import median_filter

from .table import LightFieldTable

#: Neighbourhood of the spatial median, in lenses (a square in lattice indices, 25 lenses): a group
#: of up to 12 lenses that particles fill, near focus, leaves the map alone.
NEIGHBOURHOOD_LENSES = 5
#: Samples nearer the micro-image centre than this fraction of its radius measure a lens's level
#: (the rims carry the neighbours' cross-talk and the vignetting's steepest slope).
CENTRAL_FRACTION = 0.8


@dataclass(frozen=True)
class BackgroundMap:
    """Extended light per lens, in devignetted DN (per unit white-image weight).

    Attributes
    ----------
    level : ndarray of shape (n_j, n_i), float64
        Level of lens ``(i, j)`` at ``level[j - j0, i - i0]``.
    i0, j0 : int
        Lattice index of ``level[0, 0]``.
    """

    level: np.ndarray
    i0: int
    j0: int

    @staticmethod
    def uniform(level: float) -> "BackgroundMap":
        """One level everywhere (a diffuse glow)."""
        return BackgroundMap(np.full((1, 1), float(level)), 0, 0)

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


def estimate_background(image: np.ndarray, table: LightFieldTable, *,
                        neighbourhood: int = NEIGHBOURHOOD_LENSES) -> BackgroundMap:
    """The extended light behind each lens of a raw exposure (see the module docstring).

    Parameters
    ----------
    image : ndarray of shape (H, W), uint16
        Raw sensor counts.
    table : LightFieldTable
    neighbourhood : int
        Side, in lenses, of the spatial median over each lens's neighbours.

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
    grid[table.lens_ij[:, 1] - j0, table.lens_ij[:, 0] - i0] = medians
    # Cells of the index rectangle with no lens (the sensor's parallelogram corners, lenses with no
    # central sample) take the overall median before the spatial median.
    grid = np.where(np.isfinite(grid), grid, np.nanmedian(medians) if np.isfinite(medians).any() else 0.0)
    return BackgroundMap(median_filter(grid, size=neighbourhood, mode="nearest"), i0, j0)


@njit(cache=True, parallel=True)
def _lens_medians(flat, pixel_index, weight, u_m, v_m, start, black, r2_max):  # pragma: no cover - numba
    # Median devignetted value of each lens's central samples; NaN for a lens without any. Each
    # lens writes its own entry.
    n = start.size - 1
    out = np.empty(n)
    for k in prange(n):
        a, b = start[k], start[k + 1]
        buf = np.empty(b - a)
        m = 0
        for j in range(a, b):
            if u_m[j] * u_m[j] + v_m[j] * v_m[j] <= r2_max:
                buf[m] = (np.float64(flat[pixel_index[j]]) - black) / max(np.float64(weight[j]), 1e-6)
                m += 1
        out[k] = np.median(buf[:m]) if m > 0 else np.nan
    return out
