"""A shot's structure: pair correlation g(r) and, for a ball, its shells.

g(r): the pair distances' histogram over what an ideal gas of the same density would give,
``N/2 * n * 4 pi r^2 dr`` with ``n = N / V`` and ``V`` the convex hull's volume (a flat layer, whose
thinnest extent is under half the mean nearest-neighbour distance, is done in its plane with
the hull's area and ``2 pi r dr``). In a ball the ideal gas fills a sphere of the hull's volume,
whose pairs thin out with distance as ``1 - 3x/4 + x^3/16`` (``x = r / R``), so g(r) tends to 1;
elsewhere a finite cluster's g(r) falls off beyond about its radius. Each bin's uncertainty is
Poisson (``sqrt`` of its count).

Shells (Coulomb or Yukawa balls): particles' distances from the cluster's centre, smoothed
(Gaussian kernel, 0.15 mean NN distances), fall into peaks; each dip between two peaks that
drops below ``dip`` of the lower peak splits two shells. A shell's radius is its particles' mean
distance (uncertainty: standard error), its occupation their count; the count's uncertainty
comes from the particles near a boundary: with radial position errors ``sigma_r`` (the noise
projected on each one's radial direction), a particle belongs to a shell with probability
``p``, and the count's standard deviation is ``sqrt(sum p (1 - p))``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import ConvexHull, QhullError, cKDTree
from scipy.special import ndtr


@dataclass(frozen=True)
class PairCorrelation:
    """g(r) of one shot: bin centres ``r_mm``, ``g`` and its uncertainty ``g_err``, and whether
    it was done in a plane (a flat layer)."""

    r_mm: np.ndarray
    g: np.ndarray
    g_err: np.ndarray
    planar: bool = False


@dataclass(frozen=True)
class Shells:
    """The shells of a ball, innermost first.

    Attributes
    ----------
    radius_mm, radius_err_mm : ndarray of shape (s,)
    count : ndarray of int, shape (s,)
    count_err : ndarray of shape (s,)
    label : ndarray of int, shape (n,)
        Each particle's shell (-1 for a particle without a finite position).
    centre_mm : ndarray of shape (3,)
    """

    radius_mm: np.ndarray
    radius_err_mm: np.ndarray
    count: np.ndarray
    count_err: np.ndarray
    label: np.ndarray
    centre_mm: np.ndarray


def mean_nn_mm(xyz: np.ndarray) -> float:
    """Mean 3D nearest-neighbour distance (NaN for fewer than two points)."""
    if len(xyz) < 2:
        return math.nan
    d, _ = cKDTree(xyz).query(xyz, k=2)
    return float(d[:, 1].mean())


def is_flat(xyz: np.ndarray) -> bool:
    """Whether the cluster is a layer: its thinnest principal extent (RMS) under half the mean NN."""
    if len(xyz) < 4:
        return True
    spread = np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False) / math.sqrt(len(xyz))
    return bool(spread[-1] < 0.5 * mean_nn_mm(xyz))


def is_ball(xyz: np.ndarray) -> bool:
    """Whether the cluster is round enough for shells: its principal extents within a factor 2."""
    if len(xyz) < 10:
        return False
    spread = np.linalg.svd(xyz - xyz.mean(axis=0), compute_uv=False)
    return bool(spread[-1] > 0.5 * spread[0])


def pair_correlation(xyz: np.ndarray, *, bins: int = 40, r_max_mm: float | None = None) -> PairCorrelation:
    """g(r) of one shot (see the module docstring).

    Parameters
    ----------
    xyz : ndarray of shape (n, 3)
        Positions in mm (rows with NaN are left out).
    bins : int
    r_max_mm : float, optional
        Largest distance; default: the cluster's RMS diameter.
    """
    xyz = np.asarray(xyz, float)
    xyz = xyz[np.all(np.isfinite(xyz), axis=1)]
    n = len(xyz)
    empty = PairCorrelation(np.empty(0), np.empty(0), np.empty(0))
    if n < 5:
        return empty
    planar = is_flat(xyz)
    centred = xyz - xyz.mean(axis=0)
    if r_max_mm is None:
        r_max_mm = 2 * float(np.sqrt(np.mean(np.sum(centred ** 2, axis=1))))
        if not planar and is_ball(xyz):
            # Beyond the equivalent sphere's radius few pairs are left to count.
            r_max_mm = min(r_max_mm, float(np.sqrt(5 / 3 * np.mean(np.sum(centred ** 2, axis=1)))))
    try:
        if planar:
            _, _, vt = np.linalg.svd(centred, full_matrices=False)
            size = ConvexHull(centred @ vt[:2].T).volume  # an area in 2D
        else:
            size = ConvexHull(xyz).volume
    except QhullError:
        return empty
    distances = cKDTree(xyz).sparse_distance_matrix(cKDTree(xyz), r_max_mm, output_type="ndarray")
    d = distances["v"][distances["i"] < distances["j"]]
    edges = np.linspace(0.0, r_max_mm, bins + 1)
    counts, _ = np.histogram(d, bins=edges)
    r = 0.5 * (edges[1:] + edges[:-1])
    density = n / size
    shell = np.pi * (edges[1:] ** 2 - edges[:-1] ** 2) if planar else 4 / 3 * np.pi * (edges[1:] ** 3 - edges[:-1] ** 3)
    ideal = 0.5 * n * density * shell
    if not planar and is_ball(xyz):
        # Pairs of a uniform sphere of the hull's volume thin out with distance (no pair is
        # farther apart than its diameter): divide that out, so g(r) tends to 1.
        radius = (3 * size / (4 * np.pi)) ** (1 / 3)
        x = np.minimum(r / radius, 2.0)
        ideal = ideal * np.maximum(1 - 0.75 * x + x ** 3 / 16, 1e-3)
    return PairCorrelation(r, counts / ideal, np.sqrt(counts) / ideal, planar)


def shells(xyz: np.ndarray, *, noise_mm: np.ndarray | None = None, bandwidth_nn: float = 0.15,
           dip: float = 0.7) -> Shells | None:
    """The shells of a ball (see the module docstring); None for a cluster that is no ball.

    Parameters
    ----------
    xyz : ndarray of shape (n, 3)
    noise_mm : ndarray of shape (3,), optional
        Position noise per axis (X, Y, Z), for the occupations' uncertainties.
    bandwidth_nn : float
        Smoothing of the radial distribution, in mean NN distances.
    dip : float
        A dip splits two shells where it falls below this fraction of the lower peak.
    """
    xyz = np.asarray(xyz, float)
    finite = np.all(np.isfinite(xyz), axis=1)
    pts = xyz[finite]
    if not is_ball(pts):
        return None
    centre = pts.mean(axis=0)
    rel = pts - centre
    radius = np.linalg.norm(rel, axis=1)
    h = bandwidth_nn * mean_nn_mm(pts)
    grid = np.linspace(0.0, radius.max() + 3 * h, 400)
    density = np.exp(-0.5 * ((grid[:, None] - radius[None, :]) / h) ** 2).sum(axis=1)
    bounds = _boundaries(grid, density, dip)
    edges = np.r_[0.0, bounds, np.inf]
    inner = np.searchsorted(bounds, radius)
    label = np.full(len(xyz), -1, np.int64)
    label[finite] = inner
    unit = rel / np.maximum(radius, 1e-12)[:, None]
    noise = np.zeros(3) if noise_mm is None else np.nan_to_num(np.asarray(noise_mm, float))
    sigma_r = np.maximum(np.sqrt(np.sum((unit * noise) ** 2, axis=1)), 1e-9)
    count, count_err, mean, mean_err = [], [], [], []
    for s in range(len(edges) - 1):
        members = radius[inner == s]
        p = ndtr((edges[s + 1] - radius) / sigma_r) - ndtr((edges[s] - radius) / sigma_r)
        count.append(members.size)
        count_err.append(float(np.sqrt(np.sum(p * (1 - p)))))
        mean.append(float(members.mean()) if members.size else math.nan)
        mean_err.append(float(members.std(ddof=1) / math.sqrt(members.size)) if members.size > 1 else math.nan)
    return Shells(np.array(mean), np.array(mean_err), np.array(count, np.int64), np.array(count_err), label, centre)


def _boundaries(grid: np.ndarray, density: np.ndarray, dip: float) -> np.ndarray:
    """Radii of the dips that split shells: minima below ``dip`` of the lower neighbouring peak."""
    d = density
    peaks = np.flatnonzero((d[1:-1] > d[:-2]) & (d[1:-1] >= d[2:])) + 1
    peaks = peaks[d[peaks] > 0.05 * d.max()]
    bounds = []
    keep = list(peaks[:1])
    for p in peaks[1:]:
        q = keep[-1]
        low = q + int(np.argmin(d[q:p + 1]))
        if d[low] < dip * min(d[q], d[p]):
            bounds.append(grid[low])
            keep.append(p)
        elif d[p] > d[q]:
            keep[-1] = p
    return np.array(bounds)
