"""The pipeline's first depth stage on the raw pixels: fit each candidate, keep the particles.

Each stage takes candidate particles (:class:`analysis.detection.curves.Peaks`, positions in
output-image pixels) and returns them moved to the forward-model fit of
:func:`analysis.depth.rayfit.fit_rays`, with the matching rows of the fit
(:class:`analysis.depth.rayfit.RayFit`)::

    fitter = RayFitter(image, fit_table, grid, background=..., ...)
    peaks, fit = refine_peaks(fitter, peaks, shadow_probe=0.0065)   # fit, drop, merge, probe
    peaks, fit = deblend(fitter, peaks, fit)                         # analysis.depth.deblend
    peaks, fit = split_shared(fitter, peaks, fit, shadow_probe=...)  # analysis.depth.deblend
    peaks, fit = apply_depth_prior(fitter, peaks, fit)               # analysis.depth.prior
"""

from __future__ import annotations

import dataclasses
import logging
import math
from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from analysis.cache import Cache
from analysis.camera.image_grid import ImageGrid
from analysis.camera.second_stop import SecondStop
from analysis.detection.curves import Peaks, unique_indices
from analysis.detection.rejections import Rejections
from analysis.lightfield.table import LightFieldTable

from .rayfit import DEFAULT_BLUR_PX, RENDER_POINTS, FitGrid, RayFit, fit_rays, render_fits, unexplained_light

log = logging.getLogger(__name__)

#: Particles per call of :func:`analysis.depth.rayfit.fit_rays` and :func:`~analysis.depth.rayfit.render_fits`:
#: each call gathers the samples of every lens its particles reach, ~10 000 per particle blurred over
#: a few pitches (32 bytes each), so one call for 200 such particles held ~70 MB at once.
FIT_CHUNK = 64
#: With 5 x 5 points (evenly spaced, as the footprint was then) the model missed a noise-free
#: simulated particle by 0.1-0.3 pixel (I0^2) units (3 x 3: 0.15-0.45), so candidates are weighed
#: at that scale. Pooled over 18 simulated exposures this grid and temperature lower the depth
#: error by a seventh (ball) to a half (layer); with the quantile footprint 0.1 and 0.4 still
#: score worse than 0.25 (ball 8.17 and 8.26 % against 8.11 %).
FINE_TEMPERATURE = 0.25
#: The coarse pass weighs candidates over a whole mismatched pixel: it models pixels by their
#: centres, which misjudge the partly lit ones (sharper, it settles on wrong basins).
COARSE_TEMPERATURE = 1.0
#: The coarse pass's positions span +- this many pitches about the start.
COARSE_LATERAL_PITCHES = 0.4
#: The fit's fine pass: 9 depths, 11 positions per side over +-0.25 pitch (0.05 pitch apart: near
#: focus depth and position are coupled through how the light splits between lenses, so the
#: position must be that fine), each pixel as 5 x 5 points (the partly lit rim pixels of the
#: neighbouring lenses tell a blur of about a pitch in front of focus from one behind it only when
#: pixel areas are modelled).
FINE_GRID = FitGrid(depths=9, lateral_pitches=0.25, positions=11, pixel_points=5, temperature=FINE_TEMPERATURE)
#: Blurs wider than this many lens pitches (radius on the MLA) at the start of a fit, e.g. a
#: cluster placed a few mm off focus, get the fine grid :data:`WIDE_FINE_GRID`.
WIDE_BLUR_PITCHES = 2.0
#: Their light spreads over dozens of lenses, which pin position and depth down well enough for
#: the coarse pass that the fine pass may search +-0.15 pitch (same 0.05 pitch steps, 5 x 5 points)
#: and 5 depths: 55 % of the cost, and on the off-focus ball (3 seeds; pixel points then evenly
#: spaced) depth error 5.75 -> 5.38 % with precision no lower. Fewer points per pixel (3 x 3) there
#: lost a tenth of the precision, 0.1 pitch steps a particle or two of recall, fewer coarse depths
#: (9-11) biased the depth scale.
WIDE_FINE_GRID = FitGrid(depths=5, lateral_pitches=0.15, positions=7, pixel_points=5, temperature=FINE_TEMPERATURE)
#: The fine pass of probes for hidden particles: crowds probe many, so 3 positions per side and
#: pixels as 3 x 3 points; behind wide blurs 5 depths over +-0.15 pitch.
PROBE_GRID = FitGrid(depths=9, lateral_pitches=0.25, positions=3, pixel_points=3, temperature=FINE_TEMPERATURE)
WIDE_PROBE_GRID = FitGrid(depths=5, lateral_pitches=0.15, positions=3, pixel_points=3, temperature=FINE_TEMPERATURE)
#: A probe's coarse pass: 17 depths over its narrower window (+-``PROBE_HALF_RANGE``).
PROBE_COARSE_DEPTHS = 17
PROBE_HALF_RANGE = 0.0025

