"""Hot, stuck and dead pixels of a camera, found from its calibration frames.

A sensor's defects are the same in every frame it takes, the white images and the dark white image
alike, while noise is not. Each frame's pixels are compared with what the frame predicts for them
from the micro-images around (:func:`frame_residuals`): a white image repeats from micro-image to
micro-image, and since their centres fall at every sub-pixel phase, some lattice steps are within a
tenth of a pixel of a whole, even number of pixels (:func:`witness_steps`); the pixels that far away
sit at the same place in their micro-images and are of the same Bayer colour. The median of seven
such witnesses, each scaled by the ratio of the two lenses' levels (transmission, vignetting), is
the prediction; no interpolation, whose error on the steep micro-image rims repeats in every white
image of one geometry and would pass for a defect. The noise is the frame's own at that level plus
the witnesses' disagreement. A pixel is a defect (:func:`find_defects`) when

- it is bright in a dark frame (hot pixels add a fixed number of DN, which a dark frame shows best,
  and stuck ones read the white level), or
- it deviates the same way in every white image, and so much in all of them together that noise
  cannot explain it (hot, warm, stuck pixels; dead ones read black where light falls).

Faint warm pixels whose excess drowns in the bright frames' shot noise stay unmasked unless a dark
frame shows them; they are as faint in an exposure. Dead pixels between micro-images, where no light
falls, cannot be told from their neighbours, and no look-up table uses them.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass
from functools import cached_property
from typing import Iterable, Sequence

import numpy as np

from analysis.camera.model import Lattice
from analysis.errors import CalibrationError

from .defects_kernels import (accumulate_frame, lattice_steps, lens_levels, predict_from_neighbours,
                              residual_and_sigma)

log = logging.getLogger(__name__)

#: Bump when the search changes what it finds: the defect maps' cache files carry it.
DEFECTS_VERSION = 1
#: A pixel whose excess over its prediction, one fixed number of DN in every frame (what a hot pixel
#: adds), is this many sigmas from zero over all frames together ...
REPEAT_SIGMAS = 7.0
#: ... and that no frame shows ``AGREE_SIGMAS`` the other way, is hot when at least two frames show
#: it ``AGREE_SIGMAS`` (it repeats), or a dark frame ``DARK_SIGMAS`` (it is bright in the dark).
AGREE_SIGMAS = 2.0
DARK_SIGMAS = 6.0
#: A pixel reading under this fraction of its prediction in every bright frame, where the prediction
#: is at least ``LIT_FRACTION`` of its micro-image's central level, is dead (or nearly).
DEAD_FRACTION = 0.2
LIT_FRACTION = 0.1
#: With one frame only, a deviation of this many sigmas makes a defect.
SINGLE_SIGMAS = 10.0
#: Each pixel is predicted from the ``WITNESSES`` pixels of its colour on the sensor, among the
#: micro-images within ``WITNESS_RINGS`` lattice rings, that sit nearest to the same place in theirs.
WITNESS_RINGS = 8
WITNESSES = 7


@dataclass(frozen=True)
class CalibrationFrame:
    """One frame the defect search reads: a white (or dark) image and its micro-image lattice."""

    name: str
    raw: np.ndarray
    lattice: Lattice
    dark: bool


@dataclass(frozen=True)
class FrameResiduals:
    """One frame's pixels against what its micro-images predict, in DN (float32 (H, W)).

    ``lit`` is True where the prediction is at least ``LIT_FRACTION`` of the micro-image's central
    level (light falls there).
    """

    residual_dn: np.ndarray
    sigma_dn: np.ndarray
    predicted_dn: np.ndarray
    lit: np.ndarray

    @property
    def z(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.residual_dn / self.sigma_dn


@dataclass(frozen=True, eq=False)
class DefectMap:
    """Pixels of one sensor that do not respond as their neighbours do.

    Attributes
    ----------
    height, width : int
        Sensor size.
    index : ndarray of shape (N,), int64
        Flat indices ``row * width + col`` of the defective pixels, sorted.
    kind : ndarray of shape (N,), int8
        :data:`HOT` (brighter than their micro-images predict: hot, warm, stuck) or :data:`DARK`
        (darker: dead, low response).
    frames : tuple of str
        Names of the frames searched (white images, dark ones included).
    key : str
        SHA-1 over the searched frames' SHA-1s and :data:`DEFECTS_VERSION`: what the map and the
        look-up tables built with it are filed under.
    """

    height: int
    width: int
    index: np.ndarray
    kind: np.ndarray
    frames: tuple[str, ...] = ()
    key: str = ""
    HOT = 1
    DARK = 2

    @property
    def n_hot(self) -> int:
        return int(np.count_nonzero(self.kind == self.HOT))

    @property
    def n_dark(self) -> int:
        return int(np.count_nonzero(self.kind == self.DARK))

    def __len__(self) -> int:
        return int(self.index.size)

    @cached_property
    def mask(self) -> np.ndarray:
        """ndarray (H, W) bool, True on a defect (built once)."""
        mask = np.zeros(self.height * self.width, dtype=bool)
        mask[self.index] = True
        return mask.reshape(self.height, self.width)

    @classmethod
    def empty(cls, height: int, width: int) -> "DefectMap":
        return cls(height, width, np.empty(0, np.int64), np.empty(0, np.int8))


def frames_key(sha1s: Sequence[str]) -> str:
    """The key of a defect map found from frames of these SHA-1s (order does not matter)."""
    text = f"defects v{DEFECTS_VERSION}\n" + "\n".join(sorted(sha1s))
    return hashlib.sha1(text.encode()).hexdigest()


def witness_steps(lattice: Lattice, *, rings: int = WITNESS_RINGS, n_use: int = 3 * WITNESSES
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The ``n_use`` lattice steps whose sensor vector is nearest to a whole, even number of pixels in x
    and in y (and, among equals, shortest).

    A pixel moved by such a shift lands on a pixel of its own Bayer colour at nearly the same place in
    another micro-image (the same for every pixel: pixel centres are a grid). Returns ``steps`` (n, 2)
    ``(si, sj)`` and ``shifts`` (n, 2) whole pixels ``(dx, dy)``, best match first.

    Examples
    --------
    >>> steps, shifts = witness_steps(Lattice(0.0, 0.0, 10.0), rings=3, n_use=2)
    >>> shifts.tolist()
    [[-10, 0], [10, 0]]
    """
    steps = lattice_steps(rings)
    vec = steps @ lattice.basis.T
    shifts = 2 * np.rint(vec / 2.0).astype(np.int64)
    miss = np.hypot(*(shifts - vec).T)
    order = np.lexsort((np.hypot(*vec.T), miss))[:n_use]
    return steps[order], shifts[order]


