"""Quality figures of fitted particles, from the raw pixels around them."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from analysis.detection.curves import Peaks

from .rayfit import RayFit, explained_light, point_pattern, unexplained_light
from .refine import LEFT_LIGHT_FLOOR, RayFitter

#: Light is looked for this many lens pitches beyond a particle's blur disk.
LEFTOVER_REACH_PITCHES = 2.0
#: A fit with more than this share of the light around it unexplained sits on extended light (the
#: edge of a reflected band, a glint far out of focus): on simulated exposures real particles left
#: at most 0.31 (0.53 with a blur the fit was not told), fits on reflections 0.84 (median) ...
EXTENDED_SHARE = 0.5
#: ... and is part of it when more than this share of the light on its own blur disk is unexplained
#: as well: a real particle beside a reflection leaves that light around it, not on it (seeds 1-2 of
#: the realistic scenes: the margin alone dropped 17 real particles with 202 fits on extended light,
#: both shares 4 with the same 202; real particles' own share runs to 0.35 outside crowds).
EXTENDED_OWN_SHARE = 0.4
#: ... unless the light within the lenses of its blur disk converges to a point: its point pattern
#: (:func:`analysis.depth.rayfit.point_pattern`) explains more than this share of that light's
#: variation ...
EXTENDED_POINT_PATTERN = 0.1
#: ... and this many times the share that the same fit spread over a source one lens pitch across
#: explains (a compact glint is such a source). On the realistic scenes of seeds 1-4 (all effects),
#: of the fits the shares flag, 115 on extended light explain at most 0.08 as points; 14 real
#: particles 0.15-0.69, of which 6 explain it 1.5-2.5 times better as points than spread (the
#: others, blurred over 5-8 pitches in crowds, 0.75-1.45 times, stay dropped); nine compact glints
#: (0.1 mm) on particles' lines of sight 0.0-1.0 times, the particles on them 1.8-9 times.
#: (These shares were measured with patterns rendered with 3 x 3 pixel points whatever the blur;
#: since stop 49 they are rendered as wide as the camera's blur, which under a 0.8 px blur raised
#: the ratio of real particles blurred over 8-11 pitches from about 0.7 to 1.2.)
EXTENDED_POINT_OVER_SPREAD = 1.5
#: Blurred over several pitches, a point's pattern and the same light spread over a pitch look alike
#: (real particles explain 0.75-1.45 times as much as points), so the ratio fails them; a pattern
#: that explains more than this share of the variation is a point's all the same. Of the faint
#: candidates of the second detection pass on seeds 1-6 (64 frames) that failed the ratio, 52 at a
#: real particle passed this, 2 elsewhere; taken, 39 more particles were found, one false fewer.
#: The final test of extended light (:func:`drop_extended`) takes it too.
CLEAR_POINT_PATTERN = 0.2
#: Dropping such fits leaves their light to their neighbours: looked at again this many times.
EXTENDED_ROUNDS = 3
#: A fit blurred over a pitch or more whose light within its lenses follows neither its point
#: pattern nor the same fit spread over a pitch (both explain less than this share of the
#: variation) is not a particle, whatever share of the light around it it explains: light that
#: does not converge, which the shares miss where the fit takes most of it (the edge of a
#: reflection the background model leaves, the unexplained light of strongly blurred crowds). On
#: the realistic balls and clouds of seeds 27-30 and 81-82 (3602 real particles found, 11 false),
#: the real ones explained 0.011 or more with one or the other (the faintest, blurred over 10-14
#: pitches in crowds), 7 of the false ones 0.009 or less (3 of them on reflections); through ideal
#: optics real particles explain 0.13 or more.
NO_PATTERN = 0.01
#: A particle of the final table misfits its pixels at most ``PipelineParams.max_fit_residual``
#: (misfit per sample over its intensity); the fits on the way may misfit this many times as much,
#: as a first fit still carries its neighbours' light, which the refits take off. Once they have,
#: real particles misfit at most 0.24 (4898 on the realistic scenes of seeds 1-2, each effect and
#: all), while the faint fits that remain on light a brighter neighbour's model leaves misfit
#: 0.25-0.34 (8 of the 35 false particles there); 0.35 is what the fits on the way always allowed.
FIT_RESIDUAL_SLACK = 1.4


def leftover_fraction(fitter: RayFitter, fit: RayFit, explained: np.ndarray | None = None, *,
                      reach_pitches: float = LEFTOVER_REACH_PITCHES) -> np.ndarray:
    """Per particle, the share of the light in the lenses its light reaches (its blur disk and
    ``reach_pitches`` beyond) that no fit explains.

    Near zero for a point source among point sources that the model explains (the noise floor is
    not counted, neighbours' explained light is); large where the light does not converge to a
    point: the edge or the tail of an extended source (a reflection, glare), or a particle the
    model misses. ``explained``: the light of all of ``fit`` (:meth:`RayFitter.render`), when
    already rendered.
    """
    if len(fit) == 0:
        return np.empty(0)
    explained = fitter.render(fit) if explained is None else explained
    reach = fitter.blur_radius_m(fit.alpha) + reach_pitches * fitter.pitch_m
    left = unexplained_light(fitter.image, fitter.table, fit.sx_m, fit.sy_m, reach, background=fitter.background,
                             explained=explained, floor=LEFT_LIGHT_FLOOR * fitter.min_intensity, cache=fitter.cache)
    there = explained_light(fitter.table, fit.sx_m, fit.sy_m, reach, explained=explained, cache=fitter.cache)
    return left / np.maximum(left + there, 1e-12)


def converges(fitter: RayFitter, fit: RayFit, explained: np.ndarray, *, clear: bool = False,
              over_spread: float | np.ndarray = EXTENDED_POINT_OVER_SPREAD) -> np.ndarray:
    """Fits (a mask) whose light within the lenses of their blur disk follows a point: their pattern
    (:func:`analysis.depth.rayfit.point_pattern`) explains more than :data:`EXTENDED_POINT_PATTERN`
    of its variation, and ``over_spread`` (one value, or one per fit) times what the fit spread over
    a source one pitch across explains; with ``clear``, also those whose pattern explains more than
    :data:`CLEAR_POINT_PATTERN` of it, whatever the spread source does. ``explained``: the light of
    all fits (:meth:`RayFitter.render`)."""
    point, spread = _patterns(fitter, fit, explained)
    ok = (point > EXTENDED_POINT_PATTERN) & (point > over_spread * spread)
    return ok | (point > CLEAR_POINT_PATTERN) if clear else ok


def patterned(fitter: RayFitter, fit: RayFit, explained: np.ndarray) -> np.ndarray:
    """Fits (a mask) whose point pattern explains more than :data:`EXTENDED_POINT_PATTERN` of the
    variation of the light within their lenses, or blurred less than a lens pitch (their light
    fills one lens or a few: no pattern to follow). Weaker than :func:`converges`, which real
    particles blurred over several pitches in crowds fail; a wide glint far out of focus, which
    fits as a blurred point with a small misfit, explains almost nothing (0.02; the survey's fits
    of real particles on the realistic scenes of seeds 1-10 mostly 0.15-0.9, a few crowded or
    misfitting ones less, never one at the end of a range). ``explained``: as for :func:`converges`."""
    point, _ = _patterns(fitter, fit, explained, spread=False)
    return (point > EXTENDED_POINT_PATTERN) | (fitter.blur_radius_m(fit.alpha) < fitter.pitch_m)


def _patterns(fitter: RayFitter, fit: RayFit, explained: np.ndarray, *,
              spread: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """:func:`analysis.depth.rayfit.point_pattern` over each fit's blur disk and half a pitch more
    (the spread source one pitch across; without ``spread``, NaN)."""
    return point_pattern(fitter.image, fitter.table, fit, fitter.blur_radius_m(fit.alpha) + 0.5 * fitter.pitch_m,
                         background=fitter.background, explained=explained,
                         aperture_per_lens_plane=fitter.aperture_per_lens_plane,
                         spread_m=fitter.pitch_m if spread else None, blur_px=fitter.blur_px,
                         response_slope=fitter.response_slope, second_stop=fitter.second_stop,
                         saturation=fitter.saturation, cache=fitter.cache).T


def drop_extended(fitter: RayFitter, peaks: Peaks, fit: RayFit) -> tuple[Peaks, RayFit, np.ndarray]:
    """Drop fits whose light does not converge to a point (:func:`leftover_fraction` above
    :data:`EXTENDED_SHARE` around them and :data:`EXTENDED_OWN_SHARE` on their own blur disk, and
    the light within those lenses not following a point: :func:`converges`, clearly or by the
    ratio), recorded as ``extended``; returns the rest and their leftover shares.

    In crowds far from focus the light of missed neighbours leaves most of a real particle's
    lenses unexplained; its pattern still explains over :data:`CLEAR_POINT_PATTERN` of their
    light's variation where the ratio test fails it (held-out realistic seeds 17-19, eleven
    exposures: 17 more real particles, no false one).

    Before all that, fits blurred over a pitch or more whose light follows no pattern of theirs
    (neither the point's nor the spread source's explains :data:`NO_PATTERN` of it) are dropped
    as ``extended``, whatever their shares."""
    explained = fitter.render(fit)
    # The point's pattern first, of the blurred fits only: the spread source's costs six renders
    # more, for the few left.
    bad = np.flatnonzero(fitter.blur_radius_m(fit.alpha) >= fitter.pitch_m)
    if bad.size:
        bad = bad[_patterns(fitter, fit.take(bad), explained, spread=False)[0] < NO_PATTERN]
    if bad.size:
        bad = bad[_patterns(fitter, fit.take(bad), explained)[1] < NO_PATTERN]
    if bad.size:
        peaks, fit, explained = _drop_extended_rows(fitter, peaks, fit, bad)
    share = leftover_fraction(fitter, fit, explained)
    for _ in range(EXTENDED_ROUNDS):
        bad = np.flatnonzero(share > EXTENDED_SHARE)
        if bad.size:
            # Half a pitch beyond the disk: an in-focus fit's still holds its own lens.
            own = leftover_fraction(fitter, fit.take(bad), explained, reach_pitches=0.5)
            bad = bad[own > EXTENDED_OWN_SHARE]
        if bad.size:
            bad = bad[~converges(fitter, fit.take(bad), explained, clear=True)]
        if bad.size == 0:
            break
        peaks, fit, explained = _drop_extended_rows(fitter, peaks, fit, bad)
        share = leftover_fraction(fitter, fit, explained)
    return peaks, fit, share


def _drop_extended_rows(fitter: RayFitter, peaks: Peaks, fit: RayFit,
                        rows: np.ndarray) -> tuple[Peaks, RayFit, np.ndarray]:
    """``rows`` recorded as ``extended``; the other peaks and fits, and the light of those fits."""
    fitter.reject(peaks.take(rows), fit.take(rows), "extended")
    keep = np.setdiff1d(np.arange(len(fit)), rows)
    peaks, fit = peaks.take(keep), fit.take(keep)
    return peaks, fit, fitter.render(fit)


def drop_misfits(fitter: RayFitter, peaks: Peaks, fit: RayFit, share: np.ndarray, *,
                 limit: float) -> tuple[Peaks, RayFit, np.ndarray]:
    """Drop fits misfitting beyond ``limit``, recorded as ``misfit``; returns the rest and their
    leftover shares: ``share`` (:func:`drop_extended`'s, one per fit) when none is dropped, else
    taken again without the dropped fits' light (it no longer counts as explained)."""
    bad = fit.residual > limit
    if bad.any():
        fitter.reject(peaks.take(bad), fit.take(bad), "misfit")
        peaks, fit = peaks.take(~bad), fit.take(~bad)
        share = leftover_fraction(fitter, fit)
    return peaks, fit, share


def too_close(xyz: np.ndarray, priority: np.ndarray, fraction: float) -> np.ndarray:
    """Points (a mask) closer than ``fraction`` of the median nearest-neighbour distance to a point
    of higher ``priority`` that is not itself too close (the highest first, greedily): one
    particle's light fitted twice, where particles repel one another (``PipelineParams.min_separation``).
    Points with a NaN coordinate, or fewer than three others, are never too close."""
    xyz, priority = np.asarray(xyz, float), np.asarray(priority, float)
    out = np.zeros(len(xyz), dtype=bool)
    rows = np.flatnonzero(np.isfinite(xyz).all(axis=1))
    if fraction <= 0 or rows.size < 4:
        return out
    tree = cKDTree(xyz[rows])
    limit = fraction * float(np.median(tree.query(xyz[rows], 2)[0][:, 1]))
    for i in np.argsort(-priority[rows], kind="stable"):
        if not out[rows[i]]:
            out[rows[[j for j in tree.query_ball_point(xyz[rows[i]], limit) if j != i]]] = True
    return out
