"""numba helpers on the micro-lens lattice, for kernels that walk the sensor pixel by pixel."""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, fastmath={"nsz", "arcp", "contract", "afn", "reassoc"})
def nearest_lens(x: float, y: float, basis: np.ndarray, inverse: np.ndarray
                 ) -> tuple[int, int, float, float, float]:  # pragma: no cover - compiled
    """Lens ``(i, j)`` whose micro-image centre is nearest to ``(x, y)`` (pixels from the lattice's
    origin; ``basis`` and its ``inverse`` as :class:`analysis.camera.model.Lattice` holds them), the
    offset ``(dx, dy)`` of the point from that centre, and its square ``dx^2 + dy^2``.

    The nearest centre is one of the four corners of the lattice cell the point falls in."""
    fi0 = math.floor(inverse[0, 0] * x + inverse[0, 1] * y)
    fj0 = math.floor(inverse[1, 0] * x + inverse[1, 1] * y)
    best = np.inf
    bi = 0
    bj = 0
    bx = 0.0
    by = 0.0
    for di in range(2):
        for dj in range(2):
            dx = x - (basis[0, 0] * (fi0 + di) + basis[0, 1] * (fj0 + dj))
            dy = y - (basis[1, 0] * (fi0 + di) + basis[1, 1] * (fj0 + dj))
            d = dx * dx + dy * dy
            if d < best:
                best = d
                bi = int(fi0 + di)
                bj = int(fj0 + dj)
                bx = dx
                by = dy
    return bi, bj, bx, by, best