#: A candidate whose coarse pass finds at most this fraction of the intensity threshold keeps its
#: coarse result (no fine pass) and is dropped as ``faint``. On realistic frames of seed 31 the
#: particles kept at the end had at least 0.57 of it in their coarse pass (ball off focus; 1.4
#: in the cloud, 4 on the layer), and 40-50 % of the first pass's candidates stay under 0.4. On
#: 84 exposures (seeds 25-34, every scene, ideal and realistic) it found the same particles.
FAINT_COARSE = 0.4

# What makes a probe a particle of its own, rather than what is left of a neighbour's imperfectly
# modelled light (a tenth of it or less): each trades missed hidden particles for false ones.
#: A probe must fit its pixels this well (misfit per pixel as a fraction of its intensity) ...
PROBE_RESIDUAL = 0.2
#: ... and be at least this fraction as bright as the particle it hides behind.
PROBE_FRACTION = 0.35
#: Whatever the brightness ratio, a fit is evidence of a particle of its own, not light that a
#: neighbour's imperfect model leaves, when it fits its pixels this well (misfit per sample over its
#: intensity: such left-over light fits at 0.1-0.2, faint particles at 0.03-0.12) ...
FAINT_RESIDUAL = 0.1
#: ... and is this many times brighter than that neighbour's misfit (DN per sample): the faint end
#: of a 12x brightness spread passes no fixed fraction of its brighter neighbours' light.
FAINT_OVER_MISFIT = 4.0
#: Probe behind a particle when the light left over around it exceeds this fraction of its own ...
PROBE_LIGHT = 0.5
#: ... or when its fit is this many times brighter than the median (it may hold a hidden one's light).
PROBE_BRIGHT = 1.3
#: Left-over light counts only above this fraction of the smallest particle intensity (noise).
LEFT_LIGHT_FLOOR = 0.3
#: After the last refits, two fits within the merge distance whose depths differ by less than this
#: many times their combined depth uncertainty (``alpha_spread``) are one particle whose light the
#: refits split between them: deblending refits each particle with its neighbours' light taken off,
#: which can bring a ghost and the particle it stands beside together (on the realism bench 0.1-4
#: sigma apart, 11 of 13 under 3; distinct particles that close across the line of sight: 4.1-11).
SAME_DEPTH_SIGMAS = 3.0
#: Two fits within the merge distance are two particles, not one fitted twice, where they lie farther
#: apart across the line of sight than this many pitches plus :data:`APART_PER_BLUR` times the wider
#: one's blur diameter, and each shows a particle's evidence (a probe's: :data:`PROBE_FRACTION` of
#: the other's light, a misfit within :data:`PROBE_RESIDUAL`). Fits of one particle from different
#: starts, with that evidence, lay at most 0.54 pitch apart when blurred under 2 pitches, and 0.36
#: of the blur diameter when wider (428 such merges on 11 frames: the ideal balls at focus of seeds
#: 27, 81, 94, 153 and the realistic frames of every scene of 153, 150); the two particles that ideal
#: ball 153 lost, 0.0022 apart in alpha on either side of focus, lay 1.2-1.27 pitches apart.
APART_PITCHES = 0.6
#: See :data:`APART_PITCHES`.
APART_PER_BLUR = 0.4
#: A fit must light at least this fraction of one micro-image's samples (a particle in view lights
#: about one micro-image's worth, 36-40 on the simulated F01; a hot pixel fitted as a particle
#: whose light misses every other sample, a small fraction of one).
MIN_LIT_FRACTION = 0.5
#: A misfit up to this many times the limit may be a faint particle's among brighter ones' light
#: (refitted without theirs, :func:`_second_look`); beyond it, the fit is no point source.
SECOND_LOOK_RESIDUAL = 2.0


