"""Depth and position from the raw pixels: a fit of the forward model around each particle.

A ray from aperture point ``u`` toward a point that images at lens-plane position ``s_hat``
(shared magnification) with refocus parameter ``alpha`` crosses the micro-lens-array plane at
``s = s_hat + c u`` with ``c = 1 - 1/alpha`` (docs/camera-model.md; the relation the shift-only
refocus inverts) and lands behind the lens whose hexagonal cell contains ``s``. So sample
``(lens k, aperture point u)`` of the look-up table is lit by the particle exactly when
``s_hat + c u`` falls in cell ``k``.

For each particle the predicted pattern ``I0 * [s_hat + c u in cell k]`` is compared with the
devignetted raw samples of the lenses around it, by least squares (``I0`` solved in closed
form), on a grid of ``(c, s_hat)`` candidates around the starting point. The estimate is the
mean of the candidates weighted by ``exp(-(cost - min cost) / I0^2)`` (cost in units of one
mismatched pixel): where the light splits between lenses the cost has a sharp minimum; where a
particle lights a single lens, every depth whose blur still fits in that lens explains the pixels
equally well, and the estimate is the middle of that range instead of an arbitrary end of it.
This uses how the light splits between neighbouring lenses, which the refocused stack's
brightness blurs away when the blur is under a lens pitch or two.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace
from typing import Any, Callable, NamedTuple

import numba
import numpy as np

from analysis.cache import Cache
from analysis.camera.model import IDEAL_POINT_SPREAD_PX
from analysis.camera.second_stop import SecondStop
from analysis.lightfield.table import LightFieldTable

from analysis.depth import rayfit_kernels as kern
from analysis.depth import render_kernels
from .footprint import pixel_footprint, points_per_side
from .sample_noise import SampleNoise
from .table_index import Gathered, TableIndex, table_index


@dataclass(frozen=True)
class RayFit:
    """Fitted particles; arrays of shape ``(n,)``.

    Attributes
    ----------
    sx_m, sy_m : float64
        Lens-plane position ``s_hat`` (metres from the optical axis).
    alpha : float64
        Refocus parameter at which the particle is sharp.
    intensity : float64
        Fitted brightness ``I0`` of a lit sample (DN above background per unit white weight).
    n_lit : int64
        Samples the best candidate lights.
    residual : float64
        RMS misfit of the best candidate per sample, as a fraction of ``I0``.
    alpha_spread : float64
        Standard deviation of alpha over the weighted candidates: small where the light split
        pins the depth down, about a third of the allowed range where one lens holds it all.
    prior_alpha, prior_sigma : float64
        The depth prior the fit was made with (:func:`fit_rays`), NaN where none: kept with the
        fit so that refits of it keep it too (:meth:`analysis.depth.refine.RayFitter.fit`).
    """

    sx_m: np.ndarray
    sy_m: np.ndarray
    alpha: np.ndarray
    intensity: np.ndarray
    n_lit: np.ndarray
    residual: np.ndarray
    alpha_spread: np.ndarray
    prior_alpha: np.ndarray | None = None
    prior_sigma: np.ndarray | None = None

    def __post_init__(self) -> None:
        for name in ("prior_alpha", "prior_sigma"):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(self.alpha.shape, np.nan))

    def __len__(self) -> int:
        return int(self.alpha.shape[0])

    def _map(self, how) -> "RayFit":
        return RayFit(**{f.name: how(f.name) for f in fields(self)})

    def take(self, index: np.ndarray) -> "RayFit":
        """The fits at ``index`` (integer array or mask)."""
        return self._map(lambda name: getattr(self, name)[index])

    def with_rows(self, rows: np.ndarray, new: "RayFit") -> "RayFit":
        """A copy with ``rows`` replaced by the rows of ``new``."""
        out = self._map(lambda name: getattr(self, name).copy())
        for f in fields(self):
            getattr(out, f.name)[rows] = getattr(new, f.name)
        return out

    def where(self, mask: np.ndarray, other: "RayFit") -> "RayFit":
        """Row by row, this fit where ``mask`` holds, else ``other``'s."""
        return self._map(lambda name: np.where(mask, getattr(self, name), getattr(other, name)))

    @staticmethod
    def concat(*fits: "RayFit") -> "RayFit":
        """The fits one after the other."""
        return RayFit(**{f.name: np.concatenate([getattr(fit, f.name) for fit in fits]) for f in fields(RayFit)})

    @staticmethod
    def empty() -> "RayFit":
        e = np.empty(0)
        return RayFit(e, e.copy(), e.copy(), e.copy(), np.empty(0, np.int64), e.copy(), e.copy())


