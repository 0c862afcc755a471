"""numba kernels of the simulator: arrays and scalars in, caller-allocated outputs filled."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# fastmath without nnan/ninf (style guide): infinities and NaNs keep their meaning.
_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}


@njit(cache=True, fastmath=_FASTMATH)
def paint_disks(out: np.ndarray, cx: np.ndarray, cy: np.ndarray, value: np.ndarray,
                radius: float, supersample: int) -> None:  # pragma: no cover - compiled
    """Add ``value[k] * (fraction of each pixel inside disk k)`` to ``out`` (H, W).

    Pixels whose centre is clearly inside (outside) count as 1 (0); pixels on the rim are
    supersampled ``supersample`` x ``supersample``. Serial on purpose: neighbouring rims may
    touch the same pixel.
    """
    h, w = out.shape
    n = supersample
    inner = radius - 0.7072
    outer = radius + 0.7072
    r2 = radius * radius
    inv_n = 1.0 / n
    for k in range(cx.size):
        x0 = cx[k]
        y0 = cy[k]
        c0 = max(int(math.floor(x0 - radius - 1.0)), 0)
        c1 = min(int(math.ceil(x0 + radius + 1.0)), w)
        row0 = max(int(math.floor(y0 - radius - 1.0)), 0)
        row1 = min(int(math.ceil(y0 + radius + 1.0)), h)
        v = value[k]
        for r in range(row0, row1):
            dy = r + 0.5 - y0
            for c in range(c0, c1):
                dx = c + 0.5 - x0
                rho = math.sqrt(dx * dx + dy * dy)
                if rho >= outer:
                    continue
                if rho <= inner:
                    out[r, c] += v
                    continue
                hits = 0
                for a in range(n):
                    sy = r + (a + 0.5) * inv_n - y0
                    for b in range(n):
                        sx = c + (b + 0.5) * inv_n - x0
                        if sx * sx + sy * sy <= r2:
                            hits += 1
                out[r, c] += v * hits * inv_n * inv_n
