"""Score found particles against known truth (the simulator's ``IMG_nnnn.truth.csv``).

Found and true particles are paired one-to-one by the Hungarian method on their 3D distance;
pairs farther apart than ``max_distance`` (a fraction of the mean nearest-neighbour distance)
do not count. Errors are reported as fractions of the mean 3D nearest-neighbour distance of the
truth, as the paper does.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Any, Mapping

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial import cKDTree

from .floor_kernels import lit_pattern, same_pattern_counts
from analysis.camera.model import CameraModel, Lattice
from .chamber import ChamberLight
from .render import particle_truth
from .scenarios import Particles

#: Defocus bins (blur diameter in lens pitches) for the depth error breakdown.
BLUR_BINS: tuple[tuple[float, float], ...] = ((0.0, 0.5), (0.5, 1.0), (1.0, 2.0), (2.0, math.inf))
#: Defocus bins (blur diameter in lens pitches) for the recall breakdown. Off focus, how far a
#: particle's light spreads decides whether it is found, and where a cluster lies (each realistic
#: seed draws it) sets how many particles are so blurred: recall per bin compares versions across
#: seeds whose totals the draw dominates.
RECALL_BLUR_BINS: tuple[tuple[float, float], ...] = ((0.0, 4.0), (4.0, 8.0), (8.0, 12.0), (12.0, math.inf))


def blur_bin_label(lo: float, hi: float) -> str:
    """The label of the blur bin ``[lo, hi)``: ``"lo-hi"``, or ``">lo"`` for an open one."""
    return f"{lo:g}-{hi:g}" if math.isfinite(hi) else f">{lo:g}"


@dataclass
class Score:
    """Accuracy of one exposure's particle table against its truth.

    All ``*_over_nn`` values are fractions of ``nn_mm`` (multiply by 100 for %).
    ``depth_by_blur`` maps a bin label (:data:`BLUR_BINS`) to ``(count, absolute depth RMS over NN)``,
    ``recall_by_blur`` one (:data:`RECALL_BLUR_BINS`) to ``(true particles, matched ones)``.
    ``pairs_separated`` counts shadowing pairs (true particles closer laterally than
    ``pair_lateral`` of NN, :func:`score`) whose two members both matched, of ``pairs_total``.
    """

    n_true: int
    n_found: int
    n_matched: int
    recall: float
    precision: float
    nn_mm: float
    depth_fit_rms_over_nn: float
    depth_abs_rms_over_nn: float
    lateral_rms_over_nn: float
    depth_by_blur: dict[str, tuple[int, float]] = field(default_factory=dict)
    recall_by_blur: dict[str, tuple[int, int]] = field(default_factory=dict)
    pairs_total: int = 0
    pairs_separated: int = 0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def single_lens(truth: Mapping[str, np.ndarray], lattice: Lattice) -> np.ndarray:
    """True particles whose blur disk lies inside one micro-lens cell.

    Their raw pixels are those of a particle in focus on that lens: every depth whose blur still
    fits in the cell, in front of focus or behind it, explains them exactly (in the simulator's
    geometric optics), so nothing in the exposure tells those depths apart.

    Parameters
    ----------
    truth : mapping with ``x, y`` (the chief ray on the MLA in micro-image lattice pixels) and
        ``blur_pitches`` (blur diameter in lens pitches), as the simulator's truth CSV has them.
    lattice : Lattice
    """
    x, y = (np.asarray(truth[c], float) for c in ("x", "y"))
    i, j = lattice.nearest(x, y)
    cx, cy = lattice.centre(i, j)
    offset = np.column_stack([x - cx, y - cy])
    b1, b2 = lattice.basis[:, 0], lattice.basis[:, 1]
    # Distance from the point to the nearest edge of its hexagonal cell (half-way to each neighbour).
    inner = np.min([np.linalg.norm(v) / 2 - np.abs(offset @ v) / np.linalg.norm(v) for v in (b1, b2, b2 - b1)],
                   axis=0)
    return np.asarray(truth["blur_pitches"], float) / 2 * lattice.pitch_px <= inner


def pixel_limited_alpha(truth: Mapping[str, np.ndarray], lattice: Lattice, *, tolerance: float = 0.01,
                        max_blur_pitches: float = 1.5) -> np.ndarray:
    """The best depth (alpha) that a particle's raw pixels alone allow, for each true particle.

    In geometric optics (the simulator's), a particle's pixels are set by which lens the ray from
    each aperture point reaches: its blur disk laid over the lens cells. Often other positions and
    depths lay the same pattern. A disk inside one cell: every smaller or larger one that still fits,
    in front of focus or behind. A disk over one edge, two edges that are not parallel, or one
    corner: chords and corner move alike for a step in depth and a step in position, so depth and
    position trade along a line. Only two parallel edges (a blur over a pitch) or two corners (over
    0.58 pitch) in the disk pin both.

    Knowing nothing else (position uniform, signed blur radius uniform within a pitch), the
    estimate of least mean square error is the mean depth over all that lay the same pattern, to
    within ``tolerance`` of the aperture. Particles blurred wider than ``max_blur_pitches`` are
    taken as pinned (their own alpha).

    Parameters
    ----------
    truth : mapping with ``x, y`` (the chief ray on the MLA in micro-image lattice pixels),
        ``blur_pitches`` and ``alpha``, as the simulator's truth CSV has them.
    lattice : Lattice

    Returns
    -------
    ndarray of shape (N,), float64
    """
    x, y, blur, alpha = (np.asarray(truth[c], float) for c in ("x", "y", "blur_pitches", "alpha"))
    c_true = 1.0 - 1.0 / alpha
    best = alpha.copy()
    todo = np.flatnonzero(blur < max_blur_pitches)
    if todo.size == 0:
        return best
    # The blur diameter is proportional to |c| (D / lens pitch); the signed radius carries c's sign.
    wide = blur > 0.05
    c_per_blur = float(np.median(np.abs(c_true[wide]) / blur[wide])) if wide.any() else math.nan
    fi, fj = lattice.fractional_index(x, y)
    i, j = lattice.nearest(x, y)
    # Offsets from the own lens on an ideal lattice of unit pitch (the real one is that, rotated).
    ox, oy = (fi - i) + 0.5 * (fj - j), (fj - j) * math.sqrt(3.0) / 2
    points = _aperture_points(_POINTS_PER_SIDE)
    max_mismatch = int(tolerance * points.shape[0])
    radii = np.linspace(-1.0, 1.0, 2 * _RADII_PER_PITCH + 1)
    reference = np.empty(points.shape[0], dtype=np.int64)
    counts = np.empty(radii.size)
    for k in todo:
        r_true = math.copysign(blur[k] / 2, c_true[k])
        lit_pattern(points, ox[k], oy[k], r_true, reference)
        same_pattern_counts(points, reference, ox[k], oy[k], radii, _POSITION_HALF_WIDTH, _POSITION_STEP,
                            max_mismatch, counts)
        if counts.sum() > 0 and math.isfinite(c_per_blur):  # else: pinned finer than the grid
            best[k] = 1.0 / (1.0 - 2.0 * float(np.sum(radii * counts) / counts.sum()) * c_per_blur)
    return best


#: The depth floor's grids (:func:`pixel_limited_alpha`): aperture points per side of the unit
#: disk's square, blur radii per pitch, and positions (pitches) around the particle.
#: Against finer grids (24 points, 100 radii per pitch, 0.01 pitch) the floor of each of six ball
#: exposures moves by under 0.3 % of NN, their pooled floor by 0.1 %; 20x faster (about 1 s each).
_POINTS_PER_SIDE = 16
_RADII_PER_PITCH = 50
_POSITION_HALF_WIDTH = 0.6
_POSITION_STEP = 0.02


def _aperture_points(per_side: int) -> np.ndarray:
    """Centres of a square grid's cells inside the unit disk, rim first (where patterns differ,
    so a mismatch is found after few points)."""
    g = (np.arange(per_side) + 0.5) * 2.0 / per_side - 1.0
    u, v = (a.ravel() for a in np.meshgrid(g, g))
    keep = u * u + v * v <= 1.0
    u, v = u[keep], v[keep]
    order = np.argsort(-(u * u + v * v), kind="stable")
    return np.ascontiguousarray(np.column_stack([u[order], v[order]]))


def depth_floor(truth: Mapping[str, np.ndarray], lattice: Lattice, *, nn_mm: float) -> tuple[int, float]:
    """How many particles light one lens only, and the depth RMS over NN that no estimate from the
    pixels alone can beat.

    The floor is the RMS, over all true particles, of ``|Z(best alpha) - Z|`` with the best alpha
    of :func:`pixel_limited_alpha`. A pipeline that scores below it has used more than the
    exposure: a prior (:mod:`analysis.depth.prior`).
    """
    one = single_lens(truth, lattice)
    err = floor_errors(truth, lattice)
    if err.size == 0 or not np.isfinite(err).all():
        return int(one.sum()), math.nan
    return int(one.sum()), float(np.sqrt(np.mean(err**2)) / nn_mm)


def floor_errors(truth: Mapping[str, np.ndarray], lattice: Lattice) -> np.ndarray:
    """Per true particle, the depth error (mm, signed) of the best estimate from its pixels alone
    (:func:`pixel_limited_alpha`); NaN for all where the truth spans no depth."""
    z = np.asarray(truth["Z"], float)
    alpha = np.asarray(truth["alpha"], float)
    if z.size < 2 or np.ptp(alpha) == 0:
        return np.full(z.size, math.nan)
    slope = np.polyfit(alpha, z, 1)[0]  # mm per unit alpha, locally linear
    return (pixel_limited_alpha(truth, lattice) - alpha) * slope


#: A particle that is not a one-lens one counts as open (:class:`FloorSplit`) where its floor error
#: exceeds this fraction of NN: its pixels leave the depth open along a line (a blur over one cell
#: edge, near focus), as :func:`pixel_limited_alpha` finds, rather than pinning it.
OPEN_FLOOR_NN = 0.01
#: A particle the match leaves out counts as found at its floor (:class:`FloorSplit`) where its
#: depth error is at most this many times its floor error: the issue's target for such particles.
FLOOR_SLACK = 1.2


@dataclass
class FloorSplit:
    """Matched particles' depth errors split where the floor applies: squared errors (mm^2) summed,
    so that several exposures pool by adding.

    ``one_lens_ss`` sums the squared ``|dZ|`` of the matched particles whose light falls in one
    lens (:func:`single_lens`), ``floor_ss`` their floor's (:func:`floor_errors`): their ratio's
    root is how far above the floor they are. ``rest_ss`` sums the other matched particles'.
    Of those, ``open_ss`` sums the open ones' (floor error above :data:`OPEN_FLOOR_NN` of NN) and
    ``open_floor_ss`` their floor's; the rest of the rest are pinned by their pixels.
    ``n_at_floor`` counts true particles the match left out that were found at their floor: a found
    particle the match left out lies within the match's distance across of one whose pixels leave
    its depth open (one lens, or open), with its depth error at most :data:`FLOOR_SLACK` times that
    particle's floor error. The match counts each as missed and as false, though the issue judges
    such a depth against its floor.
    """

    n_one_lens: int
    one_lens_ss: float
    floor_ss: float
    n_rest: int
    rest_ss: float
    n_open: int
    open_ss: float
    open_floor_ss: float
    n_at_floor: int = 0

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def floor_split(found: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray], lattice: Lattice, *,
                nn_mm: float | None = None, max_distance: float = 0.5) -> FloorSplit:
    """The matched particles' absolute depth errors, one-lens particles (with their floor) apart
    from the rest: the one-lens ones are judged against the floor, the others against ideal optics;
    of those, the open ones (:data:`OPEN_FLOOR_NN`) also against their floor.

    Parameters
    ----------
    found : mapping with columns ``X, Y, Z`` (mm)
    truth : the simulator's truth (``X, Y, Z``, ``x, y``, ``alpha``, ``blur_pitches``)
    lattice : Lattice
        The exposure's micro-lens lattice.
    """
    if nn_mm is None:
        nn_mm = mean_nn_distance(*(np.asarray(truth[c], float) for c in ("X", "Y", "Z")))
    rows, cols = match(found, truth, nn_mm=nn_mm, max_distance=max_distance)
    dz = np.asarray(found["Z"], float)[rows] - np.asarray(truth["Z"], float)[cols]
    one_all, floor_all = single_lens(truth, lattice), floor_errors(truth, lattice)
    one, floor = one_all[cols], floor_all[cols]
    open_ = ~one & (np.abs(floor) > OPEN_FLOOR_NN * nn_mm)
    return FloorSplit(n_one_lens=int(one.sum()), one_lens_ss=float(np.sum(dz[one] ** 2)),
                      floor_ss=float(np.sum(floor[one] ** 2)), n_rest=int((~one).sum()),
                      rest_ss=float(np.sum(dz[~one] ** 2)), n_open=int(open_.sum()),
                      open_ss=float(np.sum(dz[open_] ** 2)), open_floor_ss=float(np.sum(floor[open_] ** 2)),
                      n_at_floor=_at_floor(found, truth, rows, cols, one_all, np.abs(floor_all), max_distance * nn_mm,
                                           OPEN_FLOOR_NN * nn_mm))


def _at_floor(found: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray], rows: np.ndarray, cols: np.ndarray,
              one: np.ndarray, floor: np.ndarray, reach_mm: float, open_mm: float) -> int:
    """:class:`FloorSplit`'s ``n_at_floor``, from the match (``rows``, ``cols``) and every true
    particle's one-lens mask and absolute floor error."""
    miss = np.setdiff1d(np.arange(floor.size), cols)
    extra = np.setdiff1d(np.arange(np.asarray(found["X"]).size), rows)
    if not (miss.size and extra.size):
        return 0
    fx, fy, fz = (np.asarray(found[c], float)[extra, None] for c in ("X", "Y", "Z"))
    tx, ty, tz = (np.asarray(truth[c], float)[miss] for c in ("X", "Y", "Z"))
    lateral = np.hypot(fx - tx, fy - ty)
    ok = ((one[miss] | (floor[miss] > open_mm)) & (lateral <= reach_mm)
          & (np.abs(fz - tz) <= FLOOR_SLACK * floor[miss]))
    r, c = linear_sum_assignment(np.where(ok, lateral, 1e9))
    return int(ok[r, c].sum())


