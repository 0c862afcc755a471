"""A metric calibration from a dot target imaged at known stage positions.

The target's dots are found with the same pipeline as particles (:func:`process`), each
exposure's grid is identified (:mod:`analysis.camera.dot_grid`) and labelled alike across
positions, and the mapping ``(sx, sy, alpha) -> (X, Y, Z)`` is fitted (:mod:`analysis.camera.mapping_fit`):
a polynomial and a physical model compete on held-back positions.

Example (from a notebook)::

    calibration = load_calibration("calibration/", first.metadata, serial=first.serial)
    metric = calibrate_target(["IMG_0001.lfp", ...], calibration, positions_mm=[48.5, 50.5, ...],
                              pitch_mm=1.0)
    save_metric_calibration(metric, "metric.json")        # analysis.calibration.metric_files
    result = process(exposure, calibration, coordinates=metric)
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import logging
import math
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from analysis.cache import Cache
from analysis.calibration.calibrate import Calibration
from analysis.calibration.metric_files import camera_key
from analysis.camera.dot_grid import DotGrid, align_grids, identify_grid
from analysis.camera.front_optics import FrontOptics, sensor_reference_tan
from analysis.camera.mapping_fit import MainLens, TargetObservations, metric_calibration
from analysis.camera.model import CameraModel
from analysis.camera.target_mapping import MetricCalibration
from analysis.errors import CameraMismatchError, PositionMismatchError, TargetOutOfRangeError
from analysis.formats.exposure import Exposure, read_exposure

from .depth_range import SURVEY_BLUR_PITCHES
from .params import PipelineParams
from .process import process
from .result import Result

log = logging.getLogger(__name__)

#: How a target is processed: no particle hides behind another on a plate, so neither hidden
#: particles nor a second detection pass are looked for; nor faint blurred ones the first passes
#: missed (the late pass): a target's dots are alike and bright (the same dots on three targets
#: without it, 1.1-1.4x faster).
TARGET_PARAMS = PipelineParams(shadow_probe=0.0, passes=1, late_pass=False)
#: A target's dots are alike: detections fainter than this fraction of the median dot are the
#: left-over light of strongly blurred neighbours, not dots.
DOT_INTENSITY_FRACTION = 0.4


@dataclasses.dataclass(frozen=True)
class TargetDots:
    """The dots found in one exposure of the target.

    Attributes
    ----------
    name, sha1 : str or None
    position_mm : float
    sx_m, sy_m, alpha, intensity : ndarray of shape (n,)
        Every dot the pipeline found (lens plane, metres; refocus parameter; fitted intensity).
    grid : DotGrid or None
        Rows and columns of the dots that lie on the target's grid.
    warnings : list of str
    """

    name: str | None
    sha1: str | None
    position_mm: float
    sx_m: np.ndarray
    sy_m: np.ndarray
    alpha: np.ndarray
    intensity: np.ndarray
    grid: DotGrid | None = None
    warnings: tuple[str, ...] = ()

    @property
    def points_mm(self) -> np.ndarray:
        return np.column_stack([self.sx_m, self.sy_m]) * 1e3


def find_dots(exposure: Exposure, calibration: Calibration, position_mm: float, *,
              params: PipelineParams = TARGET_PARAMS, cache: Cache | None = None) -> TargetDots:
    """The target's dots in one exposure, its grid identified (rows, columns; (0, 0) nearest the axis).

    Raises
    ------
    TargetOutOfRangeError
        When no dot is found, or the dots lie at the edge of the range the pipeline refocuses over.
    TooFewDotsError, GridIdentificationError
        From :func:`analysis.camera.dot_grid.identify_grid`.
    """
    result = process(exposure, calibration, params, cache=cache)
    name = exposure.name or exposure.sha1
    if len(result) == 0:
        raise TargetOutOfRangeError(
            f"no dots found in {name} (stage position {position_mm} mm): the target lies outside the range the "
            f"camera refocuses to ({_reach(result)}), or is not lit; move it nearer the plane in focus. "
            f"Pipeline: {'; '.join(result.warnings) or 'nothing above the noise'}")
    dots = _dots_of(result, position_mm)
    blur = float(np.median(result.particles["blur_pitches"]))
    if blur > 2 * SURVEY_BLUR_PITCHES * 0.9:
        raise TargetOutOfRangeError(
            f"the dots of {name} (stage position {position_mm} mm) are blurred over {blur:.0f} lens pitches, at the "
            f"edge of the range the camera refocuses to ({_reach(result)}): move the target nearer the plane in "
            "focus, or span a smaller depth")
    grid = identify_grid(dots.points_mm, brightness=dots.intensity)
    return dataclasses.replace(dots, grid=grid)


def _reach(result: Result) -> str:
    return f"blur up to {2 * SURVEY_BLUR_PITCHES:.0f} lens pitches either side of focus"


def _dots_of(result: Result, position_mm: float) -> TargetDots:
    p = result.particles
    intensity = np.asarray(p["intensity"], dtype=np.float64)
    if not np.isfinite(intensity).any():
        intensity = np.asarray(p["brightness"], dtype=np.float64)
    keep = np.isfinite(intensity) & (intensity >= DOT_INTENSITY_FRACTION * np.nanmedian(intensity))
    sx, sy = result.grid.to_lens_plane(p["x"][keep], p["y"][keep])
    return TargetDots(result.exposure_name, result.exposure_sha1, float(position_mm), np.asarray(sx),
                      np.asarray(sy), np.asarray(p["alpha"][keep], float), intensity[keep],
                      warnings=tuple(result.warnings))


def calibrate_target(exposures: Sequence[Exposure | str | Path], calibration: Calibration | Callable[[Exposure], Calibration],
                     positions_mm: Sequence[float], pitch_mm: float, *, params: PipelineParams = TARGET_PARAMS,
                     cache: Cache | None = None, front_guess: FrontOptics | None = None,
                     progress: Callable[[str], None] | None = None) -> MetricCalibration:
    """Fit a metric calibration to a dot target imaged at known stage positions.

    Parameters
    ----------
    exposures : sequence of Exposure or paths
        One exposure per stage position, in the order of ``positions_mm``.
    calibration : Calibration, or a callable giving an exposure's
        The camera's white-image calibration (as for :func:`process`).
    positions_mm : sequence of float
        The stage position of each exposure (mm). The calibration's ``Z`` is in these units and
        their zero: distances from the main lens give camera-frame depths.
    pitch_mm : float
        Distance between neighbouring dots of the target.
    params : PipelineParams
        How the dots are found (default :data:`TARGET_PARAMS`).
    cache : Cache, optional
    front_guess : FrontOptics, optional
        An auxiliary lens the user knows of: a starting point for the physical model.
    progress : callable, optional
        Called with a line of text as each exposure is done.

    Returns
    -------
    MetricCalibration

    Raises
    ------
    PositionMismatchError
        Positions that do not match the exposures (count, order of depth, repeats).
    TargetOutOfRangeError, TooFewDotsError, GridIdentificationError
        For an exposure whose dots cannot be used; the message names it.
    CameraMismatchError
        Exposures of different cameras or lens settings.
    """
    say = progress or (lambda line: log.info("%s", line))
    positions = np.asarray([float(z) for z in positions_mm], dtype=np.float64)
    if len(exposures) != positions.size:
        raise PositionMismatchError(f"{len(exposures)} exposures but {positions.size} stage positions: give one "
                                    "position per exposure, in the same order")
    if np.unique(positions).size != positions.size or not np.all(np.isfinite(positions)):
        raise PositionMismatchError(f"stage positions {positions.tolist()} repeat or are not numbers: give each "
                                    "exposure's own position")
    if not (math.isfinite(pitch_mm) and pitch_mm > 0):
        raise PositionMismatchError(f"the dot pitch must be a positive number of mm, got {pitch_mm}")
    cache = Cache() if cache is None else cache
    found: list[TargetDots] = []
    key = None
    first: Exposure | None = None
    for item, z in zip(exposures, positions):
        exposure = item if isinstance(item, Exposure) else read_exposure(item)
        this_key = camera_key(exposure.metadata, exposure.serial)
        if key is not None and this_key != key:
            raise CameraMismatchError(f"the target's exposures come from {key.describe()} and {this_key.describe()}: "
                                      "a calibration holds for one camera, zoom and focus; image the target at one")
        key, first = this_key, first or exposure
        cal = calibration(exposure) if callable(calibration) else calibration
        dots = find_dots(exposure, cal, float(z), params=params, cache=cache)
        found.append(dots)
        say(f"{dots.name}: {len(dots.sx_m)} dots found, {len(dots.grid)} on the grid, stage position {z} mm")
    order = np.argsort(positions)
    _check_depth_order([found[k] for k in order])
    aligned = align_grids([found[k].points_mm for k in order], [found[k].grid for k in order])
    obs = _observations([found[k] for k in order], aligned, pitch_mm)
    model = CameraModel.from_metadata(first.metadata)
    lens = _main_lens(model)
    cal0 = calibration(first) if callable(calibration) else calibration
    metric = metric_calibration(obs, lens, key, margin_mm=0.5 * pitch_mm, front_guess=front_guess,
                                white_sha1=cal0.white_sha1,
                                created_utc=dt.datetime.now(dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"))
    metric.report["target"] = {
        "pitch_mm": float(pitch_mm), "positions_mm": positions.tolist(), "pipeline": params.to_dict(),
        "exposures": [{"name": d.name, "sha1": d.sha1, "position_mm": d.position_mm, "dots_found": int(d.sx_m.size),
                       "dots_on_grid": len(g), "rows": [int(g.rows.min()), int(g.rows.max())],
                       "cols": [int(g.cols.min()), int(g.cols.max())], "median_alpha": float(np.median(d.alpha)),
                       "warnings": list(d.warnings)}
                      for d, g in zip([found[k] for k in order], aligned)]}
    return metric


def _check_depth_order(found: list[TargetDots]) -> None:
    """The dots' alphas must fall as the stage position (sorted ascending) grows: farther is larger."""
    medians = np.array([float(np.median(d.alpha)) for d in found])
    steps = np.diff(medians)
    if steps.size and not np.all(steps < 0):
        listing = ", ".join(f"{d.name} at {d.position_mm} mm: alpha {m:.4f}" for d, m in zip(found, medians))
        hint = ("the positions grow toward the camera: give them as distances (larger = farther), e.g. the stage "
                "readings negated" if np.all(steps > 0) else "list the positions in the order of the exposures")
        raise PositionMismatchError(
            f"the target's depth in the exposures does not follow the stage positions ({listing}); a farther "
            f"target focuses at a smaller alpha: {hint}")


