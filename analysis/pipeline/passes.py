"""The detection passes after the first: each looks again at the raw image with the light of the
particles found so far taken off, and keeps the new candidates that prove to be particles.

:func:`look_again` runs between the first fits and deblending (``PipelineParams.passes``),
:func:`late_pass` once the particles are deblended (``PipelineParams.late_pass``);
:func:`above_noise` is the screen every pass's candidates go through before their fits.
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from analysis.depth.deblend import deblend
from analysis.depth.quality import converges, patterned
from analysis.depth.rayfit import RESIDUAL_POINTS, RayFit
from analysis.depth.refine import (PROBE_RESIDUAL, SAME_DEPTH_SIGMAS, RayFitter, inside, outshines_misfit, refine_peaks,
                                   residual_image)
from analysis.depth.table_index import table_index
from analysis.detection.curves import Peaks, Tracks
from analysis.lightfield.background import BackgroundMap
from analysis.lightfield.refocus import products, refocus_stack, subaperture_image
from analysis.lightfield.samples import select_samples
from analysis.lightfield.table import LightFieldTable

from .candidates import below_local_noise, locate
from .params import PipelineParams
from .stages import trim_heap
from .tables import release_table_pages

log = logging.getLogger(__name__)

#: A new particle must be this fraction as bright as the brightest found particle whose light
#: reaches it (left-over light of an imperfectly modelled one: a fifth of it or less), or outshine
#: their misfit (:func:`analysis.depth.refine.outshines_misfit`).
NEW_FRACTION = 0.2
#: In the late pass, where the found particles' light was taken off, the residual's samples are
#: kept down to this many noise sigmas of their lens (elsewhere ``PipelineParams.noise_sigmas``, 3):
#: a faint particle blurred over 10-14 pitches among brighter ones puts a few DN per pixel in each
#: lens, under the usual cut, so its refocused spot and sub-aperture point held only the samples
#: the noise lifted, and it made no candidate (tuning seeds 27-28, realistic clouds: 26 of 46
#: missed particles had none). The stack averages the extra noise down where it sums the
#: particle's light. Only the late pass: its fits are deblended, and explain their own light
#: better. In the passes before deblending too, tuning seeds 27-28 (off-focus balls and clouds,
#: every effect) found 1055 of 1100 instead of 1050 (1047 with the usual cut), but an ideal-optics
#: test ball got a false fit on a blurred particle's line of sight. Cutting every lens so in every
#: residual pass, not only those the fits reach, found 3 more for 1.28x the time of a ball's passes.
RESIDUAL_NOISE_SIGMAS = 1.0
#: The late pass's new fits blurred over at least this many lens pitches (radius) need not show a
#: point's pattern within their lenses: a faint particle's light spread that thin leaves a pattern
#: the noise swamps (on realistic tuning frames, the real ones the pass found there explained
#: 0.006-0.1 of their light's variation as points, the false ones as little) ...
THIN_PATTERN_PITCHES = 4.0
#: ... if they fit their pixels this well (misfit per sample over the intensity; those real ones
#: 0.05-0.13, the false ones there 0.05-0.2, most of which the second deblending drops).
THIN_PATTERN_RESIDUAL = 0.13


def look_again(fitter: RayFitter, table: LightFieldTable, background: BackgroundMap, params: PipelineParams,
               alphas: np.ndarray, limits: tuple[float, float], threshold: float, peaks: Peaks, tracks: Tracks,
               fit: RayFit, lens_noise: np.ndarray, *, low_cut: bool = False) -> tuple[Peaks, Tracks, RayFit] | None:
    """One more detection pass on the raw image with the found particles' light taken off.

    Crowded clusters: blobs of neighbours merge in the product images. Returns the particles with
    the new ones added, or None when the pass finds none. With ``low_cut``, the residual's samples
    in the lenses the fits reach are cut at :data:`RESIDUAL_NOISE_SIGMAS`.
    """
    if len(peaks) == 0:
        return None
    explained = fitter.render(fit, points=RESIDUAL_POINTS)
    residual = residual_image(fitter.image, fitter.table, explained)
    # The fits so far touched much of the fit table (60-100 MB on a frame with many candidates):
    # its pages go back while the residual's samples and stack are made, and are read in again
    # from the file cache.
    release_table_pages(fitter.table, fitter.cache)
    cut = residual_cut(table, fitter.image, residual, params.noise_sigmas) if low_cut else None
    rs = select_samples(residual, table, background=background, noise_sigmas=params.noise_sigmas, lens_sigmas=cut)
    # The residual image (21 MB on an F01) and the fits' light (18 MB) go before the stack: the
    # light is rendered again for the fits below (realistic off-focus ball 86: peak 605 -> 587 MB).
    del residual, explained
    trim_heap()
    rstack = refocus_stack(None, table, alphas, grid=fitter.grid, samples=rs, cache=fitter.cache)
    rsub = subaperture_image(None, table, fraction=params.aperture_fraction, blur_sigma_px=params.blur_sigma_px,
                             grid=fitter.grid, samples=rs, cache=fitter.cache)
    del rs
    # The refocus table's pages go back too, while the stack's peaks and maxima are found and the new
    # candidates fitted (held-out seed 34's realistic off-focus ball: 583-592 -> 482-492 MB there).
    release_table_pages(table, fitter.cache)
    new, new_tracks = locate(products(rstack, rsub, out=rstack), alphas, params, threshold=threshold)
    del rstack, rsub  # not needed by the fits below (an F01's: 40 MB and more)
    # Where no found particle's light reaches, the residual is the raw image: its candidates are the
    # earlier pass's, already fitted and judged, and would be judged alike (realistic off-focus ball,
    # seed 1: 113 of 510, most on reflections and glints; 8 frames' results the same without them).
    sx, sy = fitter.grid.to_lens_plane(new.x, new.y)
    new = new.take(fitter.overlapping_max(sx, sy, new.alpha, fit, np.ones(len(fit))) > 0)
    # Every candidate above the noise is fitted: a screen by peak height against the found
    # particles whose light reaches it (0.03 of theirs) dropped faint particles that the tests
    # after the fit keep (30 more found on 63 realistic exposures, one more false, 1.04-1.08x time).
    new = above_noise(fitter, new, lens_noise, threshold)
    log.debug("another pass: %d candidates", len(new))
    if len(new) == 0:
        return None
    explained = fitter.render(fit, points=RESIDUAL_POINTS)
    new, new_fit = inside(fitter, *refine_peaks(fitter, new, subtract=explained), limits)
    # A new one must fit well and be a good part as bright as the particles whose light reaches it,
    # or fit very well and outshine what their model leaves unexplained, or have light that
    # converges to a point, which the light their model leaves does not: the faint particles of a
    # wide brightness spread pass only the last two.
    neighbour = fitter.overlapping_max(new_fit.sx_m, new_fit.sy_m, new_fit.alpha, fit, fit.intensity)
    misfit_dn = fitter.overlapping_max(new_fit.sx_m, new_fit.sy_m, new_fit.alpha, fit, fit.intensity * fit.residual)
    good = (((new_fit.residual <= PROBE_RESIDUAL) & (new_fit.intensity >= NEW_FRACTION * neighbour))
            | outshines_misfit(new_fit, misfit_dn))
    if not good.all():
        rest = np.flatnonzero(~good)
        # The tested fits' own light is left out of the light taken off (elsewhere every fit's is
        # in it), and the test adds each one's back: its pattern counts twice in its own light,
        # which raises its share. The thresholds were set with it: with every fit's light taken
        # off, tuning seeds 27-30 (off-focus balls and clouds, all effects) lost 27 of 2200
        # particles for 2 false ones fewer (stop 40).
        good[rest] = converges(fitter, new_fit.take(rest), explained + fitter.render(new_fit.take(good)),
                               clear=True)
    fitter.reject(new.take(~good), new_fit.take(~good), "weak_residual")
    new, new_fit = new.take(good), new_fit.take(good)
    if len(new) == 0:
        return None
    # The new peaks' curves are tracks of the residual's stack: append them to the first pass's,
    # so each particle's track index still points at its own curve.
    both = dataclasses.replace(Peaks.concat(peaks, new), track=np.r_[peaks.track, new.track + len(tracks)])
    # A new fit merges into a found one only if their depths agree within their uncertainties, as
    # at the end (SAME_DEPTH_SIGMAS): the merge distance alone (4 slices) took a blurred particle
    # found on a brighter one's line of sight, 4.7 sigma behind it, for that one (dev seed 1).
    both, both_fit = fitter.unique(both, RayFit.concat(fit, new_fit), settled=len(peaks), max_sigmas=SAME_DEPTH_SIGMAS)
    if len(both) == len(peaks):
        return None
    tracks = Tracks(x=np.vstack([tracks.x, new_tracks.x]), y=np.vstack([tracks.y, new_tracks.y]),
                    brightness=np.vstack([tracks.brightness, new_tracks.brightness]))
    return both, tracks, both_fit


def late_pass(fitter: RayFitter, table: LightFieldTable, background: BackgroundMap, params: PipelineParams,
              alphas: np.ndarray, limits: tuple[float, float], threshold: float, peaks: Peaks, tracks: Tracks,
              fit: RayFit, lens_noise: np.ndarray) -> tuple[Peaks, Tracks, RayFit]:
    """One more detection pass once the particles are deblended, and all deblended again with what
    it finds. A particle blurred over many pitches among brighter ones often makes no peak of its
    own in the first passes (a wider sensor blur widens its refocused spot, which merges with its
    neighbours'), while started at its true place it fits well with the others' light taken off.
    The deblended fits explain their own light better than the first ones, so the residual shows
    more of it; the second deblending drops the new fits that prove to be a neighbour's light.
    What this pass finds must also show a point's pattern within its lenses (:func:`patterned`):
    the residual of a realistic frame keeps the light of reflections and glints, and without it 2
    of 8 held-out realistic clouds (seeds 33-41) kept a particle on a reflection. Fits blurred over
    :data:`THIN_PATTERN_PITCHES` or more that fit their pixels well are exempt: their pattern is
    lost in the noise. On realistic frames not tuned on (seeds 33-36, off-focus balls and clouds)
    the exemption found 13 particles more of 2200, with one false particle more, none on a
    reflection; the pass with it 41 more, with 4 false more (10 of the 2098 found)."""
    n_tracks = len(tracks)
    found = look_again(fitter, table, background, params, alphas, limits, threshold, peaks, tracks, fit, lens_noise,
                       low_cut=True)
    trim_heap()  # the residual stack, before the refits of every particle below
    if found is None:
        return peaks, tracks, fit
    both, both_tracks, both_fit = found
    new = np.flatnonzero(both.track >= n_tracks)
    new_fit = both_fit.take(new)
    thin = ((fitter.blur_radius_m(new_fit.alpha) >= THIN_PATTERN_PITCHES * fitter.pitch_m)
            & (new_fit.residual <= THIN_PATTERN_RESIDUAL))
    spread = new[~thin & ~patterned(fitter, new_fit, fitter.render(both_fit))]
    fitter.reject(both.take(spread), both_fit.take(spread), "extended")
    if spread.size == new.size:  # nothing new left: the fits stand as they were
        return peaks, tracks, fit
    keep = np.setdiff1d(np.arange(len(both)), spread)
    peaks, fit = deblend(fitter, both.take(keep), both_fit.take(keep))
    return peaks, both_tracks, fit


def residual_cut(table: LightFieldTable, image: np.ndarray, residual: np.ndarray,
                 noise_sigmas: float | None) -> np.ndarray | None:
    """The noise cut of each lens of ``table`` (sigmas) for the samples of ``residual``:
    :data:`RESIDUAL_NOISE_SIGMAS` in the lenses with a pixel the fits' light was taken off (where
    ``residual`` differs from ``image``), ``noise_sigmas`` in the others; None where the samples are
    not cut (``noise_sigmas`` None) or the cut is not lower."""
    if noise_sigmas is None or noise_sigmas <= RESIDUAL_NOISE_SIGMAS:
        return None
    changed = residual.reshape(-1)[table.pixel_index] != image.reshape(-1)[table.pixel_index]
    sigmas = np.full(table.n_lenses, float(noise_sigmas), dtype=np.float32)
    sigmas[table.lens[changed]] = RESIDUAL_NOISE_SIGMAS
    return sigmas


def above_noise(fitter: RayFitter, peaks: Peaks, lens_noise: np.ndarray, threshold: float, *,
                record: bool = True) -> Peaks:
    """``peaks`` without those that do not stand out from the local noise (recorded as ``noise`` with
    ``record``); ``lens_noise``: the noise variance ratio of each lens of the fit's table."""
    low = below_local_noise(peaks, fitter.grid, table_index(fitter.table, fitter.cache).tree, lens_noise, threshold)
    if record:
        fitter.reject(peaks.take(low), None, "noise")
    return peaks.take(~low)
