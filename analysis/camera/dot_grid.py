"""Which dot of a calibration target is which: rows, columns and the dot nearest the axis.

A target's dots, found in one exposure, are points in the image (lens-plane positions). Their
grid is identified locally, so that distortion, perspective of a tilted plate and a magnification
that changes with depth do not matter:

1. duplicates (dots closer than a third of the typical spacing to a brighter one) dropped, the
   typical spacing from the distance to the nearest dot;
2. the grid's two directions from the neighbour vectors (their angles folded four-fold); columns
   step along the direction nearest the image's ``+x``, rows along the one nearest ``+y``;
3. the dot nearest the optical axis is row 0, column 0; from it the grid grows dot by dot, each
   neighbour predicted from an affine fit to the dots already placed around it and accepted within
   ``tolerance`` of a spacing;
4. a smooth (cubic) fit of position against row and column over the whole grid throws out dots
   that do not belong.

Exposures of one target at several stage positions are labelled alike with :func:`align_grids`:
if the axis lies near the middle between dots, another dot may be nearest it at another position.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from analysis.errors import GridIdentificationError, TooFewDotsError

#: Fewest dots (and rows, columns) a grid is identified from.
MIN_DOTS = 9
MIN_LINES = 3
#: A neighbour is accepted within this fraction of a spacing of where it was predicted.
TOLERANCE = 0.3
#: Dots nearer than this fraction of a spacing to a brighter dot are duplicates.
DUPLICATE_FRACTION = 0.35
#: At least this fraction of the (deduplicated) dots must lie on the identified grid.
MIN_ON_GRID = 0.6


@dataclass(frozen=True)
class DotGrid:
    """The grid of one exposure's dots.

    Attributes
    ----------
    index : ndarray of int, shape (m,)
        Which input point each grid dot is.
    rows, cols : ndarray of int, shape (m,)
        Its row and column; ``(0, 0)`` is the dot nearest the axis (before :func:`align_grids`).
    spacing : float
        Median distance between neighbouring dots, in the input's units.
    column_step, row_step : ndarray of shape (2,)
        Typical vectors from a dot to the next column and to the next row.
    n_points : int
        Points given; those not in ``index`` are duplicates or lie off the grid.
    residual : float
        RMS distance of the grid's dots from a smooth (cubic) fit over rows and columns, in spacings.
    """

    index: np.ndarray
    rows: np.ndarray
    cols: np.ndarray
    spacing: float
    column_step: np.ndarray
    row_step: np.ndarray
    n_points: int
    residual: float

    def __len__(self) -> int:
        return int(self.index.size)

    def shifted(self, d_row: int, d_col: int) -> "DotGrid":
        """The same grid with every row and column index moved by ``(d_row, d_col)``."""
        return DotGrid(self.index, self.rows + d_row, self.cols + d_col, self.spacing, self.column_step,
                       self.row_step, self.n_points, self.residual)


def identify_grid(points: np.ndarray, *, axis: tuple[float, float] = (0.0, 0.0),
                  brightness: np.ndarray | None = None, tolerance: float = TOLERANCE,
                  min_dots: int = MIN_DOTS) -> DotGrid:
    """Rows and columns of a target's dots seen in one exposure.

    Parameters
    ----------
    points : ndarray of shape (n, 2)
        Dot positions in the image (e.g. lens-plane ``sx, sy``), ``x`` right and ``y`` down.
    axis : tuple of 2 floats
        Where the optical axis meets the image, in the same units.
    brightness : ndarray of shape (n,), optional
        Of duplicates (several detections of one dot), the brightest is kept.
    tolerance : float
        How far (in spacings) a dot may lie from where its neighbours predict it.
    min_dots : int

    Returns
    -------
    DotGrid

    Raises
    ------
    TooFewDotsError
        With fewer than ``min_dots`` points.
    GridIdentificationError
        When no regular grid holds enough of them.

    Examples
    --------
    >>> r, c = np.meshgrid(np.arange(-3, 4), np.arange(-3, 4), indexing="ij")
    >>> grid = identify_grid(np.column_stack([c.ravel() * 2.0 + 0.3, r.ravel() * 2.0 - 0.2]))
    >>> len(grid), int(grid.rows.min()), int(grid.cols.max()), round(grid.spacing, 6)
    (49, -3, 3, 2.0)
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    finite = np.all(np.isfinite(pts), axis=1)
    n = int(finite.sum())
    if n < min_dots:
        raise TooFewDotsError(f"found {n} dots, too few to identify a grid (need {min_dots}): light the target "
                              "evenly, bring it nearer the focus, or give the dot-finding a lower threshold")
    weight = np.ones(len(pts)) if brightness is None else np.nan_to_num(np.asarray(brightness, float), nan=0.0)
    ids = _deduplicate(pts, np.flatnonzero(finite), weight)
    p = pts[ids]
    tree = cKDTree(p)
    dist, _ = tree.query(p, k=2)
    spacing = float(np.median(dist[:, 1])) if len(p) > 1 else math.nan
    if not spacing > 0:
        raise GridIdentificationError("the dots lie on top of each other; is this a dot target?")
    col_step, row_step = _grid_steps(p, tree, spacing)
    spacing = 0.5 * float(np.hypot(*col_step) + np.hypot(*row_step))
    origin = int(np.argmin(np.hypot(p[:, 0] - axis[0], p[:, 1] - axis[1])))
    placed = _grow(p, tree, origin, col_step, row_step, spacing * tolerance)
    members = np.array(sorted(placed.values()), dtype=np.int64)
    rc = {v: key for key, v in placed.items()}
    rows = np.array([rc[m][0] for m in members], dtype=np.int64)
    cols = np.array([rc[m][1] for m in members], dtype=np.int64)
    keep, residual = _smooth_check(p[members], rows, cols, spacing)
    members, rows, cols = members[keep], rows[keep], cols[keep]
    if (len(members) < max(min_dots, MIN_ON_GRID * len(p)) or np.unique(rows).size < MIN_LINES
            or np.unique(cols).size < MIN_LINES):
        raise GridIdentificationError(
            f"only {len(members)} of {len(p)} dots lie on one regular grid around the dot nearest the axis "
            f"({np.unique(rows).size} rows, {np.unique(cols).size} columns): check that the whole field shows "
            "one plate of evenly spaced dots, lit evenly, with nothing else bright in view")
    return DotGrid(index=ids[members], rows=rows, cols=cols, spacing=spacing, column_step=col_step,
                   row_step=row_step, n_points=len(pts), residual=residual)


