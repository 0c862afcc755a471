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


@njit(cache=True, inline="always")
def median_of_5(a: float, b: float, c: float, d: float, e: float) -> float:  # pragma: no cover - compiled
    """Median of five values (no NaN) by minima and maxima only: no branches to mispredict, three
    times quicker than sorting them where a kernel takes millions of such medians."""
    f = max(min(a, b), min(c, d))  # neither can be the least of a ... d, which is not the median
    g = min(max(a, b), max(c, d))  # nor the greatest
    return max(min(e, f), min(max(e, f), g))  # the median of e, f, g
