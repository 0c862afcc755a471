"""Crowds on the raw pixels: refit each particle with its neighbours' light taken off, and split
fits that hold two particles on one line of sight.

Both take the particles of :func:`analysis.depth.refine.refine_peaks` and return them refitted
(:class:`analysis.detection.curves.Peaks` with the matching :class:`analysis.depth.rayfit.RayFit`).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np
from scipy.spatial import cKDTree

from analysis.detection.curves import Peaks
from analysis.lightfield.table import LightFieldTable

from .quality import EXTENDED_POINT_OVER_SPREAD, FIT_RESIDUAL_SLACK, converges
from .footprint import points_per_side
from .rayfit import RENDER_POINTS, FitGrid, RayFit, misfit_in_lenses, pattern_overlap
from .refine import (FINE_GRID, FINE_TEMPERATURE, PROBE_FRACTION, PROBE_GRID, PROBE_HALF_RANGE, PROBE_RESIDUAL,
    SAME_DEPTH_SIGMAS, WIDE_FINE_GRID, WIDE_PROBE_GRID, RayFitter, accept, moved, outshines_misfit, replace_fits)
from .sample_noise import SampleNoise

log = logging.getLogger(__name__)

# A fit taken for two particles on one line of sight (split_shared):
#: it is this many times brighter than the median fit ...
SPLIT_BRIGHT = 1.3
#: ... and misfits more than this many times the median misfit;
SPLIT_MISFIT = 1.0
#: the split is kept when the host gives up light to its partner (keeps at most this fraction) ...
SPLIT_HOST_LIGHT = 0.85
#: ... and then fits its pixels much better (misfit down to this fraction); the partner must pass
#: as a probe would (PROBE_FRACTION of the host's light, misfit <= PROBE_RESIDUAL).
SPLIT_HOST_MISFIT = 0.6
#: A fit within this many lens pitches (lens plane) of a brighter one sits on its line of sight:
#: the light a slightly wrong model leaves of the brighter particle shows there as a fainter one
#: at another depth. Such a partner must pass as a probe would (PROBE_FRACTION of the brighter
#: one's light, misfit <= PROBE_RESIDUAL), whichever stage found it.
LINE_OF_SIGHT_PITCHES = 1.0
#: A fit on a brighter one's line of sight, with less evidence than a probe needs, is that one's
#: light seen twice where their patterns overlap more than this (:func:`pattern_overlap`): on the
#: realistic scenes of seeds 25-32 (32 exposures, every scene) and seed 34's layer, the 161 real
#: fainter partners the other tests kept overlapped their brighter ones 0.19 at most (those they
#: dropped, 0.15); the two false ones they kept, 0.49 (on a reflection, 0.0018 in alpha in front
#: of a particle 5.8 times brighter) and 0.53.
SAME_PATTERN = 0.3
#: A faint partner blurred over a pitch or more, with less evidence than a probe needs, shows its
#: own light converging to a point where its point pattern explains more than what the same fit
#: spread over a pitch explains (:func:`analysis.depth.quality.converges`): by the extended-light
#: test's :data:`~analysis.depth.quality.EXTENDED_POINT_OVER_SPREAD`, or by only this many times
#: where its pattern is also distinct from the brighter one's (overlap under
#: :data:`DISTINCT_PATTERN`), so that it cannot be that one's light seen twice. Blurred over 4-6
#: pitches a point's pattern and the spread one look alike: on the realistic shadowing scenes of
#: tuning seeds 27-30 and 94, the real partners that failed 1.5 explained 1.1-1.43 times as much
#: as points (fitted at their true depth, then dropped), with overlaps of 0.000; compact glints on
#: lines of sight explain at most as much as points as spread (quality.py). The one false partner
#: that passed 1.05 on 26 tuning and fresh frames (ideal cloud 97: a particle blurred over 10
#: pitches split in two on its line of sight, 0.0026 apart in alpha) overlapped its bright one 0.22.
PARTNER_POINT_OVER_SPREAD = 1.05
#: See :data:`PARTNER_POINT_OVER_SPREAD`.
DISTINCT_PATTERN = 0.1
#: A faint partner blurred less than a pitch, with less evidence than a probe needs, is a particle
#: only if the pair explains the pixels this many times better than its brighter partner alone. On
#: the realistic shadowing and layer scenes of seeds 1-8, 11-12, such real partners did 1.34-2.9
#: times better, the false ones (light a bright neighbour's model leaves in its lens) 0.99-1.25
#: (two of 14 at 1.8); the point-pattern test they got before dropped real ones in focus.
IN_FOCUS_PAIR_GAIN = 1.3
#: Such a partner that passes one of a probe's two tests (PROBE_FRACTION of the brighter one's
#: light, or a misfit within PROBE_RESIDUAL), misfitting within the final table's limit, is a
#: particle all the same where the pair explains its own lenses (its blur disk and half a pitch)
#: this many times better than the brighter one alone.
#: Over the brighter one's many lenses, light others leave in them (a bright partner's patch the
#: model misplaces, a glint's disks) dilutes the pair's gain: fresh shadowing 141 lost a 1241 DN
#: partner in focus behind a 1995 DN one blurred over 2.3 pitches at a glint's edge (light 0.65 of
#: it, misfit 0.25; gain 1.08 over the brighter one's pixels, 2.7 over its own), fresh 143 a 705 DN
#: one behind a 2310 DN one (light 0.31, misfit 0.16; 1.28 and 2.9). On the realistic shadowing and
#: layer scenes of tuning seeds 27-30, 81-82 and 94 and held-out 132-136 and 140-141 (51 frames),
#: the pairs this test could change (one probe test passed, under 1.3 over the brighter one's
#: pixels) did 0.9-1.4 over their own lenses when real (judged one particle either way), 1.07, 1.23 and
#: 2.23 when false (the last a fragment of a 2621 DN particle, misfit 0.18): hence 2.5, not 2.
#: Fainter fits that pass neither test reach up to 9.7 (fragments of a bright particle's light).
#: :func:`split_shared` asks the same of a partner in focus split off a fit whose misfit the split
#: leaves as it was: held-out ideal ball 144's lost 1446 DN particle in focus, taken in by a 2116 DN
#: one blurred over 1.1 pitches 0.002 behind it in alpha, did 31 times better over its own lens; the
#: false splits of that kind on the tuning frames (realistic balls at focus, shadowing and layers of
#: seeds 27-30, 81-82, 94), each a fragment of its host, 0.02-1.64.
OWN_LENS_PAIR_GAIN = 2.5
#: The refits without the neighbours' light may move their fine pass this many times
#: (``fit_rays(recentre=...)``): it undoes the coarse pass's pull toward focus under a blur wider
#: than the ideal optics'. First fits, with the neighbours' light still on, keep theirs: a wider
#: search lets them slide toward a partner on their line of sight (recentring every fit: shadowing
#: pairs 2.6 -> 4.0 % NN). Pooled over seeds 1 and 2 (all effects) it lowered the depth error of
#: the off-focus ball 6.2 -> 5.8 %, the cloud 7.1 -> 6.1 %, the shadowing pairs 3.1 -> 2.7 %, the
#: layer 2.1 -> 1.4 % (ideal optics, off-focus ball: 4.1 -> 3.2 %). Two moves did as well as four.
DEBLEND_RECENTRE = 2


def deblend(fitter: RayFitter, peaks: Peaks, fit: RayFit) -> tuple[Peaks, RayFit]:
    """Refit every particle with its neighbours' fitted light taken off its pixels.

    Each first fit saw its neighbours' light too (crowds: the blurs of particles a pitch or two
    apart overlap), which pulls position and depth; the refit starts from the first fit. A fit
    that is left without enough light of its own, or that no longer fits, was a neighbour's light
    seen twice (a duplicate, or a ghost at another depth) and is dropped. Such fits are screened
    out first by a cheaper refit (:func:`seen_twice`), so the others are refitted once without
    their light rather than twice. A dropped fit is refitted once more with only the kept fits'
    light taken off, and comes back where it then passes (a held-out shadowing pair through ideal
    optics lost its in-focus particle to a ghost between the two, dropped with it).
    """
    # The light of the fits kept so far; a dropped fit's light is taken off it (fewer than re-rendering all).
    explained = fitter.render(fit)
    twice = seen_twice(fitter, fit, explained)
    if twice.any():
        explained -= fitter.render(fit.take(np.flatnonzero(twice)))
        fitter.reject(peaks.take(twice), fit.take(twice), "seen_twice")
        keep = np.flatnonzero(~twice)
        peaks, fit = peaks.take(keep), fit.take(keep)
    new = fitter.fit(fit.sx_m, fit.sy_m, fit.alpha, subtract=explained, own=fit, recentre=DEBLEND_RECENTRE)
    ok = fitter.acceptable(new) & ~weak_partners(fitter, new)
    if not ok.all():
        # The dropped fits' light was taken off their neighbours' pixels too: refit those without it.
        near = ok & _overlapping(fitter.table, fit, np.flatnonzero(~ok), pad_pitches=2.0)
        explained -= fitter.render(fit.take(np.flatnonzero(~ok)))
        kept, new = _second_chance(fitter, peaks, fit, new, ok, explained)
        if (kept & ~ok).any():
            explained += fitter.render(new.take(np.flatnonzero(kept & ~ok)))
        ok = kept
        fitter.reject(moved(fitter.grid, peaks, new).take(~ok), new.take(~ok), "seen_twice")
        keep = np.flatnonzero(ok)
        peaks, fit, new, near = peaks.take(keep), fit.take(keep), new.take(keep), near[keep]
        log.debug("deblend: %d fits dropped, %d neighbours refitted", (~ok).sum(), near.sum())
        if near.any():
            again = fitter.fit(fit.sx_m[near], fit.sy_m[near], fit.alpha[near], subtract=explained,
                               own=fit.take(near), recentre=DEBLEND_RECENTRE)
            new = replace_fits(fitter.grid, peaks, new, np.flatnonzero(near), again)[1]
    return accept(fitter, peaks, new)


def _second_chance(fitter: RayFitter, peaks: Peaks, fit: RayFit, new: RayFit, ok: np.ndarray,
                   explained: np.ndarray) -> tuple[np.ndarray, RayFit]:
    """``ok`` and ``new`` with the dropped fits back that, refitted with only the kept fits' light
    (``explained``) taken off, pass as particles and as partners and are no kept fit's duplicate.
    A ghost between two particles takes light off both in the refit; a real one dropped beside it
    gets its light back only once the ghost is gone too."""
    rows = np.flatnonzero(~ok)
    again = fitter.fit(fit.sx_m[rows], fit.sy_m[rows], fit.alpha[rows], subtract=explained,
                       recentre=DEBLEND_RECENTRE)
    good = fitter.acceptable(again)
    if not good.any():
        return ok, new
    back = rows[good]
    new = new.with_rows(back, again.take(np.flatnonzero(good)))
    order = np.r_[np.flatnonzero(ok), back]
    weak = weak_partners(fitter, new.take(order))
    order = np.r_[np.flatnonzero(ok), back[~weak[ok.sum():]]]
    kept = fitter.unique_rows(moved(fitter.grid, peaks.take(order), new.take(order)), new.take(order),
                              settled=int(ok.sum()), max_sigmas=SAME_DEPTH_SIGMAS)
    ok = ok.copy()
    ok[order[kept]] = True
    return ok, new


def refit_blurred(fitter: RayFitter, peaks: Peaks, fit: RayFit) -> tuple[Peaks, RayFit]:
    """Refit the strongly blurred particles (blur radius over
    :data:`analysis.depth.refine.WIDE_BLUR_PITCHES`) once more, with the light of every other
    particle as the earlier stages left it taken off. :func:`deblend` took each one's neighbours'
    first fits off, and those neighbours moved in that same refit; blurred particles' light
    overlaps many neighbours', so they gain most from a second round. A refit replaces the fit
    only where it is acceptable. The refits move fits along their lines of sight: those that then
    sit on a brighter one's with too little evidence of their own (:func:`weak_partners`) are
    dropped as ``seen_twice``, as :func:`deblend` drops them, and the fits their light overlaps
    are refitted once more without it."""
    rows = np.flatnonzero(fitter.strongly_blurred(fit.alpha))
    if rows.size == 0:
        return peaks, fit
    peaks, fit = _refit_where_acceptable(fitter, peaks, fit, rows)
    weak = weak_partners(fitter, fit)
    if not weak.any():
        return peaks, fit
    fitter.reject(peaks.take(weak), fit.take(weak), "seen_twice")
    near = ~weak & _overlapping(fitter.table, fit, np.flatnonzero(weak), pad_pitches=2.0)
    keep = np.flatnonzero(~weak)
    return _refit_where_acceptable(fitter, peaks.take(keep), fit.take(keep), np.flatnonzero(near[keep]))


def refit_or_drop(fitter: RayFitter, peaks: Peaks, fit: RayFit, rows: np.ndarray, reason: str, *,
                  max_residual: float | None = None) -> tuple[Peaks, RayFit]:
    """``rows`` refitted with every other fit's light taken off (after light that is no particle's
    was taken off the fitter's image under them): replaced where the refit is acceptable (misfit
    within ``max_residual``, default the fitter's), dropped as ``reason`` where it is not."""
    if rows.size == 0:
        return peaks, fit
    sub = fit.take(rows)
    new = fitter.fit(sub.sx_m, sub.sy_m, sub.alpha, subtract=fitter.render(fit), own=sub, recentre=DEBLEND_RECENTRE)
    ok = fitter.acceptable(new, max_residual)
    peaks, fit = replace_fits(fitter.grid, peaks, fit, rows[ok], new.take(ok))
    gone = np.zeros(len(fit), dtype=bool)
    gone[rows[~ok]] = True
    fitter.reject(peaks.take(gone), new.take(~ok), reason)
    return peaks.take(~gone), fit.take(~gone)