@dataclass(frozen=True)
class _Prediction:
    """One frame balanced by its Bayer channels' means, and each pixel's prediction from its witnesses."""

    balanced: np.ndarray     # (H, W) float32: raw above black over its channel's mean
    pred: np.ndarray         # (H, W) float32, same units; NaN without three witnesses
    spread: np.ndarray       # (H, W) float32: the witnesses' disagreement
    means: np.ndarray        # (2, 2) float64: the channels' means (DN)
    level: float             # median micro-image central level (balanced units)


def _predict(raw: np.ndarray, lattice: Lattice, *, black_level: float, radius_px: float) -> _Prediction:
    h, w = raw.shape
    balanced = raw.astype(np.float32)
    balanced -= np.float32(black_level)
    means = np.ones((2, 2))
    for r0 in (0, 1):
        for c0 in (0, 1):
            channel = balanced[r0::2, c0::2]
            level = float(channel.mean(dtype=np.float64))
            if level > 1.0:  # a frame without light (a lens-cap dark frame) is taken as it is
                means[r0, c0] = level
                channel *= np.float32(1.0 / level)
    basis = lattice.basis
    ij = lattice.lens_indices(w, h, margin_px=-2.0 * lattice.pitch_px)
    i0, j0 = ij.min(axis=0)
    span = ij.max(axis=0) - ij.min(axis=0) + 1
    levels = np.empty((int(span[1]), int(span[0])))
    lens_levels(balanced, lattice.origin_x, lattice.origin_y, basis, int(i0), int(j0), 0.5 * radius_px, levels)
    pred = np.empty_like(balanced)
    spread = np.empty_like(balanced)
    steps, shifts = witness_steps(lattice)
    predict_from_neighbours(balanced, lattice.origin_x, lattice.origin_y, basis, np.linalg.inv(basis), levels,
                            int(i0), int(j0), steps, shifts, WITNESSES, pred, spread)
    finite = levels[np.isfinite(levels)]
    return _Prediction(balanced, pred, spread, means, float(np.median(finite)) if finite.size else 0.0)