class FitGrid(NamedTuple):
    """One pass of the grid search of :func:`fit_rays`.

    Attributes
    ----------
    depths : int
        Candidate depths: in the coarse pass over ``alpha0 +- alpha_half_range``, in the fine pass
        over twice the coarse pass's spread (at least 1.5 of its depth steps) either side.
    lateral_pitches : float
        Candidate positions span +- this many lens pitches about the start, in x and y ...
    positions : int
        ... this many per side.
    pixel_points : int
        Each pixel modelled as this many points per side over its blurred area (1: its centre).
    temperature : float
        Cost difference, in mismatched pixels, over which candidates lose weight by ``1/e``: a
        whole one where pixel centres misjudge the partly lit pixels (the coarse pass; sharper,
        it settles on wrong basins), less where pixel areas let them count.
    vertex : bool
        The depth from the vertex of a parabola fitted to the depth profile
        (:func:`analysis.depth.candidate_kernels.profile_vertex`), not the candidates' tempered mean.
    """

    depths: int
    lateral_pitches: float
    positions: int
    pixel_points: int
    temperature: float
    vertex: bool = False


#: The ideal optics' point spread (sigma, px; camera-model.md step 4): what the fit models when it is
#: told no other (a calibration estimates the camera's own from its white image).
DEFAULT_BLUR_PX = IDEAL_POINT_SPREAD_PX
#: Footprint points per side of a render (:func:`render_fits`) under the ideal optics' blur
#: (:func:`~analysis.depth.footprint.points_per_side`).
RENDER_POINTS = 3
#: ... and of the render that the detection passes over what the fits leave take off
#: (``analysis.pipeline.passes``). Blurred over 11-13 pitches, a particle puts a patch under a pixel
#: wide in each lens; 3 x 3 points count its share in ninths, and what such a render leaves of
#: bright particles hides faint neighbours there.
RESIDUAL_POINTS = 5

#: The default passes of :func:`fit_rays` (the pipeline's own are in :mod:`analysis.depth.refine`).
COARSE = FitGrid(depths=33, lateral_pitches=0.4, positions=3, pixel_points=1, temperature=1.0)
FINE = FitGrid(depths=9, lateral_pitches=0.25, positions=3, pixel_points=3, temperature=0.5)


def background_per_sample(table: LightFieldTable, background: float | np.ndarray) -> np.ndarray:
    """The background as the kernels take it (float32): one value for all samples of ``table``, or
    one per sample (:meth:`analysis.lightfield.background.BackgroundMap.per_sample`)."""
    background = np.atleast_1d(np.asarray(background, dtype=np.float32))
    if background.size not in (1, table.n_samples):
        raise ValueError(f"background holds {background.size} levels for a table of {table.n_samples} samples")
    return background


def unexplained_light(image: np.ndarray, table: LightFieldTable, sx_m: np.ndarray, sy_m: np.ndarray,
                      radius_m: np.ndarray, *, background: float | np.ndarray, explained: np.ndarray, floor: float,
                      cache: Cache | None = None) -> np.ndarray:
    """Light above ``floor`` (devignetted DN) left unexplained in the lenses within ``radius_m`` of
    each point, after taking off ``explained`` (from :func:`render_fits`); one sum per point.
    ``background``: one level, or one per sample of ``table``."""
    def light(left: np.ndarray, raw: np.ndarray) -> np.ndarray:
        return np.where(left > floor, left, 0.0)
    return _sum_left(image, table, sx_m, sy_m, radius_m, background, explained, light, cache)