def sharpen_blurred(fitter: RayFitter, peaks: Peaks, fit: RayFit,
                    noise: SampleNoise | None = None) -> tuple[Peaks, RayFit]:
    """The strongly blurred particles' last estimate: refitted once more, with every other
    particle's light taken off, with as many pixel points as the camera's blur needs to reach
    every pixel a lens's patch of light spreads to (:func:`analysis.depth.footprint.points_per_side`),
    and the depth at the vertex of the depth profile's parabola, not the candidates' mean
    (``FitGrid.vertex``): on tuning seeds 27-30 the off-focus ball's realistic depth error 5.3 ->
    4.4 % (all effects), through ideal optics 3.44 -> 3.42 %; the clouds and shadowing pairs of
    seeds 27-28 no worse.
    Its candidates are weighed at the fine pass's temperature: a sharper one (0.15) served the
    candidates' mean, which a flat cost kept near the window's centre; with the vertex it made no
    difference on realistic frames (tuning seeds 27-30, held-out 33-34: off-focus balls and clouds,
    all effects, 0.99-1.01x) and cost 2-3 % through ideal optics (under an untold 0.3 px blur it
    did 1.3 % better). Runs after every decision on which fits are particles, so it moves fits and
    changes none of them (:func:`analysis.pipeline.process.process` then merges fits it brought
    onto one particle).
    With ``noise``, each sample counts by its inverse noise variance (:class:`SampleNoise`). On
    tuning seed 27 the off-focus ball's and the cloud's depth error through ideal optics fell
    2.6 -> 1.9 % and 2.5 -> 2.1 % of NN, with the wider blur alone 3.7 -> 3.0 % (ball); with every
    effect, 3.8 -> 4.0 % (ball) and 4.9 -> 4.1 % (cloud), and on fresh balls 70-71 3.1 -> 3.9 %
    (hence off by default: :attr:`analysis.pipeline.params.PipelineParams.weigh_noise`). Weighted
    in every stage, depths came out about as well, but compact glints' light was kept as particles
    (the tests' glint scenes): the gates on which fits are particles were chosen with unweighted
    fits.
    Without the depth prior (:mod:`analysis.depth.prior`): it comes from the neighbours' depths
    before this refit, the tempered means it corrects, and pulled the vertex back toward them
    (held-out layer 130, every effect, an untold 1.2 px blur: six particles blurred over 4.8-6.5
    pitches 0.02-0.04 NN farther off each, depth error 1.37 -> 1.53 % of NN)."""
    rows = np.flatnonzero(fitter.strongly_blurred(fit.alpha))
    return _refit_where_acceptable(fitter, peaks, fit, rows, wide_pixels=True, vertex=True, noise=noise,
                                   keep_prior=False)


