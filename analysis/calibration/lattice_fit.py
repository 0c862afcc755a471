"""Fit the global hexagonal micro-image lattice to a white image.

The white image is, apart from slow vignetting, periodic on the micro-image lattice, so its
three fundamental spatial frequencies (the shortest reciprocal-lattice vectors) carry the whole
geometry: their directions and lengths give pitch, rotation and row spacing, their phases give
the origin. :func:`fit_lattice` demodulates the image at the seed lattice's fundamentals in
overlapping Hann-windowed blocks (a short-time Fourier transform at three frequencies), unwraps
the block phases from the centre outwards, and fits the five lattice parameters to all of them
at once with a robust least-squares fit. This uses every pixel, needs no assumption about the
shape of a micro-image (only that it is centrally symmetric, bright at its centre), and is
independent of the Bayer gains once the channels are balanced.

A second stop's cat's-eye micro-images toward the corners are not centrally symmetric: their
patterns' phases move toward the uncut side, and fitted with the rest they stretched the lattice
(a white image with the typical simulated stop, 30 % of the aperture cut at the corners: the
fitted centres 0.44 px off beyond 60 % of the half-diagonal, the depths of blurred particles
there twice as far off). The blocks holding such micro-images
(:mod:`analysis.calibration.cut_lenses`) are left out of a last fit.

Per-lens intensity-weighted centroids are then measured against the fitted lattice as a check
(:class:`LatticeFit` residual statistics); they do not steer the fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange
from scipy.spatial import cKDTree

from analysis.camera.model import Lattice
from analysis.errors import CalibrationError

from .cut_lenses import cell_areas, full_shape

_FASTMATH = {"nsz", "arcp", "contract", "afn", "reassoc"}

# Block size of the short-time Fourier transform: about 6.5 micro-image pitches, so the
# Hann window separates the fundamentals from DC and from each other by over 6 bins.
_BLOCK_PX = 64
_STRIDE_PX = 32
# Radii (px from the seed origin) of the blocks used in each coarse-to-fine stage; the last
# stage uses all of them. After the coarse frequency lock, the phase model drifts far less
# than half a cycle from one stage's radius to the next, so wrapped residuals stay unambiguous.
_STAGE_RADII_PX = (300.0, 700.0, 1400.0, math.inf)
# Below this modulation depth at the fundamentals there is no micro-image pattern to fit.
_MIN_MODULATION = 0.02
# Micro-image radius in pitches for the central level of a cut micro-image's test (F01: 4.46 / 9.94);
# only the inner half of it is used, so another camera's ratio serves as well.
_RADIUS_PITCHES = 0.45


@dataclass(frozen=True)
class LatticeFit:
    """Result of :func:`fit_lattice`.

    Attributes
    ----------
    lattice : Lattice
        The fitted micro-image lattice (``scale_x`` kept from the seed).
    rms_px : float
        RMS of the block phase residuals of the final fit, each expressed as a displacement in
        pixels along its fundamental (clipped at 1 px).
    n_blocks : int
        Image blocks that entered the fit (bright enough, on the sensor).
    n_lenses : int
        Lenses whose centroid was measured and kept for the residual statistics.
    centroid_rms_px, centroid_median_px, centroid_p95_px : float
        RMS, median and 95th percentile of the distance between each kept lens's
        intensity-weighted centroid and its fitted centre.
    centroid_bias_px : tuple of float
        Mean centroid-minus-fit vector ``(dx, dy)``; near zero when the fit is unbiased.
    n_outliers : int
        Measured lenses whose centroid lies over 1 px from the fitted centre (defects, dust).
    n_cut_blocks : int
        Blocks left out of the last fit for holding micro-images a second stop cuts.
    """

    lattice: Lattice
    rms_px: float
    n_blocks: int
    n_lenses: int
    centroid_rms_px: float
    centroid_median_px: float
    centroid_p95_px: float
    centroid_bias_px: tuple[float, float]
    n_outliers: int
    n_cut_blocks: int = 0


def balance_channels(white: np.ndarray, *, black_level: float) -> np.ndarray:
    """Black-subtracted white image with the four Bayer channels scaled to a common mean.

    Parameters
    ----------
    white : ndarray of shape (H, W)
        Raw white image (any integer or float dtype), H and W even.
    black_level : float

    Returns
    -------
    ndarray of shape (H, W), float32; the overall mean is about 1.
    """
    img = white.astype(np.float32)
    img -= np.float32(black_level)
    for r in (0, 1):
        for c in (0, 1):
            channel = img[r::2, c::2]
            mean = float(channel.mean(dtype=np.float64))
            if mean > 0:
                channel *= np.float32(1.0 / mean)
    return img


def fundamental_frequencies(lattice: Lattice) -> np.ndarray:
    """The three shortest reciprocal-lattice vectors, cycles per pixel.

    Returns
    -------
    ndarray of shape (3, 2): rows ``g_i``, ``g_j`` and ``g_i + g_j`` where ``g_i . b_i = 1``,
    ``g_i . b_j = 0`` for the lattice steps ``b_i``, ``b_j``.
    """
    m = np.linalg.inv(lattice.basis)
    return np.stack([m[0], m[1], m[0] + m[1]])


@njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _demodulate_blocks(image, ex_re, ex_im, ey_re, ey_im, window, stride, out):  # pragma: no cover - numba
    # out[by, bx, k, 0:2] = sum over the block of window * image * exp(-2 pi i g_k . x).
    # The exponential is separable, ex[k, x] * ey[k, y], so each pixel costs three
    # complex-by-real multiply-adds. Each prange row of blocks writes its own outputs.
    nby, nbx = out.shape[0], out.shape[1]
    block = window.shape[0]
    for by in prange(nby):
        y0 = by * stride
        for bx in range(nbx):
            x0 = bx * stride
            acc = np.zeros((3, 2))
            for dy in range(block):
                y = y0 + dy
                row_re = np.zeros(3)
                row_im = np.zeros(3)
                for dx in range(block):
                    x = x0 + dx
                    v = image[y, x] * window[dx]
                    for k in range(3):
                        row_re[k] += v * ex_re[k, x]
                        row_im[k] += v * ex_im[k, x]
                wy = window[dy]
                for k in range(3):
                    # (row_re + i row_im) * (ey_re + i ey_im)
                    acc[k, 0] += wy * (row_re[k] * ey_re[k, y] - row_im[k] * ey_im[k, y])
                    acc[k, 1] += wy * (row_re[k] * ey_im[k, y] + row_im[k] * ey_re[k, y])
            for k in range(3):
                out[by, bx, k, 0] = acc[k, 0]
                out[by, bx, k, 1] = acc[k, 1]


def demodulate(image: np.ndarray, seed: Lattice, *, stride_px: int = _STRIDE_PX
               ) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Each block's complex amplitude at the seed's three fundamentals (blocks of 64 px every
    ``stride_px``).

    Returns block centres (N, 2) relative to the seed origin, complex amplitudes (N, 3) and
    the block grid's shape ``(rows, columns)`` (N = rows * columns, row-major).
    """
    h, w = image.shape
    g = fundamental_frequencies(seed)
    # Pixel (c, r) has its centre at (c + 0.5, r + 0.5); phases are taken from the seed origin.
    xs = np.arange(w) + 0.5 - seed.origin_x
    ys = np.arange(h) + 0.5 - seed.origin_y
    arg_x = -2.0 * np.pi * np.outer(g[:, 0], xs)
    arg_y = -2.0 * np.pi * np.outer(g[:, 1], ys)
    n = np.arange(_BLOCK_PX)
    window = np.sin(np.pi * (n + 0.5) / _BLOCK_PX) ** 2
    nby = (h - _BLOCK_PX) // stride_px + 1
    nbx = (w - _BLOCK_PX) // stride_px + 1
    out = np.empty((nby, nbx, 3, 2))
    _demodulate_blocks(image, np.cos(arg_x), np.sin(arg_x), np.cos(arg_y), np.sin(arg_y),
                       window, stride_px, out)
    z = (out[..., 0] + 1j * out[..., 1]).reshape(-1, 3)
    by, bx = np.meshgrid(np.arange(nby), np.arange(nbx), indexing="ij")
    # The symmetric window's centroid is the block's middle, c0 + B/2 in pixel coordinates.
    cx = bx.ravel() * stride_px + _BLOCK_PX / 2 - seed.origin_x
    cy = by.ravel() * stride_px + _BLOCK_PX / 2 - seed.origin_y
    return np.stack([cx, cy], axis=1), z, (nby, nbx)