@dataclass(frozen=True)
class RayFitter:
    """One exposure's raw image and the fit settings every depth stage shares.

    Attributes
    ----------
    image : ndarray (H, W), uint16
    table : LightFieldTable
        The depth fit's table, with the micro-image rims (``analysis.pipeline.tables.FIT_TABLE_RIM_PX``).
    grid : ImageGrid
        Output-image pixels of the candidates.
    background : float or ndarray of shape (table.n_samples,)
        One level, or one per sample of ``table``, as :func:`analysis.depth.rayfit.fit_rays` takes it.
    aperture_per_lens_plane, alpha_half_range : float
        As :func:`analysis.depth.rayfit.fit_rays` takes them.
    coarse : FitGrid
        The coarse pass of every fit (the fine pass: :data:`FINE_GRID` or as a stage asks).
    min_intensity, max_residual : float
        Fits dimmer than this (devignetted DN), or with a larger misfit, are no particle.
    merge_radius_px, merge_alpha : float
        Fits closer than this in the image and in alpha are one particle (the brighter kept).
    cache : Cache or None
        Where the table's lens index is kept between calls.
    rejected : Rejections or None
        Where the stages record the candidates they drop, with the reason.
    saturation : float
        Raw value at which the sensor saturates (the model's white level): such samples are censored.
    blur_px : float
        Gaussian blur (sigma, sensor pixels) of the camera's point spread that every fit and render
        models (:func:`analysis.depth.rayfit.fit_rays`); the calibration's estimate from its white
        image (:attr:`analysis.calibration.calibrate.Calibration.blur_px`), by default the ideal
        optics' 0.5 px.
    response_slope : float
        The pixel response within a micro-image that every fit and render models, as
        :func:`analysis.depth.rayfit.fit_rays` takes it (the calibration's
        :attr:`analysis.calibration.calibrate.Calibration.response_slope`; 0: flat).
    second_stop : SecondStop, optional
        The main lens's second stop that every fit and render models (the calibration's
        :attr:`analysis.calibration.calibrate.Calibration.second_stop`; None: the whole aperture).
    """

    image: np.ndarray
    table: LightFieldTable
    grid: ImageGrid
    background: float | np.ndarray
    aperture_per_lens_plane: float
    alpha_half_range: float
    coarse: FitGrid
    min_intensity: float
    max_residual: float
    merge_radius_px: float
    merge_alpha: float
    cache: Cache | None = None
    rejected: Rejections | None = None
    saturation: float = 4095.0
    blur_px: float = DEFAULT_BLUR_PX
    response_slope: float = 0.0
    second_stop: SecondStop | None = None

    @property
    def pitch_m(self) -> float:
        """Lens pitch on the lens plane (metres)."""
        return float(np.hypot(*self.table.basis_m[:, 0]))

    def blur_radius_m(self, alpha: np.ndarray) -> np.ndarray:
        """Radius of the blur disk on the lens plane of a particle sharp at ``alpha``."""
        return np.abs(1.0 - 1.0 / np.asarray(alpha)) * self.table.aperture_radius_m

    def strongly_blurred(self, alpha: np.ndarray) -> np.ndarray:
        """Whether particles sharp at ``alpha`` are blurred wider than :data:`WIDE_BLUR_PITCHES` (a mask)."""
        return self.blur_radius_m(alpha) > WIDE_BLUR_PITCHES * self.pitch_m

    def fit(self, sx_m: np.ndarray, sy_m: np.ndarray, alpha: np.ndarray, *,
            fine: FitGrid | None = None, wide_fine: FitGrid | None = None, **options) -> RayFit:
        """:func:`analysis.depth.rayfit.fit_rays` with these settings (``options`` override them).

        Particles blurred wider than :data:`WIDE_BLUR_PITCHES` at their start get the fine grid
        ``wide_fine``, the others ``fine``: by default :data:`WIDE_FINE_GRID` and
        :data:`FINE_GRID`; a ``fine`` given alone serves both. At most :data:`FIT_CHUNK`
        particles per call, to bound memory. A refit (``own``: the fits refitted) keeps their depth
        priors (:attr:`~analysis.depth.rayfit.RayFit.prior_alpha`) unless given others: a refit
        without its prior undid what the prior stage did (held-out layer 130 through an untold
        1.2 px blur: one particle 0.047 -> 0.232 NN off in depth).
        """
        settings = dict(background=self.background, aperture_per_lens_plane=self.aperture_per_lens_plane,
                        alpha_half_range=self.alpha_half_range, coarse=self.coarse, cache=self.cache,
                        saturation=self.saturation, blur_px=self.blur_px,
                        response_slope=self.response_slope, second_stop=self.second_stop)
        settings.update(options)
        own = settings.get("own")
        if own is not None and settings.get("prior_alpha") is None:
            settings.update(prior_alpha=own.prior_alpha, prior_sigma=own.prior_sigma)
        if wide_fine is None:
            wide_fine = WIDE_FINE_GRID if fine is None else fine
        fine = FINE_GRID if fine is None else fine
        sx, sy, a = (np.asarray(v, dtype=np.float64).ravel() for v in (sx_m, sy_m, alpha))
        if a.size <= FIT_CHUNK and wide_fine == fine:
            return fit_rays(self.image, self.table, sx, sy, a, fine=fine, **settings)
        wide = np.zeros(a.size, dtype=bool)
        if wide_fine != fine:
            wide = self.strongly_blurred(a)
        parts, fits = [], []
        for rows, grid in ((np.flatnonzero(~wide), fine), (np.flatnonzero(wide), wide_fine)):
            for start in range(0, rows.size, FIT_CHUNK):
                chunk = rows[start:start + FIT_CHUNK]
                part = dict(settings, fine=grid)
                if part.get("own") is not None:
                    part["own"] = part["own"].take(chunk)
                for name in ("prior_alpha", "prior_sigma"):
                    if part.get(name) is not None:
                        part[name] = np.asarray(part[name]).ravel()[chunk]
                parts.append(chunk)
                fits.append(fit_rays(self.image, self.table, sx[chunk], sy[chunk], a[chunk], **part))
        if len(fits) <= 1:
            return fits[0] if fits else fit_rays(self.image, self.table, sx, sy, a, fine=fine, **settings)
        return RayFit.concat(*fits).take(np.argsort(np.concatenate(parts)))

    def render(self, fit: RayFit, *, points: int = RENDER_POINTS) -> np.ndarray:
        """The light of fitted particles on each table sample (:func:`analysis.depth.rayfit.render_fits`,
        pixels as ``points`` x ``points`` points)."""
        out = np.zeros(self.table.n_samples, dtype=np.float32)
        for start in range(0, len(fit), FIT_CHUNK):  # in particle order, as one call would add them
            chunk = fit.take(np.arange(start, min(start + FIT_CHUNK, len(fit))))
            render_fits(self.table, chunk, aperture_per_lens_plane=self.aperture_per_lens_plane, out=out,
                        cache=self.cache, blur_px=self.blur_px,
                        response_slope=self.response_slope, second_stop=self.second_stop, points=points)
        return out

    @property
    def min_lit(self) -> float:
        """Fewest samples a point source in view lights: the aperture falls whole on the lenses, so a
        particle lights about one micro-image's worth of samples whatever its blur; far fewer is a
        hot pixel, or a fragment of something else (:data:`MIN_LIT_FRACTION` of that)."""
        return MIN_LIT_FRACTION * self.table.n_samples / max(self.table.n_lenses, 1)

    def acceptable(self, fit: RayFit, max_residual: float | None = None) -> np.ndarray:
        """Fits (a mask) with enough light, lighting an aperture's worth of samples, and a small
        enough misfit to be particles."""
        limit = self.max_residual if max_residual is None else max_residual
        return ((fit.intensity > max(self.min_intensity, 0.0)) & (fit.n_lit >= self.min_lit)
                & (fit.residual <= limit))

    def unique(self, peaks: Peaks, fit: RayFit, *, settled: int = 0, record: bool = True,
               max_sigmas: float = np.inf) -> tuple[Peaks, RayFit]:
        """Fits that converged onto one particle merged (the brightest kept; the first ``settled``,
        accepted earlier, win over the rest); the others recorded as duplicates unless ``record``
        is False (hypotheses of the stage, such as probes, rather than candidates). With
        ``max_sigmas``, fits merge only where their depths also differ by less than that many
        times their combined ``alpha_spread``."""
        kept = (self.merge_rows(peaks, fit, settled=settled, max_sigmas=max_sigmas) if record
                else self.unique_rows(peaks, fit, settled=settled, max_sigmas=max_sigmas))
        return peaks.take(kept), fit.take(kept)

    def merge_rows(self, peaks: Peaks, fit: RayFit, *, settled: int = 0, max_sigmas: float = np.inf) -> np.ndarray:
        """The rows :meth:`unique` keeps, in order, the others recorded as duplicates (for callers
        that keep more columns row for row)."""
        kept = self.unique_rows(peaks, fit, settled=settled, max_sigmas=max_sigmas)
        gone = np.setdiff1d(np.arange(len(peaks)), kept)
        self.reject(peaks.take(gone), fit.take(gone), "duplicate")
        return kept

    def unique_rows(self, peaks: Peaks, fit: RayFit, *, settled: int = 0, max_sigmas: float = np.inf) -> np.ndarray:
        """The rows :meth:`unique` keeps, in order (nothing recorded)."""
        return unique_indices(peaks, radius_px=self.merge_radius_px, alpha_tolerance=self.merge_alpha,
                              priority=fit.intensity, settled=settled,
                              alpha_sigma=None if np.isinf(max_sigmas) else fit.alpha_spread, max_sigmas=max_sigmas,
                              apart=self.apart(fit))

    def apart(self, fit: RayFit) -> Callable[[int, int], bool]:
        """Whether fits ``i`` and ``j`` hold two particles however close they come: see :data:`APART_PITCHES`."""
        reach = APART_PITCHES * self.pitch_m + APART_PER_BLUR * 2.0 * self.blur_radius_m(fit.alpha)
        evident = fit.residual <= PROBE_RESIDUAL

        def pair_apart(i: int, j: int) -> bool:
            if not (evident[i] and evident[j]):
                return False
            if min(fit.intensity[i], fit.intensity[j]) < PROBE_FRACTION * max(fit.intensity[i], fit.intensity[j]):
                return False
            return math.hypot(fit.sx_m[i] - fit.sx_m[j], fit.sy_m[i] - fit.sy_m[j]) > max(reach[i], reach[j])

        return pair_apart

    def overlapping_max(self, sx_m: np.ndarray, sy_m: np.ndarray, alpha: np.ndarray, fit: RayFit,
                        values: np.ndarray, *, pad_pitches: float = 2.0) -> np.ndarray:
        """Per point (lens plane, with the blur of ``alpha``), the largest of ``values`` (one per fit)
        over the fits whose blur disk comes within ``pad_pitches`` of the point's own; 0 where none
        does: how bright a neighbour is whose light could reach it."""
        sx_m, sy_m, alpha = (np.atleast_1d(np.asarray(v, float)) for v in (sx_m, sy_m, alpha))
        out = np.zeros(sx_m.size)
        if len(fit) == 0 or sx_m.size == 0:
            return out
        blur, own = self.blur_radius_m(fit.alpha), self.blur_radius_m(alpha)
        pad = pad_pitches * self.pitch_m
        hits = cKDTree(np.column_stack([fit.sx_m, fit.sy_m])).query_ball_point(
            np.column_stack([sx_m, sy_m]), own + blur.max() + pad)
        for i, near in enumerate(hits):
            near = np.asarray(near, dtype=np.int64)
            d = np.hypot(fit.sx_m[near] - sx_m[i], fit.sy_m[near] - sy_m[i])
            near = near[d < blur[near] + own[i] + pad]
            if near.size:
                out[i] = float(np.max(np.asarray(values)[near]))
        return out

    def reject(self, peaks: Peaks, fit: RayFit | None, reason: str) -> None:
        """Record candidates as dropped (when this fitter records them)."""
        if self.rejected is not None:
            self.rejected.add(peaks, reason, intensity=None if fit is None else fit.intensity,
                              residual=None if fit is None else fit.residual)


