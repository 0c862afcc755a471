"""A second stop of the main lens (a barrel, a front-element rim): mechanical vignetting.

Seen from a point ``s`` on the micro-lens array (metres from the optical axis), the main lens's
aperture is cut by a second, shifted disk: the rays through aperture point ``u`` (metres) pass
where ``|u + shift_per_m * s| <= radius_m``. Toward the sensor's corners the micro-images become
cat's eyes, the intersection of two disks. A stop of radius ``R2`` a distance ``z2`` behind the
aperture (toward the MLA, which lies ``P`` behind it) projects so, with ``shift_per_m = z2 / (P - z2)``
and ``radius_m = R2 P / (P - z2)``.

The simulator renders with one (:mod:`analysis.simulation.camera_effects`); the calibration fits
one to a white image's micro-image areas (:func:`analysis.calibration.second_stop_fit.fit_second_stop`),
and the depth fit counts a ray only where it passes (:mod:`analysis.depth.render_kernels`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr


@dataclass(frozen=True)
class SecondStop:
    """The second stop as seen on the aperture plane (see the module's docstring)."""

    shift_per_m: float
    radius_m: float

    def physical(self, lens_to_mla_m: float) -> dict[str, float]:
        """Distance behind the aperture and radius of the stop itself, metres."""
        z2 = self.shift_per_m * lens_to_mla_m / (1.0 + self.shift_per_m)
        return {"distance_behind_aperture_m": z2, "radius_m": self.radius_m * (lens_to_mla_m - z2) / lens_to_mla_m}

    def to_dict(self) -> dict[str, float]:
        return {"shift_per_m": self.shift_per_m, "radius_m": self.radius_m}

    @classmethod
    def from_dict(cls, doc: dict[str, float]) -> "SecondStop":
        return cls(shift_per_m=float(doc["shift_per_m"]), radius_m=float(doc["radius_m"]))


def visible_fraction(aperture_radius_m: float, stop_radius_m: float, shift_m: np.ndarray,
                     response_k: float = 0.0, n_rings: int = 48, within_m: float | None = None,
                     blur_m: float = 0.0) -> np.ndarray:
    """Share of a micro-image's light that passes a stop of ``stop_radius_m`` shifted ``shift_m``
    (``shift_per_m * |s|``, one per lens) from the aperture of ``aperture_radius_m``, each aperture
    point counted by the pixel response ``exp(response_k |u|^2)`` (``u`` in metres; 0: alike), as
    a white image's micro-image areas measure it; of the aperture points within ``within_m`` of its
    centre only, when given, with the stop's edge blurred by a Gaussian of ``blur_m`` (the optical
    blur in aperture metres: what a micro-image's centre receives from across a cut's edge)."""
    # Aperture points on rings of equal area, each ring sampled at angles spaced by about its width.
    reach = aperture_radius_m if within_m is None else min(within_m, aperture_radius_m)
    r = reach * np.sqrt((np.arange(n_rings) + 0.5) / n_rings)
    points, weights = [], []
    for radius in r:
        n = max(8, int(round(2 * np.pi * radius / reach * n_rings)))
        theta = 2 * np.pi * (np.arange(n) + 0.5) / n
        points.append(np.column_stack([radius * np.cos(theta), radius * np.sin(theta)]))
        weights.append(np.full(n, np.exp(response_k * radius * radius) / n))
    u = np.concatenate(points)
    w = np.concatenate(weights)
    shift = np.atleast_1d(np.asarray(shift_m, dtype=np.float64))
    # The shift's direction does not change the share: take it along x. Points within half a ring's
    # width of the stop's edge pass in part, so that the share changes smoothly with the stop (a fit's
    # derivatives).
    edge = 0.5 * reach / n_rings
    beyond = np.hypot(u[None, :, 0] + shift[:, None], u[None, :, 1]) - stop_radius_m
    if blur_m > 0:
        passes = ndtr(-beyond / math.hypot(blur_m, edge))
    else:
        passes = np.clip(0.5 - beyond / (2.0 * edge), 0.0, 1.0)
    return (passes * w).sum(axis=1) / w.sum()
