"""Per-table lookups of the depth fit: which samples belong to the lenses near a point.

A :class:`TableIndex` is derived from a look-up table once (a tree of lens centres, each lens's
sample range, the cell geometry) and kept in the caller's :class:`analysis.cache.Cache`
(:func:`table_index`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from analysis.cache import Cache
from analysis.camera.second_stop import SecondStop
from analysis.lightfield.table import LightFieldTable

from .rayfit_kernels import Cells


@dataclass(frozen=True)
class Gathered:
    """The samples of the lenses near each of ``n`` points, in CSR layout.

    Attributes
    ----------
    lens_ptr : ndarray (n + 1,), int64
        Point ``p``'s lenses are ``lens_ptr[p]:lens_ptr[p + 1]`` of the gathered lenses.
    sample_ptr : ndarray (n_lenses + 1,), int64
        Gathered lens ``l``'s samples are ``sample_ptr[l]:sample_ptr[l + 1]`` of ``ids``.
    ids : ndarray, int64
        Table sample ids.
    centres : ndarray (n_lenses, 2), float64
        Lens-plane centres of the gathered lenses.
    """

    lens_ptr: np.ndarray
    sample_ptr: np.ndarray
    ids: np.ndarray
    centres: np.ndarray


class TableIndex:
    """Per-table lookups: the sample range of each lens, a tree of lens centres, cell geometry."""

    def __init__(self, table: LightFieldTable) -> None:
        self.table = table
        self.tree = cKDTree(table.lens_xy_m)
        b1 = table.basis_m[:, 0]
        b2 = table.basis_m[:, 1]
        # Neighbour directions of the hexagonal lattice; a point is in a lens's cell when its
        # offset from the centre projects to at most half of each of them.
        self.normals = np.array([b1, b2, b2 - b1], dtype=np.float64)
        self.neighbours = np.array([b1, -b1, b2, -b2, b2 - b1, b1 - b2], dtype=np.float64)
        self.half_sq = 0.5 * np.einsum("ij,ij->i", self.normals, self.normals)
        self.pitch_m = float(np.hypot(*b1))
        u, v = table.u_m, table.v_m
        # In slices: a full-size table's temporaries (three of its length) would add ~40 MB.
        step = 1 << 20
        self.radius_m = float(np.sqrt(max((np.max(u[i:i + step] * u[i:i + step] + v[i:i + step] * v[i:i + step])
                                           for i in range(0, u.size, step)), default=0.0)))
        # Aperture metres per sensor pixel of offset in a micro-image.
        self.u_per_px = table.aperture_radius_m / table.micro_image_radius_px

    @property
    def nbytes(self) -> int:
        """Memory held (the lens ranges and the tree's copy of the lens centres, roughly)."""
        return int(self.table.lens_start.nbytes + 3 * self.table.lens_xy_m.nbytes)

    def cells(self, aperture_per_lens_plane: float, response_slope: float = 0.0,
              second_stop: SecondStop | None = None) -> Cells:
        """The cell geometry for the kernels; ``aperture_per_lens_plane`` as
        :func:`analysis.depth.rayfit.aperture_per_lens_plane` gives it, ``response_slope`` (the
        pixel response's ``ln`` per squared pixel of micro-image offset) and ``second_stop`` as
        :func:`analysis.depth.rayfit.fit_rays` takes them."""
        stop_k, stop_r2 = (0.0, np.inf) if second_stop is None else (second_stop.shift_per_m, second_stop.radius_m ** 2)
        return Cells(self.normals, self.half_sq, self.neighbours * aperture_per_lens_plane, self.neighbours,
                     self.table.aperture_radius_m ** 2 * (1 + 1e-9), self.pitch_m,
                     float(response_slope) / self.u_per_px ** 2, float(stop_k), float(stop_r2))

    def gather(self, sx: np.ndarray, sy: np.ndarray, reach: np.ndarray) -> Gathered:
        """The samples of the lenses within ``reach`` of each point ``(sx, sy)`` (lens-plane metres)."""
        n = sx.size
        lens_lists = self.tree.query_ball_point(np.column_stack([sx, sy]), reach)
        lens_count = np.array([len(lst) for lst in lens_lists], dtype=np.int64)
        lenses = (np.concatenate([np.asarray(lst, dtype=np.int64) for lst in lens_lists]) if lens_count.sum()
                  else np.empty(0, np.int64))
        start = self.table.lens_start
        counts = start[lenses + 1] - start[lenses]
        ids = self.table.samples_of(lenses)
        lens_ptr = np.r_[0, np.cumsum(lens_count)].astype(np.int64)
        assert lens_ptr.size == n + 1
        return Gathered(lens_ptr=lens_ptr, sample_ptr=np.r_[0, np.cumsum(counts)].astype(np.int64),
                        ids=ids.astype(np.int64), centres=np.ascontiguousarray(self.table.lens_xy_m[lenses]))

    def uv(self, ids: np.ndarray) -> np.ndarray:
        """Aperture points ``(u, v)`` of samples, float64 (n, 2)."""
        return np.column_stack([self.table.u_m[ids], self.table.v_m[ids]]).astype(np.float64)

    def weight(self, ids: np.ndarray) -> np.ndarray:
        """White-image weights of samples, floored at 1e-6 (as the kernels floor them)."""
        return np.maximum(self.table.weight[ids].astype(np.float64), 1e-6)


def table_index(table: LightFieldTable, cache: Cache | None) -> TableIndex:
    """The table's index, from ``cache`` (made and kept there when missing; made afresh without one)."""
    if cache is None:
        return TableIndex(table)
    return cache.get_or_make(("fit_index", table.uid), lambda: TableIndex(table))
