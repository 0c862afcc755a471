"""numba kernels of the realistic camera: arrays and scalars in, caller-allocated outputs filled.

``paint_micro_images`` lays each micro-image as the aperture seen through a second stop (the
intersection of two disks) with a pixel response falling toward the rim. ``trace_extended_sources``
renders out-of-focus extended light (a reflected laser band, glints) by following, for points
inside each pixel, the ray back through its micro-lens and the main lens to the source's plane.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from analysis.camera.lattice_kernels import nearest_lens

# fastmath without nnan/ninf (style guide): infinities and NaNs keep their meaning; the second
# stop's radius is +inf when there is none.
_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}

BAND = 0
GLINT = 1


@njit(cache=True, fastmath=_FASTMATH)
def _response(rho2_px: float, tan_per_px: float, half_n: float) -> float:  # pragma: no cover - compiled
    """``cos(theta)^n`` with ``tan(theta) = rho * tan_per_px``: ``(1 + tan^2)^(-n/2)``."""
    if half_n == 0.0:
        return 1.0
    return (1.0 + rho2_px * tan_per_px * tan_per_px) ** (-half_n)


@njit(cache=True, fastmath=_FASTMATH)
def paint_micro_images(out: np.ndarray, cx: np.ndarray, cy: np.ndarray, value: np.ndarray, radius: float,
                       stop_dx: np.ndarray, stop_dy: np.ndarray, radius2: float, tan_per_px: float,
                       half_n: float, supersample: int) -> None:  # pragma: no cover - compiled
    """Add micro-image ``k``: ``value[k]`` times the pixel response over the part of each pixel
    inside both the disk of ``radius`` about ``(cx, cy)[k]`` and the disk of ``radius2`` about
    ``(cx + stop_dx, cy + stop_dy)[k]`` (``radius2 = inf``: no second stop).

    The response at offset ``rho`` from the micro-image centre is ``(1 + (rho tan_per_px)^2)^-half_n``.
    Pixels clearly inside both disks take the response at their centre; pixels on either rim
    are supersampled ``supersample`` x ``supersample`` for the area inside, and take the response
    at the mean ``rho^2`` of the points inside. Serial on purpose: neighbouring rims may touch the
    same pixel.
    """
    h, w = out.shape
    n = supersample
    inv_n = 1.0 / n
    r2 = radius * radius
    q2 = radius2 * radius2
    inner = radius - 0.7072
    outer = radius + 0.7072
    inner2 = radius2 - 0.7072
    outer2 = radius2 + 0.7072
    for k in range(cx.size):
        x0 = cx[k]
        y0 = cy[k]
        x2 = x0 + stop_dx[k]
        y2 = y0 + stop_dy[k]
        c0 = max(int(math.floor(x0 - radius - 1.0)), 0)
        c1 = min(int(math.ceil(x0 + radius + 1.0)), w)
        row0 = max(int(math.floor(y0 - radius - 1.0)), 0)
        row1 = min(int(math.ceil(y0 + radius + 1.0)), h)
        v = value[k]
        for r in range(row0, row1):
            dy = r + 0.5 - y0
            dy2 = r + 0.5 - y2
            for c in range(c0, c1):
                dx = c + 0.5 - x0
                rho_sq = dx * dx + dy * dy
                rho = math.sqrt(rho_sq)
                if rho >= outer:
                    continue
                dx2 = c + 0.5 - x2
                rho2 = math.sqrt(dx2 * dx2 + dy2 * dy2)
                if rho2 >= outer2:
                    continue
                if rho <= inner and rho2 <= inner2:
                    out[r, c] += v * _response(rho_sq, tan_per_px, half_n)
                    continue
                hits = 0
                rho_sum = 0.0
                for a in range(n):
                    sy = r + (a + 0.5) * inv_n
                    sy1 = sy - y0
                    sy2 = sy - y2
                    for b in range(n):
                        sx = c + (b + 0.5) * inv_n
                        sx1 = sx - x0
                        sx2 = sx - x2
                        d1 = sx1 * sx1 + sy1 * sy1
                        if d1 <= r2 and sx2 * sx2 + sy2 * sy2 <= q2:
                            hits += 1
                            rho_sum += d1
                if hits:
                    out[r, c] += v * hits * inv_n * inv_n * _response(rho_sum / hits, tan_per_px, half_n)


@njit(cache=True, fastmath=_FASTMATH)
def _source_radiance(source: np.ndarray, x_mm: float, y_mm: float) -> float:  # pragma: no cover - compiled
    """Radiance of one source (a row of `trace_extended_sources`) at object point ``(x_mm, y_mm)``."""
    ex = x_mm - source[3]
    ey = y_mm - source[4]
    half_inv_var = 0.5 / (source[5] * source[5])
    if source[0] == BAND:
        ca = source[11]
        sa = source[12]
        across = -ex * sa + ey * ca
        along = ex * ca + ey * sa
        return source[6] * math.exp(-across * across * half_inv_var) * (
            1.0 + source[8] * math.cos(2.0 * math.pi * along / source[9] + source[10]))
    return source[6] * math.exp(-(ex * ex + ey * ey) * half_inv_var)


@njit(cache=True, fastmath=_FASTMATH, parallel=True)
def trace_extended_sources(out: np.ndarray, row0: int, row1: int, col0: int, col1: int,
                           origin_x: float, origin_y: float, basis: np.ndarray, inverse: np.ndarray,
                           axis_x: float, axis_y: float, optics: np.ndarray, gain: np.ndarray, gain_i0: int,
                           gain_j0: int, cell_dx: np.ndarray, cell_dy: np.ndarray, sources: np.ndarray,
                           supersample: int) -> None:  # pragma: no cover - compiled
    """Add the light of extended sources to ``out[row0:row1, col0:col1]`` (DN, as a green site).

    For ``supersample`` x ``supersample`` points ``q`` in each pixel: the nearest micro-image
    (lattice ``origin``, ``basis``, ``inverse``) gives the lens and the aperture point
    ``u = -(q - centre) p P / d`` (camera-model.md step 3 backwards). Rays outside the aperture
    or the second stop carry nothing. For each point ``s`` of the lens's cell (its physical centre
    plus ``cell_d*``, metres), the ray from ``u`` through ``s`` meets a source's image plane at
    ``u + (s - u) Fp/P``, the source's own plane at that times ``Z/Fp``; the pixel takes the mean
    radiance there, times the lens's chief-ray ``cos^4``, its transmission ``gain`` and the pixel
    response.

    ``optics`` = ``[P, d, pixel pitch, (P+d)/P, aperture radius, stop shift k, stop radius
    (inf: none), tan_per_px, half_n]`` (metres). ``sources`` rows = ``[kind, Fp/P, Z/Fp (mm per
    metre), x0, y0, sigma, level, angle, amp, period, phase, cos(angle), sin(angle)]`` (mm, DN, rad).
    """
    p_m = optics[0]
    d_m = optics[1]
    pix = optics[2]
    proj = optics[3]
    ap_r = optics[4]
    stop_k = optics[5]
    stop_r = optics[6]
    tan_per_px = optics[7]
    half_n = optics[8]
    px_to_ap = pix * p_m / d_m
    px_to_mla = pix / proj
    n = supersample
    inv_n = 1.0 / n
    n_cell = cell_dx.size
    gh, gw = gain.shape
    norm = 1.0 / (n * n * n_cell)
    for r in prange(row0, row1):
        for c in range(col0, col1):
            acc = 0.0
            for a in range(n):
                qy = r + (a + 0.5) * inv_n
                for b in range(n):
                    qx = c + (b + 0.5) * inv_n
                    i, j, ox, oy, _ = nearest_lens(qx - origin_x, qy - origin_y, basis, inverse)
                    mx = qx - ox
                    my = qy - oy
                    ux = -ox * px_to_ap
                    uy = -oy * px_to_ap
                    if ux * ux + uy * uy > ap_r * ap_r:
                        continue
                    sx = (mx - axis_x) * px_to_mla
                    sy = (my - axis_y) * px_to_mla
                    wx = ux + stop_k * sx
                    wy = uy + stop_k * sy
                    if wx * wx + wy * wy > stop_r * stop_r:
                        continue
                    cos2 = p_m * p_m / (p_m * p_m + sx * sx + sy * sy)
                    weight = cos2 * cos2 * _response(ox * ox + oy * oy, tan_per_px, half_n)
                    gi = i - gain_i0
                    gj = j - gain_j0
                    if 0 <= gi < gw and 0 <= gj < gh:
                        weight *= gain[gj, gi]
                    for s in range(sources.shape[0]):
                        t = sources[s, 1]
                        scale = sources[s, 2]
                        # Object point of the ray through the cell's centre; the cell's points add t * scale * delta.
                        bx = (ux + (sx - ux) * t) * scale
                        by = (uy + (sy - uy) * t) * scale
                        for e in range(n_cell):
                            acc += weight * _source_radiance(sources[s], bx + cell_dx[e] * t * scale,
                                                             by + cell_dy[e] * t * scale)
            out[r, c] += acc * norm
