"""The camera's optical blur and micro-image response, fitted to the micro-images of a white image.

Model of a white image (uniform light through every micro-lens): each micro-image is the main
lens's aperture imaged behind its lens, a disk of radius ``radius_px`` about its lattice centre,
times a pixel response that falls toward the rim, ``rim_response ** ((r / radius_px) ** 2)`` at
distance ``r`` from the centre, times the lens's own gain (its transmission and the chief ray's
``cos^4``); that light is integrated over each pixel's area and blurred by a Gaussian of sigma
``blur_px`` (diffraction, aberration, cross-talk), and the tails of neighbouring micro-images add.
This is the pixel model of the depth fit (:func:`analysis.depth.footprint.pixel_footprint`: a pixel's
area blurred by a Gaussian), so the fitted ``blur_px`` is the one the fit should use.

:func:`fit_micro_image_profile` fits ``blur_px``, ``radius_px`` and ``rim_response`` (and one gain
per lens, solved in closed form for each trial of the other three) to the green pixels of a few
hundred micro-images near the optical axis, with centres from the fitted lattice (sub-pixel: the
lenses' different sub-pixel phases sample the edge profile finely). Micro-images that a second stop
in the main lens cuts (cat's eyes toward the corners) are left out by their shape (their area, light
over central level, is smaller; a lens's gain does not change it) and by their misfit. Green pixels
only: the particles' 532 nm light is seen by them, and blur grows with wavelength.
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass
from functools import lru_cache
from typing import Any

import numpy as np
import scipy.sparse as sparse
from scipy.sparse.linalg import spsolve

from analysis.camera.model import Lattice, green_mask
from analysis.errors import CalibrationError

from .lattice_fit import balance_channels
from .cut_lenses import cell_areas, full_shape
from .profile_kernels import sample_template

log = logging.getLogger(__name__)

#: Micro-images the fit uses (nearest the optical axis among those of full shape).
FIT_LENSES = 200
#: Upper bound of the fitted blur (sigma, px); the model's reach follows from it.
MAX_BLUR_PX = 2.0
#: Light of a micro-image is followed out to this many blur sigmas beyond its rim.
_TAIL_SIGMAS = 4.0
#: Spacing (px) of the fine grid the micro-image template is computed on.
_TEMPLATE_STEP_PX = 1.0 / 16.0
#: Pixels whose misfit exceeds this many RMS are left out of the final fit (dust, missed defects) ...
_OUTLIER_SIGMAS = 6.0
#: ... and so are micro-images whose pixels misfit this many times more than the median one's
#: (a cut the area missed, a damaged lens).
_LENS_MISFIT = 3.0


@dataclass(frozen=True)
class MicroImageProfile:
    """What :func:`fit_micro_image_profile` found.

    Attributes
    ----------
    blur_px : float
        Sigma (sensor pixels) of the Gaussian point spread beyond pixel integration: what the depth
        fit's pixel model (``blur_px``) should use.
    blur_std_px : float
        Its standard error from the fit (noise only; model errors are not in it).
    radius_px : float
        Radius of the aperture's image behind each micro-lens (pixels).
    rim_response : float
        Pixel response at that radius relative to the micro-image centre (1: flat).
    lens_gain_spread : float
        Relative standard deviation of the fitted lenses' gains (transmission spread; the chief
        ray's ``cos^4`` over the few hundred central lenses adds well under 0.1 %).
    n_lenses, n_pixels : int
        Micro-images whose pixels entered the fit, and those green pixels.
    n_cut : int
        Micro-images of the fit's region (the ``n_lenses`` nearest the optical axis) left out for their
        shape (cut by a second stop, or damaged).
    residual_rms : float
        RMS misfit of the pixels, relative to the median micro-image's central level.
    """

    blur_px: float
    blur_std_px: float
    radius_px: float
    rim_response: float
    lens_gain_spread: float
    n_lenses: int
    n_pixels: int
    n_cut: int
    residual_rms: float

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_dict(cls, doc: dict[str, Any]) -> "MicroImageProfile":
        return cls(**{k: (int(v) if k.startswith("n_") else float(v)) for k, v in doc.items()})


def micro_image_template(blur_px: float, radius_px: float, rim_response: float, *, half_width_px: float,
                         step_px: float = _TEMPLATE_STEP_PX) -> np.ndarray:
    """One micro-image of unit central response as each pixel records it, on a fine grid of offsets.

    The disk of ``radius_px`` with the rim response, convolved with a pixel's unit square and a
    Gaussian of sigma ``blur_px``: ``out[n // 2 + iy, n // 2 + ix]`` is the value of a pixel whose
    centre is ``(ix, iy) * step_px`` from the micro-image's centre. Computed by FFT (the square
    and the Gaussian are exact in frequency; the disk is drawn with an anti-aliased rim).

    Returns
    -------
    ndarray of shape (n, n), float64, ``n`` even, covering ``+- half_width_px``.

    Examples
    --------
    >>> t = micro_image_template(0.5, 4.0, 1.0, half_width_px=8.0)
    >>> n = t.shape[0]
    >>> round(float(t[n // 2, n // 2]), 3), round(float(t[n // 2, n // 2 + 100]), 3)
    (1.0, 0.0)
    """
    n = _fft_size(2.0 * half_width_px / step_px)
    r2, box, f2 = _template_grids(n, step_px)
    # Only the disk's pixels: the rest of the grid is zero.
    m = int(math.ceil(radius_px / step_px)) + 2
    lo, hi = max(n // 2 - m, 0), min(n // 2 + m + 1, n)
    inner = r2[lo:hi, lo:hi]
    disk = np.zeros((n, n))
    disk[lo:hi, lo:hi] = (np.clip((radius_px - np.sqrt(inner)) / step_px + 0.5, 0.0, 1.0)
                          * np.exp(math.log(rim_response) / radius_px ** 2 * inner))
    spectrum = np.fft.rfft2(np.fft.ifftshift(disk))
    spectrum *= box * np.exp(-2.0 * math.pi ** 2 * blur_px ** 2 * f2)
    return np.fft.fftshift(np.fft.irfft2(spectrum, s=(n, n)))


@lru_cache(maxsize=4)
def _template_grids(n: int, step_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Squared radius of the grid's samples, and the pixel square's transfer function and the squared
    frequency on the ``rfft2`` grid."""
    x = (np.arange(n) - n // 2) * step_px
    fy = np.fft.fftfreq(n, d=step_px)[:, None]
    fx = np.fft.rfftfreq(n, d=step_px)[None, :]
    return x[None, :] ** 2 + x[:, None] ** 2, np.sinc(fx) * np.sinc(fy), fx * fx + fy * fy


def _fft_size(minimum: float) -> int:
    """The smallest even ``2^a 3^b 5^c`` of at least ``minimum``."""
    n = int(math.ceil(minimum))
    while True:
        n += n % 2
        m = n
        for p in (2, 3, 5):
            while m % p == 0:
                m //= p
        if m == 1:
            return n
        n += 1


@dataclass(frozen=True)
class _FitData:
    """Green pixels and, per pixel, the micro-images whose light may reach it."""

    values: np.ndarray       # (P,) pixel values, DN above black (green phases balanced)
    weights: np.ndarray      # (P,) 1 / sqrt(variance), up to a constant
    owner: np.ndarray        # (P,) the lens whose micro-image the pixel belongs to
    entry_pixel: np.ndarray  # (E,) pixel of each (pixel, lens) pair
    entry_lens: np.ndarray   # (E,) lens (0 ... L - 1) of each pair
    entry_dx: np.ndarray     # (E,) pixel centre minus micro-image centre, px
    entry_dy: np.ndarray
    prior: np.ndarray        # (L,) weight of the prior pulling each lens's gain to the typical one
    reach_px: float

    @property
    def n_lenses(self) -> int:
        return int(self.prior.size)

    def take(self, keep: np.ndarray) -> "_FitData":
        """The data without the pixels where ``keep`` is False."""
        index = np.full(self.values.size, -1, dtype=np.int64)
        index[keep] = np.arange(int(keep.sum()))
        use = keep[self.entry_pixel]
        return _FitData(self.values[keep], self.weights[keep], self.owner[keep], index[self.entry_pixel[use]],
                        self.entry_lens[use], self.entry_dx[use], self.entry_dy[use], self.prior, self.reach_px)


def fit_micro_image_profile(raw: np.ndarray, lattice: Lattice, *, black_level: float, radius_px: float,
                            white_level: float = 4095.0, defects: np.ndarray | None = None,
                            n_lenses: int = FIT_LENSES) -> MicroImageProfile:
    """Fit the optical blur, the aperture image's radius and the rim response to a white image.

    Parameters
    ----------
    raw : ndarray of shape (H, W)
        Raw white image (Bayer BGGR; only its green pixels are used).
    lattice : Lattice
        The micro-image lattice fitted to this white image (sub-pixel centres).
    black_level, white_level : float, keyword-only
        Raw black level; pixels at the white level (saturated) are left out.
    radius_px : float, keyword-only
        Radius of the aperture's image from the metadata (the fit's start; it may be off by 30 %).
    defects : ndarray of shape (H, W), bool, optional, keyword-only
        Pixels to leave out (hot, stuck, dead: :func:`analysis.calibration.defects.find_defects`).
    n_lenses : int, keyword-only
        Micro-images to fit.

    Returns
    -------
    MicroImageProfile

    Raises
    ------
    CalibrationError
        If too few micro-images of full shape lie on the sensor, or the fit does not converge.
    """
    raw = np.asarray(raw)
    data, n_cut = _gather(raw, lattice, black_level=black_level, white_level=white_level, radius_px=radius_px,
                          defects=defects, n_lenses=n_lenses)
    start = np.array([0.6, radius_px, 0.9])
    theta, gains, weighted = _solve(data, start, radius_px)
    # Leave out what the model cannot explain (dust, a missed defect, a cut lens), then fit again.
    keep = np.abs(weighted) <= _OUTLIER_SIGMAS * math.sqrt(float(np.mean(weighted ** 2)))
    per_lens = np.sqrt(np.bincount(data.owner, weights=weighted ** 2, minlength=data.n_lenses)
                       / np.maximum(np.bincount(data.owner, minlength=data.n_lenses), 1))
    owners = np.unique(data.owner)
    keep &= per_lens[data.owner] <= _LENS_MISFIT * float(np.median(per_lens[owners]))
    if not keep.all():
        data = data.take(keep)
        theta, gains, weighted = _solve(data, theta, radius_px)
    jac = _jacobian(data, theta, radius_px)
    dof = max(data.values.size - gains.size - theta.size, 1)
    cov = np.linalg.pinv(jac.T @ jac) * float(np.sum(weighted ** 2)) / dof
    blur, radius, rim = _clamped(theta, radius_px)
    fitted = gains[data.prior == 0]
    level = float(np.median(fitted))
    residual = weighted / data.weights
    profile = MicroImageProfile(
        blur_px=blur, blur_std_px=float(math.sqrt(max(cov[0, 0], 0.0))), radius_px=radius, rim_response=rim,
        lens_gain_spread=float(1.4826 * np.median(np.abs(fitted / level - 1.0))), n_lenses=int(fitted.size),
        n_pixels=int(data.values.size), n_cut=n_cut,
        residual_rms=float(math.sqrt(np.mean(residual ** 2))) / max(level, 1e-12))
    log.info("micro-image profile: blur %.3f +- %.3f px, radius %.3f px, rim response %.3f, lens gain spread %.1f %% "
             "(%d lenses, %d pixels, %d cut)", profile.blur_px, profile.blur_std_px, radius, rim,
             100 * profile.lens_gain_spread, profile.n_lenses, profile.n_pixels, n_cut)
    return profile


def _gather(raw: np.ndarray, lattice: Lattice, *, black_level: float, white_level: float, radius_px: float,
            defects: np.ndarray | None, n_lenses: int) -> tuple[_FitData, int]:
    """The fit's pixels: green and usable, of the ``n_lenses`` micro-images nearest the optical axis that
    are of full shape; and every micro-image whose light may reach them."""
    h, w = raw.shape
    image = raw.astype(np.float32) - np.float32(black_level)
    bad = raw >= white_level
    if defects is not None:
        bad |= np.asarray(defects, dtype=bool)
    image[bad | ~green_mask(h, w)] = np.nan
    # The two green phases may differ in gain (Gr / Gb): scale them to one level.
    levels = [float(np.nanmean(image[r0::2, (r0 + 1) % 2::2])) for r0 in (0, 1)]
    if not min(levels) > 0:
        raise CalibrationError("the white image's green pixels hold no light; check the white image and its "
                               "black level")
    for r0, level in zip((0, 1), levels):
        image[r0::2, (r0 + 1) % 2::2] *= np.float32(0.5 * sum(levels) / level)

    ij, centres = lattice.centres(w, h, margin_px=radius_px + 2.0)
    if len(ij) < 20:
        raise CalibrationError(f"only {len(ij)} micro-images lie on the white image; the blur cannot be estimated")
    axis = np.clip(lattice.origin, [0.0, 0.0], [w, h])
    region = np.argsort(np.hypot(*(centres - axis).T), kind="stable")[:n_lenses]
    balanced = balance_channels(raw, black_level=black_level)
    balanced[bad] = np.nan
    area = cell_areas(balanced, lattice, ij, radius_px=radius_px)
    del balanced
    finite = np.isfinite(area)
    if finite.sum() < 20:
        raise CalibrationError("too few lit micro-images on the white image to estimate the blur; check that it is "
                               "an exposed white image")
    # A second stop only ever takes light away: full micro-images are those of the largest areas.
    full = full_shape(area, region)
    n_cut = int(np.count_nonzero(finite[region] & ~full[region]))
    own = region[full[region]]
    if own.size < min(n_lenses, 40):
        raise CalibrationError(f"only {own.size} of the {region.size} micro-images nearest the optical axis are of full "
                               "shape (a second stop cuts them, or the white image is damaged); the blur cannot be "
                               "estimated")

    # Pixels of those micro-images (nearest to their centres).
    lo = np.maximum(np.floor(centres[own].min(axis=0) - lattice.pitch_px).astype(int), 0)
    hi = np.minimum(np.ceil(centres[own].max(axis=0) + lattice.pitch_px).astype(int), [w, h])
    rows, cols = np.nonzero(np.isfinite(image[lo[1]:hi[1], lo[0]:hi[0]]))
    rows += lo[1]
    cols += lo[0]
    px, py = cols + 0.5, rows + 0.5
    ni, nj = lattice.nearest(px, py)
    i0, j0 = ij.min(axis=0) - 64
    n_i = int(ij[:, 0].max() - i0 + 129)
    key = (nj - j0) * n_i + (ni - i0)
    mine = np.isin(key, (ij[own, 1] - j0) * n_i + (ij[own, 0] - i0))
    rows, cols, px, py, key = rows[mine], cols[mine], px[mine], py[mine], key[mine]

    # Every micro-image whose light may reach them (off the sensor too): the model's unknown gains.
    reach = radius_px + 1.0 + _TAIL_SIGMAS * MAX_BLUR_PX
    fi, fj = lattice.fractional_index(px, py)
    ci, cj = np.rint(fi).astype(np.int64), np.rint(fj).astype(np.int64)
    steps = int(math.ceil(reach / (lattice.pitch_px * 0.85))) + 1
    ep, ek, ex, ey = [], [], [], []
    pixel = np.arange(px.size)
    for di in range(-steps, steps + 1):
        for dj in range(-steps, steps + 1):
            li, lj = ci + di, cj + dj
            cx, cy = lattice.centre(li, lj)
            dx, dy = px - cx, py - cy
            near = dx * dx + dy * dy < reach * reach
            ep.append(pixel[near])
            ek.append(((lj - j0) * n_i + (li - i0))[near])
            ex.append(dx[near])
            ey.append(dy[near])
    lens_keys, entry_lens = np.unique(np.concatenate(ek), return_inverse=True)
    owner = np.searchsorted(lens_keys, key)
    values = image[rows, cols].astype(np.float64)
    floor = 0.01 * float(np.percentile(values, 90))
    weights = 1.0 / np.sqrt(np.maximum(values, 0.0) + floor)
    # Lenses with few pixels of their own (the ring around the region) are held near the typical gain
    # by a prior worth a pixel or two; it hardly moves lenses with pixels of their own.
    n_own = np.bincount(owner, minlength=lens_keys.size)
    prior = np.where(n_own >= 10, 0.0, 2.0) * float(np.median(weights)) ** 2
    data = _FitData(values, weights, owner, np.concatenate(ep), entry_lens.reshape(-1), np.concatenate(ex),
                    np.concatenate(ey), prior, float(reach))
    return data, n_cut


def _model(data: _FitData, theta: np.ndarray, radius0: float) -> tuple[np.ndarray, np.ndarray]:
    """Weighted residuals and lens gains for the shape parameters ``theta``."""
    blur, radius, rim = _clamped(theta, radius0)
    half_width = min(radius + 1.5 + _TAIL_SIGMAS * blur, data.reach_px) + 1.0
    template = micro_image_template(blur, radius, rim, half_width_px=half_width)
    value = np.empty(data.entry_dx.size)
    sample_template(template, _TEMPLATE_STEP_PX, data.entry_dx, data.entry_dy, value)
    n_pix = data.values.size
    design = sparse.csr_matrix((value * data.weights[data.entry_pixel], (data.entry_pixel, data.entry_lens)),
                               shape=(n_pix, data.n_lenses))
    target = data.values * data.weights
    normal = (design.T @ design).tocsc()
    rhs = design.T @ target
    diagonal = np.full(data.n_lenses, 1e-12 * max(float(normal.diagonal().max()), 1e-300))
    if data.prior.any():
        # The typical gain: pixels near their own micro-image's centre over the template's centre there.
        centre = np.flatnonzero(np.abs(value) > 0.5 * float(template.max()))
        owned = centre[data.entry_lens[centre] == data.owner[data.entry_pixel[centre]]]
        typical = float(np.median(data.values[data.entry_pixel[owned]] / value[owned])) if owned.size else 0.0
        diagonal += data.prior
        rhs = rhs + data.prior * typical
    gains = spsolve(normal + sparse.diags(diagonal, format="csc"), rhs)
    if not np.all(np.isfinite(gains)):
        raise CalibrationError("the micro-image fit is singular; check the white image")
    return target - design @ gains, gains


def _clamped(theta: np.ndarray, radius0: float) -> tuple[float, float, float]:
    return (min(abs(float(theta[0])), MAX_BLUR_PX), float(np.clip(theta[1], 0.5 * radius0, 1.5 * radius0)),
            float(np.clip(theta[2], 0.05, 1.5)))


def _solve(data: _FitData, start: np.ndarray, radius0: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares over (blur, radius, rim response), the gains solved for each trial; returns the
    parameters, the gains and the weighted residuals."""
    from scipy.optimize import least_squares  # here: 11 MB that a worker with a cached calibration never needs
    lower = [0.0, 0.6 * radius0, 0.05]
    upper = [MAX_BLUR_PX, 1.4 * radius0, 1.5]
    x0 = np.clip(np.asarray(start, dtype=np.float64), np.add(lower, 1e-6), np.subtract(upper, 1e-6))
    sol = least_squares(lambda t: _model(data, t, radius0)[0], x0, bounds=(lower, upper), x_scale=[0.1, 0.1, 0.1],
                        diff_step=1e-3, method="trf", xtol=1e-6, ftol=1e-9)
    if not sol.success:
        raise CalibrationError(f"the micro-image profile fit did not converge ({sol.message}); check the white image")
    weighted, gains = _model(data, sol.x, radius0)
    return sol.x, gains, weighted


def _jacobian(data: _FitData, theta: np.ndarray, radius0: float) -> np.ndarray:
    """Central differences of the weighted residuals (for the standard errors)."""
    cols = []
    for k, h in enumerate((1e-3, 1e-3, 1e-3)):
        up, down = theta.copy(), theta.copy()
        up[k] += h
        down[k] -= h
        cols.append((_model(data, up, radius0)[0] - _model(data, down, radius0)[0]) / (2 * h))
    return np.stack(cols, axis=1)
