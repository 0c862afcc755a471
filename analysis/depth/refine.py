"""The pipeline's depth stages on the raw pixels: refine, probe for hidden particles, deblend, prior.

Each takes candidate particles (:class:`analysis.detection.curves.Peaks`, positions in output-image pixels)
and returns them moved to the forward-model fit of :func:`analysis.depth.rayfit.fit_rays`, with
the matching rows of the fit (:class:`analysis.depth.rayfit.RayFit`)::

    fitter = RayFitter(image, fit_table, grid, background=..., ...)
    peaks, fit = refine_peaks(fitter, peaks, shadow_probe=0.0065)   # fit, drop, merge, probe
    peaks, fit = deblend(fitter, peaks, fit)                         # neighbours' light taken off
    peaks, fit = apply_depth_prior(fitter, peaks, fit)               # where one lens holds the light
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from analysis.detection.curves import Peaks, unique_indices
from .prior import neighbour_prior
from analysis.camera.image_grid import ImageGrid
from analysis.lightfield.table import LightFieldTable
from .rayfit import RayFit, fit_rays, render_fits, unexplained_light

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RayFitter:
    """One exposure's raw image and the fit settings every depth stage shares.

    Attributes
    ----------
    image : ndarray (H, W), uint16
    table : LightFieldTable
        The depth fit's table, with the micro-image rims (``analysis.pipeline.process.FIT_TABLE_RIM_PX``).
    grid : ImageGrid
        Output-image pixels of the candidates.
    background, aperture_per_lens_plane, alpha_half_range : float
        As :func:`analysis.depth.rayfit.fit_rays` takes them.
    fit_depths, fit_lateral : int
        The fit's grid: coarse depths, and positions per side in both passes.
    min_intensity, max_residual : float
        Fits dimmer than this (devignetted DN), or with a larger misfit, are no particle.
    merge_radius_px, merge_alpha : float
        Fits closer than this in the image and in alpha are one particle (the brighter kept).
    """

    image: np.ndarray
    table: LightFieldTable
    grid: ImageGrid
    background: float
    aperture_per_lens_plane: float
    alpha_half_range: float
    fit_depths: int
    fit_lateral: int
    min_intensity: float
    max_residual: float
    merge_radius_px: float
    merge_alpha: float

    def fit(self, sx_m: np.ndarray, sy_m: np.ndarray, alpha: np.ndarray, *,
            wide_fine: tuple[int, float, int, int] | None = None, **options) -> RayFit:
        """:func:`analysis.depth.rayfit.fit_rays` with these settings (``options`` override them).

        Particles blurred wider than :data:`WIDE_BLUR_PITCHES` at their start get the fine grid
        ``wide_fine`` (default: :data:`WIDE_FINE_GRID`, or the ``fine`` option when one is given),
        the others ``fine`` (default :data:`FINE_GRID`).
        """
        settings = dict(background=self.background, aperture_per_lens_plane=self.aperture_per_lens_plane,
                        alpha_half_range=self.alpha_half_range, n_alpha=self.fit_depths,
                        coarse_lateral=self.fit_lateral, fine=FINE_GRID, temperature=FINE_TEMPERATURE)
        settings.update(options)
        if wide_fine is None:
            wide_fine = settings["fine"] if "fine" in options else WIDE_FINE_GRID
        sx, sy, a = (np.asarray(v, dtype=np.float64).ravel() for v in (sx_m, sy_m, alpha))
        if a.size <= FIT_CHUNK and wide_fine == settings["fine"]:
            return fit_rays(self.image, self.table, sx, sy, a, **settings)
        wide = np.zeros(a.size, dtype=bool)
        if wide_fine != settings["fine"]:
            pitch = float(np.hypot(*self.table.basis_m[:, 0]))
            wide = np.abs(1.0 - 1.0 / a) * self.table.aperture_radius_m > WIDE_BLUR_PITCHES * pitch
        parts, fits = [], []
        for rows, fine in ((np.flatnonzero(~wide), settings["fine"]), (np.flatnonzero(wide), wide_fine)):
            for start in range(0, rows.size, FIT_CHUNK):
                chunk = rows[start:start + FIT_CHUNK]
                part = dict(settings, fine=fine)
                if part.get("own") is not None:
                    part["own"] = take_fit(part["own"], chunk)
                for name in ("prior_alpha", "prior_sigma"):
                    if part.get(name) is not None:
                        part[name] = np.asarray(part[name]).ravel()[chunk]
                parts.append(chunk)
                fits.append(fit_rays(self.image, self.table, sx[chunk], sy[chunk], a[chunk], **part))
        if len(fits) <= 1:
            return fits[0] if fits else fit_rays(self.image, self.table, sx, sy, a, **settings)
        return take_fit(concat_fits(*fits), np.argsort(np.concatenate(parts)))

    def render(self, fit: RayFit) -> np.ndarray:
        """The light of fitted particles on each table sample (:func:`analysis.depth.rayfit.render_fits`)."""
        out = np.zeros(self.table.n_samples, dtype=np.float32)
        for start in range(0, len(fit), FIT_CHUNK):  # in particle order, as one call would add them
            chunk = take_fit(fit, np.arange(start, min(start + FIT_CHUNK, len(fit))))
            render_fits(self.table, chunk, aperture_per_lens_plane=self.aperture_per_lens_plane, out=out)
        return out


#: Particles per call of :func:`analysis.depth.rayfit.fit_rays` and :func:`~analysis.depth.rayfit.render_fits`:
#: each call gathers the samples of every lens its particles reach, ~10 000 per particle blurred over
#: a few pitches (32 bytes each), so one call for 200 such particles held ~70 MB at once.
FIT_CHUNK = 64
#: The fit's fine pass (:func:`analysis.depth.rayfit.fit_rays`): 9 depths, 11 positions per side over
#: +-0.25 pitch (0.05 pitch apart: near focus depth and position are coupled through how the light
#: splits between lenses, so the position must be that fine), each pixel as 5 x 5 points (the
#: partly lit rim pixels of the neighbouring lenses tell a blur of about a pitch in front of focus
#: from one behind it only when pixel areas are modelled).
FINE_GRID = (9, 0.25, 11, 5)
#: With 5 x 5 points (evenly spaced, as the footprint was then) the model missed a noise-free
#: simulated particle by 0.1-0.3 pixel (I0^2) units (3 x 3: 0.15-0.45), so candidates are weighed
#: at that scale. Pooled over 18 simulated exposures this grid and temperature lower the depth
#: error by a seventh (ball) to a half (layer); with the quantile footprint 0.1 and 0.4 still
#: score worse than 0.25 (ball 8.17 and 8.26 % against 8.11 %).
FINE_TEMPERATURE = 0.25
#: Blurs wider than this many lens pitches (radius on the MLA) at the start of a fit, e.g. a
#: cluster placed a few mm off focus, get the fine grid :data:`WIDE_FINE_GRID`.
WIDE_BLUR_PITCHES = 2.0
#: Their light spreads over dozens of lenses, which pin position and depth down well enough for
#: the coarse pass that the fine pass may search +-0.15 pitch (same 0.05 pitch steps, 5 x 5 points)
#: and 5 depths: 55 % of the cost, and on the off-focus ball (3 seeds; pixel points then evenly
#: spaced) depth error 5.75 -> 5.38 % with precision no lower. Fewer points per pixel (3 x 3) there
#: lost a tenth of the precision, 0.1 pitch steps a particle or two of recall, fewer coarse depths
#: (9-11) biased the depth scale.
WIDE_FINE_GRID = (5, 0.15, 7, 5)
#: The fine pass of probes for hidden particles: crowds probe many, so 3 positions per side and
#: pixels as 3 x 3 points; behind wide blurs 5 depths over +-0.15 pitch.
PROBE_GRID = (9, 0.25, 3, 3)
WIDE_PROBE_GRID = (5, 0.15, 3, 3)


def refine_peaks(fitter: RayFitter, peaks: Peaks, *, shadow_probe: float = 0.0, subtract: np.ndarray | None = None,
                 probe_residual: float = 0.2, probe_fraction: float = 0.35, probe_light: float = 0.5,
                 probe_half_range: float = 0.0025) -> tuple[Peaks, RayFit]:
    """Replace each peak's position and depth by the forward-model fit to the raw pixels.

    Fits without enough light or with too large a misfit are dropped; fits that converge onto one
    particle are merged. With ``shadow_probe`` > 0, particles hidden behind the ones found are
    looked for this far in alpha in front of and behind each, where light is left over around it.
    ``subtract``: light already explained (devignetted DN per table sample), taken off first.
    """
    sx0, sy0 = fitter.grid.to_lens_plane(peaks.x, peaks.y)
    fit = fitter.fit(sx0, sy0, peaks.alpha, subtract=subtract)
    refined, fit = accept(fitter, peaks, fit, fitter.max_residual)
    kept = unique_indices(refined, radius_px=fitter.merge_radius_px, alpha_tolerance=fitter.merge_alpha,
                          priority=fit.intensity)
    refined, fit = refined.take(kept), take_fit(fit, kept)
    if shadow_probe <= 0 or len(refined) == 0:
        return refined, fit
    # A particle hidden behind another (same line of sight, other depth) often merges into its
    # neighbour's brightness curve without a maximum of its own. Take the light of the particles
    # found so far off the raw samples and probe what is left, in front of and behind each.
    table = fitter.table
    explained = fitter.render(fit)
    # Only where light is left over around a particle (a hidden one's share of the aperture), or
    # where a fit is much brighter than most (it may hold a hidden one's light as well).
    c_probe = np.abs(1.0 - 1.0 / (fit.alpha - shadow_probe))
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    left = unexplained_light(fitter.image, table, fit.sx_m, fit.sy_m, c_probe * table.aperture_radius_m + pitch,
                             background=fitter.background, explained=explained, floor=0.3 * fitter.min_intensity)
    own = fit.intensity * np.maximum(fit.n_lit, 1)
    parents = np.flatnonzero((left > probe_light * own) | (fit.intensity > 1.3 * np.median(fit.intensity)))
    probes = refined.take(np.r_[parents, parents])
    probes = dataclasses.replace(probes, alpha=np.r_[refined.alpha[parents] - shadow_probe,
                                                     refined.alpha[parents] + shadow_probe])
    parent_intensity = np.r_[fit.intensity[parents], fit.intensity[parents]]
    psx, psy = fitter.grid.to_lens_plane(probes.x, probes.y)
    # Crowds probe many: a cheaper fine pass.
    pfit = fitter.fit(psx, psy, probes.alpha, alpha_half_range=probe_half_range, n_alpha=17, subtract=explained,
                      fine=PROBE_GRID, wide_fine=WIDE_PROBE_GRID)
    log.debug("shadow probes: %d of %d particles probed", parents.size, len(refined))
    # A probe must be a particle of its own: as bright as a good part of the one it hides behind
    # (what is left of a neighbour's imperfectly modelled light is a tenth of it or less).
    good = np.flatnonzero(pfit.intensity >= probe_fraction * parent_intensity)
    probes, pfit = accept(fitter, probes.take(good), take_fit(pfit, good), min(fitter.max_residual, probe_residual))
    if len(probes) == 0:
        return refined, fit
    both, both_fit = concat_peaks(refined, probes), concat_fits(fit, pfit)
    # Found particles win over probes that converged onto them.
    priority = np.r_[fit.intensity + 1e12, pfit.intensity]
    kept = unique_indices(both, radius_px=fitter.merge_radius_px, alpha_tolerance=fitter.merge_alpha,
                          priority=priority)
    return both.take(kept), take_fit(both_fit, kept)


def deblend(fitter: RayFitter, peaks: Peaks, fit: RayFit) -> tuple[Peaks, RayFit]:
    """Refit every particle with its neighbours' fitted light taken off its pixels.

    Each first fit saw its neighbours' light too (crowds: the blurs of particles a pitch or two
    apart overlap), which pulls position and depth; the refit starts from the first fit. A fit
    that is left without enough light of its own, or that no longer fits, was a neighbour's light
    seen twice (a duplicate, or a ghost at another depth) and is dropped. Such fits are screened
    out first by a cheaper refit (:func:`seen_twice`), so the others are refitted once without
    their light rather than twice.
    """
    # The light of the fits kept so far; a dropped fit's light is taken off it (fewer than re-rendering all).
    explained = fitter.render(fit)
    twice = seen_twice(fitter, fit, explained)
    if twice.any():
        explained -= fitter.render(take_fit(fit, np.flatnonzero(twice)))
        keep = np.flatnonzero(~twice)
        peaks, fit = peaks.take(keep), take_fit(fit, keep)
    new = fitter.fit(fit.sx_m, fit.sy_m, fit.alpha, subtract=explained, own=fit)
    ok = _acceptable(fitter, new, fitter.max_residual)
    if not ok.all():
        # The dropped fits' light was taken off their neighbours' pixels too: refit those without it.
        near = ok & _overlapping(fitter.table, fit, np.flatnonzero(~ok), pad_pitches=2.0)
        explained -= fitter.render(take_fit(fit, np.flatnonzero(~ok)))
        keep = np.flatnonzero(ok)
        peaks, fit, new, near = peaks.take(keep), take_fit(fit, keep), take_fit(new, keep), near[keep]
        log.debug("deblend: %d fits dropped, %d neighbours refitted", (~ok).sum(), near.sum())
        if near.any():
            again = fitter.fit(fit.sx_m[near], fit.sy_m[near], fit.alpha[near], subtract=explained,
                               own=take_fit(fit, near))
            new = replace_fits(fitter.grid, peaks, new, np.flatnonzero(near), again)[1]
    return accept(fitter, peaks, new, fitter.max_residual)


#: The screen's refit (:func:`seen_twice`): after the full coarse pass, 5 depths and +-0.15 pitch,
#: pixels as 3 x 3 points (on the off-focus ball it drops the same fits as the full refit; the
#: probes' grid (9, 0.25, 3, 3) cost a quarter more and dropped one the full refit keeps).
SCREEN_GRID = (5, 0.15, 3, 3)
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
    pitch = float(np.hypot(*fitter.table.basis_m[:, 0]))
    blur = np.abs(1.0 - 1.0 / fit.alpha) * fitter.table.aperture_radius_m
    # Pairs from a tree: a crowd of thousands would make a full distance matrix hundreds of MB.
    pairs = cKDTree(np.column_stack([fit.sx_m, fit.sy_m])).query_pairs(float(blur.max()) + pitch,
                                                                       output_type="ndarray")
    i, j = pairs[:, 0], pairs[:, 1]
    close = np.hypot(fit.sx_m[i] - fit.sx_m[j], fit.sy_m[i] - fit.sy_m[j]) < np.maximum(blur[i], blur[j]) + pitch
    suspects = np.unique(np.r_[i[close], j[close]])
    if suspects.size == 0:
        return twice
    sub = take_fit(fit, suspects)
    explained = fitter.render(fit) if explained is None else explained
    screen = fitter.fit(sub.sx_m, sub.sy_m, sub.alpha, subtract=explained, own=sub, fine=SCREEN_GRID)
    twice[suspects] = ((screen.intensity <= max(fitter.min_intensity, 0.0))
                       | (screen.residual > SCREEN_RESIDUAL * fitter.max_residual))
    log.debug("deblend screen: %d of %d fits refitted, %d seen twice", suspects.size, len(fit), twice.sum())
    return twice


def split_shared(fitter: RayFitter, peaks: Peaks, fit: RayFit, *, shadow_probe: float,
                 probe_half_range: float = 0.0025, bright: float = 1.3, misfit: float = 1.0
                 ) -> tuple[Peaks, RayFit]:
    """Split fits that hold the light of two particles on one line of sight.

    A particle hidden behind another can give its light to the other's fit: one fit, brighter
    than most, explains both, and no light is left over for a probe (:func:`refine_peaks`) to
    find. For each fit brighter than ``bright`` times the median that also misfits more than
    ``misfit`` times the median, a partner is tried ``shadow_probe`` in front and behind,
    starting from half the light each; partner and fit are refitted with each other's light
    taken off. The split is kept where the fit gives up light to the partner and then fits its
    pixels much better (misfit down by 40 %).
    """
    # Two particles taken for one also misfit more than most.
    parents = (np.flatnonzero((fit.intensity > bright * np.median(fit.intensity))
                              & (fit.residual > misfit * np.median(fit.residual))) if len(fit) else np.empty(0, int))
    if parents.size == 0:
        return peaks, fit
    par = take_fit(fit, parents)
    # The light of the other fits that reach the parents' lenses (rendering all would cost more): a
    # fit's light lands within its blur plus 1.6 pitches (cell and crosstalk), and a fit gathers
    # lenses up to its blur plus about 2.5 pitches.
    reach = _overlapping(fitter.table, fit, parents, pad_pitches=4.5)
    reach[parents] = False
    others = fitter.render(take_fit(fit, np.flatnonzero(reach)))
    half = dataclasses.replace(par, intensity=0.5 * par.intensity)
    found: tuple[np.ndarray, RayFit, RayFit] | None = None
    for sign in (-1.0, 1.0):
        start = dataclasses.replace(half, alpha=par.alpha + sign * shadow_probe)
        # A cheap first look (the probes' grid); only where it finds light of its own, the full refits.
        partner = fitter.fit(start.sx_m, start.sy_m, start.alpha, subtract=others + fitter.render(half),
                             alpha_half_range=probe_half_range, fine=PROBE_GRID, wide_fine=WIDE_PROBE_GRID)
        good = np.zeros(len(par), dtype=bool)
        host = par
        look = np.flatnonzero(partner.intensity >= 0.35 * half.intensity)
        if look.size:
            p0, h0 = take_fit(partner, look), take_fit(par, look)
            h = fitter.fit(h0.sx_m, h0.sy_m, h0.alpha, subtract=others + fitter.render(p0))
            q = fitter.fit(p0.sx_m, p0.sy_m, p0.alpha, subtract=others + fitter.render(h),
                           alpha_half_range=probe_half_range)
            good[look] = ((q.intensity >= 0.35 * h.intensity) & (q.residual <= 0.2)
                          & (h.intensity <= 0.85 * h0.intensity) & (h.residual <= 0.6 * h0.residual)
                          & (np.abs(q.alpha - h.alpha) > fitter.merge_alpha))
            host, partner = _with_rows(par, look, h), _with_rows(partner, look, q)
        if found is None:
            found = (good, host, partner)
        else:
            # Both sides split: keep the side whose partner took more light.
            use = good & (~found[0] | (partner.intensity > found[2].intensity))
            found = (found[0] | good, _where(use, host, found[1]), _where(use, partner, found[2]))
    good, host, partner = found
    rows = np.flatnonzero(good)
    log.debug("split: %d of %d bright fits hold two particles", rows.size, parents.size)
    if rows.size == 0:
        return peaks, fit
    peaks, fit = replace_fits(fitter.grid, peaks, fit, parents[rows], take_fit(host, rows))
    new = take_fit(partner, rows)
    both = concat_peaks(peaks, _moved(fitter.grid, peaks.take(parents[rows]), new))
    kept = unique_indices(both, radius_px=fitter.merge_radius_px, alpha_tolerance=fitter.merge_alpha,
                          priority=np.r_[fit.intensity + 1e12, new.intensity])
    return both.take(kept), take_fit(concat_fits(fit, new), kept)


def _with_rows(fit: RayFit, rows: np.ndarray, new: RayFit) -> RayFit:
    """A copy of ``fit`` with ``rows`` replaced by the rows of ``new``."""
    out = RayFit(**{name: getattr(fit, name).copy() for name in RayFit.__dataclass_fields__})
    for name in RayFit.__dataclass_fields__:
        getattr(out, name)[rows] = getattr(new, name)
    return out


def _where(mask: np.ndarray, a: RayFit, b: RayFit) -> RayFit:
    return RayFit(**{name: np.where(mask, getattr(a, name), getattr(b, name)) for name in RayFit.__dataclass_fields__})


def apply_depth_prior(fitter: RayFitter, peaks: Peaks, fit: RayFit) -> tuple[Peaks, RayFit]:
    """Refit the particles whose pixels leave the depth open, with their neighbours' surface as prior.

    Only where the prior is narrower than the spread the pixels allow
    (:func:`analysis.depth.prior.neighbour_prior`); the others keep their fit.
    """
    prior = neighbour_prior(peaks.x, peaks.y, fit.alpha, fit.alpha_spread)
    todo = np.flatnonzero(np.isfinite(prior.sigma) & (fit.alpha_spread > prior.sigma))
    log.debug("depth prior: %d of %d particles refitted", todo.size, len(peaks))
    if todo.size == 0:
        return peaks, fit
    sub = take_fit(fit, todo)
    new = fitter.fit(sub.sx_m, sub.sy_m, sub.alpha, subtract=fitter.render(fit), own=sub,
                     prior_alpha=prior.alpha[todo], prior_sigma=prior.sigma[todo])
    ok = np.flatnonzero(new.intensity > 0)
    return replace_fits(fitter.grid, peaks, fit, todo[ok], take_fit(new, ok))


def accept(fitter: RayFitter, peaks: Peaks, fit: RayFit, max_residual: float) -> tuple[Peaks, RayFit]:
    """Peaks moved to their fitted position and depth, keeping fits with light and a small misfit."""
    keep = np.flatnonzero(_acceptable(fitter, fit, max_residual))
    return _moved(fitter.grid, peaks, fit).take(keep), take_fit(fit, keep)


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


def _acceptable(fitter: RayFitter, fit: RayFit, max_residual: float) -> np.ndarray:
    return (fit.intensity > max(fitter.min_intensity, 0.0)) & (fit.residual <= max_residual)


def replace_fits(grid: ImageGrid, peaks: Peaks, fit: RayFit, rows: np.ndarray, new: RayFit) -> tuple[Peaks, RayFit]:
    """``fit`` with ``rows`` replaced by the rows of ``new``, and the peaks moved to match."""
    merged = _with_rows(fit, rows, new)
    return _moved(grid, peaks, merged), merged


def inside(peaks: Peaks, fit: RayFit, alphas: np.ndarray) -> tuple[Peaks, RayFit]:
    """Drop fits that left the stack's alpha range: they found a particle of another range."""
    keep = np.flatnonzero((peaks.alpha >= alphas[0]) & (peaks.alpha <= alphas[-1]))
    if keep.size < len(peaks):
        return peaks.take(keep), take_fit(fit, keep)
    return peaks, fit


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


def concat_peaks(a: Peaks, b: Peaks) -> Peaks:
    return Peaks(**{name: np.concatenate([getattr(a, name), getattr(b, name)]) for name in a.__dataclass_fields__})


def concat_fits(*fits: RayFit) -> RayFit:
    return RayFit(**{name: np.concatenate([getattr(f, name) for f in fits]) for name in RayFit.__dataclass_fields__})


def take_fit(fit: RayFit, index: np.ndarray) -> RayFit:
    return RayFit(**{name: getattr(fit, name)[index] for name in fit.__dataclass_fields__})


def _moved(grid: ImageGrid, peaks: Peaks, fit: RayFit) -> Peaks:
    x, y = grid.to_pixels(fit.sx_m, fit.sy_m)
    return dataclasses.replace(peaks, x=np.asarray(x, float), y=np.asarray(y, float), alpha=fit.alpha,
                               residual=fit.residual)
