"""The main lens's second stop, from how a white image's micro-images shrink toward the corners.

A cat's-eye micro-image (:mod:`analysis.calibration.cut_lenses`) holds the light of the aperture
points that pass the stop (:class:`analysis.camera.second_stop.SecondStop`). Its area over its
central level, against its lens's distance from the optical axis, follows the share of the
aperture a disk of radius ``R2`` shifted by ``k |s|`` leaves; two numbers, ``k`` and ``R2``, fitted
to the median area of the lenses at each distance. The depth fit needs them: the devignetted
samples of a cut micro-image are light per unit of what passes the stop, and a model that lets the
whole aperture light them reads the particles there nearer focus than they are (by 0.5-0.7e-4 in
alpha beyond the stop's onset with the simulator's typical stop, twice the ideal optics' bias).
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.optimize import least_squares

from analysis.camera.model import CameraModel
from analysis.camera.second_stop import SecondStop, visible_fraction

from .cut_lenses import AREA_TOLERANCE, cell_areas
from .lattice_fit import balance_channels

log = logging.getLogger(__name__)

#: Distance bins from the optical axis (over the farthest lens's distance), and the fewest lenses
#: a bin's median needs.
N_BINS = 40
MIN_BIN_LENSES = 20
#: No stop is fitted unless some bin's median area is below this share of the central ones'.
MIN_CUT = 1.0 - 2.0 * AREA_TOLERANCE
#: The fit takes the bins whose median area is at least this share, and needs this many of them cut.
SHALLOW_CUT = 0.85
MIN_CUT_BINS = 4
#: A fit whose binned areas it misses by more than this (rms share) is not used.
MAX_MISFIT = 0.01


def fit_second_stop(raw: np.ndarray, model: CameraModel, *, radius_px: float, response_slope: float = 0.0,
                    blur_px: float = 0.0) -> SecondStop | None:
    """The second stop of the white image ``raw`` (of ``model``, its fitted lattice), or None when
    its micro-images show none (or none that two disks explain).

    ``radius_px``: the micro-images' radius; ``response_slope``: the pixel response's
    ``ln(response)`` per squared pixel of offset (:attr:`analysis.calibration.calibrate.Calibration.response_slope`):
    a cut takes the rim's light, which counts less than the centre's; ``blur_px``: the optical blur,
    which carries a cut's edge into the central level that the areas are measured against. Saturated pixels are left out;
    the camera's defects are not known yet, and each bin's median stands against them."""
    h, w = raw.shape
    lattice = model.lattice
    image = balance_channels(raw, black_level=model.black_level)
    image[raw >= model.white_level] = np.nan
    ij, _ = lattice.centres(w, h, margin_px=lattice.pitch_px)
    if len(ij) < N_BINS * MIN_BIN_LENSES:
        return None
    area = cell_areas(image, lattice, ij, radius_px=radius_px)
    del image
    s = np.hypot(*model.lens_plane_position_m(ij[:, 0], ij[:, 1]))
    distance, share = _binned_shares(s, area)
    if distance is None or share.min() > MIN_CUT:
        return None
    k_ap = model.optics.aperture_m_per_px
    aperture_r = radius_px * k_ap
    response_k = response_slope / (k_ap * k_ap)
    far = float(distance[-1])  # the farthest bin, fixed before the deep ones are left out

    def shares(p: np.ndarray, n_rings: int = 32) -> np.ndarray:
        # As cell_areas measures them: the light over the central level, which a deep cut lowers too.
        q, r2, scale = p
        shift = np.r_[0.0, q * aperture_r * distance / far]
        light = visible_fraction(aperture_r, r2 * aperture_r, shift, response_k, n_rings)
        central = visible_fraction(aperture_r, r2 * aperture_r, shift, response_k, n_rings,
                                   within_m=0.5 * aperture_r, blur_m=blur_px * k_ap)
        return scale * (light[1:] / light[0]) / np.maximum(central[1:] / central[0], 1e-3)

    # Deep cuts measure larger than the share a two-disk stop leaves (by 2.7 % at 0.73 on the
    # simulator's white images, whose stop is one): the fit takes the shallower ones.
    use = share >= SHALLOW_CUT
    if np.count_nonzero(use & (share <= MIN_CUT)) < MIN_CUT_BINS:
        return None
    distance, share = distance[use], share[use]
    # Start from the best of a coarse grid (the misfit has flat valleys where the stop misses the sensor).
    grid = [(q, r2) for q in np.linspace(0.1, 4.0, 14) for r2 in np.linspace(1.0, 4.0, 13)]
    start = min(grid, key=lambda g: float(np.sum((shares(np.array([*g, 1.0]), 12) - share) ** 2)))
    fit = least_squares(lambda p: shares(p) - share, x0=[*start, 1.0],
                        bounds=([0.0, 1.0, 0.8], [10.0, 10.0, 1.2]))
    misfit = float(np.sqrt(np.mean(fit.fun ** 2)))
    q, r2, _ = fit.x
    stop = SecondStop(shift_per_m=float(q * aperture_r / far), radius_m=float(r2 * aperture_r))
    if misfit > MAX_MISFIT or (r2 - 1.0) >= q:  # unexplained, or cutting no lens on the sensor
        log.warning("white image: micro-images shrink toward the corners (to %.0f %% of their area) in a way a second "
                    "stop does not explain (misfit %.3f); the depth fit models the whole aperture there",
                    100 * share.min(), misfit)
        return None
    log.info("second stop: cuts from %.0f %% of the farthest lens's distance, %.0f %% of the aperture's diameter "
             "there (area misfit %.3f)", 100 * (r2 - 1.0) / q, 100 * min((q - r2 + 1.0) / 2.0, 1.0), misfit)
    return stop


def _binned_shares(s: np.ndarray, area: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """Median distance and median area over the central bin's, per bin of distance ``s`` that holds
    enough lenses (None when too few bins do)."""
    ok = np.isfinite(area) & (area > 0)
    s, area = s[ok], area[ok]
    if s.size < N_BINS * MIN_BIN_LENSES:
        return None, np.empty(0)
    edges = np.linspace(0.0, s.max() * (1 + 1e-9), N_BINS + 1)
    which = np.digitize(s, edges) - 1
    distance, share = [], []
    for b in range(N_BINS):
        mine = which == b
        if np.count_nonzero(mine) >= MIN_BIN_LENSES:
            distance.append(np.median(s[mine]))
            share.append(np.median(area[mine]))
    if len(share) < N_BINS // 2:
        return None, np.empty(0)
    share_arr = np.asarray(share)
    return np.asarray(distance), share_arr / share_arr[0]