def mean_nn_distance(x: np.ndarray, y: np.ndarray, z: np.ndarray) -> float:
    """Mean 3D nearest-neighbour distance of a point set."""
    pts = np.column_stack([x, y, z])
    if pts.shape[0] < 2:
        return math.nan
    d, _ = cKDTree(pts).query(pts, k=2)
    return float(d[:, 1].mean())


def match(found: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray], *, nn_mm: float | None = None,
          max_distance: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """Pair found particles with true ones one-to-one (Hungarian method on the 3D distance).

    Parameters
    ----------
    found, truth : mappings with columns ``X, Y, Z`` (mm)
    nn_mm : float, optional
        Mean nearest-neighbour distance; default: computed from the truth.
    max_distance : float
        Largest 3D distance of a valid pair, as a fraction of ``nn_mm``.

    Returns
    -------
    rows, cols : ndarray of int
        Indices into ``found`` and ``truth`` of the pairs; found particles not in ``rows`` are false.
    """
    tx, ty, tz = (np.asarray(truth[c], float) for c in ("X", "Y", "Z"))
    fx, fy, fz = (np.asarray(found[c], float) for c in ("X", "Y", "Z"))
    nn = mean_nn_distance(tx, ty, tz) if nn_mm is None else float(nn_mm)
    if not (tx.size and fx.size):
        return np.empty(0, dtype=np.int64), np.empty(0, dtype=np.int64)
    cost = np.sqrt((fx[:, None] - tx) ** 2 + (fy[:, None] - ty) ** 2 + (fz[:, None] - tz) ** 2)
    limit = max_distance * nn
    cost = np.where(np.isfinite(cost), cost, 1e9)
    rows, cols = linear_sum_assignment(np.where(cost <= limit, cost, 1e9))
    ok = cost[rows, cols] <= limit
    return rows[ok], cols[ok]


