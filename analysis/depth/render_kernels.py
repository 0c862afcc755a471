"""Numba kernels that read samples for the depth fit and render fitted particles' light.

The model is :mod:`analysis.depth.rayfit_kernels`'s: :func:`lit_fraction` is it for one pixel,
one candidate at a time (the readable reference of the fit's grid costs as well).
"""

from __future__ import annotations

import numba
import numpy as np
from numba import prange

from .candidate_kernels import FASTMATH


@numba.njit(cache=True, parallel=True)
def sample_values(flat, pixel_index, weight, u_m, v_m, ids, black_level, saturation, background, subtract,
                  use_subtract, values, uv, censored):
    # The devignetted value above the background behind it (`background` per sample, or one value
    # for all when it holds one; weights floored at 1e-6, as
    # TableIndex.weight floors them) and the aperture point of each gathered sample; each
    # iteration writes only its own entries.
    for k in prange(ids.size):
        j = ids[k]
        bg = background[j] if background.size > 1 else background[0]
        raw = np.float64(flat[pixel_index[j]])
        censored[k] = raw >= saturation  # the ADC's top: the true value is at least this
        v = (raw - black_level) / max(np.float64(weight[j]), 1e-6) - bg
        if use_subtract:
            v -= np.float64(subtract[j])
        values[k] = v
        uv[k, 0] = u_m[j]
        uv[k, 1] = v_m[j]


@numba.njit(cache=True, inline="always", fastmath=FASTMATH)
def point_response(ux, uy, k):
    """The pixel response to the light of aperture point ``(ux, uy)``, ``exp(k |u|^2)`` with
    ``k = Cells.response_k``, relative to the micro-image centre's."""
    return np.exp(k * (ux * ux + uy * uy))


@numba.njit(cache=True, fastmath=FASTMATH)
def lit_fraction(u0, v0, cx, cy, sx, sy, c, cells, sub):
    """Fraction of a pixel (aperture point ``(u0, v0)`` behind the lens centred at ``(cx, cy)``)
    lit by a point at ``(sx, sy)`` with ``c = 1 - 1/alpha``, over the points ``sub`` that stand
    for its blurred area. Relative to the part of the pixel that sees any aperture, because the
    devignetted value is light per unit of the white image, which is lit over that same part.

    A point whose aperture point a second stop blocks (``cells.stop_k``, ``cells.stop_r2``: rays of
    aperture point ``u`` into the lens at ``s`` pass where ``|u + stop_k s|^2 <= stop_r2``) sees no
    aperture, in the exposure as in the white image.

    Each point counts by the pixel response to the light of the aperture point it sees,
    ``exp(response_k |u|^2)`` (``cells.response_k``; 0: alike), in the lit part and in the whole
    alike: the camera weighs the light of each ray by its angle, in the white image as in the
    exposure, before the blur spreads it. Under a wide blur near the rim a pixel's points see
    aperture points of very different response, and counting them alike biased depths by +2 %."""
    normals, half_sq, neigh_u, neigh_s, r_ap2, _, resp_k, stop_k, stop_r2 = cells
    frac = 0.0
    n_ap = 0.0
    ox = sx + c * u0 - cx
    oy = sy + c * v0 - cy
    for q in range(sub.shape[0]):
        ux = u0 + sub[q, 0]
        uy = v0 + sub[q, 1]
        qx = ox + c * sub[q, 0]
        qy = oy + c * sub[q, 1]
        lx = cx  # the lens whose aperture it sees
        ly = cy
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
                    ux, uy = vx, vy
                    lx = cx + neigh_s[nb, 0]
                    ly = cy + neigh_s[nb, 1]
                    found = True
                    break
            if not found:
                continue
        if (ux + stop_k * lx) ** 2 + (uy + stop_k * ly) ** 2 > stop_r2:
            continue  # the second stop blocks its rays: it sees no aperture, as in the white image
        w = point_response(ux, uy, resp_k) if resp_k != 0.0 else 1.0  # to the aperture point it sees
        n_ap += w
        inside = True
        for t in range(3):
            d = qx * normals[t, 0] + qy * normals[t, 1]
            if d > half_sq[t] or d < -half_sq[t]:
                inside = False
                break
        if inside:
            frac += w
    return frac / n_ap if n_ap > 0 else 0.0


@numba.njit(cache=True, parallel=True, fastmath=FASTMATH)
def render_samples(centres, sample_ptr, lens_ptr, uv, sx, sy, c, intensity, cells, sub, out):
    # Each particle writes only its own gathered samples, so particles run in parallel.
    normals, half_sq, neigh_u, neigh_s, r_ap2, _, _, _, _ = cells
    s_max = 0.0
    for q in range(sub.shape[0]):
        s_max = max(s_max, np.sqrt(sub[q, 0] * sub[q, 0] + sub[q, 1] * sub[q, 1]))
    # Samples whose footprint lies within the aperture (no crosstalk) and whose central ray lands
    # beyond a side of the cell by more than the footprint's reach are dark: skipped, as
    # lit_fraction would find none of their points in the cell (most of a wide blur's samples).
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
                f = lit_fraction(uv[j, 0], uv[j, 1], centres[lens, 0], centres[lens, 1], sx[p], sy[p], c[p],
                                 cells, sub)
                if f > 0.0:
                    out[j] = intensity[p] * f


@numba.njit(cache=True)
def scatter_add(out, ids, values):
    # Serial: samples lit by several particles collect the light of each.
    for j in range(ids.size):
        if values[j] != 0.0:
            out[ids[j]] += values[j]
