"""Depth and position from the raw pixels: a fit of the forward model around each particle.

A ray from aperture point ``u`` toward a point that images at lens-plane position ``s_hat``
(shared magnification) with refocus parameter ``alpha`` crosses the micro-lens-array plane at
``s = s_hat + c u`` with ``c = 1 - 1/alpha`` (docs/camera-model.md; the relation the shift-only
refocus inverts) and lands behind the lens whose hexagonal cell contains ``s``. So sample
``(lens k, aperture point u)`` of the look-up table is lit by the particle exactly when
``s_hat + c u`` falls in cell ``k``.

For each particle the predicted pattern ``I0 * [s_hat + c u in cell k]`` is compared with the
devignetted raw samples of the lenses around it, by least squares (``I0`` solved in closed
form), on a grid of ``(c, s_hat)`` candidates around the starting point. The estimate is the
mean of the candidates weighted by ``exp(-(cost - min cost) / I0^2)`` (cost in units of one
mismatched pixel): where the light splits between lenses the cost has a sharp minimum; where a
particle lights a single lens, every depth whose blur still fits in that lens explains the pixels
equally well, and the estimate is the middle of that range instead of an arbitrary end of it.
This uses how the light splits between neighbouring lenses, which the refocused stack's
brightness blurs away when the blur is under a lens pitch or two.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numba import prange
from scipy.spatial import cKDTree

from .lightfield import LightFieldTable

_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@dataclass(frozen=True)
class RayFit:
    """Fitted particles; arrays of shape ``(n,)``.

    Attributes
    ----------
    sx_m, sy_m : float64
        Lens-plane position ``s_hat`` (metres from the optical axis).
    alpha : float64
        Refocus parameter at which the particle is sharp.
    intensity : float64
        Fitted brightness ``I0`` of a lit sample (DN above background per unit white weight).
    n_lit : int64
        Samples the best candidate lights.
    residual : float64
        RMS misfit of the best candidate per sample, as a fraction of ``I0``.
    alpha_spread : float64
        Standard deviation of alpha over the weighted candidates: small where the light split
        pins the depth down, about a third of the allowed range where one lens holds it all.
    """

    sx_m: np.ndarray
    sy_m: np.ndarray
    alpha: np.ndarray
    intensity: np.ndarray
    n_lit: np.ndarray
    residual: np.ndarray
    alpha_spread: np.ndarray

    def __len__(self) -> int:
        return int(self.alpha.shape[0])


class _TableIndex:
    """Per-table lookups: the sample range of each lens, a tree of lens centres, cell geometry."""

    def __init__(self, table: LightFieldTable) -> None:
        self.table = table
        self.start = np.searchsorted(table.lens, np.arange(table.n_lenses + 1)).astype(np.int64)
        self.tree = cKDTree(table.lens_xy_m)
        b1 = table.basis_m[:, 0]
        b2 = table.basis_m[:, 1]
        # Neighbour directions of the hexagonal lattice; a point is in a lens's cell when its
        # offset from the centre projects to at most half of each of them.
        self.normals = np.array([b1, b2, b2 - b1], dtype=np.float64)
        self.half_sq = 0.5 * np.einsum("ij,ij->i", self.normals, self.normals)
        self.pitch_m = float(np.hypot(*b1))
        u = table.u_m.astype(np.float64)
        v = table.v_m.astype(np.float64)
        self.radius_m = float(np.sqrt(np.max(u * u + v * v))) if u.size else 0.0
        self.uv = np.column_stack([u, v])
        self.inv_weight = 1.0 / np.maximum(table.weight.astype(np.float64), 1e-6)
        # Aperture metres per sensor pixel of offset in a micro-image.
        self.u_per_px = table.aperture_radius_m / table.micro_image_radius_px


_INDEX: dict[int, _TableIndex] = {}


def _pixel_footprint(n_side: int, blur_px: float) -> np.ndarray:
    """Points (pixels) standing for one pixel's area blurred by a Gaussian: an even grid over the
    pixel, each moved by a fixed Gaussian offset (seeded, so the fit is deterministic)."""
    g = (np.arange(n_side) + 0.5) / n_side - 0.5
    gx, gy = np.meshgrid(g, g)
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    if blur_px > 0:
        pts = pts + blur_px * np.random.default_rng(12345).standard_normal(pts.shape)
    return pts


def _index(table: LightFieldTable) -> _TableIndex:
    idx = _INDEX.get(id(table))
    if idx is None or idx.table is not table:
        if len(_INDEX) > 4:
            _INDEX.clear()
        idx = _INDEX[id(table)] = _TableIndex(table)
    return idx


def fit_rays(image: np.ndarray, table: LightFieldTable, sx0_m: np.ndarray, sy0_m: np.ndarray,
             alpha0: np.ndarray, *, background: float, alpha_half_range: float = 0.002, n_alpha: int = 41,
             lateral_half_range_pitches: float = 0.45, n_lateral: int = 5, reach_pitches: float = 1.2,
             n_sub_side: int = 3, blur_px: float = 0.5, temperature: float = 1.0) -> RayFit:
    """Refine position and depth of particles by fitting the forward model to the raw samples.

    Parameters
    ----------
    image : ndarray of shape (H, W), uint16
        The raw exposure.
    table : LightFieldTable
    sx0_m, sy0_m, alpha0 : ndarray of shape (n,)
        Starting positions (lens plane, metres) and refocus parameters, e.g. from the
        brightness maxima of the refocused stack.
    background : float
        Background (DN above black per unit white weight) to subtract, e.g.
        :attr:`analysis.refocus.Samples.background`.
    alpha_half_range, n_alpha : float, int
        Candidate depths: ``n_alpha`` values of ``c = 1 - 1/alpha`` over ``alpha0 +- alpha_half_range``.
    lateral_half_range_pitches, n_lateral : float, int
        Candidate positions: an ``n_lateral`` x ``n_lateral`` grid over ``+-`` this many lens pitches.
    reach_pitches : float
        Lenses farther than the largest candidate blur plus this many pitches are left out.
    temperature : float
        Cost difference, in mismatched pixels, over which candidates lose weight by ``1/e``.
    n_sub_side, blur_px : int, float
        Each pixel is modelled by ``n_sub_side**2`` points spread over its area and a Gaussian
        blur of ``blur_px`` pixels (diffraction, pixel crosstalk), so partly lit pixels at the
        edges of a lens's share of the light count by how much of them is lit.

    Returns
    -------
    RayFit
    """
    idx = _index(table)
    sx0 = np.asarray(sx0_m, dtype=np.float64).ravel()
    sy0 = np.asarray(sy0_m, dtype=np.float64).ravel()
    a0 = np.asarray(alpha0, dtype=np.float64).ravel()
    n = sx0.size
    if n == 0:
        e = np.empty(0)
        return RayFit(e, e.copy(), e.copy(), e.copy(), np.empty(0, np.int64), e.copy(), e.copy())
    flat = np.ascontiguousarray(image).reshape(-1)
    c_lo = 1.0 - 1.0 / (a0 - alpha_half_range)
    c_hi = 1.0 - 1.0 / (a0 + alpha_half_range)
    reach = np.maximum(np.abs(c_lo), np.abs(c_hi)) * idx.radius_m + (reach_pitches + lateral_half_range_pitches) * idx.pitch_m
    # Samples of the lenses around each particle, as one concatenated (CSR) array.
    lens_lists = idx.tree.query_ball_point(np.column_stack([sx0, sy0]), reach)
    lens_count = np.array([len(lst) for lst in lens_lists], dtype=np.int64)
    lenses = np.concatenate([np.asarray(lst, dtype=np.int64) for lst in lens_lists]) if lens_count.sum() else \
        np.empty(0, np.int64)
    counts = idx.start[lenses + 1] - idx.start[lenses]
    ids = np.repeat(idx.start[lenses] - np.cumsum(np.r_[0, counts[:-1]]), counts) + np.arange(counts.sum())
    per_particle = np.bincount(np.repeat(np.arange(n), lens_count), weights=counts, minlength=n).astype(np.int64)
    bounds = np.r_[0, np.cumsum(per_particle)].astype(np.int64)
    values = (flat[table.pixel_index[ids]].astype(np.float64) - table.black_level) * idx.inv_weight[ids] - background
    centres = table.lens_xy_m[table.lens[ids]]
    uv = idx.uv[ids]
    out = np.empty((n, 7))
    _fit_all(centres, uv, values, bounds, sx0, sy0, c_lo, c_hi, int(n_alpha),
             lateral_half_range_pitches * idx.pitch_m, int(n_lateral), idx.normals, idx.half_sq,
             _pixel_footprint(n_sub_side, blur_px) * idx.u_per_px, table.aperture_radius_m ** 2 * (1 + 1e-9), float(temperature), out)
    return RayFit(sx_m=out[:, 0], sy_m=out[:, 1], alpha=1.0 / (1.0 - out[:, 2]), intensity=out[:, 3],
                  n_lit=out[:, 4].astype(np.int64), residual=out[:, 5],
                  alpha_spread=out[:, 6] / (1.0 - out[:, 2]) ** 2)


@numba.njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _fit_all(centres, uv, values, bounds, sx0, sy0, c_lo, c_hi, n_c, half_lat, n_lat, normals, half_sq, sub, r_ap2,
             temperature, out):
    # One particle per prange iteration; each writes only its own row of `out`.
    for p in prange(sx0.size):
        _fit_one(centres[bounds[p]:bounds[p + 1]], uv[bounds[p]:bounds[p + 1]], values[bounds[p]:bounds[p + 1]],
                 sx0[p], sy0[p], c_lo[p], c_hi[p], n_c, half_lat, n_lat, normals, half_sq, sub, r_ap2, temperature, out[p])


@numba.njit(cache=True, fastmath=_FASTMATH)
def _fit_one(centres, uv, values, sx0, sy0, c_lo, c_hi, n_c, half_lat, n_lat, normals, half_sq, sub, r_ap2, temperature, out):
    m = values.size
    n_sub = sub.shape[0]
    n_cand = n_c * n_lat * n_lat
    costs = np.empty(n_cand)
    cand = np.empty((n_cand, 3))
    inten = np.empty(n_cand)
    lit = np.empty(n_cand)
    sum_v2 = 0.0
    for j in range(m):
        sum_v2 += values[j] * values[j]
    k = 0
    for ic in range(n_c):
        c = c_lo + (c_hi - c_lo) * ic / max(n_c - 1, 1)
        for iy in range(n_lat):
            dy = -half_lat + 2.0 * half_lat * iy / max(n_lat - 1, 1)
            for ix in range(n_lat):
                dx = -half_lat + 2.0 * half_lat * ix / max(n_lat - 1, 1)
                sx = sx0 + dx
                sy = sy0 + dy
                s_vf = 0.0
                s_ff = 0.0
                s_f = 0.0
                for j in range(m):
                    frac = 0.0
                    for q in range(n_sub):
                        ux = uv[j, 0] + sub[q, 0]
                        uy = uv[j, 1] + sub[q, 1]
                        if ux * ux + uy * uy > r_ap2:
                            continue
                        qx = sx + c * ux - centres[j, 0]
                        qy = sy + c * uy - centres[j, 1]
                        inside = True
                        for t in range(3):
                            d = qx * normals[t, 0] + qy * normals[t, 1]
                            if d > half_sq[t] or d < -half_sq[t]:
                                inside = False
                                break
                        if inside:
                            frac += 1.0
                    if frac > 0.0:
                        frac /= n_sub
                        s_vf += values[j] * frac
                        s_ff += frac * frac
                        s_f += frac
                if s_ff > 0 and s_vf > 0:
                    costs[k] = sum_v2 - s_vf * s_vf / s_ff
                    inten[k] = s_vf / s_ff
                else:
                    costs[k] = sum_v2
                    inten[k] = 0.0
                lit[k] = s_f
                cand[k, 0] = sx
                cand[k, 1] = sy
                cand[k, 2] = c
                k += 1
    best = 0
    for k in range(n_cand):
        if costs[k] < costs[best]:
            best = k
    i0 = inten[best]
    if i0 <= 0.0:
        out[0] = sx0
        out[1] = sy0
        out[2] = 0.5 * (c_lo + c_hi)
        out[3] = 0.0
        out[4] = 0.0
        out[5] = np.nan
        out[6] = np.nan
        return
    # Weighted mean over candidates: cost in units of one mismatched pixel (I0^2).
    scale = temperature * i0 * i0
    wsum = 0.0
    mx = 0.0
    my = 0.0
    mc = 0.0
    mc2 = 0.0
    for k in range(n_cand):
        w = np.exp(-(costs[k] - costs[best]) / scale)
        wsum += w
        mx += w * cand[k, 0]
        my += w * cand[k, 1]
        mc += w * cand[k, 2]
        mc2 += w * cand[k, 2] * cand[k, 2]
    mc /= wsum
    out[0] = mx / wsum
    out[1] = my / wsum
    out[2] = mc
    out[3] = i0
    out[4] = lit[best]
    out[5] = np.sqrt(max(costs[best], 0.0) / max(m, 1)) / i0
    out[6] = np.sqrt(max(mc2 / wsum - mc * mc, 0.0))
