"""The depth fit's numba kernels (:mod:`analysis.depth.rayfit` is their Python side).

They take arrays, scalars and the small named tuples below, and fill caller-allocated outputs.
The geometry: a ray from aperture point ``u`` toward a point at lens-plane position ``s`` with
``c = 1 - 1/alpha`` crosses the micro-lens plane at ``s + c u`` and lands behind the lens whose
hexagonal cell contains it; a pixel is a set of points (its area blurred, the ``footprint``), and
points beyond the micro-image rim see the neighbouring lens's aperture instead (crosstalk).
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np
from numba import prange

from .candidate_kernels import FASTMATH, censored_intensity, profile_vertex
from .render_kernels import lit_fraction, point_response
from .sample_apertures import apertures_seen, rim_samples

#: A fine pass whose depth lies farther than this fraction of its half-window from the centre is
#: run again about it (when the caller asks for it: ``recentre``).
RECENTRE_FRACTION = 0.5


class Cells(NamedTuple):
    """The micro-lens cells as the kernels see them (lens-plane metres)."""

    normals: np.ndarray      # (3, 2) neighbour directions: a point is in a cell when its offset
    #                          projects to at most half of each of them
    half_sq: np.ndarray      # (3,) half the squared length of each normal
    neigh_u: np.ndarray      # (6, 2) aperture offset of each neighbour's micro-image (crosstalk)
    neigh_s: np.ndarray      # (6, 2) lens-plane offset of each neighbour
    r_ap2: float             # squared aperture radius (with a hair of slack)
    pitch: float             # lens pitch
    response_k: float        # the pixel response falls as exp(response_k |u|^2) with the aperture
    #                          point u it sees (0: flat); see render_kernels.lit_fraction
    stop_k: float            # a second stop passes the rays of aperture point u into the lens at s
    stop_r2: float           # where |u + stop_k s|^2 <= stop_r2 (inf: no stop); see lit_fraction


class GridPass(NamedTuple):
    """One pass of the grid search: candidate depths and positions, and how pixels are modelled."""

    n_depths: int            # depths, evenly over the pass's [c_lo, c_hi]
    half_lateral: float      # positions span +- this (metres) about the start in x and y ...
    n_lateral: int           # ... this many per side
    footprint: np.ndarray    # (n, 2) aperture-metre offsets standing for a pixel's blurred area
    temperature: float       # cost difference (mismatched pixels) over which weights fall by 1/e
    vertex: bool = False     # depth from the depth profile's vertex (candidate_kernels.profile_vertex)


class PriorTerms(NamedTuple):
    """A depth prior per particle, in ``c``: Gaussian centre, ``1 / (2 sigma^2)`` (0: none), floor."""

    centre_c: np.ndarray
    k: np.ndarray
    floor: np.ndarray


@numba.njit(cache=True, parallel=True, fastmath=FASTMATH)
def fit_all(centres, sample_ptr, lens_ptr, uv, values, root_w, censored, sx0, sy0, c_lo, c_hi, cells, coarse, fine,
            prior, recentre, coarse_floor, out, order, slot_ptr):
    # Per particle, a coarse grid search over [c_lo, c_hi] then a fine one around its result,
    # centred again on its own result up to `recentre` times while that lies beyond
    # RECENTRE_FRACTION of the window from the centre; a particle whose coarse intensity is at most
    # `coarse_floor` keeps the coarse result;
    # `coarse` and `fine` are GridPass tuples, `prior` a PriorTerms tuple (one entry per particle).
    # One slot of particles (order[slot_ptr[s]:slot_ptr[s + 1]]) per prange iteration, one slot per
    # thread; each particle writes only its own row of `out`.
    n_c = coarse.n_depths
    c_prior, prior_k, prior_floor = prior.centre_c, prior.k, prior.floor
    for s in prange(slot_ptr.size - 1):
        for i in range(slot_ptr[s], slot_ptr[s + 1]):
            p = order[i]
            la, lb = lens_ptr[p], lens_ptr[p + 1]
            cen = centres[la:lb]
            ptr = sample_ptr[la:lb + 1]
            first = np.empty(7)
            _fit_one(cen, ptr, uv, values, root_w, censored, sx0[p], sy0[p], c_lo[p], c_hi[p], coarse, cells,
                     c_prior[p], prior_k[p], prior_floor[p], first)
            if first[3] <= max(coarse_floor, 0.0):
                out[p, :] = first
                continue
            step = (c_hi[p] - c_lo[p]) / max(n_c - 1, 1)
            half_c = max(2.0 * first[6], 1.5 * step)
            _fit_one(cen, ptr, uv, values, root_w, censored, first[0], first[1], first[2] - half_c,
                     first[2] + half_c, fine, cells, c_prior[p], prior_k[p], prior_floor[p], out[p])
            for _ in range(recentre):
                if out[p, 3] <= 0.0 or abs(out[p, 2] - first[2]) <= RECENTRE_FRACTION * half_c:
                    break
                first[:] = out[p, :]
                _fit_one(cen, ptr, uv, values, root_w, censored, first[0], first[1], first[2] - half_c,
                         first[2] + half_c, fine, cells, c_prior[p], prior_k[p], prior_floor[p], out[p])


@numba.njit(cache=True, fastmath=FASTMATH)
def _fit_one(centres, ptr, uv, values, root_w, censored, sx0, sy0, c_lo, c_hi, grid, cells, c_prior, prior_k,
             prior_floor, out):
    """Grid of (c, s) candidates over the lenses ``centres`` (samples ``ptr[l]:ptr[l+1]`` each);
    writes mean s_x, s_y, c, best I0, lit samples, residual (the unweighted rms misfit over I0 of
    the best candidate), std of c."""
    temperature = grid.temperature
    m, costs, cand, inten, lit = grid_costs(centres, ptr, uv, values, root_w, censored, sx0, sy0, c_lo, c_hi, grid,
                                            cells)
    n_cand = costs.size
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
    if grid.vertex:
        out[2] = profile_vertex(costs, best, grid.n_depths, grid.n_lateral ** 2, c_lo, c_hi, scale, mc,
                                c_prior, prior_k, prior_floor)
    out[3] = i0
    out[4] = lit[best]
    if root_w.size == 0:
        out[5] = np.sqrt(max(costs[best], 0.0) / max(m, 1)) / i0
    else:
        out[5] = _plain_residual(centres, ptr, uv, values, root_w, censored, cand[best, 0], cand[best, 1],
                                 cand[best, 2], i0, cells, grid.footprint)
    out[6] = np.sqrt(max(mc2 / wsum - mc * mc, 0.0))


@numba.njit(cache=True, fastmath=FASTMATH)
def _plain_residual(centres, ptr, uv, values, root_w, censored, sx, sy, c, i0, cells, footprint):
    """The rms misfit over ``i0`` of the candidate ``(sx, sy, c)`` of intensity ``i0``, every sample
    counted alike (``values`` come multiplied by ``root_w``), as the gates on the residual were
    chosen: a weighted fit's residual is comparable with an unweighted one's."""
    cost = 0.0
    m = 0
    for lens in range(centres.shape[0]):
        for j in range(ptr[lens], ptr[lens + 1]):
            v = values[j] / root_w[j]
            short = v - i0 * lit_fraction(uv[j, 0], uv[j, 1], centres[lens, 0], centres[lens, 1], sx, sy, c, cells,
                                          footprint)
            if not censored[j] or short > 0.0:
                cost += short * short
            m += 1
    return np.sqrt(cost / max(m, 1)) / i0


@numba.njit(cache=True, fastmath=FASTMATH)
def grid_costs(centres, ptr, uv, values, root_w, censored, sx0, sy0, c_lo, c_hi, grid, cells):
    """Cost, best I0 and lit samples of each candidate ``(s_x, s_y, c)`` of ``grid`` (a
    :class:`GridPass`: depths over ``[c_lo, c_hi]``, positions about ``(sx0, sy0)``) in its order
    (depth, then y, then x): returns the number of samples and the arrays ``costs``, ``cand``
    (candidate s_x, s_y, c), ``inten`` and ``lit``.

    The cost is weighted least squares where ``root_w`` holds one value per sample: sample ``j``'s
    misfit counts ``root_w[j]^2`` times (its inverse noise variance, relative to a typical
    sample's), and ``values`` come multiplied by ``root_w`` already, so only the model's fractions
    are multiplied here. An empty ``root_w``: every sample counts once.

    A sample's lit fraction is that of :func:`analysis.depth.render_kernels.lit_fraction`, with the same shortcuts (a footprint
    wholly inside or outside the cell by the margin ``|c| s_max``, crosstalk only near the rim),
    but the ``n_lat`` x ``n_lat`` positions of one depth are handled together: whether a ray lands
    in a cell is decided by its projections on the cell's three normals, to which a position adds
    the same offset for every ray, so each sample's are computed once per depth. Samples whose
    rays stay beyond a side of the cell at every position (a bound on the positions' offsets)
    are skipped, and so are whole lenses and, within a lens, the rows of samples too far from the
    cell. Sums run over lenses and samples in the order of one candidate at a time.
    """
    normals, half_sq, neigh_u, neigh_s, r_ap2, pitch, resp_k, stop_k, stop_r2 = cells
    n_c, half_lat, n_lat, sub = grid.n_depths, grid.half_lateral, grid.n_lateral, grid.footprint
    n_sub = sub.shape[0]
    n_lens = centres.shape[0]
    n_pos = n_lat * n_lat
    n_cand = n_c * n_pos
    costs = np.empty(n_cand)
    cand = np.empty((n_cand, 3))
    inten = np.empty(n_cand)
    lit = np.empty(n_cand)
    weighted = root_w.size > 0
    j_first = ptr[0] if n_lens > 0 else 0
    m = ptr[n_lens] - j_first if n_lens > 0 else 0
    # Saturated samples are censored: their true value is at least the one read, so they weigh only
    # where the model predicts less (a lower bound), and not in the least-squares intensity.
    sum_v2 = 0.0
    n_cens = 0
    for j in range(j_first, j_first + m):
        if censored[j]:
            n_cens += 1
        else:
            sum_v2 += values[j] * values[j]
    cens_slot = np.full(m if n_cens > 0 else 0, -1, dtype=np.int64)
    cens_v = np.empty(n_cens)
    c_k = 0
    for j in range(j_first, j_first + m):
        if censored[j]:
            cens_slot[j - j_first] = c_k
            cens_v[c_k] = values[j]
            c_k += 1
    cens_f = np.zeros((n_cens, n_pos))
    walked = np.empty(n_cens, dtype=np.bool_)
    r_ap = np.sqrt(r_ap2)
    # Circumradius of a lens cell (a regular hexagon's is pitch / sqrt(3)), and the farthest
    # point of a pixel's footprint; samples within `inner` of the aperture centre see no crosstalk.
    cell_r = 0.6 * pitch
    s_max = 0.0
    for q in range(n_sub):
        s_max = max(s_max, np.sqrt(sub[q, 0] * sub[q, 0] + sub[q, 1] * sub[q, 1]))
    inner = max(r_ap - s_max, 0.0)
    inner2 = inner * inner * (1.0 - 1e-9)
    is_inner, code, n_ap, used = apertures_seen(uv, ptr, centres, sub, neigh_u, neigh_s, r_ap2, inner2, stop_k,
                                                 stop_r2)
    rim_ptr, rim_j, v_sorted, most = rim_samples(ptr, uv, is_inner, n_ap)
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
    open_pts = np.empty(n_sub, dtype=np.int64)
    pw = np.ones(n_sub)  # the points' response weights (all 1 where the response is flat)
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
        cens_f[:, :] = 0.0
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
                        total = 0.0
                        for q in range(n_sub):
                            base[q, 0] = p0 + c * sub_t[q, 0]
                            base[q, 1] = p1 + c * sub_t[q, 1]
                            base[q, 2] = p2 + c * sub_t[q, 2]
                            if resp_k != 0.0:
                                pw[q] = point_response(uv[j, 0] + sub[q, 0], uv[j, 1] + sub[q, 1], resp_k)
                            total += pw[q]
                        _count_inside(base, n_sub, d0, d1, d2, h0, h1, h2, lat_t, pw, cnt, open_pts)
                        for q in range(n_pos):
                            if frac[q] < 0.0:
                                frac[q] = cnt[q] / total
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
                    total = 0.0
                    for q in range(n_sub):
                        w = code[i, q] + 1
                        if w >= 0:
                            base[n_pt, 0] = p0 + shift_t[w, 0] + c * sub_t[q, 0]
                            base[n_pt, 1] = p1 + shift_t[w, 1] + c * sub_t[q, 1]
                            base[n_pt, 2] = p2 + shift_t[w, 2] + c * sub_t[q, 2]
                            if resp_k != 0.0:  # the response to the aperture point it sees
                                ax = uv[j, 0] + sub[q, 0] + (neigh_u[w - 1, 0] if w > 0 else 0.0)
                                ay = uv[j, 1] + sub[q, 1] + (neigh_u[w - 1, 1] if w > 0 else 0.0)
                                pw[n_pt] = point_response(ax, ay, resp_k)
                            total += pw[n_pt]
                            n_pt += 1
                    if not _count_inside(base, n_pt, d0, d1, d2, h0, h1, h2, lat_t, pw, cnt, open_pts):
                        continue  # no point lands in the cell at any position
                    # A point in the cell puts the footprint around its own ray within the margin
                    # of the cell, so the per-candidate shortcut needs no test of its own here.
                    for q in range(n_pos):
                        frac[q] = cnt[q] / total if within[q] else 0.0
                v = values[j]
                rw = root_w[j] if weighted else 1.0
                if n_cens > 0 and censored[j]:
                    for q in range(n_pos):
                        cens_f[cens_slot[i], q] = frac[q] * rw
                        s_f[q] += frac[q]
                    continue
                for q in range(n_pos):
                    f = frac[q]
                    if f > 0.0:
                        s_vf[q] += v * f * rw
                        s_ff[q] += f * f * rw * rw
                        s_f[q] += f
        for q in range(n_pos):
            if s_ff[q] > 0 and s_vf[q] > 0:
                costs[k] = sum_v2 - s_vf[q] * s_vf[q] / s_ff[q]
                inten[k] = s_vf[q] / s_ff[q]
            else:
                costs[k] = sum_v2
                inten[k] = 0.0
            if n_cens > 0:
                costs[k], inten[k] = censored_intensity(s_vf[q], s_ff[q], sum_v2, cens_v, cens_f[:, q], walked)
            lit[k] = s_f[q]
            cand[k, 0] = sx0 + off_x[q]
            cand[k, 1] = sy0 + off_y[q]
            cand[k, 2] = c
            k += 1
    return m, costs, cand, inten, lit


@numba.njit(cache=True, fastmath=FASTMATH)
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


@numba.njit(cache=True, inline="always", fastmath=FASTMATH)
def _beyond(p0, p1, p2, margin, lat_t, half_sq):
    """True when every ray whose projections on the cell normals lie within ``lat_t`` of
    ``(p0, p1, p2)`` is beyond one side of the cell by more than ``margin``."""
    return (abs(p0) - lat_t[0] - margin > half_sq[0] or abs(p1) - lat_t[1] - margin > half_sq[1]
            or abs(p2) - lat_t[2] - margin > half_sq[2])


@numba.njit(cache=True, fastmath=FASTMATH)
def _count_inside(base, n_pt, d0, d1, d2, h0, h1, h2, lat_t, weight, cnt, open_pts):
    """``cnt[q]``: the total ``weight`` of the points ``base[:n_pt]`` (projections on the three
    normals) that lie in the cell (half-widths ``h``) when moved by position ``q``'s offsets
    ``(d0, d1, d2)[q]``.

    Points inside (or beyond a side) by more than the positions' reach along each normal
    (``lat_t``, with a hair of slack) are so at every position and counted once: this count took
    40 % of a fit's time, and most points of a footprint that straddles a cell edge lie well
    inside or outside. The counts are the same as testing every point at every position.
    Returns whether any point can be in the cell at some position."""
    n_pos = cnt.shape[0]
    n_in = 0.0
    n_open = 0
    for i in range(n_pt):
        a0 = abs(base[i, 0])
        a1 = abs(base[i, 1])
        a2 = abs(base[i, 2])
        if (a0 + lat_t[0] <= h0) & (a1 + lat_t[1] <= h1) & (a2 + lat_t[2] <= h2):
            n_in += weight[i]
        elif not ((a0 - lat_t[0] > h0) | (a1 - lat_t[1] > h1) | (a2 - lat_t[2] > h2)):
            open_pts[n_open] = i
            n_open += 1
    for q in range(n_pos):
        cnt[q] = n_in
    for k in range(n_open):
        i = open_pts[k]
        b0 = base[i, 0]
        b1 = base[i, 1]
        b2 = base[i, 2]
        wi = weight[i]
        for q in range(n_pos):
            cnt[q] += wi if (abs(b0 + d0[q]) <= h0) & (abs(b1 + d1[q]) <= h1) & (abs(b2 + d2[q]) <= h2) else 0.0
    return n_in > 0.0 or n_open > 0