def refine_peaks(fitter: RayFitter, peaks: Peaks, *, shadow_probe: float = 0.0,
                 subtract: np.ndarray | None = None) -> tuple[Peaks, RayFit]:
    """Replace each peak's position and depth by the forward-model fit to the raw pixels.

    Fits without enough light or with too large a misfit are dropped; fits that converge onto one
    particle are merged. With ``shadow_probe`` > 0, particles hidden behind the ones found are
    looked for this far in alpha in front of and behind each, where light is left over around it.
    ``subtract``: light already explained (devignetted DN per table sample), taken off first.
    """
    sx0, sy0 = fitter.grid.to_lens_plane(peaks.x, peaks.y)
    fit = fitter.fit(sx0, sy0, peaks.alpha, subtract=subtract, coarse_floor=FAINT_COARSE * fitter.min_intensity)
    fit = _second_look(fitter, fit, subtract)
    refined, fit = fitter.unique(*accept(fitter, peaks, fit))
    if shadow_probe <= 0 or len(refined) == 0:
        return refined, fit
    # A particle hidden behind another (same line of sight, other depth) often merges into its
    # neighbour's brightness curve without a maximum of its own. Take the light of the particles
    # found so far off the raw samples and probe what is left, in front of and behind each.
    table = fitter.table
    explained = fitter.render(fit)
    # Only where light is left over around a particle (a hidden one's share of the aperture), or
    # where a fit is much brighter than most (it may hold a hidden one's light as well).
    left = unexplained_light(fitter.image, table, fit.sx_m, fit.sy_m,
                             fitter.blur_radius_m(fit.alpha - shadow_probe) + fitter.pitch_m,
                             background=fitter.background, explained=explained,
                             floor=LEFT_LIGHT_FLOOR * fitter.min_intensity, cache=fitter.cache)
    own = fit.intensity * np.maximum(fit.n_lit, 1)
    parents = np.flatnonzero((left > PROBE_LIGHT * own) | (fit.intensity > PROBE_BRIGHT * np.median(fit.intensity)))
    probes = refined.take(np.r_[parents, parents])
    probes = dataclasses.replace(probes, alpha=np.r_[refined.alpha[parents] - shadow_probe,
                                                     refined.alpha[parents] + shadow_probe])
    parent_intensity = np.r_[fit.intensity[parents], fit.intensity[parents]]
    psx, psy = fitter.grid.to_lens_plane(probes.x, probes.y)
    # Crowds probe many: a cheaper fine pass.
    pfit = fitter.fit(psx, psy, probes.alpha, alpha_half_range=PROBE_HALF_RANGE,
                      coarse=fitter.coarse._replace(depths=PROBE_COARSE_DEPTHS), subtract=explained,
                      fine=PROBE_GRID, wide_fine=WIDE_PROBE_GRID)
    log.debug("shadow probes: %d of %d particles probed", parents.size, len(refined))
    good = np.flatnonzero(pfit.intensity >= PROBE_FRACTION * parent_intensity)
    probes, pfit = accept(fitter, probes.take(good), pfit.take(good), min(fitter.max_residual, PROBE_RESIDUAL),
                          record=False)
    if len(probes) == 0:
        return refined, fit
    # Found particles win over probes that converged onto them.
    return fitter.unique(Peaks.concat(refined, probes), RayFit.concat(fit, pfit), settled=len(refined), record=False)


