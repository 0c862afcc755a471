"""The refocus range of an exposure: the one its particles need, found from the exposure itself.

A fixed alpha range silently loses every particle outside it. By default the pipeline first looks
over the whole range in which a particle still images onto a handful of lenses (a blur of up to
:data:`SURVEY_BLUR_PITCHES` lens pitches either side of focus), coarsely, and then refocuses
finely over the range that holds the brightness peaks it saw. A range the user gives wins; then
the particles seen at its edges are reported instead.
"""

from __future__ import annotations

import math

import numpy as np

from analysis.depth.rayfit import FitGrid
from analysis.lightfield.table import LightFieldTable

#: The survey looks as far from focus as a blur of this many lens pitches (radius on the MLA):
#: beyond it a particle's light spreads over hundreds of lenses, a few DN each.
SURVEY_BLUR_PITCHES = 12.0
#: Slices of the survey: about two per width of a brightness peak (a blur change of a pitch).
SURVEY_SLICES = 48
#: The found range is widened by this many survey steps either side (a peak's half width) ...
SURVEY_MARGIN_STEPS = 2.0
#: The fit that checks the survey's peaks: a cheap fine pass (it sets a range, not positions).
SURVEY_GRID = FitGrid(depths=5, lateral_pitches=0.15, positions=3, pixel_points=3, temperature=0.25)
#: ... and is at least this wide in alpha: the paper's 0.987 ... 1.013, which the stack covers
#: with ``n_slices`` slices (a compact cluster gets the step the pipeline's thresholds were set
#: with; a wider range gets more slices of that step).
MIN_RANGE = 0.026
#: The fine stack's alphas lie on one lattice, ``ANCHOR + k * step`` (the paper's 0.987 ... 1.013
#: among them), so that stacks of different exposures share the refocus normalisations of their
#: slices (each costs about 25 ms full size to work out).
ANCHOR = 0.987
#: A fit may leave the found range by at most this many of its steps. The survey saw no point
#: source beyond it, so a fit there is explaining light that is not a particle's: a compact glint
#: far out of focus (held-out cloud seed 21: one 0.08 mm across, at alpha 1.052 against the
#: particles' 1.016 at most, whose blurred disk 18 fits tiled, at alphas of 1.016-1.044, each
#: leaving little of its light unexplained). Real particles were fitted at most 2.5 steps beyond
#: the range (seeds 17-21, 21 realistic exposures).
FIT_MARGIN_STEPS = 4.0


def survey_alphas(table: LightFieldTable, *, blur_pitches: float = SURVEY_BLUR_PITCHES,
                  n: int = SURVEY_SLICES) -> np.ndarray:
    """Alphas evenly spaced over the range where a particle's blur radius stays below
    ``blur_pitches`` lens pitches, in front of focus and behind it."""
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    c_max = min(blur_pitches * pitch / table.aperture_radius_m, 0.5)  # c = 1 - 1/alpha
    return np.linspace(1.0 / (1.0 + c_max), 1.0 / (1.0 - c_max), n)


def lattice_step(n_slices: int) -> float:
    """The fine stack's alpha step for a found range: ``n_slices`` per :data:`MIN_RANGE`."""
    return MIN_RANGE / (n_slices - 1)


#: A cluster's point sources lie close in depth: on the realistic scenes of seeds 106-109 (layers,
#: shadowing pairs, balls, clouds) no gap between one particle's alpha and the next exceeds 1.6
#: survey steps. At most :data:`LONE_MAX` point fits farther than this many steps in alpha from
#: all the others, at an end of the survey's fits, while at least :data:`LONE_REST` lie together,
#: are kept out of the range: a compact glint far out of focus fits as a point (seed 108: 0.09 mm
#: across, 11-16 steps from the particles, set the range's end, tripled the time and left seven
#: false particles) and so would a lone particle; :func:`apart` finds them, and the pipeline
#: reports them.
LONE_GAP_STEPS = 6.0
LONE_MAX = 2
LONE_REST = 10


def apart(alpha: np.ndarray, survey: np.ndarray) -> np.ndarray:
    """Which of the survey's point fits (their ``alpha``) lie apart from the others: in a group of at
    most :data:`LONE_MAX` at an end, more than :data:`LONE_GAP_STEPS` steps of ``survey`` from the
    next fit, with at least :data:`LONE_REST` fits left (a mask)."""
    alpha = np.asarray(alpha, dtype=np.float64)
    out = np.zeros(alpha.size, dtype=bool)
    if alpha.size == 0:
        return out
    order = np.argsort(alpha)
    group = np.r_[0, np.cumsum(np.diff(alpha[order]) > LONE_GAP_STEPS * float(survey[1] - survey[0]))]
    size = np.bincount(group)
    lone = np.zeros(size.size, dtype=bool)
    left, lo, hi = alpha.size, 0, size.size - 1
    while lo < hi and size[lo] <= LONE_MAX and left - size[lo] >= LONE_REST:
        lone[lo], left, lo = True, left - size[lo], lo + 1
    while lo < hi and size[hi] <= LONE_MAX and left - size[hi] >= LONE_REST:
        lone[hi], left, hi = True, left - size[hi], hi - 1
    out[order] = lone[group]
    return out


def range_of_peaks(peak_alpha: np.ndarray, survey: np.ndarray, *, n_slices: int,
                   margin: float = 0.0) -> np.ndarray | None:
    """The fine stack's alphas: the span of the survey's peaks, widened by a margin
    (:data:`SURVEY_MARGIN_STEPS` survey steps plus ``margin``) and to at least :data:`MIN_RANGE`,
    within the survey, on the lattice of ``MIN_RANGE / (n_slices - 1)`` steps; None when the
    survey saw no peak."""
    peak_alpha = np.asarray(peak_alpha, dtype=np.float64)
    peak_alpha = peak_alpha[np.isfinite(peak_alpha)]
    if peak_alpha.size == 0:
        return None
    step = lattice_step(n_slices)
    margin += SURVEY_MARGIN_STEPS * float(survey[1] - survey[0])
    lo = max(float(peak_alpha.min()) - margin, float(survey[0]))
    hi = min(float(peak_alpha.max()) + margin, float(survey[-1]))
    k_lo = math.floor((lo - ANCHOR) / step + 1e-9)
    k_hi = math.ceil((hi - ANCHOR) / step - 1e-9)
    n = max(int(n_slices), k_hi - k_lo + 1)
    k_lo -= (n - (k_hi - k_lo + 1)) // 2  # widened evenly about the peaks
    return ANCHOR + (k_lo + np.arange(n)) * step


def fit_limits(found: np.ndarray, survey: np.ndarray) -> tuple[float, float]:
    """The alphas a fit may take when the range was found (``found``) by the ``survey``: the found
    range widened by :data:`FIT_MARGIN_STEPS` of its steps, within the survey's."""
    margin = FIT_MARGIN_STEPS * float(found[1] - found[0])
    return max(float(survey[0]), float(found[0]) - margin), min(float(survey[-1]), float(found[-1]) + margin)


def edge_maxima(brightness: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Which brightness curves (rows of (n, n_slices), NaN where undetected, seen in at least 3
    slices) are brightest on the first slice, and which on the last: particles whose peak may lie
    outside the range (two arrays of row indices)."""
    b = np.where(np.isfinite(brightness), brightness, -np.inf)
    seen = np.sum(np.isfinite(brightness), axis=1) >= 3
    top = np.argmax(b, axis=1) if b.size else np.zeros(0, dtype=np.int64)
    return np.flatnonzero(seen & (top == 0)), np.flatnonzero(seen & (top == brightness.shape[1] - 1))
