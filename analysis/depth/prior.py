"""A prior on each particle's depth from its neighbours: locally, a cluster is often a surface.

Where one micro-lens holds all of a particle's light, the raw pixels allow every depth whose
blur still fits in that lens, in front of focus or behind it (:mod:`analysis.depth.rayfit`). Its
neighbours often tell more: in a monolayer crystal, or on a shell of a Coulomb ball, particles
a neighbour apart lie on one smooth surface. For each particle a plane ``alpha = a + b x + c y``
is fitted to its nearest neighbours (lateral distance), each weighted by how well its own depth
is known; the prior is that plane's prediction, as wide as the neighbours' scatter about it.

Every particle with a prior is refitted with it: where the pixels leave the depth open the
prior decides, where they pin it as well as the prior the two combine, and where they pin it
better the pixels decide.

Where the neighbours do not form a surface (a 3D crowd, several layers, a chain along the line
of sight), too few of them agree on any plane: there is no prior, and the pixels decide alone.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import logging

import numpy as np
from scipy.spatial import cKDTree

from analysis.detection.curves import Peaks

from .rayfit import RayFit
from .refine import RayFitter, replace_fits

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class DepthPrior:
    """Per particle, arrays of shape ``(n,)``: centre and width of the prior on alpha (NaN: none)."""

    alpha: np.ndarray
    sigma: np.ndarray


def neighbour_prior(x: np.ndarray, y: np.ndarray, alpha: np.ndarray, alpha_std: np.ndarray, *,
                    neighbours: int = 12, agree: float = 2 / 3) -> DepthPrior:
    """The depth each particle's neighbours predict for it, and how far to trust that.

    Parameters
    ----------
    x, y : ndarray of shape (n,)
        Image positions (any unit shared by both).
    alpha, alpha_std : ndarray of shape (n,)
        Depths and their uncertainties (e.g. :attr:`analysis.depth.rayfit.RayFit.alpha_spread`);
        neighbours count by ``1 / alpha_std^2``, so ambiguous ones hardly count.
    neighbours : int
        How many nearest neighbours (in the image) to consider.
    agree : float
        The fraction of them that must lie on one plane (within 3 of their own sigmas) for a
        prior; otherwise (a 3D crowd, too few particles) none: NaN. A high bar, because among
        a dozen neighbours at random depths a few lie on some plane by chance.

    Returns
    -------
    DepthPrior
        ``sigma`` is the neighbours' weighted RMS scatter about their plane (corrected for the 3
        fitted parameters) combined with the uncertainty of the plane's prediction.
    """
    x, y, alpha, std = (np.asarray(v, dtype=np.float64).ravel() for v in (x, y, alpha, alpha_std))
    n = x.size
    centre = np.full(n, np.nan)
    sigma = np.full(n, np.nan)
    k = min(neighbours, n - 1)
    if k < 5:
        return DepthPrior(centre, sigma)
    _, nb = cKDTree(np.column_stack([x, y])).query(np.column_stack([x, y]), k=k + 1)
    nb = nb[:, 1:]  # the nearest is the particle itself
    known = std[np.isfinite(std)]
    # A floor on each neighbour's variance, so one exactly known neighbour cannot take all the weight.
    floor = 0.25 * float(np.median(known)) if known.size else 0.0
    var = np.where(np.isfinite(std), std, np.inf)[nb] ** 2 + floor**2
    w = np.where(np.isfinite(alpha[nb]), 1.0 / np.maximum(var, 1e-30), 0.0)
    design = np.stack([np.ones((n, k)), x[nb] - x[:, None], y[nb] - y[:, None]], axis=-1)  # (n, k, 3)
    target = np.where(np.isfinite(alpha[nb]), alpha[nb], 0.0)
    # Neighbours off the surface (a particle of another layer, a shadowing partner) must not tilt
    # it: start from the plane through three neighbours that most others agree with (a RANSAC
    # over every triple), then refit to those within 3 sigmas of it, twice.
    use = np.where(_inliers(design, target, var, _best_triple_plane(design, target, var)), w, 0.0)
    for _ in range(2):
        coef, inverse = _plane_fit(design, target, use)
        use = np.where(_inliers(design, target, var, coef), w, 0.0)
    coef, inverse = _plane_fit(design, target, use)
    resid = target - np.einsum("nki,ni->nk", design, coef)
    wsum = use.sum(axis=1)
    m = np.count_nonzero(use > 0, axis=1)
    scatter2 = np.einsum("nk,nk->n", use, resid**2) / np.maximum(wsum, 1e-300) * m / np.maximum(m - 3, 1)
    # Variance of the intercept with the weights scaled to the observed scatter.
    predict2 = inverse[:, 0, 0] * scatter2 * wsum / np.maximum(m, 1)
    ok = (m >= np.maximum(agree * np.count_nonzero(w > 0, axis=1), 5)) & np.isfinite(coef[:, 0])
    centre[ok] = coef[ok, 0]
    sigma[ok] = np.sqrt(scatter2[ok] + predict2[ok])
    return DepthPrior(centre, sigma)


def _plane_fit(design: np.ndarray, target: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted least squares per row: coefficients (n, 3) and the inverse normal matrices (n, 3, 3)."""
    normal = np.einsum("nk,nki,nkj->nij", w, design, design)
    rhs = np.einsum("nk,nki,nk->ni", w, design, target)
    # Neighbours all on one line leave the tilt across it free: a small ridge keeps the fit defined
    # (and, with no neighbour left at all, the intercept too: its variance is then huge).
    for i in range(3):
        normal[:, i, i] += 1e-9 * np.maximum(normal[:, i, i], 1.0)
    inverse = np.linalg.inv(normal)
    return np.einsum("nij,nj->ni", inverse, rhs), inverse


