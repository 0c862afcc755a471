"""numba helpers for order statistics of the few values a kernel gathers per pixel or lens."""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def median_in_place(values: np.ndarray, n: int) -> float:  # pragma: no cover - compiled
    """Median of ``values[:n]`` (tens of values at most), by insertion sort: ``values[:n]`` is left sorted."""
    for a in range(1, n):
        v = values[a]
        b = a - 1
        while b >= 0 and values[b] > v:
            values[b + 1] = values[b]
            b -= 1
        values[b + 1] = v
    if n % 2:
        return values[n // 2]
    return 0.5 * (values[n // 2 - 1] + values[n // 2])