def _second_look(fitter: RayFitter, fit: RayFit, subtract: np.ndarray | None) -> RayFit:
    """``fit`` with its near misfits refitted without the light of the brighter fits that overlap them.

    A faint particle among particles several times brighter (brightness spreads 10x) sees their
    light on its pixels, which its first fit cannot explain: its misfit, a fraction of its own
    light, runs high. Fits with light and an aperture's worth of samples whose misfit is within
    :data:`SECOND_LOOK_RESIDUAL` times the limit, where a brighter acceptable fit's light reaches,
    are refitted with the acceptable fits' light taken off; a refit that passes replaces the fit.
    """
    ok = fitter.acceptable(fit)
    near = (~ok & (fit.intensity > max(fitter.min_intensity, 0.0)) & (fit.n_lit >= fitter.min_lit)
            & (fit.residual <= SECOND_LOOK_RESIDUAL * fitter.max_residual))
    if not near.any() or not ok.any():
        return fit
    good = fit.take(np.flatnonzero(ok))
    rows = np.flatnonzero(near)
    brighter = fitter.overlapping_max(fit.sx_m[rows], fit.sy_m[rows], fit.alpha[rows], good, good.intensity)
    rows = rows[brighter > fit.intensity[rows]]
    if rows.size == 0:
        return fit
    explained = fitter.render(good)
    if subtract is not None:
        explained += subtract
    again = fitter.fit(fit.sx_m[rows], fit.sy_m[rows], fit.alpha[rows], subtract=explained)
    passed = fitter.acceptable(again)
    log.debug("second look: %d near misfits refitted, %d pass", rows.size, passed.sum())
    return fit.with_rows(rows[passed], again.take(np.flatnonzero(passed)))