def score(found: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray], *, nn_mm: float | None = None,
          max_distance: float = 0.5, pair_lateral: float = 0.35) -> Score:
    """Pair found particles with true ones and measure recall, precision and errors.

    Parameters
    ----------
    found : mapping with columns ``X, Y, Z`` (mm)
    truth : mapping with columns ``X, Y, Z`` (mm) and optionally ``blur_pitches``
    nn_mm : float, optional
        Mean nearest-neighbour distance; default: computed from the truth.
    max_distance : float
        Largest 3D distance of a valid pair, as a fraction of ``nn_mm``.
    pair_lateral : float
        True particles closer than this fraction of ``nn_mm`` in ``(X, Y)`` form a shadowing pair.

    Returns
    -------
    Score
    """
    tx, ty, tz = (np.asarray(truth[c], float) for c in ("X", "Y", "Z"))
    fx, fy, fz = (np.asarray(found[c], float) for c in ("X", "Y", "Z"))
    nn = mean_nn_distance(tx, ty, tz) if nn_mm is None else float(nn_mm)
    n_true, n_found = tx.size, fx.size
    rows, cols = match(found, truth, nn_mm=nn, max_distance=max_distance)
    m = rows.size
    dz = fz[rows] - tz[cols]
    lateral = np.hypot(fx[rows] - tx[cols], fy[rows] - ty[cols])
    if m >= 3:
        slope, intercept = np.polyfit(fz[rows], tz[cols], 1)
        fit_res = tz[cols] - (slope * fz[rows] + intercept)
        fit_rms = float(np.sqrt(np.mean(fit_res**2)))
    else:
        fit_rms = math.nan
    by_blur: dict[str, tuple[int, float]] = {}
    recall_by_blur: dict[str, tuple[int, int]] = {}
    if "blur_pitches" in truth:
        blur_true = np.asarray(truth["blur_pitches"], float)
        blur = blur_true[cols]  # of the matched ones
        if m:
            for lo, hi in BLUR_BINS:
                sel = (blur >= lo) & (blur < hi)
                by_blur[blur_bin_label(lo, hi)] = (int(sel.sum()), float(np.sqrt(np.mean(dz[sel] ** 2)) / nn)
                                                   if sel.any() else math.nan)
        for lo, hi in RECALL_BLUR_BINS:
            recall_by_blur[blur_bin_label(lo, hi)] = (int(np.sum((blur_true >= lo) & (blur_true < hi))),
                                                      int(np.sum((blur >= lo) & (blur < hi))))
    # Shadowing pairs: true particles nearly on one line of sight.
    pairs = cKDTree(np.column_stack([tx, ty])).query_pairs(pair_lateral * nn) if n_true > 1 else set()
    matched = set(cols.tolist())
    separated = sum(1 for a, b in pairs if a in matched and b in matched)
    return Score(n_true=n_true, n_found=n_found, n_matched=m,
                 recall=m / n_true if n_true else math.nan, precision=m / n_found if n_found else math.nan,
                 nn_mm=nn, depth_fit_rms_over_nn=fit_rms / nn,
                 depth_abs_rms_over_nn=float(np.sqrt(np.mean(dz**2))) / nn if m else math.nan,
                 lateral_rms_over_nn=float(np.sqrt(np.mean(lateral**2))) / nn if m else math.nan,
                 depth_by_blur=by_blur, recall_by_blur=recall_by_blur, pairs_total=len(pairs),
                 pairs_separated=separated)