def _coarse_frequencies(z: np.ndarray, grid: tuple[int, int], use: np.ndarray, seed: Lattice) -> Lattice:
    """Pitch, rotation and row spacing from the phase steps between neighbouring blocks.

    A frequency error dG turns the block phase by 2 pi dG . stride from one block to the next,
    unambiguous while |dG| < 1 / (2 stride): about 13 % in pitch or 0.1 rad in rotation.
    """
    from scipy.optimize import least_squares  # here: 11 MB that a worker with a cached calibration never needs
    zg = z.reshape(grid[0], grid[1], 3)
    ug = use.reshape(grid)
    both_x = (ug[:, 1:] & ug[:, :-1])[..., None]
    both_y = (ug[1:, :] & ug[:-1, :])[..., None]
    step_x = np.sum(np.where(both_x, zg[:, 1:] * np.conj(zg[:, :-1]), 0.0), axis=(0, 1))
    step_y = np.sum(np.where(both_y, zg[1:, :] * np.conj(zg[:-1, :]), 0.0), axis=(0, 1))
    dg = np.stack([np.angle(step_x), np.angle(step_y)], axis=1) / (2.0 * np.pi * _STRIDE_PX)
    target = fundamental_frequencies(seed) + dg
    scale = 1.0 / np.linalg.norm(target, axis=1, keepdims=True)

    def residuals(q: np.ndarray) -> np.ndarray:
        lat = seed.with_changes(pitch_px=float(q[0]), rotation_rad=float(q[1]), scale_y=float(q[2]))
        return ((fundamental_frequencies(lat) - target) * scale).ravel()

    q = least_squares(residuals, [seed.pitch_px, seed.rotation_rad, seed.scale_y],
                      x_scale=[0.01, 1e-3, 1e-3]).x
    return seed.with_changes(pitch_px=float(q[0]), rotation_rad=float(q[1]), scale_y=float(q[2]))


