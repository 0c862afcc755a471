"""numba kernels of the depth floor (:func:`analysis.simulation.scoring.pixel_limited_alpha`).

Geometry on an ideal hexagonal lattice of unit pitch: lens ``(i, j)`` is centred at
``(i + j / 2, j sqrt(3) / 2)``, and a point belongs to the cell of its nearest centre.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

_ROW = math.sqrt(3.0) / 2.0


@njit(cache=True, inline="always")
def lens_code(x: float, y: float) -> int:  # pragma: no cover - compiled
    """The lens whose cell holds ``(x, y)``, as one integer (``i * 1024 + j``; near the origin)."""
    fj = y / _ROW
    fi = x - 0.5 * fj
    i0 = math.floor(fi)
    j0 = math.floor(fj)
    best = math.inf
    code = 0
    # The nearest centre is a corner of the lattice cell holding the point.
    for di in range(2):
        for dj in range(2):
            cx = (i0 + di) + 0.5 * (j0 + dj)
            cy = (j0 + dj) * _ROW
            d = (cx - x) ** 2 + (cy - y) ** 2
            if d < best:
                best = d
                code = int(i0 + di) * 1024 + int(j0 + dj)
    return code


@njit(cache=True)
def lit_pattern(points: np.ndarray, x: float, y: float, radius: float, out: np.ndarray) -> None:  # pragma: no cover
    """``out[m]``: the lens reached by the ray of aperture point ``points[m]`` (unit disk) of a
    particle at ``(x, y)`` whose signed blur radius is ``radius`` (pitches)."""
    for m in range(points.shape[0]):
        out[m] = lens_code(x + radius * points[m, 0], y + radius * points[m, 1])


@njit(cache=True, parallel=True)
def same_pattern_counts(points: np.ndarray, reference: np.ndarray, x0: float, y0: float, radii: np.ndarray,
                        half_width: float, step: float, max_mismatch: int,
                        counts: np.ndarray) -> None:  # pragma: no cover - compiled
    """``counts[k]``: positions of a square grid (``x0, y0 +- half_width``, ``step`` apart) at which
    a particle of signed blur radius ``radii[k]`` lights ``reference`` but for at most
    ``max_mismatch`` aperture points. Each radius writes only its own count."""
    n = int(round(2.0 * half_width / step)) + 1
    for k in prange(radii.size):
        r = radii[k]
        c = 0
        for a in range(n):
            x = x0 - half_width + a * step
            for b in range(n):
                y = y0 - half_width + b * step
                miss = 0
                for m in range(points.shape[0]):
                    if lens_code(x + r * points[m, 0], y + r * points[m, 1]) != reference[m]:
                        miss += 1
                        if miss > max_mismatch:
                            break
                if miss <= max_mismatch:
                    c += 1
        counts[k] = c