def misfit_in_lenses(image: np.ndarray, table: LightFieldTable, sx_m: np.ndarray, sy_m: np.ndarray,
                     radius_m: np.ndarray, *, background: float | np.ndarray, explained: np.ndarray,
                     saturation: float = 4095.0, cache: Cache | None = None) -> np.ndarray:
    """How far ``explained`` (from :func:`render_fits`) misses the light in the lenses within
    ``radius_m`` of each point: the sum of squared differences (devignetted DN^2), one per point.
    A saturated sample counts only where the model falls short of it, as in the fits."""
    def squares(left: np.ndarray, raw: np.ndarray) -> np.ndarray:
        return np.where((raw < saturation) | (left > 0.0), left * left, 0.0)
    return _sum_left(image, table, sx_m, sy_m, radius_m, background, explained, squares, cache)


def _sum_left(image: np.ndarray, table: LightFieldTable, sx_m: np.ndarray, sy_m: np.ndarray, radius_m: np.ndarray,
              background: float | np.ndarray, explained: np.ndarray,
              term: Callable[[np.ndarray, np.ndarray], np.ndarray], cache: Cache | None) -> np.ndarray:
    """Per point, the sum of ``term(left, raw)`` over the samples of the lenses within ``radius_m``
    of it: ``left`` the light above background that ``explained`` leaves, ``raw`` the pixel values."""
    idx = table_index(table, cache)
    flat = np.ascontiguousarray(image).reshape(-1)
    bg = background_per_sample(table, background)
    sx, sy, radius = _points(sx_m, sy_m, radius_m)

    def part(rows: slice) -> np.ndarray:
        g = idx.gather(sx[rows], sy[rows], radius[rows])
        raw = flat[table.pixel_index[g.ids]]
        left = ((raw.astype(np.float64) - table.black_level) / idx.weight(g.ids) - _at(bg, g.ids)
                - explained[g.ids])
        return _sum_per_point(term(left, raw), g, sx[rows].size)
    return _in_chunks(sx.size, part)


def point_pattern(image: np.ndarray, table: LightFieldTable, fit: RayFit, radius_m: np.ndarray, *,
                  background: float | np.ndarray, explained: np.ndarray, aperture_per_lens_plane: float,
                  spread_m: float | None, blur_px: float = DEFAULT_BLUR_PX, response_slope: float = 0.0,
                  second_stop: SecondStop | None = None,
                  saturation: float = 4095.0, cache: Cache | None = None) -> np.ndarray:
    """Per fit, how much of the variation of the light within the lenses (each lens's own mean
    level taken out) its point-source pattern explains, and how much the same fit spread over a
    source ``spread_m`` across does (its centre and six points on a ring): the squared
    correlations, pooled over the lenses within ``radius_m`` of it, between that light and each
    pattern, 0 where they anticorrelate. Returns an array of shape ``(n, 2)``: point, spread
    (NaN with ``spread_m`` None: six renders fewer where only the point's share is wanted).

    Extended light (a reflection, glow, glare) lights each micro-image nearly evenly, so a fit
    on it explains little of the variation within lenses, whatever share of their light it
    takes; a point source puts a spot in each lens, which its fit follows, better than a spread
    one does. Other fits' light (``explained``, from :func:`render_fits`, less the fit's own) is
    taken off first; saturated samples are left out.

    The patterns are rendered with as many pixel points as the camera's blur needs
    (:func:`~analysis.depth.footprint.points_per_side`): with the ideal optics' 3 x 3 under a 0.8 px
    blur, a point blurred over 8 pitches or more rendered narrower than its light falls, and a source
    spread over a pitch matched that light better than the point did (realistic off-focus ball of
    tuning seed 27, point over spread, medians: 0.73 at 8-11 pitches, 0.61 beyond; so rendered, 1.18
    and 1.54).
    """
    radius = _points(fit.sx_m, radius_m)[1]

    def part(rows: slice) -> np.ndarray:
        return _point_pattern(image, table, fit.take(rows), radius[rows], background=background,
                              explained=explained, aperture_per_lens_plane=aperture_per_lens_plane,
                              blur_px=blur_px, response_slope=response_slope, second_stop=second_stop,
                              saturation=saturation,
                              spread_m=spread_m, cache=cache)
    return _in_chunks(len(fit), part, columns=2)


