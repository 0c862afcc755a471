"""What a grid pass of the depth fit (:mod:`analysis.depth.rayfit_kernels`) makes of its candidates:
the intensity of a candidate some of whose samples are censored (saturated), and the depth at the
vertex of the depth profile. Numba kernels on scalars and arrays.
"""

from __future__ import annotations

import numba
import numpy as np

#: The fast-math flags of the depth fit's kernels (here and in its other kernel modules).
FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@numba.njit(cache=True, fastmath=FASTMATH)
def censored_intensity(s_vf, s_ff, sum_v2, cens_v, cens_f, walked):
    """A candidate's cost and intensity with the censored samples as lower bounds: the intensity
    that minimises the others' squared misfit plus ``max(0, v_c - I f_c)^2`` for each bound the
    prediction falls short of, and that cost. The cost is convex and quadratic between the
    bounds' break points ``v_c / f_c``; walking them down from the top finds its minimum
    (``walked``: a work array as long as ``cens_v``).
    (Raising the intensity to the highest break point instead lets a candidate that lights dark
    samples fully and a saturated one slightly take an intensity of tens of thousands: a ghost
    whose relative misfit looks small and whose light then hides the saturated particle.)"""
    for c in range(cens_v.size):
        walked[c] = not (cens_f[c] > 0.0 and cens_v[c] > 0.0)
    a = s_ff
    b = s_vf
    inten = max(b / a, 0.0) if a > 0.0 else 0.0
    while True:
        top = -1
        upper = -1.0
        for c in range(cens_v.size):  # the highest break point not walked past (few: no sort)
            if not walked[c] and cens_v[c] / cens_f[c] > upper:
                upper = cens_v[c] / cens_f[c]
                top = c
        if top < 0 or (a > 0.0 and inten >= upper):
            break  # the minimum lies above this break point: its bound is met
        walked[top] = True
        a += cens_f[top] * cens_f[top]
        b += cens_f[top] * cens_v[top]
        inten = min(max(b / a, 0.0), upper)
    cost = sum_v2 - 2.0 * inten * s_vf + inten * inten * s_ff
    for c in range(cens_v.size):
        short = cens_v[c] - inten * cens_f[c]
        if short > 0.0:
            cost += short * short
    return cost, inten


@numba.njit(cache=True, fastmath=FASTMATH)
def profile_vertex(costs, best, n_depths, n_pos, c_lo, c_hi, scale, mean_c, c_prior, prior_k, prior_floor):
    """The depth ``c`` at the vertex of a parabola fitted to the depth profile: at each depth, the
    costs of its ``n_pos`` positions marginalised at the candidates' temperature (``scale``), plus
    the depth prior's (as the candidates weigh it: ``prior_k`` 0 is none), fitted by least squares
    weighted as the candidates are; clipped to the window. Where the parabola opens downward,
    ``mean_c`` (the tempered mean), or at the window's ends the lowest depth.

    Why not the tempered mean: a strongly blurred particle's cost rises more slowly toward focus
    (larger patches per lens) than away from it, so the mean over a window leans toward focus; on
    noise-free isolated particles blurred over 10-16 pitches, told a 1.2 px blur, by 2.5-4 % of
    ``c``. The vertex of the three lowest profile points alone was as unbiased, but noisier: through
    ideal optics it added a tenth to the off-focus ball's depth error."""
    base = costs[best]
    step = (c_hi - c_lo) / max(n_depths - 1, 1)
    profile = np.empty(n_depths)
    for ic in range(n_depths):
        acc = 0.0
        for q in range(ic * n_pos, (ic + 1) * n_pos):
            acc += np.exp(-(costs[q] - base) / scale)
        dc = c_lo + step * ic - c_prior
        acc *= np.exp(-prior_k * dc * dc) + prior_floor
        profile[ic] = -scale * np.log(max(acc, 1e-300))
    ib = np.argmin(profile)
    # Weighted least squares of profile - profile[ib] = a x^2 + b x + c0, x in depth steps from ib.
    m = np.zeros((3, 3))
    rhs = np.zeros(3)
    for ic in range(n_depths):
        w = np.exp(-(profile[ic] - profile[ib]) / scale)
        x = float(ic - ib)
        y = profile[ic] - profile[ib]
        powers = np.array([x * x, x, 1.0])
        for r in range(3):
            rhs[r] += w * powers[r] * y
            for k in range(3):
                m[r, k] += w * powers[r] * powers[k]
    if abs(np.linalg.det(m)) < 1e-12 * m[0, 0] * m[1, 1] * m[2, 2]:
        return mean_c
    a, b, _ = np.linalg.solve(m, rhs)
    if a <= 0.0:
        # At the window's end the lowest depth itself, so that a recentred pass goes on.
        return c_lo + step * ib if ib == 0 or ib == n_depths - 1 else mean_c
    x = min(max(-b / (2.0 * a), -float(ib)), float(n_depths - 1 - ib))
    return c_lo + step * (ib + x)
