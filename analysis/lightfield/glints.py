"""Compact sources far out of focus (glints): found in the exposure, fitted, and taken off.

A glint (laser light scattered off an electrode or a window, a fraction of a millimetre across)
far in front of or behind the cluster lights a disk of hundreds of lenses, one spot in each: the
ray from aperture point ``u`` toward a source that images at lens-plane position ``s`` with
``c = 1 - 1/alpha`` enters the lens at ``s + c u`` (docs/camera-model.md), so the spot of a source
spread over the lens plane as a Gaussian of ``sigma`` lies in lens ``k`` (centre ``x_k``) about the
aperture point ``(x_k - s) / c``. In each sub-aperture image such a source is as compact as a
particle blurred over several pitches, so the background's medians over neighbouring lenses keep
most of it; left in, its light stands unexplained around every particle in its disk, which the
tests of extended light then drop (25 realistic frames, docs/realism-history.md stop 55: recall
91 % inside glints' disks, 99 % elsewhere).

Per sample the model is ``intensity * exp(-|x_k - c u - s|^2 / (2 sigma^2))`` (devignetted DN above
the lens's glow level): fitted by least squares to the samples of the disk, it explains a glint's
spots to near the noise. A source is taken for a glint only where it is extended (a particle is a
point: its fitted ``sigma`` is that of the sensor's blur, a fraction of a pitch) and lies in depth
beyond the particles' range.

:func:`find_glints` starts the fits at the maxima of a map of each lens's light; :func:`glints_at`
at given places, for a glint the map cannot show behind a crowded cluster
(:mod:`analysis.pipeline.hidden_glints` starts them at fits that show no point's pattern).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numba
import numpy as np
from scipy.ndimage import gaussian_filter, maximum_filter
from scipy.optimize import least_squares

from .table import LightFieldTable

log = logging.getLogger(__name__)

#: Lens-plane smoothing (lens pitches) of the map of each lens's light above its glow level, in
#: which a glint's disk is a plateau and a particle in focus a lone lens.
MAP_SMOOTH_PITCHES = 4.0
#: At most this many of the map's highest maxima are tried as glints.
MAX_CANDIDATES = 4
#: A maximum is tried when it stands this many times above the map's median.
CANDIDATE_OVER_MEDIAN = 4.0
#: A fitted source is a glint when its spread on the lens plane is at least this (pitches) ...
MIN_SIGMA_PITCHES = 2.0
#: ... it explains at least this share of the light above the glow in its disk's samples ...
MIN_EXPLAINED = 0.3
#: ... and its depth lies beyond the particles' range by at least this (in c = 1 - 1/alpha).
RANGE_MARGIN_C = 0.002
#: The samples of a first fit of each candidate (both signs of its depth tried), and of the last
#: fit of those that pass: at most about this many (every n-th lens beyond).
FIRST_FIT_SAMPLES = 3_000
LAST_FIT_SAMPLES = 40_000
#: Fits started at given places (:func:`glints_at`) cover a disk of this radius (lens pitches).
SEED_RADIUS_PITCHES = 10.0


@dataclass(frozen=True)
class Glint:
    """A compact source far out of focus, as fitted (lens-plane metres, ``c = 1 - 1/alpha``,
    devignetted DN at a spot's centre); ``explained``: the share of the light above the glow in
    its disk's samples that it explains."""

    sx_m: float
    sy_m: float
    c: float
    sigma_m: float
    intensity: float
    explained: float

    @property
    def alpha(self) -> float:
        return 1.0 / (1.0 - self.c)

    @property
    def params(self) -> np.ndarray:
        """The model's parameters (:func:`_model`)."""
        return np.array([self.sx_m, self.sy_m, self.c, np.log(self.sigma_m), np.log(self.intensity)])


def _model(p: np.ndarray, cx: np.ndarray, cy: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    sx, sy, c, log_sigma, log_i = p
    return np.exp(log_i - ((cx - c * u - sx) ** 2 + (cy - c * v - sy) ** 2) * (0.5 * np.exp(-2.0 * log_sigma)))


def _jacobian(p: np.ndarray, cx: np.ndarray, cy: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """d model / d p, one row per sample."""
    sx, sy, c, log_sigma, _ = p
    ex, ey = cx - c * u - sx, cy - c * v - sy
    inv = np.exp(-2.0 * log_sigma)
    m = _model(p, cx, cy, u, v)
    return np.column_stack([m * ex * inv, m * ey * inv, m * (ex * u + ey * v) * inv,
                            m * (ex * ex + ey * ey) * inv, m])


def find_glints(image: np.ndarray, table: LightFieldTable, level: np.ndarray, *,
                particle_c: tuple[float, float], saturation: float) -> list[Glint]:
    """The glints of a raw exposure (see the module docstring).

    Parameters
    ----------
    image : ndarray (H, W), uint16
    table : LightFieldTable
        The depth fit's table (with the micro-image rims).
    level : ndarray of shape (table.n_lenses,)
        Each lens's glow level (devignetted DN; :meth:`analysis.lightfield.background.BackgroundMap.per_lens`).
    particle_c : (low, high)
        The particles' range in ``c = 1 - 1/alpha``: a glint lies beyond it.
    saturation : float
        Raw value at which the ADC saturates (such samples are left out of the fits).
    """
    above, pitch = _samples_above(image, table, level, saturation)
    per_lens = np.zeros(table.n_lenses)
    _light_above(np.ascontiguousarray(image).reshape(-1), table.pixel_index, table.weight, table.lens_start,
                 np.ascontiguousarray(level, dtype=np.float64), float(table.black_level), per_lens)
    # The map on a grid of one pitch over the lens plane.
    xy = table.lens_xy_m
    ij = np.floor((xy - xy.min(axis=0)) / pitch).astype(np.int64)
    shape = tuple(ij.max(axis=0)[::-1] + 1)
    grid = np.bincount(ij[:, 1] * shape[1] + ij[:, 0], weights=per_lens, minlength=shape[0] * shape[1]).reshape(shape)
    smooth = gaussian_filter(grid, MAP_SMOOTH_PITCHES)
    peaks = (smooth == maximum_filter(smooth, size=int(4 * MAP_SMOOTH_PITCHES) + 1)) & (
        smooth > CANDIDATE_OVER_MEDIAN * max(float(np.median(smooth)), 1e-9))
    rows, cols = np.nonzero(peaks)
    order = np.argsort(-smooth[rows, cols])[:MAX_CANDIDATES]
    starts = [xy.min(axis=0) + (np.array([q, r]) + 0.5) * pitch for r, q in zip(rows[order], cols[order])]
    radii = [_half_radius(smooth, r, q) * pitch for r, q in zip(rows[order], cols[order])]
    return _glints_from(table, above, starts, radii, pitch, particle_c)


def glints_at(image: np.ndarray, table: LightFieldTable, level: np.ndarray, starts: np.ndarray, *,
              particle_c: tuple[float, float], saturation: float) -> list[Glint]:
    """The glints of a raw exposure found by fits started at ``starts`` (n, 2; lens-plane metres),
    each over a disk of :data:`SEED_RADIUS_PITCHES`; other arguments as for :func:`find_glints`.

    For a glint the map of :func:`find_glints` cannot show: one seen through a crowded cluster,
    whose light there is the particles' (the pipeline starts these fits at the particles' fits that
    show no point's pattern, in an image with the other fits' light taken off)."""
    above, pitch = _samples_above(image, table, level, saturation)
    starts = np.asarray(starts, dtype=np.float64).reshape(-1, 2)
    return _glints_from(table, above, list(starts), [SEED_RADIUS_PITCHES * pitch] * len(starts), pitch, particle_c)


def _samples_above(image: np.ndarray, table: LightFieldTable, level: np.ndarray, saturation: float):
    """``above(ids)`` (the samples' devignetted light above their lens's glow ``level``, and which
    are below ``saturation``), and the lens pitch."""
    flat = np.ascontiguousarray(image).reshape(-1)
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    level = np.ascontiguousarray(level, dtype=np.float64)

    def above(ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        raw = flat[table.pixel_index[ids]].astype(np.float64)
        return ((raw - table.black_level) / np.maximum(table.weight[ids].astype(np.float64), 1e-6)
                - level[table.lens[ids]], raw < saturation)
    return above, pitch


def _glints_from(table: LightFieldTable, above, starts: list[np.ndarray], radii: list[float], pitch: float,
                 particle_c: tuple[float, float]) -> list[Glint]:
    """The glints among fits started at ``starts`` over disks of ``radii`` (lens-plane metres)."""
    lo, hi = particle_c
    found: list[Glint] = []

    def passes(g: Glint, slack: float) -> bool:
        if not np.all(np.isfinite([g.c, g.sigma_m, g.intensity, g.explained])):
            return False
        beyond = g.c < lo - RANGE_MARGIN_C * slack or g.c > hi + RANGE_MARGIN_C * slack
        return beyond and g.sigma_m >= slack * MIN_SIGMA_PITCHES * pitch and g.explained >= slack * MIN_EXPLAINED

    for start, radius in zip(starts, radii):
        # A quick fit on a sample of the disk's lenses, both sides of focus; the full one where it
        # looks like a glint (particles' crowds, fitted so, do not).
        glint = _fit(table, above, start, radius, pitch, FIRST_FIT_SAMPLES, None)
        if glint is None or not passes(glint, 0.5):
            continue
        glint = _fit(table, above, np.array([glint.sx_m, glint.sy_m]), radius, pitch, LAST_FIT_SAMPLES, glint)
        if glint is None:  # its disk, about the first fit's place, held too little light
            continue
        log.debug("glint candidate at alpha %.4f: sigma %.1f pitches, %.0f DN, explains %.2f", glint.alpha,
                  glint.sigma_m / pitch, glint.intensity, glint.explained)
        if passes(glint, 1.0) and not any(overlap(g, glint) for g in found):
            found.append(glint)
    return found


def overlap(a: Glint, b: Glint) -> bool:
    """Whether two fitted glints are one source (their centres within their spreads)."""
    return bool(np.hypot(a.sx_m - b.sx_m, a.sy_m - b.sy_m) < a.sigma_m + b.sigma_m)


@numba.njit(cache=True, parallel=True)
def _light_above(flat, pixel_index, weight, first, level, black, out):  # pragma: no cover - numba
    # Per lens (its samples first[k]:first[k + 1]), the sum of their devignetted light above its
    # glow level; each lens writes its own entry.
    for k in numba.prange(out.size):
        total = 0.0
        for j in range(first[k], first[k + 1]):
            v = (flat[pixel_index[j]] - black) / max(weight[j], 1e-6) - level[k]
            if v > 0.0:
                total += v
        out[k] = total


def _half_radius(smooth: np.ndarray, r: int, q: int) -> float:
    """How far (grid cells) the map falls to half its value at ``(r, q)``, over the four axes' mean."""
    half = 0.5 * smooth[r, q]
    reach = []
    for dr, dq in ((0, 1), (0, -1), (1, 0), (-1, 0)):
        k = 1
        while 0 <= r + k * dr < smooth.shape[0] and 0 <= q + k * dq < smooth.shape[1] and smooth[r + k * dr, q + k * dq] > half:
            k += 1
        reach.append(k)
    return float(np.mean(reach))


def _fit(table: LightFieldTable, above, start: np.ndarray, radius: float, pitch: float,
         max_samples: int, prior: Glint | None) -> Glint | None:
    """The Gaussian source that best explains the light above the glow about ``start`` (a disk of
    about ``radius``), from ``prior`` or with its depth tried on both sides of focus; None when
    there is too little light. ``above(ids)``: the samples' light above the glow, and which are
    not saturated."""
    near = np.flatnonzero(np.hypot(*(table.lens_xy_m - start).T) < radius + 4.0 * MIN_SIGMA_PITCHES * pitch)
    if near.size < 20:
        return None
    near = near[:: max(1, int(np.ceil(near.size * 80 / max_samples)))]  # about 80 samples a lens
    ids = table.samples_of(near)
    y, unsaturated = above(ids)
    ids, y = ids[unsaturated], y[unsaturated]
    cx, cy = table.lens_xy_m[table.lens[ids]].T
    u, v = table.u_m[ids].astype(np.float64), table.v_m[ids].astype(np.float64)
    total = float(np.sum(np.maximum(y, 0.0) ** 2))
    if total <= 0:
        return None
    peak = max(float(np.percentile(y, 99.5)), 1.0)
    c_size = radius / table.aperture_radius_m
    if prior is None:
        starts = [np.array([start[0], start[1], sign * c_size, np.log(MIN_SIGMA_PITCHES * pitch), np.log(peak)])
                  for sign in (-1.0, 1.0)]
    else:
        starts = [prior.params]
    best = None
    for p0 in starts:
        fit = least_squares(lambda p: _model(p, cx, cy, u, v) - y, p0, jac=lambda p: _jacobian(p, cx, cy, u, v),
                            x_scale=np.array([pitch, pitch, 0.1 * c_size, 0.3, 0.3]), max_nfev=20)
        if best is None or fit.cost < best.cost:
            best = fit
    sx, sy, c, log_sigma, log_i = best.x
    return Glint(sx_m=float(sx), sy_m=float(sy), c=float(c), sigma_m=float(np.exp(log_sigma)),
                 intensity=float(np.exp(log_i)), explained=1.0 - 2.0 * float(best.cost) / total)


def without_glints(image: np.ndarray, table: LightFieldTable, glints: list[Glint], *,
                   saturation: float) -> np.ndarray:
    """A copy of the raw ``image`` with the glints' light taken off its pixels (those at
    ``saturation`` kept as read: their true value is unknown). Only the glints' disks are touched:
    a whole table's worth of temporaries would add 150 MB to the frame's peak."""
    out = np.ascontiguousarray(image).reshape(-1).copy()
    for g in glints:
        reach = abs(g.c) * table.aperture_radius_m + 5.0 * g.sigma_m
        lenses = np.flatnonzero(np.hypot(table.lens_xy_m[:, 0] - g.sx_m, table.lens_xy_m[:, 1] - g.sy_m) < reach)
        ids = table.samples_of(lenses)
        cx, cy = table.lens_xy_m[table.lens[ids]].T
        light = _model(g.params, cx, cy, table.u_m[ids].astype(np.float64), table.v_m[ids].astype(np.float64))
        pixels = table.pixel_index[ids]
        raw = out[pixels].astype(np.float64)
        clean = np.clip(np.rint(raw - table.weight[ids].astype(np.float64) * light), 0.0, saturation)
        out[pixels] = np.where(raw >= saturation, raw, clean).astype(image.dtype)
    return out.reshape(image.shape)