def _observations(found: list[TargetDots], grids: list[DotGrid], pitch_mm: float) -> TargetObservations:
    sx, sy, alpha, world, position = [], [], [], [], []
    for k, (dots, grid) in enumerate(zip(found, grids)):
        sx.append(dots.sx_m[grid.index])
        sy.append(dots.sy_m[grid.index])
        alpha.append(dots.alpha[grid.index])
        world.append(np.column_stack([grid.cols * pitch_mm, grid.rows * pitch_mm,
                                      np.full(len(grid), dots.position_mm)]))
        position.append(np.full(len(grid), k, dtype=np.int64))
    return TargetObservations(np.concatenate(sx), np.concatenate(sy), np.concatenate(alpha), np.vstack(world),
                              np.concatenate(position), np.array([d.position_mm for d in found]))


def _main_lens(model: CameraModel) -> MainLens | None:
    optics = model.optics
    if optics.exit_pupil_m is None:
        return None  # no thin lens to start a physical model from: the polynomial alone
    return MainLens(focal_length_mm=optics.focal_length_m * 1e3, lens_to_mla_mm=optics.exit_pupil_m * 1e3,
                    reference_tan=sensor_reference_tan(model.width, model.height, optics.pixel_pitch_m,
                                                       optics.exit_pupil_m))