def _inliers(design: np.ndarray, target: np.ndarray, var: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """Neighbours within 3 of their own sigmas of each row's plane ``coef`` (n, 3)."""
    resid = target - np.einsum("nki,ni->nk", design, coef)
    return resid**2 <= 9.0 * var


def _best_triple_plane(design: np.ndarray, target: np.ndarray, var: np.ndarray) -> np.ndarray:
    """Per row, the plane through the three neighbours that the most neighbours agree with."""
    n, k, _ = design.shape
    triples = np.array(list(combinations(range(k), 3)))  # (t, 3)
    a = design[:, triples]  # (n, t, 3, 3)
    b = target[:, triples]  # (n, t, 3)
    det = np.linalg.det(a)
    ok = np.abs(det) > 1e-12 * np.max(np.abs(a), axis=(2, 3)) ** 2
    safe = np.where(ok[..., None, None], a, np.eye(3))
    planes = np.linalg.solve(safe, b[..., None])[..., 0]  # (n, t, 3)
    resid = target[:, None, :] - np.einsum("nki,nti->ntk", design, planes)
    z2 = resid**2 / var[:, None, :]
    votes = np.where(ok, np.count_nonzero(z2 <= 9.0, axis=2), -1)
    # Ties: the plane the agreeing neighbours sit closest to.
    spread = np.where(z2 <= 9.0, z2, 0.0).sum(axis=2)
    best = np.lexsort((spread, -votes), axis=-1)[:, 0] if n else np.zeros(0, np.int64)
    return planes[np.arange(n), best]


def apply_depth_prior(fitter: RayFitter, peaks: Peaks, fit: RayFit) -> tuple[Peaks, RayFit]:
    """Refit every particle that has a prior (:func:`analysis.depth.prior.neighbour_prior`) with
    its neighbours' surface as that prior; the others keep their fit.

    The fit weighs the pixels and the prior together, and the prior's uniform floor lets the
    pixels win where they clearly disagree, so particles whose pixels pin their depth are
    refitted too: a particle near focus whose light spills into a second lens knows its depth
    about as well as its neighbours do, and both together beat either (refitting only where the
    prior was the narrower left one such particle of a realistic layer 0.175 NN off in depth; with
    the prior it is 0.07 off, as through ideal optics).
    """
    prior = neighbour_prior(peaks.x, peaks.y, fit.alpha, fit.alpha_spread)
    todo = np.flatnonzero(np.isfinite(prior.sigma))
    log.debug("depth prior: %d of %d particles refitted", todo.size, len(peaks))
    if todo.size == 0:
        return peaks, fit
    sub = fit.take(todo)
    new = fitter.fit(sub.sx_m, sub.sy_m, sub.alpha, subtract=fitter.render(fit), own=sub,
                     prior_alpha=prior.alpha[todo], prior_sigma=prior.sigma[todo])
    ok = np.flatnonzero(new.intensity > 0)
    return replace_fits(fitter.grid, peaks, fit, todo[ok], new.take(ok))
