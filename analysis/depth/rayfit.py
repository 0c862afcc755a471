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
from typing import Any

import numba
import numpy as np
from numba import prange
from scipy.spatial import cKDTree
from scipy.special import ndtr

from analysis.lightfield.table import LightFieldTable

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


_INDEX: dict[int, _TableIndex] = {}


def _uv(table: LightFieldTable, ids: np.ndarray) -> np.ndarray:
    return np.column_stack([table.u_m[ids], table.v_m[ids]]).astype(np.float64)


def _weight(table: LightFieldTable, ids: np.ndarray) -> np.ndarray:
    return np.maximum(table.weight[ids].astype(np.float64), 1e-6)


def _gather(idx: "_TableIndex", sx: np.ndarray, sy: np.ndarray, reach: np.ndarray
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Samples of the lenses within ``reach`` of each point, as CSR arrays: lens ranges per point
    (``lens_ptr``), sample ranges per lens (``sample_ptr``), table sample ids, lens centres."""
    table = idx.table
    n = sx.size
    lens_lists = idx.tree.query_ball_point(np.column_stack([sx, sy]), reach)
    lens_count = np.array([len(lst) for lst in lens_lists], dtype=np.int64)
    lenses = (np.concatenate([np.asarray(lst, dtype=np.int64) for lst in lens_lists]) if lens_count.sum()
              else np.empty(0, np.int64))
    counts = idx.start[lenses + 1] - idx.start[lenses]
    ids = np.repeat(idx.start[lenses] - np.cumsum(np.r_[0, counts[:-1]]), counts) + np.arange(counts.sum())
    lens_ptr = np.r_[0, np.cumsum(lens_count)].astype(np.int64)
    sample_ptr = np.r_[0, np.cumsum(counts)].astype(np.int64)
    assert lens_ptr.size == n + 1
    return lens_ptr, sample_ptr, ids.astype(np.int64), np.ascontiguousarray(table.lens_xy_m[lenses])


def unexplained_light(image: np.ndarray, table: LightFieldTable, sx_m: np.ndarray, sy_m: np.ndarray,
                      radius_m: np.ndarray, *, background: float, explained: np.ndarray, floor: float) -> np.ndarray:
    """Light above ``floor`` (devignetted DN) left unexplained in the lenses within ``radius_m`` of
    each point, after taking off ``explained`` (from :func:`render_fits`); one sum per point."""
    idx = _index(table)
    lens_ptr, sample_ptr, ids, _ = _gather(idx, np.asarray(sx_m, float), np.asarray(sy_m, float),
                                           np.asarray(radius_m, float))
    flat = np.ascontiguousarray(image).reshape(-1)
    left = ((flat[table.pixel_index[ids]].astype(np.float64) - table.black_level) / _weight(table, ids)
            - background - explained[ids])
    left = np.where(left > floor, left, 0.0)
    per_lens = np.add.reduceat(left, sample_ptr[:-1]) if left.size else np.zeros(0)
    per_lens = np.where(np.diff(sample_ptr) > 0, per_lens, 0.0)
    owner = np.repeat(np.arange(len(sx_m)), np.diff(lens_ptr))
    return np.bincount(owner, weights=per_lens, minlength=len(sx_m))


def render_fits(table: LightFieldTable, fit: "RayFit", *, aperture_per_lens_plane: float, blur_px: float = 0.5,
                out: np.ndarray | None = None) -> np.ndarray:
    """The light that fitted particles put on each sample of ``table`` (devignetted DN).

    Returns
    -------
    ndarray of shape (table.n_samples,), float32
        Added to ``out`` when given.
    """
    idx = _index(table)
    if out is None:
        out = np.zeros(table.n_samples, dtype=np.float32)
    if len(fit) == 0:
        return out
    reach = np.abs(1.0 - 1.0 / fit.alpha) * idx.radius_m + 1.8 * idx.pitch_m
    lens_ptr, sample_ptr, ids, centres = _gather(idx, fit.sx_m, fit.sy_m, reach)
    light = _render_gathered(fit, idx, lens_ptr, sample_ptr, centres, _uv(table, ids), aperture_per_lens_plane, blur_px)
    _scatter_add(out, ids, light)
    return out


def _render_gathered(fit: "RayFit", idx: "_TableIndex", lens_ptr: np.ndarray, sample_ptr: np.ndarray,
                     centres: np.ndarray, uv: np.ndarray, aperture_per_lens_plane: float, blur_px: float
                     ) -> np.ndarray:
    """The light of particle ``p`` on each of its own gathered samples (:func:`_gather`'s layout)."""
    out = np.zeros(uv.shape[0])
    _render(centres, sample_ptr, lens_ptr, uv, fit.sx_m, fit.sy_m, 1.0 - 1.0 / fit.alpha, fit.intensity,
            idx.normals, idx.half_sq, idx.neighbours * aperture_per_lens_plane, idx.neighbours,
            _pixel_footprint(3, blur_px) * idx.u_per_px, idx.table.aperture_radius_m ** 2 * (1 + 1e-9), out)
    return out


def _prior_in_c(n: int, prior_alpha: np.ndarray | None, prior_sigma: np.ndarray | None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Per particle: the prior's centre in ``c = 1 - 1/alpha`` and ``1 / (2 sigma_c^2)`` (0: none)."""
    if prior_alpha is None or prior_sigma is None:
        return np.zeros(n), np.zeros(n)
    a = np.asarray(prior_alpha, dtype=np.float64).ravel()
    sigma_c = np.asarray(prior_sigma, dtype=np.float64).ravel() / a**2  # dc = dalpha / alpha^2
    if a.size != n or sigma_c.size != n:
        raise ValueError(f"prior_alpha and prior_sigma need {n} values each")
    use = np.isfinite(a) & np.isfinite(sigma_c) & (sigma_c > 0)
    k = np.zeros(n)
    k[use] = 0.5 / sigma_c[use] ** 2
    return np.where(use, 1.0 - 1.0 / np.where(use, a, 1.0), 0.0), k


def aperture_per_lens_plane(optics: Any) -> float:
    """``(P + d) / d``: a lens-plane step between lens centres moves their micro-images by this many
    aperture metres (optics of :class:`analysis.camera.model.Optics`)."""
    return optics.aperture_m_per_px * optics.projection_factor / optics.pixel_pitch_m


def _pixel_footprint(n_side: int, blur_px: float) -> np.ndarray:
    """Points (pixels) standing for one pixel's area blurred by a Gaussian: an ``n_side`` x
    ``n_side`` grid at the quantiles ``(k + 1/2) / n_side`` of that spread along each axis, so
    that each point stands for an equal share of the light (symmetric: a lopsided footprint shifts
    every fitted position). Points spaced evenly with the spread's variance, as before, misjudge
    how the few pixels of a strongly blurred particle's small lit patches are lit: on isolated
    simulated particles its depth came out 1.1 % too far from focus, with these 0.1 %."""
    if n_side <= 1:
        return np.zeros((1, 2))  # the pixel centre alone
    x = np.linspace(-0.5 - 5.0 * blur_px, 0.5 + 5.0 * blur_px, 2001)
    if blur_px > 0:
        # Cumulative distribution of a unit box convolved with a Gaussian of sd blur_px.
        def g(y: np.ndarray) -> np.ndarray:
            return y * ndtr(y / blur_px) + blur_px * np.exp(-0.5 * (y / blur_px) ** 2) / np.sqrt(2.0 * np.pi)
        cdf = g(x + 0.5) - g(x - 0.5)
    else:
        cdf = np.clip(x + 0.5, 0.0, 1.0)
    g1 = np.interp((np.arange(n_side) + 0.5) / n_side, cdf, x)
    g1 = 0.5 * (g1 - g1[::-1])  # exactly symmetric
    gx, gy = np.meshgrid(g1, g1)
    return np.column_stack([gx.ravel(), gy.ravel()])


def _index(table: LightFieldTable) -> _TableIndex:
    idx = _INDEX.get(id(table))
    if idx is None or idx.table is not table:
        if len(_INDEX) > 4:
            _INDEX.clear()
        idx = _INDEX[id(table)] = _TableIndex(table)
    return idx


def fit_rays(image: np.ndarray, table: LightFieldTable, sx0_m: np.ndarray, sy0_m: np.ndarray,
             alpha0: np.ndarray, *, background: float, aperture_per_lens_plane: float, alpha_half_range: float = 0.004, n_alpha: int = 33,
             lateral_half_range_pitches: float = 0.4, reach_pitches: float = 1.2, blur_px: float = 0.5,
             temperature: float = 0.5, coarse_temperature: float = 1.0,
             fine: tuple[int, float, int, int] = (9, 0.25, 3, 3),
             subtract: np.ndarray | None = None, own: "RayFit | None" = None, coarse_points: int = 1,
             coarse_lateral: int = 3, prior_alpha: np.ndarray | None = None,
             prior_sigma: np.ndarray | None = None, prior_outlier: float = 0.05) -> RayFit:
    """Refine position and depth of particles by fitting the forward model to the raw samples.

    Two passes: a coarse grid of ``n_alpha`` depths over ``alpha0 +- alpha_half_range`` and 3 x 3
    positions (pixels as ``coarse_points**2`` points; 1: the centre), then a fine grid around the coarse estimate (``fine``: by
    default 9 depths over twice its spread, 3 x 3 positions over +-0.25 pitch, 3 x 3 points).
    Where a blur of about a pitch spills a sliver of light into the neighbouring lenses, only
    the fine pass's pixel areas (partly lit rim pixels) tell in front of focus from behind it:
    the aperture lands on the MLA mirrored, so the other side of those micro-images is lit.

    The table should include the micro-images' rim pixels (``build_table(..., rim_px=-0.5)``):
    where a particle's light splits between lenses, the neighbour's share often lands there.

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
        :attr:`analysis.lightfield.refocus.Samples.background`.
    aperture_per_lens_plane : float
        Aperture metres per lens-plane metre between neighbouring micro-images, ``(P + d) / d``
        (:func:`aperture_per_lens_plane`): how far apart two lenses' images of one aperture point are.
    alpha_half_range, n_alpha : float, int
        Candidate depths of the coarse pass.
    lateral_half_range_pitches : float
        Candidate positions of the coarse pass, in lens pitches either side of the start.
    reach_pitches : float
        Lenses farther than the largest candidate blur plus this many pitches are left out.
    blur_px : float
        Gaussian blur (pixels) of the sensor image (diffraction, crosstalk): each pixel is
        modelled by points spread over its area and this blur, so partly lit pixels at the
        edges of a lens's share of the light count by how much of them is lit.
    temperature, coarse_temperature : float
        Cost difference, in mismatched pixels, over which candidates lose weight by ``1/e``, in
        the fine and the coarse pass. Half a pixel in the fine pass, whose pixel areas let the few
        partly lit pixels that decide the sign of the defocus count; a whole one in the coarse
        pass, whose pixel centres misjudge those pixels (sharper, it settles on wrong basins).
    fine : (n_alpha, lateral_half_range_pitches, n_lateral, pixel_points_per_side)
        The fine pass's grid.
    prior_alpha, prior_sigma, prior_outlier : ndarray of shape (n,), ndarray, float
        A prior on each particle's depth (e.g. :func:`analysis.depth.prior.neighbour_prior`): a
        Gaussian of this centre and width with probability ``1 - prior_outlier``, else uniform over
        the coarse window (so the pixels still win where they disagree with it). It decides only
        where the pixels cannot tell the depth: one lens holds all the light, and every depth whose
        blur fits in it (either sign of the defocus) explains them equally well. ``prior_sigma``
        NaN: no prior for that particle.
    subtract : ndarray of shape (table.n_samples,), optional
        Light already explained (devignetted DN per sample, from :func:`render_fits`), taken off
        before fitting: particles hidden behind others are then fitted to what is left.
    own : RayFit, optional
        Earlier fits of these same particles (row for row), whose light ``subtract`` includes: each
        particle's own share is added back, so it is refitted to its pixels with only its
        neighbours' light taken off (deblending a crowd).

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
    lens_ptr, sample_ptr, ids, centres = _gather(idx, sx0, sy0, reach)
    values = np.empty(ids.size)
    uv = np.empty((ids.size, 2))
    _sample_values(flat, table.pixel_index, table.weight, table.u_m, table.v_m, ids, float(table.black_level),
                   float(background), np.zeros(0, np.float32) if subtract is None else subtract,
                   subtract is not None, values, uv)
    if own is not None:
        if len(own) != n:
            raise ValueError(f"own holds {len(own)} fits for {n} particles")
        values += _render_gathered(own, idx, lens_ptr, sample_ptr, centres, uv, aperture_per_lens_plane, blur_px)
    c_prior, prior_k = _prior_in_c(n, prior_alpha, prior_sigma)
    # The uniform part's density relative to the Gaussian's peak.
    with np.errstate(divide="ignore"):
        sigma_c = np.sqrt(0.5 / prior_k)
    prior_floor = np.where(prior_k > 0, prior_outlier / max(1.0 - prior_outlier, 1e-12) * np.sqrt(2 * np.pi)
                           * sigma_c / np.abs(c_hi - c_lo), 0.0)
    out = np.empty((n, 7))
    _fit_all(centres, sample_ptr, lens_ptr, uv, values, sx0, sy0, c_lo, c_hi, int(n_alpha),
             lateral_half_range_pitches * idx.pitch_m, idx.pitch_m, idx.normals, idx.half_sq,
             idx.neighbours * aperture_per_lens_plane, idx.neighbours,
             _pixel_footprint(coarse_points, blur_px) * idx.u_per_px, _pixel_footprint(int(fine[3]), blur_px) * idx.u_per_px,
             table.aperture_radius_m ** 2 * (1 + 1e-9), float(temperature), float(coarse_temperature), int(fine[0]),
             float(fine[1]), int(fine[2]),
             int(coarse_lateral), c_prior, prior_k, prior_floor, out,
             *_balanced_slots(sample_ptr[lens_ptr[1:]] - sample_ptr[lens_ptr[:-1]], numba.get_num_threads()))
    return RayFit(sx_m=out[:, 0], sy_m=out[:, 1], alpha=1.0 / (1.0 - out[:, 2]), intensity=out[:, 3],
                  n_lit=out[:, 4].astype(np.int64), residual=out[:, 5],
                  alpha_spread=out[:, 6] / (1.0 - out[:, 2]) ** 2)


@numba.njit(cache=True, parallel=True)
def _sample_values(flat, pixel_index, weight, u_m, v_m, ids, black_level, background, subtract, use_subtract,
                   values, uv):
    # The devignetted value above background (as _weight: weights floored at 1e-6) and the
    # aperture point of each gathered sample; each iteration writes only its own entries.
    for k in prange(ids.size):
        j = ids[k]
        v = (np.float64(flat[pixel_index[j]]) - black_level) / max(np.float64(weight[j]), 1e-6) - background
        if use_subtract:
            v -= np.float64(subtract[j])
        values[k] = v
        uv[k, 0] = u_m[j]
        uv[k, 1] = v_m[j]


def _balanced_slots(cost: np.ndarray, n_slots: int) -> tuple[np.ndarray, np.ndarray]:
    """Split items of roughly known ``cost`` into ``n_slots`` runs of about equal total cost (dealt
    out by decreasing cost, back and forth): ``order[slot_ptr[s]:slot_ptr[s + 1]]`` is slot ``s``.
    A particle's fit costs about in proportion to its samples, and few reach many lenses: in
    equal runs of the input order, one thread may get most of those."""
    n = cost.size
    n_slots = max(1, min(int(n_slots), n))
    rank = np.argsort(-cost, kind="stable")
    turn = np.arange(n) % (2 * n_slots)
    slot = np.where(turn < n_slots, turn, 2 * n_slots - 1 - turn)
    order = rank[np.argsort(slot, kind="stable")].astype(np.int64)
    slot_ptr = np.r_[0, np.cumsum(np.bincount(slot, minlength=n_slots))].astype(np.int64)
    return order, slot_ptr


@numba.njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _fit_all(centres, sample_ptr, lens_ptr, uv, values, sx0, sy0, c_lo, c_hi, n_c, half_lat, pitch, normals,
             half_sq, neigh_u, neigh_s, sub_coarse, sub_fine, r_ap2, temperature, coarse_temperature, n_c_fine,
             fine_lat, n_lat_fine, n_lat_coarse, c_prior, prior_k, prior_floor, out, order, slot_ptr):
    # One slot of particles (order[slot_ptr[s]:slot_ptr[s + 1]]) per prange iteration, one slot per
    # thread; each particle writes only its own row of `out`.
    for s in prange(slot_ptr.size - 1):
        for i in range(slot_ptr[s], slot_ptr[s + 1]):
            p = order[i]
            la, lb = lens_ptr[p], lens_ptr[p + 1]
            cen = centres[la:lb]
            ptr = sample_ptr[la:lb + 1]
            coarse = np.empty(7)
            _fit_one(cen, ptr, uv, values, sx0[p], sy0[p], c_lo[p], c_hi[p], n_c, half_lat, n_lat_coarse, pitch,
                     normals, half_sq, neigh_u, neigh_s, sub_coarse, r_ap2, coarse_temperature, c_prior[p],
                     prior_k[p], prior_floor[p], coarse)
            if coarse[3] <= 0.0:
                out[p, :] = coarse
                continue
            step = (c_hi[p] - c_lo[p]) / max(n_c - 1, 1)
            half_c = max(2.0 * coarse[6], 1.5 * step)
            _fit_one(cen, ptr, uv, values, coarse[0], coarse[1], coarse[2] - half_c, coarse[2] + half_c,
                     n_c_fine, fine_lat * pitch, n_lat_fine, pitch, normals, half_sq, neigh_u, neigh_s, sub_fine,
                     r_ap2, temperature, c_prior[p], prior_k[p], prior_floor[p], out[p])


@numba.njit(cache=True, fastmath=_FASTMATH)
def _fit_one(centres, ptr, uv, values, sx0, sy0, c_lo, c_hi, n_c, half_lat, n_lat, pitch, normals, half_sq,
             neigh_u, neigh_s, sub, r_ap2, temperature, c_prior, prior_k, prior_floor, out):
    """Grid of (c, s) candidates over the lenses ``centres`` (samples ``ptr[l]:ptr[l+1]`` each);
    writes mean s_x, s_y, c, best I0, lit samples, residual, std of c."""
    n_cand = n_c * n_lat * n_lat
    costs = np.empty(n_cand)
    cand = np.empty((n_cand, 3))
    inten = np.empty(n_cand)
    lit = np.empty(n_cand)
    m = _grid_costs(centres, ptr, uv, values, sx0, sy0, c_lo, c_hi, n_c, half_lat, n_lat, pitch, normals, half_sq,
                    neigh_u, neigh_s, sub, r_ap2, costs, cand, inten, lit)
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
        dc = cand[k, 2] - c_prior
        w = np.exp(-(costs[k] - costs[best]) / scale) * (np.exp(-prior_k * dc * dc) + prior_floor)
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


@numba.njit(cache=True, fastmath=_FASTMATH)
def _grid_costs(centres, ptr, uv, values, sx0, sy0, c_lo, c_hi, n_c, half_lat, n_lat, pitch, normals, half_sq,
                neigh_u, neigh_s, sub, r_ap2, costs, cand, inten, lit):
    """Cost, best I0 and lit samples of each candidate ``(s_x, s_y, c)`` of the grid of
    :func:`_fit_one`, in its order (depth, then y, then x), into ``costs``, ``inten``, ``lit`` and
    ``cand``; returns the number of samples.

    A sample's lit fraction is that of :func:`_lit_fraction`, with the same shortcuts (a footprint
    wholly inside or outside the cell by the margin ``|c| s_max``, crosstalk only near the rim),
    but the ``n_lat`` x ``n_lat`` positions of one depth are handled together: whether a ray lands
    in a cell is decided by its projections on the cell's three normals, to which a position adds
    the same offset for every ray, so each sample's are computed once per depth. Samples whose
    rays stay beyond a side of the cell at every position (a bound on the positions' offsets)
    are skipped, and so are whole lenses and, within a lens, the rows of samples too far from the
    cell. Sums run over lenses and samples in the order of one candidate at a time.
    """
    n_sub = sub.shape[0]
    n_lens = centres.shape[0]
    n_pos = n_lat * n_lat
    j_first = ptr[0] if n_lens > 0 else 0
    m = ptr[n_lens] - j_first if n_lens > 0 else 0
    sum_v2 = 0.0
    for j in range(j_first, j_first + m):
        sum_v2 += values[j] * values[j]
    r_ap = np.sqrt(r_ap2)
    # Circumradius of a lens cell (a regular hexagon's is pitch / sqrt(3)), and the farthest
    # point of a pixel's footprint; samples within `inner` of the aperture centre see no crosstalk.
    cell_r = 0.6 * pitch
    s_max = 0.0
    for q in range(n_sub):
        s_max = max(s_max, np.sqrt(sub[q, 0] * sub[q, 0] + sub[q, 1] * sub[q, 1]))
    inner = max(r_ap - s_max, 0.0)
    inner2 = inner * inner * (1.0 - 1e-9)
    is_inner, code, n_ap, used = _apertures_seen(uv, j_first, m, sub, neigh_u, r_ap2, inner2)
    rim_ptr, rim_j, v_sorted, most = _rim_samples(ptr, uv, is_inner, n_ap)
    off_x, off_y, d0, d1, d2 = _position_offsets(half_lat, n_lat, normals)
    h0 = half_sq[0]
    h1 = half_sq[1]
    h2 = half_sq[2]
    # How far a position lies from the grid's centre: as a distance, and along each normal; with
    # a little slack, so that rounding cannot make a bound reject a lit sample.
    lat_r = half_lat * np.sqrt(2.0) * (1.0 + 1e-9) + 1e-9 * pitch
    lat_t = np.empty(3)
    for t in range(3):
        lat_t[t] = half_lat * (abs(normals[t, 0]) + abs(normals[t, 1])) * (1.0 + 1e-9) + 1e-9 * half_sq[t]
    sub_t = np.empty((n_sub, 3))  # footprint points along each normal, per unit c
    sub_ext = np.zeros(3)  # their farthest, per normal
    for q in range(n_sub):
        for t in range(3):
            sub_t[q, t] = sub[q, 0] * normals[t, 0] + sub[q, 1] * normals[t, 1]
            sub_ext[t] = max(sub_ext[t], abs(sub_t[q, t]))
    pt_t = np.empty(3)
    shift_t = np.zeros((7, 3))  # crosstalk ray offsets along the normals (row 0: the own ray)
    todo = np.empty(most, dtype=np.int64)
    base = np.empty((n_sub, 3))
    within = np.empty(n_pos, dtype=np.bool_)
    frac = np.empty(n_pos)
    cnt = np.empty(n_pos)
    s_vf = np.empty(n_pos)
    s_ff = np.empty(n_pos)
    s_f = np.empty(n_pos)
    k = 0
    for ic in range(n_c):
        c = c_lo + (c_hi - c_lo) * ic / max(n_c - 1, 1)
        # A lens can only be lit if its cell (or, by crosstalk, a neighbour's) meets the footprint.
        reach = abs(c) * r_ap + 1.8 * pitch
        reach2 = reach * reach
        lim = cell_r + abs(c) * s_max
        margin = abs(c) * s_max * pitch
        lim2 = lim * lim
        near_in = lim + lat_r  # a ray farther than this from a cell centre misses it at every position
        for t in range(3):
            pt_t[t] = lat_t[t] + abs(c) * sub_ext[t] * (1.0 + 1e-9)
        for nb in range(6):
            # A rim point that sees neighbour nb's aperture point is lit when its ray, offset by
            # c neigh_u - neigh_s, lands in this lens's cell.
            sx_nb = c * neigh_u[nb, 0] - neigh_s[nb, 0]
            sy_nb = c * neigh_u[nb, 1] - neigh_s[nb, 1]
            for t in range(3):
                shift_t[nb + 1, t] = sx_nb * normals[t, 0] + sy_nb * normals[t, 1]
        s_vf[:] = 0.0
        s_ff[:] = 0.0
        s_f[:] = 0.0
        for lens in range(n_lens):
            cx = centres[lens, 0]
            cy = centres[lens, 1]
            gx = cx - sx0
            gy = cy - sy0
            if np.sqrt(gx * gx + gy * gy) > reach + lat_r:
                continue
            n_within = 0
            for q in range(n_pos):
                ex = gx - off_x[q]
                ey = gy - off_y[q]
                within[q] = ex * ex + ey * ey <= reach2
                n_within += within[q]
            if n_within == 0:
                continue
            n_todo = _samples_to_visit(uv, ptr[lens], ptr[lens + 1], rim_j[rim_ptr[lens]:rim_ptr[lens + 1]],
                                       v_sorted[lens], gx, gy, c, near_in + abs(c) * inner * (1.0 + 1e-9)
                                       + 1e-9 * pitch, near_in * (1.0 + 1e-9) + 1e-9 * pitch, todo)
            for t_j in range(n_todo):
                j = todo[t_j]
                i = j - j_first
                # The grid centre's ray, from the lens centre, and along each normal.
                ox = sx0 + c * uv[j, 0] - cx
                oy = sy0 + c * uv[j, 1] - cy
                p0 = ox * normals[0, 0] + oy * normals[0, 1]
                p1 = ox * normals[1, 0] + oy * normals[1, 1]
                p2 = ox * normals[2, 0] + oy * normals[2, 1]
                if is_inner[i]:
                    if ox * ox + oy * oy > near_in * near_in or _beyond(p0, p1, p2, margin, lat_t, half_sq):
                        continue
                    # Per position: 0 beyond `lim` or where the footprint lies outside the cell by
                    # the margin, 1 where wholly inside, else the share of its points inside.
                    straddles = False
                    for q in range(n_pos):
                        fx = ox + off_x[q]
                        fy = oy + off_y[q]
                        a0 = abs(p0 + d0[q])
                        a1 = abs(p1 + d1[q])
                        a2 = abs(p2 + d2[q])
                        f = 1.0
                        if (a0 + margin > h0) or (a1 + margin > h1) or (a2 + margin > h2):
                            f = -1.0
                        if (a0 - margin > h0) or (a1 - margin > h1) or (a2 - margin > h2):
                            f = 0.0
                        if fx * fx + fy * fy > lim2 or not within[q]:
                            f = 0.0
                        frac[q] = f
                        straddles |= f < 0.0
                    if straddles:
                        for q in range(n_sub):
                            base[q, 0] = p0 + c * sub_t[q, 0]
                            base[q, 1] = p1 + c * sub_t[q, 1]
                            base[q, 2] = p2 + c * sub_t[q, 2]
                        _count_inside(base, n_sub, d0, d1, d2, h0, h1, h2, cnt)
                        for q in range(n_pos):
                            if frac[q] < 0.0:
                                frac[q] = cnt[q] / n_sub
                else:
                    if n_ap[i] == 0:
                        continue
                    # Skip unless some point, through its own ray or the crosstalk ray of the
                    # aperture it sees, may land in the cell at some position (`pt_t` bounds the
                    # footprint's and the positions' extent along each normal).
                    near = False
                    for w in range(7):
                        if (used[i] >> w) & 1 and not _beyond(p0 + shift_t[w, 0], p1 + shift_t[w, 1],
                                                              p2 + shift_t[w, 2], 0.0, pt_t, half_sq):
                            near = True
                            break
                    if not near:
                        continue
                    n_pt = 0
                    for q in range(n_sub):
                        w = code[i, q] + 1
                        if w >= 0:
                            base[n_pt, 0] = p0 + shift_t[w, 0] + c * sub_t[q, 0]
                            base[n_pt, 1] = p1 + shift_t[w, 1] + c * sub_t[q, 1]
                            base[n_pt, 2] = p2 + shift_t[w, 2] + c * sub_t[q, 2]
                            n_pt += 1
                    _count_inside(base, n_pt, d0, d1, d2, h0, h1, h2, cnt)
                    # Where points land in the cell, the per-candidate shortcut still applies: the
                    # footprint around the ray, or around one of its six crosstalk rays (whether
                    # or not a point sees that neighbour), must meet the cell by the margin.
                    for q in range(n_pos):
                        f = 0.0
                        if cnt[q] > 0.0 and within[q]:
                            for w in range(7):
                                a0 = abs(p0 + shift_t[w, 0] + d0[q])
                                a1 = abs(p1 + shift_t[w, 1] + d1[q])
                                a2 = abs(p2 + shift_t[w, 2] + d2[q])
                                if not ((a0 - margin > h0) or (a1 - margin > h1) or (a2 - margin > h2)):
                                    f = cnt[q] / n_ap[i]
                                    break
                        frac[q] = f
                v = values[j]
                for q in range(n_pos):
                    f = frac[q]
                    if f > 0.0:
                        s_vf[q] += v * f
                        s_ff[q] += f * f
                        s_f[q] += f
        for q in range(n_pos):
            if s_ff[q] > 0 and s_vf[q] > 0:
                costs[k] = sum_v2 - s_vf[q] * s_vf[q] / s_ff[q]
                inten[k] = s_vf[q] / s_ff[q]
            else:
                costs[k] = sum_v2
                inten[k] = 0.0
            lit[k] = s_f[q]
            cand[k, 0] = sx0 + off_x[q]
            cand[k, 1] = sy0 + off_y[q]
            cand[k, 2] = c
            k += 1
    return m


@numba.njit(cache=True, fastmath=_FASTMATH)
def _apertures_seen(uv, j_first, m, sub, neigh_u, r_ap2, inner2):
    """Per sample ``j_first + i``: whether it lies within ``inner`` (no crosstalk), and for the
    others which aperture each point of its footprint sees (``code``: -1 its own, ``nb`` that of
    neighbour ``nb`` by crosstalk, -2 none), how many see one (``n_ap``), and which (``used``: bit
    ``w`` for aperture ``w - 1``), as :func:`_lit_fraction` decides it."""
    n_sub = sub.shape[0]
    # A point nearer the centre than the nearest neighbour's aperture (|neigh_u| - r_ap) sees none
    # of theirs.
    nu_min = np.inf
    for nb in range(6):
        nu_min = min(nu_min, np.sqrt(neigh_u[nb, 0] * neigh_u[nb, 0] + neigh_u[nb, 1] * neigh_u[nb, 1]))
    no_neigh = max(nu_min - np.sqrt(r_ap2), 0.0) * (1.0 - 1e-9)
    is_inner = np.empty(m, dtype=np.bool_)
    code = np.full((m, n_sub), -1, dtype=np.int8)
    n_ap = np.full(m, n_sub, dtype=np.int64)
    used = np.ones(m, dtype=np.int64)
    for i in range(m):
        u0 = uv[j_first + i, 0]
        v0 = uv[j_first + i, 1]
        is_inner[i] = u0 * u0 + v0 * v0 <= inner2
        if is_inner[i]:
            continue
        n = 0
        bits = 0
        for q in range(n_sub):
            ux = u0 + sub[q, 0]
            uy = v0 + sub[q, 1]
            r2 = ux * ux + uy * uy
            if r2 > r_ap2:
                code[i, q] = -2
                if r2 < no_neigh * no_neigh:
                    continue
                for nb in range(6):
                    vx = ux + neigh_u[nb, 0]
                    vy = uy + neigh_u[nb, 1]
                    if vx * vx + vy * vy <= r_ap2:
                        code[i, q] = nb
                        break
            if code[i, q] != -2:
                n += 1
                bits |= 1 << (code[i, q] + 1)
        n_ap[i] = n
        used[i] = bits
    return is_inner, code, n_ap, used


@numba.njit(cache=True)
def _rim_samples(ptr, uv, is_inner, n_ap):
    """Per lens: its rim samples that some aperture lights (``rim_j[rim_ptr[l]:rim_ptr[l + 1]]``,
    in order), whether its samples run by non-increasing v (rows of the micro-image), and the
    most samples of one lens."""
    n_lens = ptr.size - 1
    j_first = ptr[0] if n_lens > 0 else 0
    rim_ptr = np.zeros(n_lens + 1, dtype=np.int64)
    rim_j = np.empty(is_inner.size, dtype=np.int64)
    v_sorted = np.ones(n_lens, dtype=np.bool_)
    n_rim = 0
    most = 0
    for lens in range(n_lens):
        most = max(most, ptr[lens + 1] - ptr[lens])
        for j in range(ptr[lens], ptr[lens + 1]):
            if not is_inner[j - j_first] and n_ap[j - j_first] > 0:
                rim_j[n_rim] = j
                n_rim += 1
            if j > ptr[lens] and uv[j, 1] > uv[j - 1, 1]:
                v_sorted[lens] = False
        rim_ptr[lens + 1] = n_rim
    return rim_ptr, rim_j, v_sorted, most


@numba.njit(cache=True, fastmath=_FASTMATH)
def _position_offsets(half_lat, n_lat, normals):
    """Offsets of the ``n_lat`` x ``n_lat`` candidate positions from the grid's centre along x, y
    and each cell normal (position ``iy * n_lat + ix``, spaced as :func:`_fit_one` spaces them)."""
    n_pos = n_lat * n_lat
    step = np.empty(n_lat)
    for i in range(n_lat):
        step[i] = -half_lat + 2.0 * half_lat * i / max(n_lat - 1, 1)
    off_x = np.empty(n_pos)
    off_y = np.empty(n_pos)
    d0 = np.empty(n_pos)
    d1 = np.empty(n_pos)
    d2 = np.empty(n_pos)
    for iy in range(n_lat):
        for ix in range(n_lat):
            q = iy * n_lat + ix
            off_x[q] = step[ix]
            off_y[q] = step[iy]
            d0[q] = step[ix] * normals[0, 0] + step[iy] * normals[0, 1]
            d1[q] = step[ix] * normals[1, 0] + step[iy] * normals[1, 1]
            d2[q] = step[ix] * normals[2, 0] + step[iy] * normals[2, 1]
    return off_x, off_y, d0, d1, d2


@numba.njit(cache=True, inline="always")
def _samples_to_visit(uv, j0, j1, rim, v_sorted, gx, gy, c, inner_reach, near_in, todo):
    """Samples ``j0:j1`` of one lens (centre ``(gx, gy)`` from the grid's centre) that may be lit
    at depth ``c``, in order, into ``todo``; returns how many. Those away from the rim need a ray
    within ``near_in`` of the centre: none when the lens is farther than ``inner_reach``, else
    (samples by rows) those whose v puts it within ``near_in`` along y. The rim samples ``rim``
    (crosstalk) are all visited."""
    ja = j0
    jb = j0
    if np.sqrt(gx * gx + gy * gy) <= inner_reach:
        jb = j1
        if v_sorted and c != 0.0:
            half_band = near_in / abs(c)  # |sy0 + c v - cy| <= near_in
            ja = _first_below(uv, j0, j1, gy / c + half_band)
            jb = max(ja, _first_below(uv, ja, j1, gy / c - half_band))
    n = 0
    r = 0
    while r < rim.size and rim[r] < ja:  # rim samples before the band
        todo[n] = rim[r]
        n += 1
        r += 1
    for j in range(ja, jb):
        todo[n] = j
        n += 1
    while r < rim.size:  # and after it
        if rim[r] >= jb:
            todo[n] = rim[r]
            n += 1
        r += 1
    return n


@numba.njit(cache=True, inline="always")
def _first_below(uv, lo, hi, v):
    """First sample in ``lo:hi`` (v non-increasing) whose v is below ``v``; ``hi`` if none."""
    while lo < hi:
        mid = (lo + hi) // 2
        if uv[mid, 1] >= v:
            lo = mid + 1
        else:
            hi = mid
    return lo


@numba.njit(cache=True, inline="always", fastmath=_FASTMATH)
def _beyond(p0, p1, p2, margin, lat_t, half_sq):
    """True when every ray whose projections on the cell normals lie within ``lat_t`` of
    ``(p0, p1, p2)`` is beyond one side of the cell by more than ``margin``."""
    return (abs(p0) - lat_t[0] - margin > half_sq[0] or abs(p1) - lat_t[1] - margin > half_sq[1]
            or abs(p2) - lat_t[2] - margin > half_sq[2])


@numba.njit(cache=True, fastmath=_FASTMATH)
def _count_inside(base, n_pt, d0, d1, d2, h0, h1, h2, cnt):
    """``cnt[q]``: how many of the points ``base[:n_pt]`` (projections on the three normals) lie in
    the cell (half-widths ``h``) when moved by position ``q``'s offsets ``(d0, d1, d2)[q]``."""
    n_pos = cnt.shape[0]
    for q in range(n_pos):
        cnt[q] = 0.0
    for i in range(n_pt):
        b0 = base[i, 0]
        b1 = base[i, 1]
        b2 = base[i, 2]
        for q in range(n_pos):
            cnt[q] += 1.0 if (abs(b0 + d0[q]) <= h0) & (abs(b1 + d1[q]) <= h1) & (abs(b2 + d2[q]) <= h2) else 0.0


@numba.njit(cache=True, fastmath=_FASTMATH)
def _lit_fraction(u0, v0, cx, cy, sx, sy, c, normals, half_sq, neigh_u, neigh_s, sub, r_ap2):
    """Fraction of a pixel (aperture point ``(u0, v0)`` behind the lens centred at ``(cx, cy)``)
    lit by a point at ``(sx, sy)`` with ``c = 1 - 1/alpha``, over the points ``sub`` that stand
    for its blurred area. Relative to the part of the pixel that sees any aperture, because the
    devignetted value is light per unit of the white image, which is lit over that same part."""
    frac = 0.0
    n_ap = 0
    ox = sx + c * u0 - cx
    oy = sy + c * v0 - cy
    for q in range(sub.shape[0]):
        ux = u0 + sub[q, 0]
        uy = v0 + sub[q, 1]
        qx = ox + c * sub[q, 0]
        qy = oy + c * sub[q, 1]
        if ux * ux + uy * uy > r_ap2:
            # Blurred into the neighbouring micro-image (crosstalk): there it sees that lens's
            # aperture point, and is lit if its ray enters that lens.
            found = False
            for nb in range(6):
                vx = ux + neigh_u[nb, 0]
                vy = uy + neigh_u[nb, 1]
                if vx * vx + vy * vy <= r_ap2:
                    qx = sx + c * vx - cx - neigh_s[nb, 0]
                    qy = sy + c * vy - cy - neigh_s[nb, 1]
                    found = True
                    break
            if not found:
                continue
        n_ap += 1
        inside = True
        for t in range(3):
            d = qx * normals[t, 0] + qy * normals[t, 1]
            if d > half_sq[t] or d < -half_sq[t]:
                inside = False
                break
        if inside:
            frac += 1.0
    return frac / n_ap if n_ap > 0 else 0.0


@numba.njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _render(centres, sample_ptr, lens_ptr, uv, sx, sy, c, intensity, normals, half_sq, neigh_u, neigh_s,
            sub, r_ap2, out):
    # Each particle writes only its own gathered samples, so particles run in parallel.
    s_max = 0.0
    for q in range(sub.shape[0]):
        s_max = max(s_max, np.sqrt(sub[q, 0] * sub[q, 0] + sub[q, 1] * sub[q, 1]))
    # Samples whose footprint lies within the aperture (no crosstalk) and whose central ray lands
    # beyond a side of the cell by more than the footprint's reach are dark: skipped, as
    # _lit_fraction would find none of their points in the cell (most of a wide blur's samples).
    inner = max(np.sqrt(r_ap2) - s_max, 0.0)
    inner2 = inner * inner * (1.0 - 1e-9)
    norm_t = np.empty(3)
    for t in range(3):
        norm_t[t] = np.sqrt(normals[t, 0] * normals[t, 0] + normals[t, 1] * normals[t, 1])
    for p in prange(sx.size):
        if intensity[p] <= 0.0:
            continue
        reach_t = np.empty(3)
        shift_t = np.zeros((7, 3))  # along each normal: the own ray (row 0), and the crosstalk rays
        for t in range(3):
            reach_t[t] = half_sq[t] + abs(c[p]) * s_max * norm_t[t] * (1.0 + 1e-9) + 1e-9 * norm_t[t] ** 2
            for nb in range(6):
                shift_t[nb + 1, t] = ((c[p] * neigh_u[nb, 0] - neigh_s[nb, 0]) * normals[t, 0]
                                      + (c[p] * neigh_u[nb, 1] - neigh_s[nb, 1]) * normals[t, 1])
        for lens in range(lens_ptr[p], lens_ptr[p + 1]):
            for j in range(sample_ptr[lens], sample_ptr[lens + 1]):
                ox = sx[p] + c[p] * uv[j, 0] - centres[lens, 0]
                oy = sy[p] + c[p] * uv[j, 1] - centres[lens, 1]
                p0 = ox * normals[0, 0] + oy * normals[0, 1]
                p1 = ox * normals[1, 0] + oy * normals[1, 1]
                p2 = ox * normals[2, 0] + oy * normals[2, 1]
                # Near the rim a point may see a neighbour's aperture: its ray is shifted.
                n_rays = 1 if uv[j, 0] * uv[j, 0] + uv[j, 1] * uv[j, 1] <= inner2 else 7
                near = False
                for w in range(n_rays):
                    if (abs(p0 + shift_t[w, 0]) <= reach_t[0] and abs(p1 + shift_t[w, 1]) <= reach_t[1]
                            and abs(p2 + shift_t[w, 2]) <= reach_t[2]):
                        near = True
                        break
                if not near:
                    continue
                f = _lit_fraction(uv[j, 0], uv[j, 1], centres[lens, 0], centres[lens, 1], sx[p], sy[p], c[p],
                                  normals, half_sq, neigh_u, neigh_s, sub, r_ap2)
                if f > 0.0:
                    out[j] = intensity[p] * f


@numba.njit(cache=True)
def _scatter_add(out, ids, values):
    # Serial: samples lit by several particles collect the light of each.
    for j in range(ids.size):
        if values[j] != 0.0:
            out[ids[j]] += values[j]
