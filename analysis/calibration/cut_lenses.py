"""Micro-images a second stop cuts: toward the sensor's corners the main lens's aperture, seen
through a second stop (a barrel, a front-element rim), is the intersection of two disks, and the
micro-images are cat's eyes.

A cut micro-image holds less light than a full one of the same central level, whatever its lens's
gain; and its centroid, like the phase of its pattern, moves toward the uncut side, while the lens's
optical centre (where the aperture's centre lands, what the lattice and every sample's aperture
point are measured from) stays. The fits of the lattice and of the micro-image profile leave such
micro-images out.
"""

from __future__ import annotations

import numpy as np

from analysis.camera.model import Lattice

from .profile_kernels import cell_sums

#: A micro-image is of full shape when its area (light of its cell over its central level) is within
#: this fraction (or three times the areas' own spread) of the largest areas on the sensor.
AREA_TOLERANCE = 0.015


def cell_areas(image: np.ndarray, lattice: Lattice, ij: np.ndarray, *, radius_px: float) -> np.ndarray:
    """Per lens ``ij`` (n, 2): the light of its cell over its central level (the mean within half
    ``radius_px`` of its centre), px^2; NaN for cells with a NaN pixel (left out) or no light.

    ``image``: the white image with its channels balanced (float, NaN where pixels are left out).
    """
    i0, j0 = ij.min(axis=0)
    span = ij.max(axis=0) - ij.min(axis=0) + 1
    sums = np.zeros((span[1], span[0], 7))
    cell_sums(image, lattice.origin_x, lattice.origin_y, lattice.basis, np.linalg.inv(lattice.basis), int(i0), int(j0),
              0.5 * radius_px, sums)
    s = sums[ij[:, 1] - j0, ij[:, 0] - i0]
    with np.errstate(invalid="ignore", divide="ignore"):
        area = s[:, 0] / (s[:, 3] / s[:, 4])
    area[(s[:, 6] > 0) | ~(s[:, 3] > 0)] = np.nan
    return area


def full_shape(area: np.ndarray, central: np.ndarray) -> np.ndarray:
    """Which micro-images (a mask over ``area``) are of full shape: within :data:`AREA_TOLERANCE`,
    or three times the spread of the ``central`` ones' areas (a mask or indices), of the largest
    areas (their 90th percentile). NaN areas are not."""
    finite = np.isfinite(area)
    if not finite.any():
        return finite
    reference = float(np.percentile(area[finite], 90))
    near = area[central]
    near = near[np.isfinite(near)]
    spread = 1.4826 * float(np.median(np.abs(near - np.median(near)))) if near.size else 0.0
    tolerance = max(AREA_TOLERANCE, 3.0 * spread / reference)
    return finite & (area >= (1.0 - tolerance) * reference)