def false_on_reflection(found: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray], chamber: ChamberLight,
                        model: CameraModel, *, nn_mm: float | None = None, max_distance: float = 0.5) -> int:
    """How many found particles match no true one and sit where a reflection's light falls.

    A found particle's place on the sensor is its chief ray through ``model``'s thin lens (as the
    truth's ``x, y``); the reflections' footprints are :meth:`ChamberLight.on_reflection`'s.

    Parameters
    ----------
    found, truth : mappings with columns ``X, Y, Z`` (mm)
    chamber : ChamberLight
        The exposure's chamber (``ChamberLight.from_dict`` of its ``scenario.json``).
    model : CameraModel
        The exposure's camera model (from its metadata).
    """
    rows, _ = match(found, truth, nn_mm=nn_mm, max_distance=max_distance)
    fx, fy, fz = (np.asarray(found[c], float) for c in ("X", "Y", "Z"))
    false = np.setdiff1d(np.arange(fx.size), rows)
    false = false[np.isfinite(fz[false]) & (fz[false] > model.optics.focal_length_m * 1e3)]
    if not chamber.sources or false.size == 0:
        return 0
    where = particle_truth(model, Particles(fx[false], fy[false], fz[false], np.zeros(false.size)))
    return int(np.sum(chamber.on_reflection(model, where.x_px, where.y_px)))


