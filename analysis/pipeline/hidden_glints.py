"""Glints seen through a crowded cluster: found once the particles are fitted, taken off, and the
fits in their light refitted.

The glint stage (:func:`analysis.lightfield.glints.find_glints`) looks for glints in a map of
each lens's light, where a glint behind the middle of a crowded cluster is hidden by the
particles' own light (held-out seed 148: a 0.16 mm glint 3 mm in front of an off-focus ball, two
false particles fitted on its light). Such light does not converge to a point, so the fits made
on it are blurred thin and show no point's pattern within their lenses; started there, in the
image with the other fits' light taken off, the glint fit finds the source.
"""

from __future__ import annotations

import numpy as np

from analysis.depth.deblend import refit_or_drop
from analysis.depth.quality import patterned
from analysis.depth.rayfit import RayFit
from analysis.depth.refine import RayFitter, residual_image
from analysis.detection.curves import Peaks
from analysis.lightfield.glints import SEED_RADIUS_PITCHES, Glint, glints_at, overlap

from .passes import THIN_PATTERN_PITCHES


def glints_behind(fitter: RayFitter, fit: RayFit, level: np.ndarray, limits: tuple[float, float],
                  known: list[Glint]) -> list[Glint]:
    """Glints not in ``known`` found by fits started at the fits blurred over
    :data:`~analysis.pipeline.passes.THIN_PATTERN_PITCHES` or more whose light shows no point's
    pattern (:func:`~analysis.depth.quality.patterned`), one start per disk of
    :data:`~analysis.lightfield.glints.SEED_RADIUS_PITCHES`, brightest first; ``level``: each fit-table
    lens's glow level, ``limits``: the particles' alpha range."""
    pitch = fitter.pitch_m
    blurred = np.flatnonzero(fitter.blur_radius_m(fit.alpha) >= THIN_PATTERN_PITCHES * pitch)
    if blurred.size == 0:
        return []
    explained = fitter.render(fit)
    thin = blurred[~patterned(fitter, fit.take(blurred), explained)]
    if thin.size == 0:
        return []
    explained -= fitter.render(fit.take(thin))  # in place: each copy is 4 bytes a sample (20 MB on an F01)
    residual = residual_image(fitter.image, fitter.table, explained)
    del explained
    starts: list[int] = []
    for i in thin[np.argsort(-fit.intensity[thin], kind="stable")]:
        if all(np.hypot(fit.sx_m[i] - fit.sx_m[j], fit.sy_m[i] - fit.sy_m[j]) > SEED_RADIUS_PITCHES * pitch
               for j in starts):
            starts.append(i)
    found = glints_at(residual, fitter.table, level, np.column_stack([fit.sx_m[starts], fit.sy_m[starts]]),
                      particle_c=(1.0 - 1.0 / limits[0], 1.0 - 1.0 / limits[1]), saturation=fitter.saturation)
    return [g for g in found if not any(overlap(g, k) for k in known)]


def refit_in_glints(fitter: RayFitter, peaks: Peaks, fit: RayFit, glints: list[Glint], *,
                    max_residual: float) -> tuple[Peaks, RayFit]:
    """The fits whose light falls in the ``glints``' disks refitted on ``fitter``'s image (the
    glints' light taken off), those no longer particles dropped as ``glint``: too faint, or
    misfitting beyond ``max_residual`` (the final table's limit, which the glint's light had helped
    them meet)."""
    reach = np.zeros(len(fit), dtype=bool)
    radius = fitter.blur_radius_m(fit.alpha)
    for g in glints:
        disk = abs(g.c) * fitter.table.aperture_radius_m + 3.0 * g.sigma_m
        reach |= np.hypot(fit.sx_m - g.sx_m, fit.sy_m - g.sy_m) < disk + radius
    return refit_or_drop(fitter, peaks, fit, np.flatnonzero(reach), "glint", max_residual=max_residual)
