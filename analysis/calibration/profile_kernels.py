"""numba kernels of the micro-image profile fit (:mod:`analysis.calibration.profile`): arrays and
scalars in, caller-allocated outputs filled."""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from analysis.camera.lattice_kernels import nearest_lens

# fastmath without nnan/ninf (style guide): NaN marks pixels left out.
_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@njit(cache=True, fastmath=_FASTMATH)
def cell_sums(image: np.ndarray, origin_x: float, origin_y: float, basis: np.ndarray, inverse: np.ndarray,
              i0: int, j0: int, r_inner: float, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Per lens cell (the pixels nearest to lens ``(i0 + a, j0 + b)``'s micro-image centre on the
    lattice of ``origin``, ``basis`` and its ``inverse``): ``out[b, a] += (light, light * dx,
    light * dy, light within r_inner, pixels within r_inner, pixels, NaN pixels)``, ``(dx, dy)``
    the pixel centre's offset from the micro-image centre. Serial: cells share no pixel, but rows do.
    """
    h, w = image.shape
    nb, na = out.shape[0], out.shape[1]
    ri2 = r_inner * r_inner
    for r in range(h):
        y = r + 0.5 - origin_y
        for c in range(w):
            x = c + 0.5 - origin_x
            bi, bj, bx, by, best = nearest_lens(x, y, basis, inverse)
            a = bi - i0
            b = bj - j0
            if a < 0 or b < 0 or a >= na or b >= nb:
                continue
            v = image[r, c]
            out[b, a, 5] += 1.0
            if not math.isfinite(v):
                out[b, a, 6] += 1.0
                continue
            out[b, a, 0] += v
            out[b, a, 1] += v * bx
            out[b, a, 2] += v * by
            if best <= ri2:
                out[b, a, 3] += v
                out[b, a, 4] += 1.0


@njit(cache=True, parallel=True, fastmath=_FASTMATH)
def sample_template(template: np.ndarray, step: float, dx: np.ndarray, dy: np.ndarray,
                    out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Bilinear interpolation of ``template`` (a square grid of spacing ``step`` px, centred on its
    middle sample ``n // 2``) at offsets ``(dx, dy)``; 0 outside it."""
    n = template.shape[0]
    half = n // 2
    inv = 1.0 / step
    for k in prange(dx.size):
        gx = dx[k] * inv + half
        gy = dy[k] * inv + half
        x0 = int(math.floor(gx))
        y0 = int(math.floor(gy))
        if x0 < 0 or y0 < 0 or x0 >= n - 1 or y0 >= n - 1:
            out[k] = 0.0
            continue
        tx = gx - x0
        ty = gy - y0
        out[k] = ((template[y0, x0] * (1.0 - tx) + template[y0, x0 + 1] * tx) * (1.0 - ty)
                  + (template[y0 + 1, x0] * (1.0 - tx) + template[y0 + 1, x0 + 1] * tx) * ty)
