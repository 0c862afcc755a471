"""Kinetic temperature from linked positions, with the position noise taken out.

Velocities from positions carry the positions' errors: a central difference over ``dt`` adds
``2 sigma^2 / dt^2`` to each component's variance, and depth errors (5 to 10 times the lateral
ones) can double the apparent depth temperature. :func:`position_noise` measures ``sigma`` per
axis from the run itself:

1. For each lag ``tau`` = 1 ... ``lags`` frames, the particles' displacements from frame ``k`` to
   ``k + tau`` with the cluster's rigid motion taken off (a Kabsch fit of the linked pairs, its six
   degrees of freedom corrected for) give a mean squared displacement ``MSD(dt)`` per axis at the
   pairs' mean time apart ``dt``.
2. Noise adds ``2 sigma^2`` at every lag from ``first_lag`` (2) on; motion grows with the lag:
   ``<v^2> dt^2`` while it is ballistic, bending away as damping or the particle's cage act. A
   least-squares fit of ``MSD(dt) = 2 sigma^2 + <v^2> dt^2 + c dt^4 + d dt^6`` over lags 2-7 gives
   ``sigma`` (the intercept) and the bend. Lag 1 is left out of it: displacements one shot apart
   carry less of the depth noise than the velocities (two shots apart) do, because depth errors are
   heavy-tailed and the outlier cut below, set by each lag's own spread, takes more of their tail
   where the motion is small, and because a particle's depth errors in consecutive shots are
   correlated. On the bench's realistic run the velocities' depth noise was 1.4 times what lag 1
   shows, and a fit through lag 1 left the depth temperature a quarter high. The longer span
   needs the ``dt^6`` term: fitted to true positions it leaves under 2.5 % of ``MSD`` at lag 2.
   The noise one shot apart (``short_sigma_mm``: ``MSD`` at lag 1 less the fitted motion there) is
   kept for velocities taken across one shot interval (a trajectory's ends).
3. A shot's temperature (:func:`shot_temperature`) is then, per axis, the variance of its
   particles' velocities about the cluster's rigid motion, less ``2 sigma^2 / dt^2``, divided by
   the bend's factor ``1 + (c dt^2 + d dt^4) / <v^2>`` at the velocities' own ``dt``, times ``m / e``.

Both mean squares are taken robustly: values beyond ``CLIP_SIGMA`` (4) robust standard deviations
(1.4826 times the median absolute value) are left out, the rigid motion fitted again without
them, and the mean square of the rest divided by what the cut takes from a Gaussian (0.1 % at
4). Velocities and displacements are Gaussian (Maxwellian motion plus Gaussian position errors),
so nothing changes for them; a wrong link or a detection far off is not Gaussian, and one in two
hundred of them, each a step of half a neighbour distance, would otherwise add a third to the
temperature (and, since a wrong link enters more displacements the longer the lag, bend the
noise fit's intercept negative).

Uncertainties come from a jackknife over blocks of frames (noise) and the sampling error of a
variance of ``n`` values (a shot).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .motion import kabsch
from .units import ev_per_mm2_s2

AXES = ("X", "Y", "Z")
CLIP_SIGMA = 4.0  # robust standard deviations beyond which a velocity or displacement is left out


def gaussian_kept_fraction(k: float) -> float:
    """The mean square of a standard Gaussian within ``+-k``, over its full mean square (1).

    >>> round(gaussian_kept_fraction(4.0), 5)
    0.99893
    """
    inside = math.erf(k / math.sqrt(2.0))
    density = math.exp(-0.5 * k * k) / math.sqrt(2.0 * math.pi)
    return 1.0 - 2.0 * k * density / inside


def inliers(residual: np.ndarray, clip: float = CLIP_SIGMA) -> np.ndarray:
    """Rows of ``residual`` (n, 3), about zero, whose every component lies within ``clip``
    robust standard deviations (1.4826 times that axis's median absolute value)."""
    scale = 1.4826 * np.median(np.abs(residual), axis=0)
    return np.all(np.abs(residual) <= clip * np.where(scale > 0, scale, np.inf), axis=1)


@dataclass(frozen=True)
class NoiseEstimate:
    """Position noise per axis and the fit it came from.

    Attributes
    ----------
    sigma_mm, sigma_err_mm : ndarray of shape (3,)
        Standard deviation of the position error per axis (X, Y, Z) and its uncertainty.
    speed2_mm2_s2 : ndarray of shape (3,)
        ``<v^2>`` per axis from the fit (about the rigid motion).
    bend_s2, bend_s4 : ndarray of shape (3,)
        ``c / <v^2>`` and ``d / <v^2>``: how the displacements bend away from ballistic (per s^2,
        per s^4).
    short_sigma_mm : ndarray of shape (3,)
        The noise as displacements one shot apart carry it (velocities across one interval).
    dt_s : ndarray of shape (L,)
        Mean time apart of the pairs at each lag.
    msd_mm2 : ndarray of shape (L, 3)
        Mean squared displacement per lag and axis.
    pairs : ndarray of shape (L,)
        Displacements per lag.
    """

    sigma_mm: np.ndarray
    sigma_err_mm: np.ndarray
    speed2_mm2_s2: np.ndarray
    bend_s2: np.ndarray
    dt_s: np.ndarray = field(default_factory=lambda: np.empty(0))
    msd_mm2: np.ndarray = field(default_factory=lambda: np.empty((0, 3)))
    pairs: np.ndarray = field(default_factory=lambda: np.empty(0, np.int64))
    bend_s4: np.ndarray = field(default_factory=lambda: np.zeros(3))
    short_sigma_mm: np.ndarray | None = None

    @classmethod
    def unknown(cls) -> NoiseEstimate:
        nan = np.full(3, np.nan)
        return cls(nan, nan.copy(), nan.copy(), np.zeros(3))

    def bend_factor(self, dt_s: np.ndarray) -> np.ndarray:
        """Per axis, the mean over ``dt_s`` of ``MSD_motion(dt) / (<v^2> dt^2)``, shape (3,)."""
        dt2 = np.asarray(dt_s, float) ** 2
        return 1.0 + self.bend_s2 * float(np.mean(dt2)) + self.bend_s4 * float(np.mean(dt2 ** 2))

    def to_dict(self) -> dict[str, Any]:
        return {"sigma_mm": _list(self.sigma_mm), "sigma_err_mm": _list(self.sigma_err_mm),
                "speed2_mm2_s2": _list(self.speed2_mm2_s2), "bend_s2": _list(self.bend_s2),
                "bend_s4": _list(self.bend_s4),
                "short_sigma_mm": _list(self.sigma_mm if self.short_sigma_mm is None else self.short_sigma_mm),
                "dt_s": _list(self.dt_s), "msd_mm2": [_list(m) for m in self.msd_mm2],
                "pairs": [int(p) for p in self.pairs]}


def _list(values: np.ndarray) -> list:
    return [None if not np.isfinite(v) else float(v) for v in np.asarray(values, float)]


def trajectory_matrix(particle: np.ndarray, frame: np.ndarray, xyz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions as an array (frames, trajectories, 3), NaN where a trajectory is not seen; and the
    sorted frame numbers. Rows with ``particle < 0`` are left out."""
    ok = particle >= 0
    frames, fi = np.unique(frame[ok], return_inverse=True)
    _, pi = np.unique(particle[ok], return_inverse=True)
    out = np.full((frames.size, pi.max() + 1 if pi.size else 0, 3), np.nan)
    out[fi, pi] = xyz[ok]
    return out, frames


def rigid_residuals(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``b`` less the rigid motion (Kabsch) that best carries ``a`` onto it, scaled for the six
    degrees of freedom the fit takes (so its mean square is unbiased)."""
    r, t = kabsch(a, b)
    res = b - (a @ r.T + t)
    n = len(a)
    return res * np.sqrt(3 * n / max(3 * n - 6, 1))


def position_noise(particle: np.ndarray, frame: np.ndarray, t: np.ndarray, xyz: np.ndarray, *,
                   lags: int = 7, first_lag: int = 2, blocks: int = 10) -> NoiseEstimate:
    """Position noise per axis from the run's displacements at several lags (module docstring).

    Parameters
    ----------
    particle, frame, t : ndarray of shape (n,)
        Trajectory id, frame and time (s) of each row.
    xyz : ndarray of shape (n, 3)
        Positions (mm).
    lags : int
        Largest lag in frames (7 by default).
    first_lag : int
        The noise fit starts at this lag (2: the central velocities' own; module docstring).
    blocks : int
        Blocks of frames for the jackknife's uncertainties.

    Returns
    -------
    NoiseEstimate
        ``unknown()`` where too few linked pairs exist.
    """
    positions, frames = trajectory_matrix(np.asarray(particle), np.asarray(frame), np.asarray(xyz, float))
    times = np.full(frames.size, np.nan)
    order = np.argsort(frame)
    times = np.interp(frames, np.asarray(frame)[order], np.asarray(t, float)[order])
    nf = frames.size
    if nf < 3:
        return NoiseEstimate.unknown()
    block_of = np.minimum((np.arange(nf) * blocks) // nf, blocks - 1)
    sums = np.zeros((blocks, lags, 3))
    counts = np.zeros((blocks, lags))
    dts = np.zeros((blocks, lags))
    for k in range(nf):
        for lag in range(1, lags + 1):
            j = np.searchsorted(frames, frames[k] + lag)
            if j >= nf or frames[j] != frames[k] + lag:
                continue
            both = np.all(np.isfinite(positions[k]), axis=1) & np.all(np.isfinite(positions[j]), axis=1)
            if both.sum() < 8:
                continue
            a_xyz, b_xyz = positions[k][both], positions[j][both]
            keep = inliers(rigid_residuals(a_xyz, b_xyz))
            if keep.sum() < 8:
                continue
            res = rigid_residuals(a_xyz[keep], b_xyz[keep])
            b = block_of[k]
            sums[b, lag - 1] += np.sum(res ** 2, axis=0) / gaussian_kept_fraction(CLIP_SIGMA)
            counts[b, lag - 1] += keep.sum()
            dts[b, lag - 1] += keep.sum() * (times[j] - times[k])
    estimate = _fit(sums.sum(0), counts.sum(0), dts.sum(0), first_lag)
    if estimate is None:
        return NoiseEstimate.unknown()
    sigma, speed2, bend, bend4, short = estimate
    # Jackknife over blocks of frames.
    leave = []
    for b in range(blocks):
        fit = _fit(sums.sum(0) - sums[b], counts.sum(0) - counts[b], dts.sum(0) - dts[b], first_lag)
        if fit is not None:
            leave.append(fit[0])
    m = len(leave)
    err = np.sqrt((m - 1) / m * np.sum((np.array(leave) - np.mean(leave, axis=0)) ** 2, axis=0)) if m > 2 \
        else np.full(3, np.nan)
    total_counts = counts.sum(0)
    with np.errstate(invalid="ignore", divide="ignore"):
        msd = sums.sum(0) / total_counts[:, None]
        dt = dts.sum(0) / total_counts
    return NoiseEstimate(sigma, err, speed2, bend, dt, msd, total_counts.astype(np.int64), bend_s4=bend4,
                         short_sigma_mm=short)


def _fit(sums: np.ndarray, counts: np.ndarray, dts: np.ndarray, first_lag: int = 1) -> tuple[np.ndarray, ...] | None:
    """``sigma, <v^2>, c / <v^2>, d / <v^2>`` and the noise one shot apart, from the MSD per lag:
    ``2 sigma^2 + <v^2> dt^2 + c dt^4 + d dt^6`` over the lags from ``first_lag`` (as many motion
    terms as leave the fit a degree of freedom, at least ``<v^2>``)."""
    lag = np.arange(1, len(counts) + 1)
    use = (counts > 0) & (lag >= first_lag)
    if use.sum() < 2:
        return None
    msd = sums[use] / counts[use, None]
    dt = dts[use] / counts[use]
    w = np.sqrt(counts[use])
    powers = [2, 4, 6][:max(1, min(3, int(use.sum()) - 2))]
    design = np.stack([np.ones_like(dt)] + [dt ** q for q in powers], axis=1)
    coef, *_ = np.linalg.lstsq(design * w[:, None], msd * w[:, None], rcond=None)
    intercept, speed2 = coef[0], coef[1]
    safe = np.where(speed2 != 0, speed2, np.nan)
    bend = np.nan_to_num(coef[2] / safe) if len(powers) > 1 else np.zeros(3)
    bend4 = np.nan_to_num(coef[3] / safe) if len(powers) > 2 else np.zeros(3)
    sigma = np.sqrt(np.maximum(intercept, 0.0) / 2)
    short = sigma.copy()
    if counts[0] > 0 and first_lag > 1:  # lag 1 less the fitted motion there
        dt1 = dts[0] / counts[0]
        motion1 = sum(coef[k + 1] * dt1 ** q for k, q in enumerate(powers))
        short = np.sqrt(np.maximum(sums[0] / counts[0] - motion1, 0.0) / 2)
    return sigma, speed2, bend, bend4, short


@dataclass(frozen=True)
class ShotTemperature:
    """One shot's velocities about the cluster's rigid motion.

    Attributes
    ----------
    count : int
        Particles whose velocity was used (with a velocity, and not left out as an outlier).
    drift_mm_s : ndarray of shape (3,)
        The cluster's mean velocity (its centre's).
    omega_rad_s : ndarray of shape (3,)
        The cluster's rotation (rotation vector per second).
    rms_mm_s, rms_err_mm_s : ndarray of shape (3,)
        RMS velocity per axis about the rigid motion, noise taken out.
    temperature_ev, temperature_err_ev : ndarray of shape (3,)
        Kinetic temperature per axis.
    """

    count: int
    drift_mm_s: np.ndarray
    omega_rad_s: np.ndarray
    rms_mm_s: np.ndarray
    rms_err_mm_s: np.ndarray
    temperature_ev: np.ndarray
    temperature_err_ev: np.ndarray


def shot_temperature(xyz: np.ndarray, velocity: np.ndarray, dt_s: np.ndarray, noise: NoiseEstimate, *,
                     mass_kg: float) -> ShotTemperature:
    """Kinetic temperature of one shot (see the module docstring).

    Parameters
    ----------
    xyz, velocity : ndarray of shape (n, 3)
        Positions (mm) and velocities (mm/s); rows with a NaN velocity component are left out.
    dt_s : ndarray of shape (n,)
        The time apart of the two positions each velocity was taken from.
    noise : NoiseEstimate
    mass_kg : float
    """
    ok = np.all(np.isfinite(velocity), axis=1) & np.all(np.isfinite(xyz), axis=1) & (dt_s > 0)
    n = int(ok.sum())
    nan = np.full(3, np.nan)
    if n < 8:
        return ShotTemperature(n, nan, nan.copy(), nan.copy(), nan.copy(), nan.copy(), nan.copy())
    r, v, dt = xyz[ok], velocity[ok], dt_s[ok]
    coef, residual = _rigid_fit(r, v)
    keep = inliers(residual)  # wrong links and far-off detections out (module docstring)
    if keep.sum() >= 8 and not keep.all():
        r, v, dt = r[keep], v[keep], dt[keep]
        n = int(keep.sum())
        coef, residual = _rigid_fit(r, v)
    var = np.mean(residual ** 2, axis=0) * (3 * n / (3 * n - 6)) / gaussian_kept_fraction(CLIP_SIGMA)
    sigma = np.nan_to_num(noise.sigma_mm)
    row_sigma = np.broadcast_to(sigma, (len(dt), 3))
    if noise.short_sigma_mm is not None and noise.dt_s.size:  # velocities across one interval
        row_sigma = np.where((dt < 1.5 * noise.dt_s[0])[:, None], np.nan_to_num(noise.short_sigma_mm), row_sigma)
    noise_var = np.mean(2 * row_sigma ** 2 / dt[:, None] ** 2, axis=0)
    bend = noise.bend_factor(dt)
    true_var = (var - noise_var) / np.where(bend > 0.2, bend, 1.0)
    sigma_err = np.nan_to_num(noise.sigma_err_mm)
    var_err = np.sqrt((var * np.sqrt(2.0 / max(n - 6, 1))) ** 2
                      + (np.mean(4 * sigma[None, :] * sigma_err[None, :] / dt[:, None] ** 2, axis=0)) ** 2)
    factor = ev_per_mm2_s2(mass_kg)
    rms = np.sqrt(np.maximum(true_var, 0.0))
    # d(sqrt(v)) = dv / (2 sqrt(v)), but no larger than sqrt(dv) where v is near zero.
    rms_err = np.minimum(var_err / (2 * np.maximum(rms, 1e-12)), np.sqrt(var_err))
    return ShotTemperature(n, coef[:3], coef[3:], rms, rms_err, factor * true_var, factor * var_err)


def _rigid_fit(r: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``v = u + omega x (r - centre)`` by linear least squares: ``(u, omega)`` and the residuals."""
    n = len(r)
    rel = r - r.mean(axis=0)
    design = np.zeros((3 * n, 6))
    for a in range(3):
        design[a::3, a] = 1.0
    design[0::3, 4], design[0::3, 5] = rel[:, 2], -rel[:, 1]
    design[1::3, 3], design[1::3, 5] = -rel[:, 2], rel[:, 0]
    design[2::3, 3], design[2::3, 4] = rel[:, 1], -rel[:, 0]
    coef, *_ = np.linalg.lstsq(design, v.reshape(-1), rcond=None)
    return coef, (v.reshape(-1) - design @ coef).reshape(n, 3)