@dataclass(frozen=True)
class RecallInLight:
    """True particles where a reflection's or glint's light falls (``in``) and elsewhere
    (``out``), and how many of each were found (matched)."""

    true_in: int
    found_in: int
    true_out: int
    found_out: int


def recall_in_reflections(found: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray], chamber: ChamberLight,
                          model: CameraModel, *, nn_mm: float | None = None,
                          max_distance: float = 0.5) -> RecallInLight:
    """The true particles split by whether their chief ray meets the sensor where a reflection's
    light falls (:meth:`ChamberLight.on_reflection`), and how many of each ``found`` matches: a
    glint's wide disk over a cluster hides the particles in it from tests that read unexplained light."""
    _, cols = match(found, truth, nn_mm=nn_mm, max_distance=max_distance)
    tx, ty, tz = (np.asarray(truth[c], float) for c in ("X", "Y", "Z"))
    where = particle_truth(model, Particles(tx, ty, tz, np.zeros(tx.size)))
    lit = chamber.on_reflection(model, where.x_px, where.y_px)
    hit = np.zeros(tx.size, dtype=bool)
    hit[cols] = True
    return RecallInLight(true_in=int(lit.sum()), found_in=int((lit & hit).sum()), true_out=int((~lit).sum()),
                         found_out=int((~lit & hit).sum()))