def _refit_where_acceptable(fitter: RayFitter, peaks: Peaks, fit: RayFit, rows: np.ndarray, *,
                            wide_pixels: bool = False, vertex: bool = False,
                            noise: SampleNoise | None = None, keep_prior: bool = True) -> tuple[Peaks, RayFit]:
    """``rows`` refitted with every other fit's light taken off, where the refit is acceptable;
    with ``wide_pixels``, pixels as :func:`~analysis.depth.footprint.points_per_side` gives them; with
    ``vertex``, depths from the depth profile's vertex (:class:`~analysis.depth.rayfit.FitGrid`);
    with ``noise``, samples weighed by it (:func:`~analysis.depth.rayfit.fit_rays`); with
    ``keep_prior``, each with the depth prior its fit was made with."""
    if rows.size == 0:
        return peaks, fit
    fine, wide_fine = (g._replace(vertex=vertex) for g in (FINE_GRID, WIDE_FINE_GRID))
    points = RENDER_POINTS
    if wide_pixels:
        fine, wide_fine = (g._replace(pixel_points=points_per_side(g.pixel_points, fitter.blur_px))
                           for g in (fine, wide_fine))
        points = points_per_side(points, fitter.blur_px)
    sub = fit.take(rows)
    none = np.full(rows.size, np.nan)
    priors = {} if keep_prior else dict(prior_alpha=none, prior_sigma=none)
    new = fitter.fit(sub.sx_m, sub.sy_m, sub.alpha, subtract=fitter.render(fit, points=points), own=sub,
                     render_points=points, recentre=DEBLEND_RECENTRE, fine=fine, wide_fine=wide_fine, noise=noise,
                     **priors)
    ok = np.flatnonzero(fitter.acceptable(new))
    return replace_fits(fitter.grid, peaks, fit, rows[ok], new.take(ok))