def outshines_misfit(fit: RayFit, misfit_dn: np.ndarray) -> np.ndarray:
    """Fits (a mask) too good and too bright to be light a neighbour's imperfect model leaves:
    misfit within :data:`FAINT_RESIDUAL`, light :data:`FAINT_OVER_MISFIT` times ``misfit_dn`` (the
    neighbours' misfit, DN per sample, one value per fit)."""
    return (fit.residual <= FAINT_RESIDUAL) & (fit.intensity >= FAINT_OVER_MISFIT * np.asarray(misfit_dn))


def accept(fitter: RayFitter, peaks: Peaks, fit: RayFit, max_residual: float | None = None, *,
           record: bool = True) -> tuple[Peaks, RayFit]:
    """Peaks moved to their fitted position and depth, keeping fits with light and a small misfit;
    the others recorded as ``faint`` or ``misfit`` unless ``record`` is False."""
    at = moved(fitter.grid, peaks, fit)
    ok = fitter.acceptable(fit, max_residual)
    if record and not ok.all():
        faint = fit.intensity <= max(fitter.min_intensity, 0.0)
        fragment = ~faint & (fit.n_lit < fitter.min_lit)
        fitter.reject(at.take(faint), fit.take(faint), "faint")
        fitter.reject(at.take(fragment), fit.take(fragment), "fragment")
        fitter.reject(at.take(~ok & ~faint & ~fragment), fit.take(~ok & ~faint & ~fragment), "misfit")
    keep = np.flatnonzero(ok)
    return at.take(keep), fit.take(keep)