def frame_residuals(raw: np.ndarray, lattice: Lattice, *, black_level: float, radius_px: float,
                    rng: np.random.Generator | None = None) -> FrameResiduals:
    """Each pixel of a white or dark frame against the same place in the micro-images around it.

    Parameters
    ----------
    raw : ndarray of shape (H, W)
        The frame (raw counts, Bayer).
    lattice : Lattice
        Its micro-image lattice (only the steps between lenses matter, not the origin).
    black_level : float
    radius_px : float
        Micro-image radius; each lens's level is the median of its pixels within half of it.
    rng : numpy.random.Generator, optional
        Draws the pixels the noise level is measured on (a fixed seed by default).

    Returns
    -------
    FrameResiduals
        ``residual_dn`` the pixel minus its prediction (:func:`witness_steps`); ``sigma_dn`` the noise
        expected there: the frame's own noise at that level (robustly measured where the witnesses
        agree) and their disagreement, in quadrature, scaled so that the residuals' robust spread is
        one sigma. NaN where fewer than three witnesses are on the sensor.
    """
    p = _predict(np.asarray(raw), lattice, black_level=black_level, radius_px=radius_px)
    residual, sigma = _residuals(p, rng=rng)
    lit = p.pred >= LIT_FRACTION * p.level
    return FrameResiduals(residual_dn=residual, sigma_dn=sigma, predicted_dn=p.pred * _channel_map(p.means, p.pred.shape),
                          lit=lit)