def _point_pattern(image: np.ndarray, table: LightFieldTable, fit: RayFit, radius_m: np.ndarray, *,
                   background: float | np.ndarray, explained: np.ndarray, aperture_per_lens_plane: float,
                   blur_px: float, response_slope: float, second_stop: SecondStop | None, saturation: float,
                   spread_m: float | None,
                   cache: Cache | None) -> np.ndarray:
    n = len(fit)
    idx = table_index(table, cache)
    g = idx.gather(fit.sx_m, fit.sy_m, radius_m)
    raw = np.ascontiguousarray(image).reshape(-1)[table.pixel_index[g.ids]].astype(np.float64)
    uv = idx.uv(g.ids)
    cells = idx.cells(aperture_per_lens_plane, response_slope, second_stop)
    points = points_per_side(RENDER_POINTS, blur_px)
    own = _render_gathered(fit, idx, g, uv, cells, blur_px, points)
    spread = None
    if spread_m is not None:
        spread = own / 7.0
        for a in np.arange(6) * np.pi / 3:
            moved = replace(fit, sx_m=fit.sx_m + spread_m * np.cos(a), sy_m=fit.sy_m + spread_m * np.sin(a))
            spread += _render_gathered(moved, idx, g, uv, cells, blur_px, points) / 7.0
    # The fit's own light goes back as ``explained`` holds it (a render's points).
    back = own if points == RENDER_POINTS else _render_gathered(fit, idx, g, uv, cells, blur_px)
    light = ((raw - table.black_level) / idx.weight(g.ids) - _at(background_per_sample(table, background), g.ids)
             - explained[g.ids] + back)
    use = (raw < saturation).astype(np.float64)
    out = np.full((n, 2), np.nan)
    for k, pattern in enumerate((own, spread)):
        if pattern is not None:
            out[:, k] = _lens_correlation(light, pattern, g, use, n)
    return out


def pattern_overlap(table: LightFieldTable, fit: RayFit, other: RayFit, radius_m: np.ndarray, *,
                    aperture_per_lens_plane: float, blur_px: float = DEFAULT_BLUR_PX, response_slope: float = 0.0,
                    second_stop: SecondStop | None = None,
                    cache: Cache | None = None) -> np.ndarray:
    """Per row, how alike the light of ``fit`` and of ``other`` (row for row) falls within the lenses
    within ``radius_m`` of ``fit``: the squared correlation of their renders, each lens's mean
    taken out, pooled over those lenses; 0 where they anticorrelate.

    Near 1, the pixels can hardly tell the two apart: what a slightly wrong model leaves of one
    particle is then fitted well by a point at nearly its place. A second particle on the line of
    sight at another depth puts its spot elsewhere in each lens (near 0).
    """
    if len(fit) != len(other):
        raise ValueError(f"{len(fit)} fits against {len(other)} others")
    idx = table_index(table, cache)
    radius = _points(fit.sx_m, radius_m)[1]
    cells = idx.cells(aperture_per_lens_plane, response_slope, second_stop)

    def part(rows: slice) -> np.ndarray:
        one, two = fit.take(rows), other.take(rows)
        g = idx.gather(one.sx_m, one.sy_m, radius[rows])
        uv = idx.uv(g.ids)
        return _lens_correlation(_render_gathered(one, idx, g, uv, cells, blur_px),
                                 _render_gathered(two, idx, g, uv, cells, blur_px),
                                 g, np.ones(g.ids.size), len(one))
    return _in_chunks(len(fit), part)


def _lens_correlation(a: np.ndarray, b: np.ndarray, g: Gathered, use: np.ndarray, n: int) -> np.ndarray:
    """Per point of ``g``, the squared correlation of ``a`` and ``b`` over its gathered samples where
    ``use`` (0 or 1), each lens's mean over those taken out; 0 where they anticorrelate."""
    lens = np.repeat(np.arange(g.sample_ptr.size - 1), np.diff(g.sample_ptr))
    count = np.maximum(np.bincount(lens, weights=use, minlength=g.sample_ptr.size - 1), 1.0)
    owner = np.repeat(np.arange(n), np.diff(g.lens_ptr))[lens]

    def centred(values: np.ndarray) -> np.ndarray:
        return use * (values - (np.bincount(lens, weights=use * values, minlength=count.size) / count)[lens])

    def per_point(values: np.ndarray) -> np.ndarray:
        return np.bincount(owner, weights=values, minlength=n)
    da, db = centred(a), centred(b)
    s_ab = per_point(da * db)
    return np.where(s_ab > 0, s_ab * s_ab / np.maximum(per_point(da * da) * per_point(db * db), 1e-300), 0.0)