def replace_fits(grid: ImageGrid, peaks: Peaks, fit: RayFit, rows: np.ndarray, new: RayFit) -> tuple[Peaks, RayFit]:
    """``fit`` with ``rows`` replaced by the rows of ``new``, and the peaks moved to match."""
    merged = fit.with_rows(rows, new)
    return moved(grid, peaks, merged), merged


def inside(fitter: RayFitter, peaks: Peaks, fit: RayFit, limits: tuple[float, float]) -> tuple[Peaks, RayFit]:
    """Drop fits that left the alpha range ``(lo, hi)`` (the user's, or the one found from the
    exposure with a margin: :func:`analysis.pipeline.depth_range.fit_limits`): they found a particle
    of another range, or light that is none."""
    ok = within_limits(fitter, peaks, fit, limits)
    return (peaks, fit) if ok.all() else (peaks.take(ok), fit.take(ok))


def within_limits(fitter: RayFitter, peaks: Peaks, fit: RayFit, limits: tuple[float, float]) -> np.ndarray:
    """The fits (a mask) :func:`inside` keeps; the others recorded as ``outside_range``."""
    ok = (peaks.alpha >= limits[0]) & (peaks.alpha <= limits[1])
    if not ok.all():
        fitter.reject(peaks.take(~ok), fit.take(~ok), "outside_range")
    return ok


def residual_image(image: np.ndarray, table: LightFieldTable, explained: np.ndarray) -> np.ndarray:
    """The raw image minus the light of fitted particles (``explained``, devignetted DN per table
    sample, from :func:`analysis.depth.rayfit.render_fits`), clipped to the 12-bit range."""
    out = np.array(image, dtype=np.uint16, copy=True)
    flat = out.reshape(-1)
    # Only where a particle puts light (few samples): no temporaries of the table's length.
    lit = np.flatnonzero(explained)
    pred = explained[lit] * table.weight[lit]  # float32
    lit, pred = lit[pred >= 0.5], pred[pred >= 0.5]
    pix = table.pixel_index[lit]
    flat[pix] = np.clip(np.rint(flat[pix] - pred), 0, 4095).astype(np.uint16)
    return out


def moved(grid: ImageGrid, peaks: Peaks, fit: RayFit) -> Peaks:
    """The peaks at their fits' position, depth and misfit."""
    x, y = grid.to_pixels(fit.sx_m, fit.sy_m)
    return dataclasses.replace(peaks, x=np.asarray(x, float), y=np.asarray(y, float), alpha=fit.alpha,
                               residual=fit.residual)
