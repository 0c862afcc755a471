"""Which raw samples an exposure's refocus uses: the table's samples above the background and the noise.

Samples (table entries) are read from the raw image, minus the black level and the background
(glow and other extended light, ``level * weight`` per sample: it lights the sensor like the
white image). Unless ``noise_sigmas=None``, only samples above ``noise_sigmas`` robust standard
deviations contribute: dust frames are sparse, so this skips almost all the work, and the
skipped samples are pure noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np

from analysis.errors import ParameterError

from . import kernels as kern
from .background import BackgroundMap, local_noise
from .table import LightFieldTable

# Below this many DN the noise estimate is taken as quantisation-limited.
_MIN_SIGMA_DN = 0.5
# Histogram for the robust background and noise: 1/8 DN bins over -512 ... 4096 DN.
_HIST_BIN_DN = 0.125
_HIST_LO = -512.0
_HIST_BINS = int(4608 / _HIST_BIN_DN)


@dataclass(frozen=True)
class Samples:
    """Samples of one raw image chosen for the splat (reuse it for the stack and sub-aperture).

    Attributes
    ----------
    ids : ndarray (M,), int32
        Indices into the table's samples.
    values : ndarray (M,), float32
        ``raw - black_level - background * weight`` of those samples.
    background : float
        Diffuse background (plasma glow) in DN of a median-weight pixel: the median of ``levels``.
    levels : ndarray (table.n_samples,), float32
        The background behind each sample (DN of a median-weight pixel), subtracted in proportion
        to the sample's weight, as extended light lights a micro-image like the white image does.
    sigma : float
        Robust noise of the background-subtracted samples (1.4826 * MAD), DN.
    threshold : float
        Samples with a value ``<= threshold`` were skipped (``-inf``: none), in a typical lens;
        elsewhere the threshold follows the lens's own scatter about the background
        (:func:`analysis.lightfield.background.local_noise`) when the background is a
        :class:`~analysis.lightfield.background.BackgroundMap`, else the noise model ``noise``.
    noise : (float, float)
        ``(a, b)`` of one sample's noise variance, ``a + b * signal`` (DN^2; signal: the extended
        light on it, ``level * weight`` in DN), as the samples show it: shot noise grows with the
        light behind it, and so does what the background model misses of that light (this one
        model over the frame follows the brightest extended light, and overstates the noise of
        the rest: :meth:`variance_ratio` uses it for ratios only).
    """

    ids: np.ndarray
    values: np.ndarray
    background: float
    sigma: float
    threshold: float
    levels: np.ndarray
    noise: tuple[float, float] = (0.0, 0.0)

    def variance_ratio(self, level: np.ndarray) -> np.ndarray:
        """How many times noisier (in variance) a sample is with extended light ``level`` behind
        it (as in ``levels``) than with the typical one, ``background``; at least 1."""
        a, b = self.noise
        typical = a + b * max(self.background, 0.0)
        if typical <= 0:
            return np.ones(np.shape(level))
        return np.maximum((a + b * np.maximum(np.asarray(level, dtype=np.float64), 0.0)) / typical, 1.0)


def check_image(image: np.ndarray, table: LightFieldTable) -> np.ndarray:
    image = np.asarray(image)
    if image.shape != (table.height, table.width):
        raise ParameterError(f"raw image is {image.shape}, the look-up table was built for "
                             f"{(table.height, table.width)}; use the calibration of this camera")
    if image.dtype != np.uint16:
        if not np.issubdtype(image.dtype, np.integer) or (image.size and (image.min() < 0 or image.max() > 65535)):
            raise ParameterError(f"raw image must hold raw counts 0 ... 65535 (uint16), got {image.dtype}; "
                                 "pass the exposure's raw image, not a processed one")
        image = image.astype(np.uint16)
    return np.ascontiguousarray(image).reshape(-1)


def select_samples(image: np.ndarray, table: LightFieldTable, *, black_level: float | None = None,
                   background: float | BackgroundMap | None = None, noise_sigmas: float | None = 3.0,
                   local: bool = True, lens_sigmas: np.ndarray | None = None) -> Samples:
    """Read the table's samples from a raw image, subtract the background, keep those above the noise.

    Parameters
    ----------
    image : ndarray of shape (H, W), uint16
        Raw sensor counts.
    table : LightFieldTable
    black_level : float, optional
        Raw black level; default ``table.black_level``.
    background : float or BackgroundMap, optional
        Extended light in DN of a median-weight pixel, subtracted as ``level * weight`` from each
        sample: one level (a diffuse glow), or a level behind each sample
        (:func:`analysis.lightfield.background.estimate_background`); default: the median of
        ``(raw - black) / weight`` over all samples (robust: particles light a small fraction of
        them). Pass ``0.0`` to keep everything.
    noise_sigmas : float or None
        Keep samples more than this many robust standard deviations above the background;
        ``None`` keeps every sample (dense, slower, same normalisation).
    local : bool
        With a :class:`~analysis.lightfield.background.BackgroundMap`, take each lens's own noise
        (:func:`~analysis.lightfield.background.local_noise`); else, or with False, one model of
        the noise against the light behind the samples for the whole frame, which follows its
        brightest extended light and cuts harder over glow.
    lens_sigmas : ndarray of shape (table.n_lenses,), optional
        With each lens's own noise (a ``BackgroundMap`` and ``local``): the cut of each lens in its
        noise sigmas, in place of ``noise_sigmas``.

    Returns
    -------
    Samples

    Raises
    ------
    ParameterError
        If the image does not match the table, or ``noise_sigmas`` is negative.
    """
    flat = check_image(image, table)
    black = table.black_level if black_level is None else float(black_level)
    stride = _stride(table)
    values, weights = kern.gather_subsample(flat, table.pixel_index, table.weight, float(black), stride)
    if background is None:
        background = _level_and_noise(values, weights)[0]
    levels = (background.per_sample(table) if isinstance(background, BackgroundMap)
              else np.full(table.n_samples, float(background), dtype=np.float32))
    sub_levels = levels[::stride][:values.size]
    if lens_sigmas is not None and (noise_sigmas is None or not local or not isinstance(background, BackgroundMap)
                                    or np.shape(lens_sigmas) != (table.n_lenses,)):
        raise ParameterError("lens_sigmas needs noise_sigmas, local noise (a BackgroundMap) and one value per lens")
    if noise_sigmas is None:
        threshold, sigma, noise = -np.inf, float("nan"), (0.0, 0.0)
    else:
        if noise_sigmas < 0:
            raise ParameterError(f"noise_sigmas must be >= 0 or None, got {noise_sigmas}")
        hist = np.zeros(_HIST_BINS, dtype=np.int64)
        kern.value_histogram(values, weights, sub_levels, False, _HIST_LO, 1.0 / _HIST_BIN_DN, hist)
        centre, sigma = _median_and_sigma(hist, _HIST_LO, _HIST_BIN_DN)
        sigma = max(sigma, _MIN_SIGMA_DN)
        noise = _noise_model(values - sub_levels * weights - centre, sub_levels * weights, sigma)
        typical = float(np.median(sub_levels * weights))
        threshold = centre + float(noise_sigmas) * float(np.sqrt(noise[0] + noise[1] * max(typical, 0.0)))
    lens_threshold = np.empty(0, np.float32)
    if noise_sigmas is not None and isinstance(background, BackgroundMap) and local:
        # Each lens's own noise: over glow the shot noise, over a reflection much more. The one
        # model of the noise against the light behind it (above) follows the reflections and
        # overstates the glow's three- to fourfold on the realistic camera, which cut the samples
        # of faint blurred particles (off-focus ball and cloud, seeds 1-2: 34 more found of 1100,
        # as many false).
        offset, spread = local_noise(image, table, levels).per_lens(table)
        sigmas = float(noise_sigmas) if lens_sigmas is None else np.asarray(lens_sigmas, dtype=np.float64)
        lens_threshold = (offset + sigmas * np.maximum(spread, _MIN_SIGMA_DN)).astype(np.float32)
        threshold = float(np.median(lens_threshold))
    ids, values = kern.select_samples(flat, table.pixel_index, table.weight, float(black), levels,
                                      float(centre) if noise_sigmas is not None else -np.inf,
                                      float(noise_sigmas or 0.0), noise[0], noise[1], table.lens, lens_threshold,
                                      numba.get_num_threads())
    return Samples(ids=ids, values=values, background=float(np.median(sub_levels)), sigma=float(sigma),
                   threshold=float(threshold), levels=levels, noise=(float(noise[0]), float(noise[1])))


def _noise_model(residual: np.ndarray, signal: np.ndarray, sigma: float) -> tuple[float, float]:
    """``(a, b)`` of the noise of one sample, ``sigma^2 = a + b * signal`` (shot noise grows with the
    background's signal in DN): robust spreads of ``residual`` in bins of ``signal``, fitted by least
    squares. Where the background is the same everywhere, ``(sigma^2, 0)``."""
    if signal.size < 1000 or np.ptp(signal) < 4 * sigma:
        return sigma * sigma, 0.0
    edges = np.unique(np.quantile(signal, np.linspace(0.0, 1.0, 11)))
    which = np.clip(np.searchsorted(edges, signal, side="right") - 1, 0, edges.size - 2).astype(np.int8)
    # The bins one after another (a radix sort of the small bin numbers), instead of a mask per bin.
    order = np.argsort(which, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(np.bincount(which, minlength=edges.size - 1))])
    residual, signal = residual[order], signal[order]
    s_mid, var, count = [], [], []
    for k in range(edges.size - 1):
        r = residual[bounds[k]:bounds[k + 1]]
        if r.size >= 50:
            s_mid.append(float(np.median(signal[bounds[k]:bounds[k + 1]])))
            var.append((1.4826 * float(np.median(np.abs(r - np.median(r))))) ** 2)
            count.append(r.size)
    if len(var) < 2:
        return sigma * sigma, 0.0
    design = np.column_stack([np.ones(len(s_mid)), s_mid]) * np.sqrt(count)[:, None]
    a, b = np.linalg.lstsq(design, np.asarray(var) * np.sqrt(count), rcond=None)[0]
    b = max(float(b), 0.0)
    return max(float(a), _MIN_SIGMA_DN ** 2), b


def background_and_noise(image: np.ndarray, table: LightFieldTable) -> tuple[float, float]:
    """The typical background (DN of a median-weight pixel) and the noise of one sample about it
    (DN, robust), from a subsample of the table's samples."""
    flat = check_image(image, table)
    values, weights = kern.gather_subsample(flat, table.pixel_index, table.weight, float(table.black_level),
                                            _stride(table))
    return _level_and_noise(values, weights)


def _level_and_noise(values: np.ndarray, weights: np.ndarray) -> tuple[float, float]:
    hist = np.zeros(_HIST_BINS, dtype=np.int64)
    kern.value_histogram(values, weights, np.zeros(values.size, np.float32), True, _HIST_LO, 1.0 / _HIST_BIN_DN, hist)
    level = _median_and_sigma(hist, _HIST_LO, _HIST_BIN_DN)[0]
    hist[:] = 0
    kern.value_histogram(values, weights, np.full(values.size, level, np.float32), False, _HIST_LO,
                         1.0 / _HIST_BIN_DN, hist)
    return level, _median_and_sigma(hist, _HIST_LO, _HIST_BIN_DN)[1]


def _stride(table: LightFieldTable) -> int:
    """Every how many samples the background statistics look at: about 200 000 are plenty."""
    return max(1, table.n_samples // 200_000)


def _median_and_sigma(hist: np.ndarray, lo: float, width: float) -> tuple[float, float]:
    """Median and 1.4826 * MAD of values given by their histogram (bin ``k`` centred on
    ``lo + k * width``), values taken as spread evenly within their bin."""
    total = float(hist.sum())
    if total == 0:
        return 0.0, 0.0
    nonzero = np.flatnonzero(hist)
    first, last = int(nonzero[0]), int(nonzero[-1])
    counts = hist[first:last + 1].astype(np.float64)
    edges = lo + (np.arange(first, last + 2, dtype=np.float64) - 0.5) * width
    cdf = np.concatenate([[0.0], np.cumsum(counts)]) / total
    k = int(np.searchsorted(cdf, 0.5, side="left"))      # cdf[k-1] < 0.5 <= cdf[k]
    k = min(max(k, 1), cdf.size - 1)
    median = edges[k - 1] + (0.5 - cdf[k - 1]) / max(cdf[k] - cdf[k - 1], 1e-300) * width
    # MAD: the half-width d with half the values in [median - d, median + d] (bisection).
    d_lo, d_hi = 0.0, float(edges[-1] - edges[0])
    for _ in range(50):
        d = 0.5 * (d_lo + d_hi)
        inside = np.interp(median + d, edges, cdf) - np.interp(median - d, edges, cdf)
        if inside < 0.5:
            d_lo = d
        else:
            d_hi = d
    return float(median), 1.4826 * 0.5 * (d_lo + d_hi)
