"""Which aperture each sample the depth fit gathers sees, point by point of its footprint: its own
lens's, a neighbour's (light blurred across the micro-image rim), or none (beyond every rim, or
blocked by a second stop); and which samples are rim samples. The grid search
(:func:`analysis.depth.rayfit_kernels.grid_costs`) decides so once per fit, as
:func:`analysis.depth.render_kernels.lit_fraction` decides it per pixel.
"""

from __future__ import annotations

import numba
import numpy as np

from .candidate_kernels import FASTMATH


@numba.njit(cache=True, fastmath=FASTMATH)
def apertures_seen(uv, ptr, centres, sub, neigh_u, neigh_s, r_ap2, inner2, stop_k, stop_r2):
    """Per sample ``ptr[0] + i`` (of lens ``l`` for ``ptr[l] <= ptr[0] + i < ptr[l + 1]``): whether it
    lies within ``inner`` (no crosstalk) with its whole footprint passing the second stop, and for
    the others which aperture each point of its footprint sees (``code``: -1 its own, ``nb`` that of
    neighbour ``nb`` by crosstalk, -2 none, or one the stop blocks), how many see one (``n_ap``),
    and which (``used``: bit ``w`` for aperture ``w - 1``), as
    :func:`analysis.depth.render_kernels.lit_fraction` decides it."""
    n_lens = centres.shape[0]
    j_first = ptr[0] if n_lens > 0 else 0
    m = ptr[n_lens] - j_first if n_lens > 0 else 0
    n_sub = sub.shape[0]
    # A point nearer the centre than the nearest neighbour's aperture (|neigh_u| - r_ap) sees none
    # of theirs.
    nu_min = np.inf
    for nb in range(6):
        nu_min = min(nu_min, np.sqrt(neigh_u[nb, 0] * neigh_u[nb, 0] + neigh_u[nb, 1] * neigh_u[nb, 1]))
    no_neigh = max(nu_min - np.sqrt(r_ap2), 0.0) * (1.0 - 1e-9)
    s_max = 0.0
    for q in range(n_sub):
        s_max = max(s_max, np.sqrt(sub[q, 0] * sub[q, 0] + sub[q, 1] * sub[q, 1]))
    stop_r = np.sqrt(stop_r2)
    is_inner = np.empty(m, dtype=np.bool_)
    code = np.full((m, n_sub), -1, dtype=np.int8)
    n_ap = np.full(m, n_sub, dtype=np.int64)
    used = np.ones(m, dtype=np.int64)
    for lens in range(n_lens):
        kx = stop_k * centres[lens, 0]
        ky = stop_k * centres[lens, 1]
        for j in range(ptr[lens], ptr[lens + 1]):
            i = j - j_first
            u0 = uv[j, 0]
            v0 = uv[j, 1]
            clear = np.sqrt((u0 + kx) * (u0 + kx) + (v0 + ky) * (v0 + ky)) + s_max < stop_r
            is_inner[i] = u0 * u0 + v0 * v0 <= inner2 and clear
            if is_inner[i]:
                continue
            n = 0
            bits = 0
            for q in range(n_sub):
                ux = u0 + sub[q, 0]
                uy = v0 + sub[q, 1]
                lx = kx
                ly = ky
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
                            ux = vx
                            uy = vy
                            lx = stop_k * (centres[lens, 0] + neigh_s[nb, 0])
                            ly = stop_k * (centres[lens, 1] + neigh_s[nb, 1])
                            break
                if code[i, q] != -2 and not clear and (ux + lx) * (ux + lx) + (uy + ly) * (uy + ly) > stop_r2:
                    code[i, q] = -2
                if code[i, q] != -2:
                    n += 1
                    bits |= 1 << (code[i, q] + 1)
            n_ap[i] = n
            used[i] = bits
    return is_inner, code, n_ap, used


@numba.njit(cache=True)
def rim_samples(ptr, uv, is_inner, n_ap):
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
