"""Fitting a target calibration: polynomial against physical, judged on held-back positions.

The target's dots, identified in each exposure (:mod:`analysis.camera.dot_grid`), give pairs of
where the pipeline saw them (``sx, sy, alpha``) and where they were (row and column times the pitch,
and the stage position). :func:`fit_target_mapping` fits both mappings of
:mod:`analysis.camera.target_mapping` to them, holds back each inner stage position in turn
(predicting it from the others, as the calibration will be used between positions), keeps the
mapping whose held-back predictions were best, and fits it again to every position. Each dot is
weighted by its position's scatter and by the error all dots of that position share
(:func:`with_shared_error`).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from analysis.errors import ParameterError, PositionMismatchError
from .front_optics import FrontOptics
from .target_mapping import (CalibratedVolume, CameraKey, Mapping3D, MetricCalibration, PhysicalMapping,
                             PolynomialMapping, polynomial_terms)

#: Soloff et al. used cubic terms across the image and quadratic ones in depth.
LATERAL_DEGREE = 3
ALPHA_DEGREE = 2
#: Fewest stage positions: two to fit depth, one more to hold back.
MIN_POSITIONS = 3
#: Dots farther than this many robust sigmas from a first polynomial fit are dropped as misfound.
OUTLIER_SIGMAS = 6.0
#: Noise estimates are at least this fraction of the median over positions (no position dominates).
NOISE_FLOOR = 0.25
#: Rounds of fitting a mapping and widening each stage position's noise by the error its dots share
#: (:func:`with_shared_error`).
SHARED_ERROR_ROUNDS = 3
#: Starting points of the physical fit: auxiliary lens powers (1/mm) and distances (fractions of
#: the target's distance).
_POWER_STARTS = (0.0, 1 / 600, 1 / 300, 1 / 175, 1 / 120, -1 / 300)
_DISTANCE_STARTS = (0.15, 0.45)
#: The starting points are compared on about this many dots.
_START_DOTS = 150


@dataclass(frozen=True)
class TargetObservations:
    """Every identified dot of a target's exposures.

    Attributes
    ----------
    sx_m, sy_m, alpha : ndarray of shape (n,)
        Where the pipeline found the dot (lens plane, metres; refocus parameter).
    world_mm : ndarray of shape (n, 3)
        Where it was, in the target's frame (``X, Y`` on the plate, ``Z`` the stage position).
    position : ndarray of int, shape (n,)
        Index of its stage position in ``positions_mm``.
    positions_mm : ndarray of shape (p,)
    sigma_mm : ndarray of shape (n, 3), optional
        Measurement noise of each coordinate (:func:`noise_per_position`); the fits weight by its
        inverse. None: equal weights.
    """

    sx_m: np.ndarray
    sy_m: np.ndarray
    alpha: np.ndarray
    world_mm: np.ndarray
    position: np.ndarray
    positions_mm: np.ndarray
    sigma_mm: np.ndarray | None = None

    def take(self, keep: np.ndarray) -> "TargetObservations":
        return TargetObservations(self.sx_m[keep], self.sy_m[keep], self.alpha[keep], self.world_mm[keep],
                                  self.position[keep], self.positions_mm,
                                  None if self.sigma_mm is None else self.sigma_mm[keep])

    def weights(self) -> np.ndarray:
        """``1 / sigma`` per coordinate (n, 3); ones without noise estimates."""
        return np.ones((len(self), 3)) if self.sigma_mm is None else 1.0 / self.sigma_mm

    def __len__(self) -> int:
        return int(self.sx_m.size)


@dataclass(frozen=True)
class MainLens:
    """The main lens as calibrated (the metadata's thin lens) and the field that distortion refers to."""

    focal_length_mm: float
    lens_to_mla_mm: float
    reference_tan: float


def fit_polynomial(obs: TargetObservations, *, lateral_degree: int = LATERAL_DEGREE,
                   alpha_degree: int = ALPHA_DEGREE) -> PolynomialMapping:
    """Least-squares polynomial mapping (:class:`PolynomialMapping`) through the observations."""
    alpha_degree = min(alpha_degree, np.unique(obs.position).size - 1)
    scale = float(np.max(np.hypot(obs.sx_m, obs.sy_m))) or 1.0
    lo, hi = float(np.min(obs.alpha)), float(np.max(obs.alpha))
    empty = np.zeros((len(polynomial_terms(lateral_degree, alpha_degree)), 3))
    mapping = PolynomialMapping(lateral_degree, alpha_degree, scale, 0.5 * (lo + hi), max(0.5 * (hi - lo), 1e-6),
                                empty)
    design = mapping.design(obs.sx_m, obs.sy_m, obs.alpha)
    w = obs.weights()
    coef = np.column_stack([np.linalg.lstsq(design * w[:, a:a + 1], obs.world_mm[:, a] * w[:, a], rcond=None)[0]
                            for a in range(3)])
    return PolynomialMapping(lateral_degree, alpha_degree, scale, mapping.alpha_centre, mapping.alpha_scale, coef)


def _physical(params: np.ndarray, lens: MainLens) -> PhysicalMapping:
    front = FrontOptics(aux_power_per_mm=params[0] * 1e-3, aux_distance_mm=max(params[1] * 10.0, 0.0),
                        k1=params[2] * 0.1, k2=params[3] * 0.1, reference_tan=lens.reference_tan)
    return PhysicalMapping(lens.focal_length_mm, lens.lens_to_mla_mm, front, rotation=tuple(params[4:7]),
                           origin_mm=tuple(params[7:10]), stage_slope=tuple(params[10:12]))


def _vector(mapping: PhysicalMapping) -> np.ndarray:
    f = mapping.front
    return np.r_[f.aux_power_per_mm * 1e3, f.aux_distance_mm / 10.0, f.k1 * 10.0, f.k2 * 10.0,
                 mapping.rotation, mapping.origin_mm, mapping.stage_slope]


def _frame_start(obs: TargetObservations, lens: MainLens, power: float, distance: float) -> np.ndarray | None:
    """Parameters with the target's frame fitted linearly to the camera points that the optics
    ``(power, distance)`` give: ``c = origin + X u + Y v + Z d``."""
    start = np.r_[power * 1e3, distance / 10.0, 0.0, 0.0, np.zeros(8)]
    c = np.stack(_physical(start, lens).camera_points(obs.sx_m, obs.sy_m, obs.alpha), axis=1)
    if not np.all(np.isfinite(c)):
        return None
    n = len(obs)
    design = np.zeros((3 * n, 12))
    for axis in range(3):
        rows = slice(axis, 3 * n, 3)
        design[rows, axis] = 1.0
        for q in range(3):
            design[rows, 3 + 3 * q + axis] = obs.world_mm[:, q]
    sol, *_ = np.linalg.lstsq(design, c.ravel(), rcond=None)
    origin, u, v, d = sol[:3], sol[3:6], sol[6:9], sol[9:12]
    if not (abs(d[2]) > 1e-9 and np.linalg.norm(u) > 0 and np.linalg.norm(v) > 0):
        return None
    basis = np.column_stack([u, v, np.cross(u, v)])
    w, _, vt = np.linalg.svd(basis)
    rot = w @ vt
    if np.linalg.det(rot) < 0:
        return None
    start[4:7] = Rotation.from_matrix(rot).as_rotvec()
    start[7:10] = origin
    start[10:12] = d[:2] / d[2]
    return start


def fit_physical(obs: TargetObservations, lens: MainLens, *, start: PhysicalMapping | None = None,
                 front_guess: FrontOptics | None = None) -> PhysicalMapping:
    """The physical mapping (:class:`PhysicalMapping`) of least squared error in the target frame.

    Parameters
    ----------
    obs : TargetObservations
    lens : MainLens
    start : PhysicalMapping, optional
        Start from this mapping only (e.g. the fit to every position, when holding one back).
    front_guess : FrontOptics, optional
        An auxiliary lens the user knows of, tried first among the starting points.
    """
    if start is not None:
        return _least_squares(obs, lens, [_vector(start)])
    distance = float(np.median(obs.world_mm[:, 2]))
    candidates = [(p, f * distance) for p in _POWER_STARTS for f in _DISTANCE_STARTS]
    if front_guess is not None:
        candidates.insert(0, (front_guess.aux_power_per_mm, front_guess.aux_distance_mm))
    starts = [s for s in (_frame_start(obs, lens, p, d) for p, d in candidates) if s is not None]
    if not starts:
        starts = [np.zeros(12)]
    # The many starting points on every few dots; the best of them on all of them.
    thin = obs.take(np.arange(0, len(obs), max(1, len(obs) // _START_DOTS)))
    return _least_squares(obs, lens, [_vector(_least_squares(thin, lens, starts))])


def _least_squares(obs: TargetObservations, lens: MainLens, starts: list[np.ndarray]) -> PhysicalMapping:
    """The best of least-squares fits from each of ``starts``, weighted by the dots' noise."""
    w = obs.weights() / np.median(obs.weights(), axis=0)

    def residual(params: np.ndarray) -> np.ndarray:
        try:
            pred = np.stack(_physical(params, lens)(obs.sx_m, obs.sy_m, obs.alpha), axis=1)
        except (np.linalg.LinAlgError, ParameterError):  # a step beyond what the optics allow
            return np.full(3 * len(obs), 1e3)
        return (np.nan_to_num(pred - obs.world_mm, nan=1e3, posinf=1e3, neginf=-1e3) * w).ravel()

    best = None
    for params in starts:
        sol = least_squares(residual, params, x_scale="jac", max_nfev=400, method="lm")
        if best is None or sol.cost < best.cost:
            best = sol
    return _physical(best.x, lens)


def predict(mapping: Mapping3D, obs: TargetObservations) -> np.ndarray:
    """Predicted target-frame positions of the observed dots: (n, 3), mm."""
    return np.stack(mapping(obs.sx_m, obs.sy_m, obs.alpha), axis=1)


def residual_table(mapping: Mapping3D, obs: TargetObservations) -> list[dict]:
    """RMS error per stage position and axis, in micrometres."""
    err = (predict(mapping, obs) - obs.world_mm) * 1e3
    out = []
    for k in np.unique(obs.position):
        sel = obs.position == k
        rms = np.sqrt(np.nanmean(err[sel] ** 2, axis=0))
        out.append({"position_mm": float(obs.positions_mm[k]), "dots": int(sel.sum()),
                    "rms_um": {axis: float(rms[a]) for a, axis in enumerate("XYZ")}})
    return out


def _rms(err_um: np.ndarray) -> dict[str, float]:
    rms = np.sqrt(np.nanmean(err_um ** 2, axis=0))
    return {"X": float(rms[0]), "Y": float(rms[1]), "Z": float(rms[2]),
            "3d": float(np.sqrt(np.nanmean(np.sum(err_um ** 2, axis=1))))}


def drop_outliers(obs: TargetObservations) -> tuple[TargetObservations, int]:
    """The observations without dots a polynomial fit through all of them cannot explain
    (misfound or misidentified), and how many were dropped."""
    keep = np.ones(len(obs), dtype=bool)
    for _ in range(3):
        fit = fit_polynomial(obs.take(keep))
        err = np.linalg.norm(predict(fit, obs) - obs.world_mm, axis=1)
        sigma = 1.4826 * float(np.median(err[keep])) + 1e-6
        new = err <= OUTLIER_SIGMAS * sigma
        if np.array_equal(new, keep):
            break
        keep = new
    return obs.take(keep), int((~keep).sum())


def noise_per_position(obs: TargetObservations, *, floor: float = NOISE_FLOOR) -> TargetObservations:
    """The observations with each coordinate's measurement noise: the scatter, per stage position and
    axis, of the dots about a flexible fit (its mean offset at that position taken off), at least
    ``floor`` times the median over positions.

    Dots near focus are placed on their micro-lens only (coarse across, sharp in depth where their
    neighbours' plane pins it); strongly blurred ones the other way round: weighting by the noise
    lets each position count for what it measures well.
    """
    fit = fit_polynomial(obs)
    err = predict(fit, obs) - obs.world_mm
    sigma = np.empty((np.max(obs.position) + 1, 3))
    for k in np.unique(obs.position):
        sel = obs.position == k
        sigma[k] = np.sqrt(np.mean((err[sel] - err[sel].mean(axis=0)) ** 2, axis=0)) if sel.sum() > 1 else np.nan
    present = np.unique(obs.position)
    median = np.nanmedian(sigma[present], axis=0)
    sigma = np.where(np.isfinite(sigma), np.maximum(sigma, floor * median), median)
    sigma = np.maximum(sigma, 1e-6)
    return dataclasses.replace(obs, sigma_mm=sigma[obs.position])


def with_shared_error(obs: TargetObservations, mapping: Mapping3D) -> TargetObservations:
    """The observations with each coordinate's noise widened by the error its dots share with the
    others of their stage position: ``sqrt(sigma^2 + n tau^2)``, where ``sigma`` is ``obs``'s noise
    (:func:`noise_per_position`), ``n`` the position's dots and ``tau`` their mean misfit to
    ``mapping`` beyond what ``sigma`` explains.

    The depth fit's errors depend on how far out of focus a dot is, so all dots of a stage position
    share one: strongly blurred dots are measured nearer focus, by about 1.5e-4 in alpha (20-30 um)
    15 lens pitches out. Such a position tells the mapping one thing, however many dots it has;
    weighting its dots as independent lets it bend the mapping at the positions that agree.
    """
    if obs.sigma_mm is None:
        obs = noise_per_position(obs)
    err = predict(mapping, obs) - obs.world_mm
    sigma = obs.sigma_mm.copy()
    for k in np.unique(obs.position):
        sel = obs.position == k
        n = int(sel.sum())
        noise2 = np.mean(obs.sigma_mm[sel] ** 2, axis=0)
        shared2 = np.maximum(np.nanmean(err[sel], axis=0) ** 2 - noise2 / n, 0.0)
        sigma[sel] = np.sqrt(obs.sigma_mm[sel] ** 2 + n * shared2)
    return dataclasses.replace(obs, sigma_mm=sigma)


def _fit_kind(obs: TargetObservations, kind: str, lens: MainLens | None, front_guess: FrontOptics | None,
              start: Mapping3D | None = None) -> Mapping3D:
    if kind == "polynomial":
        return fit_polynomial(obs)
    return fit_physical(obs, lens, start=start, front_guess=front_guess)  # type: ignore[arg-type]


def _fit_weighted(obs: TargetObservations, kind: str, lens: MainLens | None,
                  front_guess: FrontOptics | None) -> tuple[Mapping3D, TargetObservations]:
    """A mapping of ``kind`` fitted with each position's shared error in its weights
    (:data:`SHARED_ERROR_ROUNDS` rounds), and the observations with those weights."""
    mapping = _fit_kind(obs, kind, lens, front_guess)
    weighted = obs
    for _ in range(SHARED_ERROR_ROUNDS):
        weighted = with_shared_error(obs, mapping)
        mapping = _fit_kind(weighted, kind, lens, front_guess, start=mapping)
    return mapping, weighted


def fit_target_mapping(obs: TargetObservations, lens: MainLens | None, *, front_guess: FrontOptics | None = None
                       ) -> tuple[Mapping3D, dict[str, Mapping3D], dict]:
    """Fit both mappings, compare them on held-back positions, keep the better.

    Each inner stage position (never the nearest or the farthest: the calibration is meant to be
    used between them) is held back in turn; each mapping is fitted to the others and predicts it.
    Without a main lens (metadata with no usable exit-pupil distance) only the polynomial is fitted.

    Returns
    -------
    best : mapping
        The one with the smallest 3D RMS error on held-back positions, fitted to every position.
    fitted : dict
        Both mappings, fitted to every position, by kind.
    report : dict
        ``comparison`` (per kind: held-back RMS per axis, ``held_out`` per position), ``residuals``
        (``fit`` and ``held_out`` per position of the chosen mapping), ``outliers`` dropped.

    Raises
    ------
    PositionMismatchError
        With fewer than :data:`MIN_POSITIONS` stage positions holding dots.
    """
    positions = np.unique(obs.position)
    if positions.size < MIN_POSITIONS:
        raise PositionMismatchError(f"dots were found at {positions.size} stage position(s); a target calibration "
                                    f"needs at least {MIN_POSITIONS} (two to fit depth, one more to check it): "
                                    "image the target at more positions across the volume")
    obs, outliers = drop_outliers(obs)
    obs = noise_per_position(obs)
    order = positions[np.argsort(obs.positions_mm[positions])]
    fitted: dict[str, Mapping3D] = {}
    weighted: dict[str, TargetObservations] = {}
    for kind in ("polynomial",) if lens is None else ("polynomial", "physical"):
        fitted[kind], weighted[kind] = _fit_weighted(obs, kind, lens, front_guess)
    comparison: dict[str, dict] = {}
    for kind, full in fitted.items():
        errors, per_position = [], []
        for k in order[1:-1]:
            train, test = weighted[kind].take(obs.position != k), obs.take(obs.position == k)
            mapping = _fit_kind(train, kind, lens, front_guess, start=full)
            err = (predict(mapping, test) - test.world_mm) * 1e3
            errors.append(err)
            per_position.append({"position_mm": float(obs.positions_mm[k]), "dots": int(len(test)),
                                 "rms_um": {a: v for a, v in _rms(err).items() if a != "3d"}})
        comparison[kind] = {"mapping": full.name, "held_out_rms_um": _rms(np.concatenate(errors)),
                            "held_out": per_position, "fit_rms_um": _rms((predict(full, obs) - obs.world_mm) * 1e3)}
    best_kind = min(comparison, key=lambda kind: comparison[kind]["held_out_rms_um"]["3d"])
    best = fitted[best_kind]
    report = {"chosen": best_kind, "comparison": comparison, "outliers": outliers,
              "residuals": {"fit": residual_table(best, obs), "held_out": comparison[best_kind]["held_out"]},
              "field_of_view_mm": float(np.ptp(obs.world_mm[:, 0])) if len(obs) else math.nan,
              "depth_range_mm": float(np.ptp(obs.positions_mm))}
    return best, fitted, report


def metric_calibration(obs: TargetObservations, lens: MainLens | None, camera: CameraKey, *, margin_mm: float,
                       front_guess: FrontOptics | None = None, white_sha1: str | None = None,
                       created_utc: str = "") -> MetricCalibration:
    """The :class:`MetricCalibration` of a target's observations: the better mapping
    (:func:`fit_target_mapping`), the volume the dots covered (widened by ``margin_mm``), the report."""
    best, fitted, report = fit_target_mapping(obs, lens, front_guess=front_guess)
    world = obs.world_mm
    volume = CalibratedVolume(x_mm=(float(world[:, 0].min()), float(world[:, 0].max())),
                              y_mm=(float(world[:, 1].min()), float(world[:, 1].max())),
                              z_mm=(float(world[:, 2].min()), float(world[:, 2].max())),
                              alpha=(float(obs.alpha.min()), float(obs.alpha.max())), margin_mm=float(margin_mm))
    return MetricCalibration(mapping=best, camera=camera, volume=volume, alternatives=fitted, report=report,
                             white_sha1=white_sha1, created_utc=created_utc)