def weak_partners(fitter: RayFitter, fit: RayFit) -> np.ndarray:
    """Fits (a mask) on a brighter fit's line of sight (within :data:`LINE_OF_SIGHT_PITCHES`) that
    are its light seen twice.

    A fit with less evidence of its own than a probe needs (under :data:`PROBE_FRACTION` of the
    brighter one's light, or misfitting beyond :data:`PROBE_RESIDUAL`), that does not outshine the
    brighter one's misfit (:func:`analysis.depth.refine.outshines_misfit`), is weak where it lights
    its lenses much as the brighter one does (:data:`SAME_PATTERN`), or where its light does not
    converge to a point (:func:`analysis.depth.quality.converges`; one blurred less than a pitch,
    whose light shows no pattern, unless the pair explains the pixels :data:`IN_FOCUS_PAIR_GAIN`
    times better than one particle, or, passing one of a probe's two tests within the final misfit
    limit, its own lenses :data:`OWN_LENS_PAIR_GAIN` times better). Any fainter fit is weak where one particle explains its
    light and the brighter one's better than the pair does (:func:`one_particle`)."""
    weak = np.zeros(len(fit), dtype=bool)
    if len(fit) < 2:
        return weak
    xy = np.column_stack([fit.sx_m, fit.sy_m])
    pairs = cKDTree(xy).query_pairs(LINE_OF_SIGHT_PITCHES * fitter.pitch_m, output_type="ndarray")
    if pairs.size == 0:
        return weak
    a, b = pairs[:, 0], pairs[:, 1]
    a_fainter = fit.intensity[a] < fit.intensity[b]
    faint, bright = np.where(a_fainter, a, b), np.where(a_fainter, b, a)
    probe_light = fit.intensity[faint] >= PROBE_FRACTION * fit.intensity[bright]
    probe_misfit = fit.residual[faint] <= PROBE_RESIDUAL
    unproven = (~(probe_light & probe_misfit)
                & ~outshines_misfit(fit.take(faint), fit.intensity[bright] * fit.residual[bright]))
    # Unproven, and lighting its lenses nearly as the brighter one does: the pixels cannot tell its
    # light from what a slightly wrong model leaves of the brighter one's (the tests below would
    # take that leftover for a point of its own).
    overlap = np.zeros(faint.size)
    if unproven.any():
        rows = np.flatnonzero(unproven)
        overlap[rows] = pattern_overlap(fitter.table, fit.take(faint[rows]), fit.take(bright[rows]),
                                        fitter.blur_radius_m(fit.alpha[faint[rows]]) + 0.5 * fitter.pitch_m,
                                        aperture_per_lens_plane=fitter.aperture_per_lens_plane,
                                        blur_px=fitter.blur_px, response_slope=fitter.response_slope,
                                        second_stop=fitter.second_stop,
                                        cache=fitter.cache)
    alike = overlap > SAME_PATTERN
    weak[faint[alike]] = True
    # One of a probe's two tests passed, within the final table's misfit limit (a partner that
    # limit drops at the end takes its brighter one's fit along: tuning shadowing 94 lost both).
    final_limit = fitter.max_residual / FIT_RESIDUAL_SLACK
    half_proven = ((probe_light | probe_misfit) & (fit.residual[faint] <= final_limit))[~alike]
    faint, bright, unproven, overlap = faint[~alike], bright[~alike], unproven[~alike], overlap[~alike]
    explained = fitter.render(fit)  # the light of all fits, for both tests below
    # A fit blurred less than a pitch lights a lens or two evenly: no point pattern to follow.
    # Such an unproven one must instead explain the pixels, with its brighter partner, clearly
    # better than that partner alone (IN_FOCUS_PAIR_GAIN).
    sharp = unproven & (fitter.blur_radius_m(fit.alpha[faint]) < fitter.pitch_m)
    if (unproven & ~sharp).any():
        rows = np.flatnonzero(unproven & ~sharp)
        distinct = overlap[rows] < DISTINCT_PATTERN
        unproven[rows] = ~converges(fitter, fit.take(faint[rows]), explained,
                                    over_spread=np.where(distinct, PARTNER_POINT_OVER_SPREAD, EXTENDED_POINT_OVER_SPREAD))
    unproven &= ~sharp
    weak[faint[unproven]] = True
    gain = np.where(sharp, IN_FOCUS_PAIR_GAIN, 1.0)[~unproven]
    own_lenses = (sharp & half_proven)[~unproven]
    faint, bright = faint[~unproven], bright[~unproven]
    weak[faint[one_particle(fitter, fit, faint, bright, explained, gain=gain, own_lenses=own_lenses)]] = True
    return weak