def _central_slices(shape: tuple[int, ...], seed: Lattice) -> tuple[slice, slice]:
    r = int(_STAGE_RADII_PX[0])
    cx = min(max(int(seed.origin_x), 0), shape[1])
    cy = min(max(int(seed.origin_y), 0), shape[0])
    return slice(max(cy - r, 0), cy + r), slice(max(cx - r, 0), cx + r)


def _lattice_from_params(p: np.ndarray, seed: Lattice) -> Lattice:
    return seed.with_changes(origin_x=float(seed.origin_x + p[0]), origin_y=float(seed.origin_y + p[1]),
                             pitch_px=float(p[2]), rotation_rad=float(p[3]), scale_y=float(p[4]))


def _model_phases(p: np.ndarray, seed: Lattice, g_seed: np.ndarray, centres: np.ndarray) -> np.ndarray:
    # Block k-phase of a lattice with fundamentals G and origin shift delta, demodulated at the
    # seed's fundamentals G_s from the seed origin: 2 pi ((G - G_s) . x - G . delta).
    g = fundamental_frequencies(_lattice_from_params(p, seed))
    delta = p[:2]
    return 2.0 * np.pi * (centres @ (g - g_seed).T - (g @ delta)[None, :])


def _wrap(phase: np.ndarray) -> np.ndarray:
    return (phase + np.pi) % (2.0 * np.pi) - np.pi