def _deduplicate(pts: np.ndarray, ids: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """Input indices of the points kept: of points closer than a fraction of the spacing, the brightest."""
    p = pts[ids]
    if len(p) < 5:
        return ids
    dist, _ = cKDTree(p).query(p, k=5)
    radius = DUPLICATE_FRACTION * float(np.median(dist[:, 4]))
    order = np.argsort(-weight[ids], kind="stable")
    tree = cKDTree(p)
    dropped = np.zeros(len(p), dtype=bool)
    for i in order:
        if dropped[i]:
            continue
        for j in tree.query_ball_point(p[i], radius):
            if j != i:
                dropped[j] = True
    return ids[~dropped]


def _grid_steps(p: np.ndarray, tree: cKDTree, spacing: float) -> tuple[np.ndarray, np.ndarray]:
    """The typical column and row steps, from the vectors to each dot's nearest neighbours."""
    k = min(5, len(p))
    dist, nb = tree.query(p, k=k)
    vec = (p[nb[:, 1:]] - p[:, None, :]).reshape(-1, 2)
    length = dist[:, 1:].ravel()
    vec = vec[(length > 0.7 * spacing) & (length < 1.3 * spacing)]
    if len(vec) < 4:
        raise GridIdentificationError("the dots show no regular spacing; is this a dot target?")
    theta = np.arctan2(vec[:, 1], vec[:, 0])
    phase = np.angle(np.mean(np.exp(4j * theta))) / 4  # the grid's direction, modulo 90 degrees
    # Of its four directions, columns step along the one nearest +x; rows 90 degrees on (+y, down).
    col_angle = max((phase + k * math.pi / 2 for k in range(4)), key=math.cos)
    col_dir = np.array([math.cos(col_angle), math.sin(col_angle)])
    row_dir = np.array([-col_dir[1], col_dir[0]])
    out = []
    for unit in (col_dir, row_dir):
        along = vec @ unit
        cos = along / np.linalg.norm(vec, axis=1)
        near = cos > math.cos(math.radians(25))
        if near.sum() < 2:
            raise GridIdentificationError("the dots are not on a square grid (no neighbours along one of its "
                                          "directions); is this a dot target, rows roughly along the image's?")
        out.append(np.median(vec[near], axis=0))
    return out[0], out[1]


def _grow(p: np.ndarray, tree: cKDTree, origin: int, col_step: np.ndarray, row_step: np.ndarray,
          radius: float) -> dict[tuple[int, int], int]:
    """Place dots on the grid from ``origin`` outward: ``{(row, col): point}``."""
    placed: dict[tuple[int, int], int] = {(0, 0): origin}
    taken = {origin}
    queue = deque([(0, 0)])
    while queue:
        r, c = queue.popleft()
        for dr, dc in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            key = (r + dr, c + dc)
            if key in placed:
                continue
            guess = _predict(p, placed, r, c, dr, dc, col_step, row_step)
            dist, j = tree.query(guess)
            if dist <= radius and j not in taken:
                placed[key] = int(j)
                taken.add(int(j))
                queue.append(key)
    return placed


def _predict(p: np.ndarray, placed: dict[tuple[int, int], int], r: int, c: int, dr: int, dc: int,
             col_step: np.ndarray, row_step: np.ndarray) -> np.ndarray:
    """Where dot ``(r + dr, c + dc)`` should be: an affine fit to the placed dots within two rows and
    columns of ``(r, c)``, or one step from it where they are too few."""
    near = [(rr, cc, placed[(rr, cc)]) for rr in range(r - 2, r + 3) for cc in range(c - 2, c + 3)
            if (rr, cc) in placed]
    rows = np.array([a for a, _, _ in near], dtype=np.float64)
    cols = np.array([b for _, b, _ in near], dtype=np.float64)
    if len(near) >= 4 and np.unique(rows).size >= 2 and np.unique(cols).size >= 2:
        design = np.column_stack([np.ones(len(near)), rows - r, cols - c])
        coef, *_ = np.linalg.lstsq(design, p[[m for _, _, m in near]], rcond=None)
        return coef[0] + dr * coef[1] + dc * coef[2]
    return p[placed[(r, c)]] + dr * row_step + dc * col_step


def _smooth_check(p: np.ndarray, rows: np.ndarray, cols: np.ndarray, spacing: float) -> tuple[np.ndarray, float]:
    """Which dots a cubic surface over (row, col) explains within a quarter spacing, and its RMS
    misfit in spacings."""
    keep = np.ones(len(p), dtype=bool)
    if len(p) < 16:
        return keep, 0.0
    r = rows / max(1, np.abs(rows).max())
    c = cols / max(1, np.abs(cols).max())
    design = np.column_stack([r ** i * c ** j for i in range(4) for j in range(4 - i)])
    misfit = np.zeros(len(p))
    for _ in range(3):
        coef, *_ = np.linalg.lstsq(design[keep], p[keep], rcond=None)
        misfit = np.hypot(*(design @ coef - p).T) / spacing
        new = misfit < 0.25
        if np.array_equal(new, keep):
            break
        keep = new
    return keep, float(np.sqrt(np.mean(misfit[keep] ** 2))) if keep.any() else math.nan


def align_grids(points: list[np.ndarray], grids: list[DotGrid], *, axis: tuple[float, float] = (0.0, 0.0),
                max_shift: int = 2) -> list[DotGrid]:
    """Label one target's dots alike in every exposure (ordered by stage position).

    Each grid after the first is shifted by the whole rows and columns that best match its dots to
    the previous exposure's, scaled about the axis by the ratio of their spacings (the
    magnification changes with depth). Then row 0, column 0 is the dot that lies nearest the axis
    where any does (in spacings): a dot the pipeline missed in one exposure does not move the origin.

    Parameters
    ----------
    points : list of ndarray (n_k, 2)
        Each exposure's points, as given to :func:`identify_grid`.
    grids : list of DotGrid
    axis : tuple of 2 floats
    max_shift : int
        Largest shift tried, in rows and columns.

    Returns
    -------
    list of DotGrid
    """
    out = [grids[0]]
    centre = np.asarray(axis, dtype=np.float64)
    for k in range(1, len(grids)):
        prev, cur = out[-1], grids[k]
        prev_at = {(int(r), int(c)): points[k - 1][i] for r, c, i in zip(prev.rows, prev.cols, prev.index)}
        scale = cur.spacing / prev.spacing
        best, best_cost = (0, 0), math.inf
        for d_row in range(-max_shift, max_shift + 1):
            for d_col in range(-max_shift, max_shift + 1):
                cost = []
                for r, c, i in zip(cur.rows, cur.cols, cur.index):
                    ref = prev_at.get((int(r) + d_row, int(c) + d_col))
                    if ref is not None:
                        cost.append(np.hypot(*(centre + (ref - centre) * scale - points[k][i])))
                if len(cost) >= MIN_DOTS and np.median(cost) < best_cost:
                    best, best_cost = (d_row, d_col), float(np.median(cost))
        if not best_cost < 0.5 * cur.spacing:
            raise GridIdentificationError(
                f"the dots of exposure {k + 1} do not line up with those of exposure {k} (best match "
                f"{best_cost / cur.spacing:.2f} spacings off): move the target along the camera's axis between "
                "positions, without turning it")
        out.append(cur.shifted(*best))
    nearest = []
    for pts, grid in zip(points, out):
        d = np.hypot(*(pts[grid.index] - centre).T) / grid.spacing
        i = int(np.argmin(d))
        nearest.append((float(d[i]), int(grid.rows[i]), int(grid.cols[i])))
    _, row0, col0 = min(nearest)
    return [grid.shifted(-row0, -col0) for grid in out]