def one_particle(fitter: RayFitter, fit: RayFit, faint: np.ndarray, bright: np.ndarray,
                 explained: np.ndarray | None = None, *, gain: float | np.ndarray = 1.0,
                 own_lenses: np.ndarray | None = None) -> np.ndarray:
    """Pairs of fits on one line of sight (rows ``faint[k]``, ``bright[k]``) that are one particle
    (a mask over the pairs): the brighter refitted with both fits' light on its pixels misfits them
    less (DN per sample) than it did with the fainter's light taken off. Two particles must explain
    the pixels better than one: a blurred particle whose depth the first fit misjudged can leave
    enough light at its true depth for a second fit of about its brightness, as good, at nearly its
    place (most of the false particles on the off-focus ball with a 0.8 px blur). Pairs of true
    particles misfit 1.3-5 times more as one on the realistic shadowing scenes, 0.7-2 in crowds.
    ``explained``: the light of all of ``fit`` (:meth:`RayFitter.render`), when already rendered.
    ``gain`` (one value, or one per pair): how many times better the pair must explain the pixels.
    ``own_lenses`` (a mask over the pairs): pairs that are also two where the pair explains the
    fainter one's own lenses (its blur disk and half a pitch) :data:`OWN_LENS_PAIR_GAIN` times better
    than the brighter one refitted alone."""
    if faint.size == 0:
        return np.zeros(0, dtype=bool)
    everything = fitter.render(fit) if explained is None else explained
    # All light but the pairs'; the brighter is refitted to what is left (its own share added back).
    # Where pairs overlap, each single fit also sees the other pairs' fainter light: it then
    # misfits more, so the rule errs toward keeping both.
    explained = everything - fitter.render(fit.take(np.unique(faint)))
    single = fitter.fit(fit.sx_m[bright], fit.sy_m[bright], fit.alpha[bright], subtract=explained,
                        own=fit.take(bright), recentre=DEBLEND_RECENTRE)
    # RayFit.residual is the misfit per sample over the intensity: compare misfits in DN.
    one = single.residual * single.intensity < gain * fit.residual[bright] * fit.intensity[bright]
    rows = np.flatnonzero(one & (False if own_lenses is None else own_lenses))
    if rows.size:
        alone = (explained - fitter.render(fit.take(np.setdiff1d(bright[rows], faint)))
                 + fitter.render(single.take(rows)))
        at = (fit.sx_m[faint[rows]], fit.sy_m[faint[rows]],
              fitter.blur_radius_m(fit.alpha[faint[rows]]) + 0.5 * fitter.pitch_m)
        pair_sq, alone_sq = (misfit_in_lenses(fitter.image, fitter.table, *at, background=fitter.background,
                                              explained=model, saturation=fitter.saturation, cache=fitter.cache)
                             for model in (everything, alone))
        one[rows] = alone_sq < OWN_LENS_PAIR_GAIN ** 2 * pair_sq
    log.debug("line of sight: %d of %d pairs are one particle", one.sum(), one.size)
    return one