def _initial_shift(psi: np.ndarray, lattice: Lattice) -> np.ndarray:
    """Origin shift from the three mean phases ``psi = -2 pi g_k . delta`` (mod 2 pi), taken as
    the representative nearest zero: the lens nearest to the seed origin becomes lens (0, 0)."""
    g = fundamental_frequencies(lattice)
    # Two fundamentals fix delta modulo the lattice; pick the representative nearest zero.
    delta0 = np.linalg.solve(g[:2], -psi[:2] / (2.0 * np.pi))
    basis = lattice.basis
    candidates = [delta0 - basis @ np.array([a, b]) for a in (-1, 0, 1) for b in (-1, 0, 1)]
    delta = min(candidates, key=lambda d: float(d @ d))
    # With the ambiguity resolved, refine with all three phases.
    u = -psi / (2.0 * np.pi)
    u = u + np.round(g @ delta - u)
    return np.linalg.lstsq(g, u, rcond=None)[0]


def fit_lattice(white: np.ndarray, seed: Lattice, *, black_level: float = 168.0,
                min_relative_amplitude: float = 0.25) -> LatticeFit:
    """Fit the micro-image lattice to a white image, starting from a seed lattice.

    Parameters
    ----------
    white : ndarray of shape (H, W)
        Raw white image (uint16 counts, or float). Bayer channels may have different gains.
    seed : Lattice
        Starting lattice, e.g. ``CameraModel.from_metadata(meta).lattice``. It may be off
        by up to about 4 px in origin (less than half a pitch: the fitted origin is the centre
        of the lens nearest to the seed origin), about 10 % in pitch and 0.05 rad in rotation.
    black_level : float, keyword-only
    min_relative_amplitude : float, keyword-only
        Blocks whose fundamental amplitude is below this fraction of the median (vignetted
        corners, sensor edges) are left out.

    Returns
    -------
    LatticeFit

    Raises
    ------
    CalibrationError
        If the image is too small, shows no micro-image pattern near the seed, or the fit
        does not converge.
    """
    white = np.asarray(white)
    if white.ndim != 2 or min(white.shape) < 2 * _BLOCK_PX:
        raise CalibrationError(
            f"white image of shape {white.shape} is too small for a lattice fit; "
            f"it must be 2-D and at least {2 * _BLOCK_PX} px on each side")
    if not (3.0 <= seed.pitch_px <= _BLOCK_PX / 4):
        raise CalibrationError(f"seed pitch {seed.pitch_px:.3f} px is outside the supported 3..16 px")
    image = balance_channels(white, black_level=black_level)
    centres, z, grid = demodulate(image, seed)
    phases, amps = np.angle(z), np.abs(z)
    g_seed = fundamental_frequencies(seed)

    amp = amps.mean(axis=1)
    bright = amp > min_relative_amplitude * np.median(amp)
    radius = np.hypot(centres[:, 0], centres[:, 1])
    central = bright & (radius <= _STAGE_RADII_PX[0])
    # Modulation depth at the seed's fundamentals: amplitude over the window-weighted mean.
    # Micro-image patterns give tens of percent; noise or a wrong pitch gives well under 1 %.
    near = radius <= _STAGE_RADII_PX[0]
    window_sum = (_BLOCK_PX * 0.5) ** 2
    level = max(float(np.mean(image[_central_slices(image.shape, seed)])), 1e-12)
    modulation = float(np.median(amp[near])) / window_sum / level if near.any() else 0.0
    if central.sum() < 4 or modulation < _MIN_MODULATION:
        raise CalibrationError(
            f"the white image shows no micro-image pattern at the seed lattice's pitch "
            f"({seed.pitch_px:.3f} px) and rotation ({seed.rotation_rad * 1e3:.2f} mrad) around its origin "
            f"(modulation {modulation:.2%}); check that it is an exposed white image of this camera and "
            "that the seed comes from its metadata")

    coarse = _coarse_frequencies(z, grid, central, seed)
    p = np.array([0.0, 0.0, coarse.pitch_px, coarse.rotation_rad, coarse.scale_y])
    # Mean central phase once the coarse frequency ramp is taken out: -2 pi g_k . delta.
    ramp = _model_phases(p, seed, g_seed, centres[central])
    psi = np.angle(np.sum(z[central] * np.exp(-1j * ramp), axis=0))
    p[:2] = _initial_shift(psi, coarse)
    weights = amps / np.median(amps[bright])
    for stage_radius in _STAGE_RADII_PX:
        use = bright & (radius <= stage_radius)
        p = _fit_phases(p, seed, g_seed, centres[use], phases[use], weights[use])
    lattice = _lattice_from_params(p, seed)
    cut = use & _holding_cut_lenses(image, lattice, centres + [seed.origin_x, seed.origin_y])
    if cut.any() and (use & ~cut).sum() >= max(20, use.sum() // 4):
        use &= ~cut
        p = _fit_phases(p, seed, g_seed, centres[use], phases[use], weights[use])
        lattice = _lattice_from_params(p, seed)
    c, ph = centres[use], phases[use]
    res = _wrap(ph - _model_phases(p, seed, g_seed, c))
    # A phase error e on fundamental g is a displacement of e / (2 pi |g|) pixels along g.
    g_len = np.linalg.norm(fundamental_frequencies(lattice), axis=1)
    disp = res / (2.0 * np.pi * g_len[None, :])
    rms = float(np.sqrt(np.mean(np.clip(disp, -1.0, 1.0) ** 2)))
    stats = _centroid_statistics(image, lattice)
    return LatticeFit(lattice=lattice, rms_px=rms, n_blocks=int(use.sum()), n_cut_blocks=int(cut.sum()), **stats)


def _fit_phases(p: np.ndarray, seed: Lattice, g_seed: np.ndarray, centres: np.ndarray, phases: np.ndarray,
                weights: np.ndarray) -> np.ndarray:
    """The lattice parameters that fit the blocks' phases best, starting from ``p``."""
    from scipy.optimize import least_squares  # here: 11 MB that a worker with a cached calibration never needs

    def residuals(q: np.ndarray) -> np.ndarray:
        return (weights * _wrap(phases - _model_phases(q, seed, g_seed, centres))).ravel()

    # Phase noise of ~0.05 rad is typical; larger residuals are treated as outliers.
    sol = least_squares(residuals, p, loss="huber", f_scale=0.1, x_scale=[1.0, 1.0, 0.01, 1e-3, 1e-3], method="trf")
    if not sol.success:
        raise CalibrationError(f"the lattice fit did not converge ({sol.message}); check the seed lattice and the "
                               "white image")
    return sol.x


def _holding_cut_lenses(image: np.ndarray, lattice: Lattice, blocks_px: np.ndarray) -> np.ndarray:
    """Which blocks (centres ``blocks_px``, image pixels) hold micro-images that a second stop cuts
    (a mask; over half of theirs: noise takes several % of full ones for cut); micro-images whose
    cells leave the sensor are not judged."""
    h, w = image.shape
    ij, lens_xy = lattice.centres(w, h, margin_px=lattice.pitch_px)
    if len(ij) < 20:
        return np.zeros(len(blocks_px), dtype=bool)
    area = cell_areas(image, lattice, ij, radius_px=_RADIUS_PITCHES * lattice.pitch_px)
    axis = np.clip(lattice.origin, [0.0, 0.0], [w, h])
    cut = np.isfinite(area) & ~full_shape(area, np.hypot(*(lens_xy - axis).T) <= _STAGE_RADII_PX[0])
    if not cut.any():
        return np.zeros(len(blocks_px), dtype=bool)
    inside = cKDTree(lens_xy).query_ball_point(blocks_px, r=_BLOCK_PX / 2, p=np.inf)
    return np.array([len(hits) > 0 and np.count_nonzero(cut[hits]) > len(hits) / 2 for hits in inside], dtype=bool)


@njit(cache=True, parallel=True, fastmath=_FASTMATH)
def _centroids(image, cx, cy, radius, iterations, out_x, out_y, out_w):  # pragma: no cover - numba
    # Intensity-weighted centroid of (I - t)+ inside a disk of `radius` around each predicted
    # centre, t halfway between the disk's min and max, re-centred `iterations` times.
    h, w = image.shape
    r2 = radius * radius
    half = int(math.ceil(radius)) + 1
    for n in prange(cx.shape[0]):
        x, y = cx[n], cy[n]
        total = 0.0
        for _ in range(iterations):
            c0 = int(math.floor(x)) - half
            r0 = int(math.floor(y)) - half
            lo, hi = np.inf, -np.inf
            for r in range(max(r0, 0), min(r0 + 2 * half + 1, h)):
                for c in range(max(c0, 0), min(c0 + 2 * half + 1, w)):
                    if (c + 0.5 - x) ** 2 + (r + 0.5 - y) ** 2 <= r2:
                        v = image[r, c]
                        lo = min(lo, v)
                        hi = max(hi, v)
            t = 0.5 * (lo + hi)
            sx = sy = total = 0.0
            for r in range(max(r0, 0), min(r0 + 2 * half + 1, h)):
                for c in range(max(c0, 0), min(c0 + 2 * half + 1, w)):
                    if (c + 0.5 - x) ** 2 + (r + 0.5 - y) ** 2 <= r2:
                        v = image[r, c] - t
                        if v > 0:
                            sx += v * (c + 0.5)
                            sy += v * (r + 0.5)
                            total += v
            if total > 0:
                x, y = sx / total, sy / total
        out_x[n], out_y[n], out_w[n] = x, y, total


def lens_centroids(image: np.ndarray, lattice: Lattice, *, margin_px: float | None = None,
                   iterations: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intensity-weighted centroid of every micro-image on the sensor.

    Parameters
    ----------
    image : ndarray of shape (H, W), float32
        Channel-balanced white image (:func:`balance_channels`).
    lattice : Lattice
        Predicted centres; each window starts there and follows the centroid.
    margin_px : float, optional
        Lenses closer than this to a sensor edge are skipped (default: one pitch).
    iterations : int

    Returns
    -------
    ij : ndarray of shape (N, 2), int64
    predicted, measured : ndarray of shape (N, 2), float64, pixels
    """
    h, w = image.shape
    margin = lattice.pitch_px if margin_px is None else margin_px
    ij, xy = lattice.centres(w, h, margin_px=margin)
    out_x = np.empty(len(ij))
    out_y = np.empty(len(ij))
    out_w = np.empty(len(ij))
    _centroids(np.ascontiguousarray(image, dtype=np.float32), xy[:, 0].copy(), xy[:, 1].copy(),
               0.45 * lattice.pitch_px, iterations, out_x, out_y, out_w)
    return ij, xy, np.stack([out_x, out_y], axis=1)


def _centroid_statistics(image: np.ndarray, lattice: Lattice) -> dict:
    _, predicted, measured = lens_centroids(image, lattice)
    d = measured - predicted
    dist = np.hypot(d[:, 0], d[:, 1])
    ok = np.isfinite(dist)
    outlier = ok & (dist > 1.0)
    keep = ok & ~outlier
    if keep.sum() < 0.5 * max(len(dist), 1):
        raise CalibrationError(
            f"only {int(keep.sum())} of {len(dist)} micro-image centroids lie within 1 px of the fitted "
            "lattice, so the fit locked onto something else; check that the white image and the seed "
            "lattice come from the same camera and zoom")
    dk = dist[keep]
    return dict(n_lenses=int(keep.sum()), centroid_rms_px=float(np.sqrt(np.mean(dk ** 2))),
                centroid_median_px=float(np.median(dk)), centroid_p95_px=float(np.percentile(dk, 95)),
                centroid_bias_px=(float(d[keep, 0].mean()), float(d[keep, 1].mean())),
                n_outliers=int(outlier.sum()))