def _at(values: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """``values[ids]``, or the one value for all."""
    return values[ids] if values.size > 1 else np.full(ids.size, values[0])


def explained_light(table: LightFieldTable, sx_m: np.ndarray, sy_m: np.ndarray, radius_m: np.ndarray, *,
                    explained: np.ndarray, cache: Cache | None = None) -> np.ndarray:
    """The light of fitted particles (``explained``, from :func:`render_fits`) in the lenses within
    ``radius_m`` of each point; one sum per point (devignetted DN)."""
    idx = table_index(table, cache)
    sx, sy, radius = _points(sx_m, sy_m, radius_m)

    def part(rows: slice) -> np.ndarray:
        g = idx.gather(sx[rows], sy[rows], radius[rows])
        return _sum_per_point(explained[g.ids].astype(np.float64), g, sx[rows].size)
    return _in_chunks(sx.size, part)


#: Points per gather in :func:`unexplained_light`, :func:`explained_light` and
#: :func:`point_pattern`: a point blurred over ten pitches gathers some 20 000 samples, and
#: gathering a held-out cloud's candidates at once took 260 MB more at its peak.
GATHER_CHUNK = 32


def _points(*columns: np.ndarray) -> list[np.ndarray]:
    """Per-point columns as float arrays of one length (scalars repeated)."""
    return np.broadcast_arrays(*(np.atleast_1d(np.asarray(c, dtype=np.float64)) for c in columns))


def _in_chunks(n: int, part: Callable[[slice], np.ndarray], columns: int = 1) -> np.ndarray:
    """``part(rows)`` over slices of :data:`GATHER_CHUNK` of ``n`` rows, joined: one value (or
    ``columns`` values) per row."""
    out = np.zeros(n if columns == 1 else (n, columns))
    for start in range(0, n, GATHER_CHUNK):
        rows = slice(start, min(start + GATHER_CHUNK, n))
        out[rows] = part(rows)
    return out


def _sum_per_point(values: np.ndarray, g: Gathered, n: int) -> np.ndarray:
    """The sum of ``values`` (one per gathered sample) over each of the ``n`` points' samples.
    (``np.add.reduceat`` over the lenses failed where a point's last lens had no sample.)"""
    lens_owner = np.repeat(np.arange(n), np.diff(g.lens_ptr))
    return np.bincount(np.repeat(lens_owner, np.diff(g.sample_ptr)), weights=values, minlength=n)


def render_fits(table: LightFieldTable, fit: RayFit, *, aperture_per_lens_plane: float, blur_px: float = DEFAULT_BLUR_PX,
                response_slope: float = 0.0, second_stop: SecondStop | None = None, out: np.ndarray | None = None,
                cache: Cache | None = None,
                points: int = RENDER_POINTS) -> np.ndarray:
    """The light that fitted particles put on each sample of ``table`` (devignetted DN), each pixel
    modelled as ``points`` x ``points`` points (:func:`~analysis.depth.footprint.pixel_footprint`).

    Returns
    -------
    ndarray of shape (table.n_samples,), float32
        Added to ``out`` when given.
    """
    idx = table_index(table, cache)
    if out is None:
        out = np.zeros(table.n_samples, dtype=np.float32)
    if len(fit) == 0:
        return out
    reach = np.abs(1.0 - 1.0 / fit.alpha) * idx.radius_m + 1.8 * idx.pitch_m
    g = idx.gather(fit.sx_m, fit.sy_m, reach)
    cells = idx.cells(aperture_per_lens_plane, response_slope, second_stop)
    light = _render_gathered(fit, idx, g, idx.uv(g.ids), cells, blur_px, points)
    render_kernels.scatter_add(out, g.ids, light)
    return out


def _render_gathered(fit: RayFit, idx: TableIndex, g: Gathered, uv: np.ndarray, cells: kern.Cells,
                     blur_px: float, points: int = RENDER_POINTS) -> np.ndarray:
    """The light of particle ``p`` on each of its own gathered samples (``points`` x ``points`` per pixel)."""
    out = np.zeros(uv.shape[0])
    render_kernels.render_samples(g.centres, g.sample_ptr, g.lens_ptr, uv, fit.sx_m, fit.sy_m, 1.0 - 1.0 / fit.alpha,
                                  fit.intensity, cells, pixel_footprint(points, blur_px) * idx.u_per_px, out)
    return out


def _prior_in_c(n: int, prior_alpha: np.ndarray | None, prior_sigma: np.ndarray | None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Per particle: the prior's centre in ``c = 1 - 1/alpha`` and ``1 / (2 sigma_c^2)`` (0: none)."""
    if prior_alpha is None or prior_sigma is None:
        return np.zeros(n), np.zeros(n)
    a = np.asarray(prior_alpha, dtype=np.float64).ravel()
    sigma_c = np.asarray(prior_sigma, dtype=np.float64).ravel() / a**2  # dc = dalpha / alpha^2
    if a.size != n or sigma_c.size != n:
        raise ValueError(f"prior_alpha and prior_sigma need {n} values each")
    use = np.isfinite(a) & np.isfinite(sigma_c) & (sigma_c > 0)
    k = np.zeros(n)
    k[use] = 0.5 / sigma_c[use] ** 2
    return np.where(use, 1.0 - 1.0 / np.where(use, a, 1.0), 0.0), k


def aperture_per_lens_plane(optics: Any) -> float:
    """``(P + d) / d``: a lens-plane step between lens centres moves their micro-images by this many
    aperture metres (optics of :class:`analysis.camera.model.Optics`)."""
    return optics.aperture_m_per_px * optics.projection_factor / optics.pixel_pitch_m


def fit_rays(image: np.ndarray, table: LightFieldTable, sx0_m: np.ndarray, sy0_m: np.ndarray,
             alpha0: np.ndarray, *, background: float | np.ndarray, aperture_per_lens_plane: float,
             alpha_half_range: float = 0.004, coarse: FitGrid = COARSE, fine: FitGrid = FINE,
             reach_pitches: float = 1.2, blur_px: float = DEFAULT_BLUR_PX, response_slope: float = 0.0,
             second_stop: SecondStop | None = None,
             subtract: np.ndarray | None = None,
             own: RayFit | None = None, prior_alpha: np.ndarray | None = None,
             prior_sigma: np.ndarray | None = None, prior_outlier: float = 0.05, saturation: float = 4095.0,
             recentre: int = 0, coarse_floor: float = 0.0, noise: SampleNoise | None = None,
             cache: Cache | None = None, render_points: int = RENDER_POINTS) -> RayFit:
    """Refine position and depth of particles by fitting the forward model to the raw samples.

    Two passes (:class:`FitGrid`): a coarse grid of depths over ``alpha0 +- alpha_half_range`` and
    positions about the start (pixels as their centres by default), then a fine grid around the
    coarse estimate (by default 9 depths over twice its spread, 3 x 3 positions over +-0.25 pitch,
    pixels as 3 x 3 points). Where a blur of about a pitch spills a sliver of light into the
    neighbouring lenses, only the fine pass's pixel areas (partly lit rim pixels) tell in front of
    focus from behind it: the aperture lands on the MLA mirrored, so the other side of those
    micro-images is lit.

    The table should include the micro-images' rim pixels (``build_table(..., rim_px=-0.5)``):
    where a particle's light splits between lenses, the neighbour's share often lands there.

    Parameters
    ----------
    image : ndarray of shape (H, W), uint16
        The raw exposure.
    table : LightFieldTable
    sx0_m, sy0_m, alpha0 : ndarray of shape (n,)
        Starting positions (lens plane, metres) and refocus parameters, e.g. from the
        brightness maxima of the refocused stack.
    background : float or ndarray of shape (table.n_samples,)
        Background (DN above black per unit white weight) to subtract: one level, or one per sample
        (:meth:`analysis.lightfield.background.BackgroundMap.per_sample`).
    aperture_per_lens_plane : float
        Aperture metres per lens-plane metre between neighbouring micro-images, ``(P + d) / d``
        (:func:`aperture_per_lens_plane`): how far apart two lenses' images of one aperture point are.
    alpha_half_range : float
        The coarse pass's depths span ``alpha0 +-`` this.
    coarse, fine : FitGrid
        The two passes' grids.
    reach_pitches : float
        Lenses farther than the largest candidate blur plus this many pitches are left out.
    blur_px : float
        Gaussian blur (pixels) of the sensor image (diffraction, crosstalk): each pixel is
        modelled by points spread over its area and this blur, so partly lit pixels at the
        edges of a lens's share of the light count by how much of them is lit.
    response_slope : float
        The pixel response within a micro-image, ``ln(response)`` per squared pixel of offset from
        its centre (:attr:`analysis.calibration.calibrate.Calibration.response_slope`; 0: flat):
        each of a pixel's points counts by the response to the aperture point it sees.
    second_stop : SecondStop, optional
        The main lens's second stop (:attr:`analysis.calibration.calibrate.Calibration.second_stop`):
        a pixel's points whose rays it blocks see no aperture, as in the white image.
    prior_alpha, prior_sigma, prior_outlier : ndarray of shape (n,), ndarray, float
        A prior on each particle's depth (e.g. :func:`analysis.depth.prior.neighbour_prior`): a
        Gaussian of this centre and width with probability ``1 - prior_outlier``, else uniform over
        the coarse window (so the pixels still win where they disagree with it). It decides only
        where the pixels cannot tell the depth: one lens holds all the light, and every depth whose
        blur fits in it (either sign of the defocus) explains them equally well. ``prior_sigma``
        NaN: no prior for that particle.
    subtract : ndarray of shape (table.n_samples,), optional
        Light already explained (devignetted DN per sample, from :func:`render_fits`), taken off
        before fitting: particles hidden behind others are then fitted to what is left.
    own : RayFit, optional
        Earlier fits of these same particles (row for row), whose light ``subtract`` includes: each
        particle's own share is added back, so it is refitted to its pixels with only its
        neighbours' light taken off (deblending a crowd).
    render_points : int
        Pixel points per side of ``own``'s render: as ``subtract``'s (:func:`render_fits`).
    saturation : float
        Raw value at which the ADC saturates: samples that read it are censored (their true value
        is at least that: they count only where the model predicts less, and do not set the
        intensity).
    recentre : int
        Run the fine pass again about its own result, at most this many more times, while that
        result lies beyond half the fine window from its centre. The coarse pass models pixels by
        their centres: under a blur wider than the ideal optics' it reads each micro-image's blurred
        spot of a defocused particle as a larger spot, a depth nearer focus (by 1e-4 to 6e-4 in
        alpha at 5-13 pitches of blur), and a fine pass about that depth alone cannot reach the
        true one. Worth it where the neighbours' light is off the pixels (``own``): with it on, a
        wider search lets a fit slide toward a partner on its line of sight.
    coarse_floor : float
        Particles whose coarse pass finds at most this intensity keep the coarse result, without
        the fine pass (most of a fit's cost): candidates far too faint to be particles.
    noise : SampleNoise, optional
        Weigh each sample by its inverse noise variance (weighted least squares); without it, every
        sample counts alike. Devignetted samples at the micro-image rims and in vignetted corners
        are several times noisier than full ones: unweighted, they cost 15-25 % in depth error on
        tuning frames through ideal optics and with each realistic effect alone. The residual
        stays the unweighted one, as the gates on it were chosen.
    cache : Cache, optional
        Keeps the table's lens index between calls.

    Returns
    -------
    RayFit
    """
    idx = table_index(table, cache)
    cells = idx.cells(aperture_per_lens_plane, response_slope, second_stop)
    sx0 = np.asarray(sx0_m, dtype=np.float64).ravel()
    sy0 = np.asarray(sy0_m, dtype=np.float64).ravel()
    a0 = np.asarray(alpha0, dtype=np.float64).ravel()
    n = sx0.size
    if n == 0:
        return RayFit.empty()
    flat = np.ascontiguousarray(image).reshape(-1)
    c_lo = 1.0 - 1.0 / (a0 - alpha_half_range)
    c_hi = 1.0 - 1.0 / (a0 + alpha_half_range)
    reach = (np.maximum(np.abs(c_lo), np.abs(c_hi)) * idx.radius_m
             + (reach_pitches + coarse.lateral_pitches) * idx.pitch_m)
    g = idx.gather(sx0, sy0, reach)
    values = np.empty(g.ids.size)
    uv = np.empty((g.ids.size, 2))
    censored = np.empty(g.ids.size, dtype=np.bool_)
    bg = background_per_sample(table, background)
    render_kernels.sample_values(flat, table.pixel_index, table.weight, table.u_m, table.v_m, g.ids,
                                 float(table.black_level), float(saturation), bg,
                                 np.zeros(0, np.float32) if subtract is None else subtract, subtract is not None,
                                 values, uv, censored)
    if own is not None:
        if len(own) != n:
            raise ValueError(f"own holds {len(own)} fits for {n} particles")
        values += _render_gathered(own, idx, g, uv, cells, blur_px, render_points)
    root_w = np.empty(0)  # every sample counts alike
    if noise is not None:
        root_w = noise.root_weights(idx.weight(g.ids), _at(bg, g.ids).astype(np.float64))
        values *= root_w
    c_prior, prior_k = _prior_in_c(n, prior_alpha, prior_sigma)
    # The uniform part's density relative to the Gaussian's peak.
    with np.errstate(divide="ignore"):
        sigma_c = np.sqrt(0.5 / prior_k)
    prior_floor = np.where(prior_k > 0, prior_outlier / max(1.0 - prior_outlier, 1e-12) * np.sqrt(2 * np.pi)
                           * sigma_c / np.abs(c_hi - c_lo), 0.0)
    out = np.empty((n, 7))
    kern.fit_all(g.centres, g.sample_ptr, g.lens_ptr, uv, values, root_w, censored, sx0, sy0, c_lo, c_hi,
                 cells, _grid_pass(coarse, idx, blur_px), _grid_pass(fine, idx, blur_px),
                 kern.PriorTerms(c_prior, prior_k, prior_floor), int(recentre), float(coarse_floor), out,
                 *_balanced_slots(g.sample_ptr[g.lens_ptr[1:]] - g.sample_ptr[g.lens_ptr[:-1]],
                                  numba.get_num_threads()))
    no_prior = np.full(n, np.nan)
    return RayFit(sx_m=out[:, 0], sy_m=out[:, 1], alpha=1.0 / (1.0 - out[:, 2]), intensity=out[:, 3],
                  n_lit=out[:, 4].astype(np.int64), residual=out[:, 5],
                  alpha_spread=out[:, 6] / (1.0 - out[:, 2]) ** 2,
                  prior_alpha=no_prior if prior_alpha is None else np.asarray(prior_alpha, np.float64).ravel(),
                  prior_sigma=no_prior if prior_sigma is None else np.asarray(prior_sigma, np.float64).ravel())


def _grid_pass(grid: FitGrid, idx: TableIndex, blur_px: float) -> kern.GridPass:
    return kern.GridPass(int(grid.depths), float(grid.lateral_pitches) * idx.pitch_m, int(grid.positions),
                         pixel_footprint(int(grid.pixel_points), blur_px) * idx.u_per_px, float(grid.temperature),
                         bool(grid.vertex))


def _balanced_slots(cost: np.ndarray, n_slots: int) -> tuple[np.ndarray, np.ndarray]:
    """Split items of roughly known ``cost`` into ``n_slots`` runs of about equal total cost (dealt
    out by decreasing cost, back and forth): ``order[slot_ptr[s]:slot_ptr[s + 1]]`` is slot ``s``.
    A particle's fit costs about in proportion to its samples, and few reach many lenses: in
    equal runs of the input order, one thread may get most of those."""
    n = cost.size
    n_slots = max(1, min(int(n_slots), n))
    rank = np.argsort(-cost, kind="stable")
    turn = np.arange(n) % (2 * n_slots)
    slot = np.where(turn < n_slots, turn, 2 * n_slots - 1 - turn)
    order = rank[np.argsort(slot, kind="stable")].astype(np.int64)
    slot_ptr = np.r_[0, np.cumsum(np.bincount(slot, minlength=n_slots))].astype(np.int64)
    return order, slot_ptr
