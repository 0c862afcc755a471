"""Particle detection in one image by the moment method (Feng, Goree & Liu 2007).

Pixels above a threshold just over the noise are grouped into contiguous blobs; each blob's
position is its intensity-weighted centroid with the threshold subtracted from every pixel
(which is what keeps the centroid from locking onto pixel centres), and its apparent
brightness is its mean intensity per pixel.

Positions are in *index* coordinates of the image: the centre of pixel ``image[r, c]`` is
``(x, y) = (c, r)``.

References
----------
Y. Feng, J. Goree and B. Liu, "Accurate particle position measurement from images",
Rev. Sci. Instrum. 78, 053704 (2007).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from analysis.errors import ParameterError

# 1.4826 * MAD is the standard deviation of normally distributed noise.
_MAD_TO_SIGMA = 1.4826
# The noise estimate needs no more than this many pixels; larger inputs are strided.
_NOISE_SAMPLE = 1 << 18


@dataclass(frozen=True)
class Detections:
    """Blobs found in one image; every array has shape ``(n,)``.

    Attributes
    ----------
    x, y : float64
        Threshold-subtracted intensity-weighted centroid, index coordinates (pixel
        ``[r, c]`` has its centre at ``(c, r)``).
    brightness : float64
        Apparent brightness: mean intensity per pixel of the blob (Feng et al.).
    mass : float64
        Sum of ``intensity - threshold`` over the blob.
    npix : int64
        Number of pixels in the blob.
    peak : float64
        Highest pixel value in the blob.
    threshold : float
        The threshold that was applied.
    """

    x: np.ndarray
    y: np.ndarray
    brightness: np.ndarray
    mass: np.ndarray
    npix: np.ndarray
    peak: np.ndarray
    threshold: float

    def __len__(self) -> int:
        return int(self.x.shape[0])

    @classmethod
    def empty(cls, threshold: float = float("nan")) -> "Detections":
        f = np.empty(0, dtype=np.float64)
        return cls(x=f, y=f.copy(), brightness=f.copy(), mass=f.copy(),
                   npix=np.empty(0, dtype=np.int64), peak=f.copy(), threshold=threshold)


@dataclass(frozen=True)
class NoiseLevel:
    """Robust background level and noise of an image (median and scaled MAD)."""

    background: float
    sigma: float

    def threshold(self, threshold_sigma: float) -> float:
        return self.background + threshold_sigma * self.sigma


def estimate_noise(image: np.ndarray) -> NoiseLevel:
    """Robust background and noise of an image (or a stack) from its median and MAD.

    Particles cover a small part of the image, so the median is the background and the
    median absolute deviation the noise. Where more than half of the pixels share one value
    (a noise-free or zero-padded image), the deviation is taken over the other pixels.

    Parameters
    ----------
    image : ndarray of any shape
        Finite values; a stack is treated as one sample.

    Returns
    -------
    NoiseLevel

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> level = estimate_noise(10 + 2 * rng.standard_normal((200, 200)))
    >>> round(level.background), round(level.sigma)
    (10, 2)
    """
    values = np.asarray(image).ravel()
    if values.size == 0:
        return NoiseLevel(0.0, 0.0)
    if values.size > _NOISE_SAMPLE:
        values = values[:: values.size // _NOISE_SAMPLE]
    values = values[np.isfinite(values)].astype(np.float64)
    if values.size == 0:
        return NoiseLevel(0.0, 0.0)
    background = float(np.median(values))
    deviation = np.abs(values - background)
    sigma = _MAD_TO_SIGMA * float(np.median(deviation))
    if sigma <= 0.0:
        off = deviation[deviation > 0]
        sigma = _MAD_TO_SIGMA * float(np.median(off)) if off.size else 0.0
    return NoiseLevel(background, sigma)


def detect(image: np.ndarray, *, threshold: float | None = None, threshold_sigma: float = 5.0,
           min_pixels: int = 2, dilate_px: int = 0) -> Detections:
    """Find blobs above a threshold and measure their centroid and apparent brightness.

    Parameters
    ----------
    image : ndarray of shape (H, W)
        One image (a refocused slice times the sub-aperture image, in the pipeline).
    threshold : float, optional
        Absolute threshold. Default: ``background + threshold_sigma * noise`` from
        :func:`estimate_noise`.
    threshold_sigma : float
        Threshold in units of the noise above the background, when ``threshold`` is None.
    min_pixels : int
        Blobs with fewer pixels than this are dropped (isolated noise pixels).
    dilate_px : int
        Grow each blob by this many pixels before measuring (pixels below the threshold
        then weigh zero in the centroid but count for the brightness); 0 keeps Feng's method.

    Returns
    -------
    Detections
        Sorted by blob label (top-left to bottom-right).

    Raises
    ------
    ParameterError
        If the image is not 2-D or a setting is out of range.

    Examples
    --------
    >>> img = np.zeros((9, 9)); img[3:6, 4:7] = [[1, 2, 1], [2, 4, 2], [1, 2, 1]]
    >>> d = detect(img, threshold=0.5)
    >>> float(d.x[0]), float(d.y[0]), float(d.brightness[0])
    (5.0, 4.0, 1.7777777777777777)
    """
    image = np.asarray(image)
    if image.ndim != 2:
        raise ParameterError(f"detect needs a 2-D image, got shape {image.shape}; detect each slice of a stack")
    if min_pixels < 1:
        raise ParameterError(f"min_pixels must be at least 1, got {min_pixels}")
    if dilate_px < 0:
        raise ParameterError(f"dilate_px must be 0 or more, got {dilate_px}")
    if threshold is None:
        threshold = estimate_noise(image).threshold(threshold_sigma)
    threshold = float(threshold)
    if image.size == 0:
        return Detections.empty(threshold)

    mask = image > threshold  # NaN compares False, so non-finite pixels never join a blob
    if dilate_px:
        size = 2 * dilate_px + 1
        mask = cv2.dilate(mask.view(np.uint8), np.ones((size, size), np.uint8)).view(bool)
    count, labels, stats, _ = cv2.connectedComponentsWithStats(
        mask.view(np.uint8), connectivity=8, ltype=cv2.CV_32S)
    if count <= 1:
        return Detections.empty(threshold)

    flat = np.flatnonzero(mask)
    lab = labels.ravel()[flat]
    vals = image.ravel()[flat].astype(np.float64)
    if dilate_px:
        vals = np.where(np.isfinite(vals), vals, 0.0)
    weight = np.maximum(vals - threshold, 0.0)
    rows, cols = np.divmod(flat, image.shape[1])
    wsum = np.bincount(lab, weights=weight, minlength=count)
    wx = np.bincount(lab, weights=weight * cols, minlength=count)
    wy = np.bincount(lab, weights=weight * rows, minlength=count)
    isum = np.bincount(lab, weights=vals, minlength=count)
    peak = np.full(count, -np.inf)
    np.maximum.at(peak, lab, vals)
    npix = stats[:, cv2.CC_STAT_AREA].astype(np.int64)

    keep = (npix >= min_pixels) & (wsum > 0)
    keep[0] = False  # label 0 is the background
    wsum, npix = wsum[keep], npix[keep]
    return Detections(x=wx[keep] / wsum, y=wy[keep] / wsum, brightness=isum[keep] / npix,
                      mass=wsum, npix=npix, peak=peak[keep], threshold=threshold)