def _channel_map(means: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    h, w = shape
    return np.tile(means.astype(np.float32), ((h + 1) // 2, (w + 1) // 2))[:h, :w]


@dataclass(frozen=True)
class _NoiseModel:
    """A frame's noise by predicted level (DN) and the scale that makes its residuals' spread one sigma."""

    level: np.ndarray
    noise: np.ndarray
    scale: float


def _noise_model(p: _Prediction, *, rng: np.random.Generator | None = None, n_sample: int = 200_000) -> _NoiseModel:
    """The frame's noise, measured on a sample of its pixels.

    Noise by level where the witnesses agree best, in quadrature with their disagreement: the two
    overlap (witnesses that agree still differ a little), so sigma is scaled to make the residuals'
    robust spread one.
    """
    rng = np.random.default_rng(0) if rng is None else rng
    h, w = p.pred.shape
    rows, cols = np.divmod(rng.integers(0, h * w, size=min(n_sample, h * w)), w)
    m = p.means[rows % 2, cols % 2]
    pred, spread = p.pred[rows, cols] * m, p.spread[rows, cols] * m
    res = p.balanced[rows, cols] * m - pred
    ok = np.isfinite(pred) & np.isfinite(res)
    if ok.sum() < 1000:
        raise CalibrationError("too few pixels of the calibration frame have micro-images around them; check its "
                               "lattice")
    pred, spread, res = pred[ok], spread[ok], res[ok]
    level, noise = _noise_by_level(pred, spread, res)
    z = res / np.sqrt(np.interp(pred, level, noise) ** 2 + spread ** 2)
    z = z[np.isfinite(z)]
    scale = max(1.4826 * float(np.median(np.abs(z - np.median(z)))), 0.25) if z.size else 1.0
    return _NoiseModel(level, noise, scale)


def _residuals(p: _Prediction, *, rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Residuals and sigmas (DN) of a prediction (float32 (H, W))."""
    noise = _noise_model(p, rng=rng)
    residual = np.empty_like(p.pred)
    sigma = np.empty_like(p.pred)
    residual_and_sigma(p.balanced, p.pred, p.spread, p.means, noise.level, noise.noise, noise.scale, residual, sigma)
    return residual, sigma


def _noise_by_level(pred: np.ndarray, spread: np.ndarray, residual: np.ndarray, *,
                    n_bins: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """The frame's noise (DN) by predicted level: in bins of the level, the robust spread of the
    residuals where the witnesses agree best (lowest third of their disagreement). Returns the bins'
    levels (increasing) and noise."""
    edges = np.unique(np.quantile(pred, np.linspace(0.0, 1.0, n_bins + 1)))
    centres, sigmas = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        inside = (pred >= lo) & (pred <= hi)
        if inside.sum() < 60:
            continue
        quiet = inside & (spread <= np.quantile(spread[inside], 1.0 / 3.0))
        rr = residual[quiet]
        centres.append(float(np.median(pred[quiet])))
        sigmas.append(1.4826 * float(np.median(np.abs(rr - np.median(rr)))))
    if not centres:
        raise CalibrationError("the calibration frame is too small to measure its noise")
    level = np.asarray(centres)
    keep = np.r_[True, np.diff(level) > 0]
    # Noise never falls as the level rises (shot noise): a running maximum steadies the bins.
    return level[keep], np.maximum.accumulate(np.maximum(np.asarray(sigmas), 1e-3))[keep]


def find_defects(frames: Iterable[CalibrationFrame], *, black_level: float, radius_px: float,
                 key: str = "") -> DefectMap:
    """Hot, stuck and dead pixels from a camera's calibration frames (see the module's doc).

    Parameters
    ----------
    frames : iterable of CalibrationFrame
        Frames of one camera (same sensor size), bright white images and dark ones; read one at a
        time (a generator keeps one in memory).
    black_level : float
    radius_px : float
        Micro-image radius (pixels).
    key : str
        Stored with the map (:func:`frames_key` of the frames' SHA-1s).

    Returns
    -------
    DefectMap

    Raises
    ------
    CalibrationError
        If there is no frame, or the frames' sizes differ.
    """
    acc: dict[str, np.ndarray] = {}
    names: list[str] = []
    n_bright = 0
    for frame in frames:
        if not acc:
            h, w = frame.raw.shape
            acc = {"sum_w": np.zeros((h, w), np.float32), "sum_wr": np.zeros((h, w), np.float32),
                   "n_up": np.zeros((h, w), np.int8), "n_down": np.zeros((h, w), np.int8),
                   "dark_hot": np.zeros((h, w), bool), "n_dead": np.zeros((h, w), np.int8)}
        elif frame.raw.shape != acc["sum_w"].shape:
            raise CalibrationError("the calibration frames differ in size; give frames of one camera and sensor crop")
        p = _predict(frame.raw, frame.lattice, black_level=black_level, radius_px=radius_px)
        noise = _noise_model(p)
        accumulate_frame(p.balanced, p.pred, p.spread, p.means, noise.level, noise.noise, noise.scale, frame.dark,
                         LIT_FRACTION * p.level, DEAD_FRACTION, AGREE_SIGMAS, DARK_SIGMAS, acc["sum_w"], acc["sum_wr"],
                         acc["n_up"], acc["n_down"], acc["dark_hot"], acc["n_dead"])
        del p
        names.append(frame.name)
        n_bright += not frame.dark
        log.debug("defects: frame %s searched", frame.name)
    if not acc:
        raise CalibrationError("no calibration frame to find defective pixels in; pull the camera's white images")
    h, w = acc["sum_w"].shape
    with np.errstate(invalid="ignore", divide="ignore"):
        combined = acc["sum_wr"] / np.sqrt(acc["sum_w"])
    n_up, n_down = acc["n_up"], acc["n_down"]
    if len(names) >= 2:
        hot = (combined > REPEAT_SIGMAS) & (n_down == 0) & ((n_up >= 2) | acc["dark_hot"])
        dark = (combined < -REPEAT_SIGMAS) & (n_up == 0) & (n_down >= min(2, n_bright))
    else:
        hot = combined > SINGLE_SIGMAS
        dark = combined < -SINGLE_SIGMAS
    if n_bright:
        dark |= acc["n_dead"] >= n_bright
    dark &= ~hot
    index = np.flatnonzero((hot | dark).reshape(-1))
    kind = np.where(hot.reshape(-1)[index], DefectMap.HOT, DefectMap.DARK).astype(np.int8)
    found = DefectMap(h, w, index.astype(np.int64), kind, tuple(names), key)
    log.info("defects: %d hot or stuck, %d dead or dark pixels in %d frames (%d dark)", found.n_hot, found.n_dark,
             len(names), len(names) - n_bright)
    return found
