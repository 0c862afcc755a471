"""How far the micro-lens lattice has moved between the white images and an exposure.

Warming by a few kelvin between calibration and exposure moves the micro-lens array by a few
tenths of a micrometre: a fraction of a pixel, enough to make the depth fit misjudge which
aperture point each pixel sees and how the light splits between lenses. The exposure itself
says where its micro-images are: the glow (and every defocused particle) lights them, and its
pattern, demodulated at the lattice's three fundamental frequencies block by block as for the
lattice fit (:func:`analysis.calibration.lattice_fit.demodulate`), is shifted in phase against
the white image's by ``-2 pi g . delta`` where the micro-images moved by ``delta``. A shift and
a rotation about the lattice's origin are fitted to those phases, weighted by their noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from analysis.camera.model import Lattice

from .lattice_fit import demodulate, fundamental_frequencies

#: Blocks whose amplitude at a fundamental is below this many times its noise are left out.
MIN_BLOCK_SNR = 5.0
#: A drift is only trusted from at least this many blocks.
MIN_BLOCKS = 20
#: Blocks (64 px) every this many pixels: a sixteenth of the sensor gives the shift to a few
#: thousandths of a pixel on a glow of tens of DN, in a few tens of milliseconds.
BLOCK_STRIDE_PX = 128
#: No block's phase counts as surer than this (rad; 0.01 px at the F01's 10 px pitch).
PHASE_FLOOR_RAD = 0.05
#: Phase residuals beyond this many of their noise sigmas (particles' partial micro-images, not the
#: lattice) are left out of the second fit.
OUTLIER_SIGMAS = 4.0


@dataclass(frozen=True)
class LatticeDrift:
    """The exposure's micro-images, relative to the white image's.

    Attributes
    ----------
    shift_px : tuple of float
        Displacement ``(dx, dy)`` (pixels) of the micro-image at the lattice's origin.
    rotation_rad : float
        Rotation about the lattice's origin: the displacement at ``(x, y)`` adds
        ``rotation * (-(y - y0), x - x0)``.
    sigma_px : float
        Standard error of the shift.
    n_blocks : int
        Image blocks the estimate rests on.
    """

    shift_px: tuple[float, float]
    rotation_rad: float
    sigma_px: float
    n_blocks: int

    def displacement(self, x: np.ndarray, y: np.ndarray, lattice: Lattice) -> tuple[np.ndarray, np.ndarray]:
        """``(dx, dy)`` of the micro-images centred at ``(x, y)`` (sensor pixels)."""
        rx = np.asarray(x, dtype=np.float64) - lattice.origin_x
        ry = np.asarray(y, dtype=np.float64) - lattice.origin_y
        return self.shift_px[0] - self.rotation_rad * ry, self.shift_px[1] + self.rotation_rad * rx

    def to_dict(self) -> dict:
        return {"shift_px": list(self.shift_px), "rotation_rad": self.rotation_rad, "sigma_px": self.sigma_px,
                "n_blocks": self.n_blocks}


def block_phases(image: np.ndarray, lattice: Lattice) -> tuple[np.ndarray, np.ndarray]:
    """Block centres (N, 2, pixels from the lattice origin) and complex amplitudes (N, 3) of an
    image (raw counts, or the white image's devignetting map) at the lattice's fundamentals.

    Read as it is, no copy: the black level is a constant, which the windowed blocks keep off the
    fundamentals, and the image's own gain does not move their phases."""
    centres, z, _ = demodulate(np.asarray(image), lattice, stride_px=BLOCK_STRIDE_PX)
    return centres, z


def estimate_drift(image: np.ndarray, lattice: Lattice, white_phases: tuple[np.ndarray, np.ndarray], *,
                   noise_dn: float) -> LatticeDrift | None:
    """The exposure's lattice drift against the white image (see the module docstring).

    Parameters
    ----------
    image : ndarray of shape (H, W), uint16
        The raw exposure.
    lattice : Lattice
        The white image's fitted lattice.
    white_phases : (centres, amplitudes)
        :func:`block_phases` of the white image (or its devignetting map) on that lattice.
    noise_dn : float
        Noise of one raw pixel about the background (DN).

    Returns
    -------
    LatticeDrift, or None where the exposure shows too little of its micro-image pattern.
    """
    centres, z_exp = block_phases(image, lattice)
    _, z_white = white_phases
    if z_white.shape != z_exp.shape:
        return None
    # A Hann block's noise amplitude: sigma * sqrt(sum of the squared window) = 24 sigma for 64 px.
    noise = max(noise_dn, 0.5) * 24.0
    g = fundamental_frequencies(lattice)
    cross = z_exp * np.conj(z_white)
    use = (np.abs(z_exp) > MIN_BLOCK_SNR * noise) & (np.abs(z_white) > 0)
    if np.count_nonzero(use.any(axis=1)) < MIN_BLOCKS:
        return None
    phase = np.angle(cross)
    # Phase noise (rad), floored: where the pattern is bright (a reflection, a crowd of particles)
    # it may still not be the white image's, so no few blocks may outweigh the rest.
    sigma = np.maximum(noise / np.maximum(np.abs(z_exp), 1e-12), PHASE_FLOOR_RAD)
    rows, k = np.nonzero(use)
    # phase = -2 pi g_k . (shift + rotation * (-y, x)): linear in (dx, dy, rotation).
    gx, gy = g[k, 0], g[k, 1]
    cx, cy = centres[rows, 0], centres[rows, 1]
    design = -2.0 * np.pi * np.column_stack([gx, gy, -gx * cy + gy * cx])
    target = phase[rows, k]
    weight = 1.0 / sigma[rows, k]
    params, keep = None, np.ones(target.size, dtype=bool)
    for _ in range(2):
        if keep.sum() < MIN_BLOCKS:
            return None
        params, *_ = np.linalg.lstsq(design[keep] * weight[keep, None], target[keep] * weight[keep], rcond=None)
        residual = (target - design @ params) * weight
        scale = max(1.4826 * float(np.median(np.abs(residual[keep]))), 1.0)
        keep = np.abs(residual) < OUTLIER_SIGMAS * scale
    # A shift needs two lattice directions: one alone (a featureless frame's leakage) leaves the
    # fit singular, and its covariance meaningless (with numpy 2.4, negative).
    a = design[keep] * weight[keep, None]
    covariance = np.linalg.inv(a.T @ a) * scale ** 2
    if np.unique(k[keep]).size < 2 or not (covariance[0, 0] > 0 and covariance[1, 1] > 0):
        return None
    return LatticeDrift(shift_px=(float(params[0]), float(params[1])), rotation_rad=float(params[2]),
                        sigma_px=float(np.sqrt(max(covariance[0, 0], covariance[1, 1]))),
                        n_blocks=int(np.unique(rows[keep]).size))