#: The screen's refit (:func:`seen_twice`): after the full coarse pass, 5 depths and +-0.15 pitch,
#: pixels as 3 x 3 points (on the off-focus ball it drops the same fits as the full refit; the
#: probes' grid (9, 0.25, 3, 3) cost a quarter more and dropped one the full refit keeps).
SCREEN_GRID = FitGrid(depths=5, lateral_pitches=0.15, positions=3, pixel_points=3, temperature=FINE_TEMPERATURE)
#: With 3 x 3 points a good fit's misfit runs a little above the fine pass's, so the screen drops a
#: fit only beyond this multiple of the misfit limit (on the off-focus ball, 1.0 also dropped two
#: fits the full refit keeps; 1.5 none, and it finds 36-41 of the 38-42 the full refit drops;
#: both measured with evenly spaced pixel points).
SCREEN_RESIDUAL = 1.5


def seen_twice(fitter: RayFitter, fit: RayFit, explained: np.ndarray | None = None) -> np.ndarray:
    """Fits whose light another fit already explains (a mask): refitted on the grid
    :data:`SCREEN_GRID` with the others' light taken off, they keep too little light or misfit it.
    ``explained``: the light of all of ``fit`` (:meth:`RayFitter.render`), when already rendered.

    Only fits whose blur disk overlaps another's by at least the larger one's radius are refitted:
    duplicates lie within a pitch or two of the fit of their particle, mostly with wide blurs.
    """
    twice = np.zeros(len(fit), dtype=bool)
    if len(fit) < 2:
        return twice
    pitch = fitter.pitch_m
    blur = fitter.blur_radius_m(fit.alpha)
    # Pairs from a tree: a crowd of thousands would make a full distance matrix hundreds of MB.
    pairs = cKDTree(np.column_stack([fit.sx_m, fit.sy_m])).query_pairs(float(blur.max()) + pitch,
                                                                       output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    close = np.hypot(fit.sx_m[i] - fit.sx_m[j], fit.sy_m[i] - fit.sy_m[j]) < np.maximum(blur[i], blur[j]) + pitch
    suspects = np.unique(np.r_[i[close], j[close]])
    if suspects.size == 0:
        return twice
    sub = fit.take(suspects)
    explained = fitter.render(fit) if explained is None else explained
    screen = fitter.fit(sub.sx_m, sub.sy_m, sub.alpha, subtract=explained, own=sub, fine=SCREEN_GRID)
    twice[suspects] = ((screen.intensity <= max(fitter.min_intensity, 0.0))
                       | (screen.residual > SCREEN_RESIDUAL * fitter.max_residual))
    log.debug("deblend screen: %d of %d fits refitted, %d seen twice", suspects.size, len(fit), twice.sum())
    return twice


def split_shared(fitter: RayFitter, peaks: Peaks, fit: RayFit, *, shadow_probe: float,
                 bright: float = SPLIT_BRIGHT, misfit: float = SPLIT_MISFIT) -> tuple[Peaks, RayFit]:
    """Split fits that hold the light of two particles on one line of sight.

    A particle hidden behind another can give its light to the other's fit: one fit, brighter
    than most, explains both, and no light is left over for a probe
    (:func:`analysis.depth.refine.refine_peaks`) to find. For each fit brighter than ``bright``
    times the median that also misfits more than ``misfit`` times the median, a partner is tried
    ``shadow_probe`` in front and behind, starting from half the light each; partner and fit are
    refitted with each other's light taken off. The split is kept where the partner passes as a
    probe would, and the fit gives up light to it and then fits its pixels much better. A partner
    in focus (blurred less than a pitch) can leave its host's misfit as low as before, and lie
    within the merge distance of it in depth: it is kept where the pair explains its own lenses
    :data:`OWN_LENS_PAIR_GAIN` times better than the one fit did.
    """
    # Two particles taken for one also misfit more than most.
    parents = (np.flatnonzero((fit.intensity > bright * np.median(fit.intensity))
                              & (fit.residual > misfit * np.median(fit.residual))) if len(fit) else np.empty(0, int))
    if parents.size == 0:
        return peaks, fit
    par = fit.take(parents)
    # The light of the other fits that reach the parents' lenses (rendering all would cost more): a
    # fit's light lands within its blur plus 1.6 pitches (cell and crosstalk), and a fit gathers
    # lenses up to its blur plus about 2.5 pitches.
    reach = _overlapping(fitter.table, fit, parents, pad_pitches=4.5)
    reach[parents] = False
    others = fitter.render(fit.take(np.flatnonzero(reach)))
    half = dataclasses.replace(par, intensity=0.5 * par.intensity)
    found: tuple[np.ndarray, RayFit, RayFit] | None = None
    for sign in (-1.0, 1.0):
        start = dataclasses.replace(half, alpha=par.alpha + sign * shadow_probe)
        # A cheap first look (the probes' grid); only where it finds light of its own, the full refits.
        partner = fitter.fit(start.sx_m, start.sy_m, start.alpha, subtract=others + fitter.render(half),
                             alpha_half_range=PROBE_HALF_RANGE, fine=PROBE_GRID, wide_fine=WIDE_PROBE_GRID)
        good = np.zeros(len(par), dtype=bool)
        own = np.zeros(len(par), dtype=bool)
        host = par
        look = np.flatnonzero(partner.intensity >= PROBE_FRACTION * half.intensity)
        if look.size:
            p0, h0 = partner.take(look), par.take(look)
            h = fitter.fit(h0.sx_m, h0.sy_m, h0.alpha, subtract=others + fitter.render(p0))
            q = fitter.fit(p0.sx_m, p0.sy_m, p0.alpha, subtract=others + fitter.render(h),
                           alpha_half_range=PROBE_HALF_RANGE)
            probe = ((q.intensity >= PROBE_FRACTION * h.intensity) & (q.residual <= PROBE_RESIDUAL)
                     & (h.intensity <= SPLIT_HOST_LIGHT * h0.intensity))
            better = (h.residual <= SPLIT_HOST_MISFIT * h0.residual) & (np.abs(q.alpha - h.alpha) > fitter.merge_alpha)
            sharp = probe & ~better & (fitter.blur_radius_m(q.alpha) < fitter.pitch_m)
            if sharp.any():  # judged by the partner's own lenses instead
                judge = np.flatnonzero(sharp)
                at = (q.sx_m[judge], q.sy_m[judge], fitter.blur_radius_m(q.alpha[judge]) + 0.5 * fitter.pitch_m)
                pair_sq, alone_sq = (misfit_in_lenses(fitter.image, fitter.table, *at, background=fitter.background,
                                                      explained=model, saturation=fitter.saturation,
                                                      cache=fitter.cache)
                                     for model in (others + fitter.render(h.take(judge)) + fitter.render(q.take(judge)),
                                                   others + fitter.render(h0.take(judge))))
                sharp[judge] = alone_sq >= OWN_LENS_PAIR_GAIN ** 2 * pair_sq
            good[look] = probe & (better | sharp)
            own[look] = sharp
            host, partner = par.with_rows(look, h), partner.with_rows(look, q)
        if found is None:
            found = (good, host, partner, own)
        else:
            # Both sides split: keep the side whose partner took more light.
            use = good & (~found[0] | (partner.intensity > found[2].intensity))
            found = (found[0] | good, host.where(use, found[1]), partner.where(use, found[2]),
                     np.where(use, own, found[3]))
    good, host, partner, own = found
    rows = np.flatnonzero(good)
    log.debug("split: %d of %d bright fits hold two particles", rows.size, parents.size)
    if rows.size == 0:
        return peaks, fit
    peaks, fit = replace_fits(fitter.grid, peaks, fit, parents[rows], host.take(rows))
    new = partner.take(rows)
    both, both_fit = Peaks.concat(peaks, moved(fitter.grid, peaks.take(parents[rows]), new)), RayFit.concat(fit, new)
    # The fits kept so far win. A partner proven by its own lenses may lie within the merge distance
    # of its host (in focus, its depth is open over the range its one lens allows): it gives way
    # to the others only.
    kept = fitter.unique_rows(both, both_fit, settled=len(peaks))
    hosts = parents[rows[own[rows]]]
    if hosts.size:
        rest = np.setdiff1d(np.arange(len(both)), hosts)
        apart = rest[fitter.unique_rows(both.take(rest), both_fit.take(rest), settled=len(peaks) - hosts.size)]
        kept = np.union1d(kept, np.intersect1d(apart, len(peaks) + np.flatnonzero(own[rows])))
    return both.take(kept), both_fit.take(kept)


def _overlapping(table: LightFieldTable, fit: RayFit, rows: np.ndarray, *, pad_pitches: float) -> np.ndarray:
    """Fits (a mask) whose blur disk, grown with that of one of the fits ``rows`` by ``pad_pitches``
    in all, meets it: ``distance < blur + blur_row + pad`` (blur radii on the MLA)."""
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    blur = np.abs(1.0 - 1.0 / fit.alpha) * table.aperture_radius_m
    out = np.zeros(len(fit), dtype=bool)
    if len(fit) == 0 or rows.size == 0:
        return out
    xy = np.column_stack([fit.sx_m, fit.sy_m])
    # Candidates from a tree (a crowd of thousands would make a full distance matrix hundreds of MB).
    hits = cKDTree(xy).query_ball_point(xy[rows], blur[rows] + blur.max() + pad_pitches * pitch)
    for r, near in zip(rows, hits):
        near = np.asarray(near, dtype=np.int64)
        d = np.hypot(fit.sx_m[near] - fit.sx_m[r], fit.sy_m[near] - fit.sy_m[r])
        out[near[d < blur[near] + blur[r] + pad_pitches * pitch]] = True
    return out
