"""How well a particle table pins each particle's depth, from its own columns.

Lateral positions are good to about 1 % of the inter-particle distance; depth is 5 to 10 times
worse, and where one micro-lens holds all of a particle's light (``blur_pitches`` below about
1) the pixels leave its depth open over the whole range in which its blur stays inside one
lens, in front of focus or behind (README, "Accuracy and speed"). The table says both:

- ``alpha_std``: the spread of ``alpha`` over the depths the raw pixels allow (with the
  neighbours' depth prior, where ``prior_std`` is finite), turned into mm
  with the table's own ``alpha -> Z`` relation (``Z`` depends on ``alpha`` alone, for the thin
  lens and for a user calibration alike, so a fit of ``Z`` against ``alpha`` over the table's rows
  gives the slope);
- ``blur_pitches``: below ``open_blur_pitches`` the depth is open over the interval of ``alpha``
  where the blur is under that size (``blur = k |1 - 1/alpha|``, ``k`` from the rows themselves).

Linking then measures the depth gap between two such intervals, not between two points.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np


@dataclass(frozen=True)
class DepthErrors:
    """Per particle: an extra depth standard deviation (mm) from ``alpha_std`` (beyond the table's
    median, which the linker's measured step spread already holds) and the interval of
    depths ``[z_low, z_high]`` (mm) its pixels leave open (``z_low = z_high = Z`` when settled)."""

    extra_sigma_mm: np.ndarray
    z_low: np.ndarray
    z_high: np.ndarray

    @property
    def open(self) -> np.ndarray:
        return self.z_high > self.z_low

    @classmethod
    def none(cls, z: np.ndarray) -> DepthErrors:
        z = np.asarray(z, float)
        return cls(np.zeros(len(z)), z.copy(), z.copy())

    def take(self, index: np.ndarray) -> DepthErrors:
        return DepthErrors(self.extra_sigma_mm[index], self.z_low[index], self.z_high[index])


def depth_errors(table: Mapping[str, np.ndarray], *, open_blur_pitches: float = 1.0) -> DepthErrors:
    """The depth uncertainty of each row of a particle table (see the module docstring).

    Parameters
    ----------
    table : mapping of str to ndarray
        Needs ``Z``; uses ``alpha``, ``alpha_std`` and ``blur_pitches`` where present.
    open_blur_pitches : float
        Below this blur diameter (lens pitches) a particle's depth counts as open.

    Returns
    -------
    DepthErrors
    """
    z = np.asarray(table["Z"], float)
    out = DepthErrors.none(z)
    alpha = np.asarray(table["alpha"], float) if "alpha" in table else None
    if alpha is None or len(z) == 0:
        return out
    fit = _inverse_fit(alpha, z)
    if fit is None:
        return out
    p, q = fit
    slope = np.abs(q) / (p + q / alpha) ** 2 / alpha ** 2  # |dZ/dalpha| of Z = 1 / (p + q / alpha)
    extra = np.zeros(len(z))
    if "alpha_std" in table:
        spread = np.asarray(table["alpha_std"], float)
        sigma = np.where(np.isfinite(spread) & np.isfinite(slope), spread * slope, 0.0)
        # The run's typical depth error is in the step spread the linker measures; only what a
        # particle has beyond the table's typical one is added for it.
        typical = float(np.median(sigma ** 2)) if len(sigma) else 0.0
        extra = np.sqrt(np.maximum(sigma ** 2 - typical, 0.0))
    low, high = z.copy(), z.copy()
    if "blur_pitches" in table:
        blur = np.asarray(table["blur_pitches"], float)
        defocus = np.abs(1.0 - 1.0 / alpha)
        usable = np.isfinite(blur) & (defocus > 1e-6) & (blur > 0.2)
        is_open = np.isfinite(blur) & (blur < open_blur_pitches) & np.isfinite(z)
        if usable.any() and is_open.any():
            k = float(np.median(blur[usable] / defocus[usable]))  # blur per unit |1 - 1/alpha|
            half = open_blur_pitches / k
            ends = 1.0 / (p + q * (1.0 - np.array([-half, half])))  # 1/alpha = 1 -+ half
            low[is_open] = np.minimum(ends.min(), z[is_open])
            high[is_open] = np.maximum(ends.max(), z[is_open])
    return DepthErrors(extra, low, high)


def _inverse_fit(alpha: np.ndarray, z: np.ndarray) -> tuple[float, float] | None:
    """``(p, q)`` of ``1/Z = p + q/alpha`` fitted to the rows: exact for the thin lens, and close
    for a user calibration (``Z`` linear in ``alpha``) over a table's narrow range of alpha."""
    ok = np.isfinite(alpha) & np.isfinite(z) & (z > 0) & (alpha > 0)
    if np.unique(np.round(alpha[ok], 9)).size < 2:
        return None
    q, p = np.polyfit(1.0 / alpha[ok], 1.0 / z[ok], 1)
    return float(p), float(q)
