"""The work a worker process does for one job: read the exposure, calibrate, run the pipeline.

Runs in a pool process or on a Dask worker, so it takes and returns plain picklable
objects (:class:`JobTask`, :class:`JobOutput`) and imports the analysis lazily.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path

import numpy as np

from service.results import JobOutput, JobTask

log = logging.getLogger(__name__)

# Slices kept for the dashboard's viewer: all of them up to this many (every n-th beyond), so
# the viewer can show each particle at its own depth; shrunk to MAX_VIEW_SIDE they cost a few
# hundred kB per exposure.
MAX_VIEW_SLICES = 64
# Longest side of a kept slice, in pixels (the viewer does not need full resolution).
MAX_VIEW_SIDE = 512


def read_task_exposure(task: JobTask):
    """The :class:`analysis.formats.exposure.Exposure` a task points at."""
    from analysis.formats.exposure import exposure_from_lfp_bytes, exposure_from_raw_pair

    paths = [Path(p) for p in task.raw_paths]
    if len(paths) == 1:
        return exposure_from_lfp_bytes(paths[0].read_bytes(), name=paths[0].stem)
    raw = next(p for p in paths if p.suffix.upper() == ".RAW")
    txt = next(p for p in paths if p.suffix.upper() == ".TXT")
    return exposure_from_raw_pair(raw.read_bytes(), txt.read_bytes(), name=raw.stem)


def _calibration(calibration_dir: str | None, cache_dir: str | None, metadata: dict, serial: str | None):
    from analysis.calibration.cache import load_calibration
    from analysis.errors import NoWhiteImageError

    if calibration_dir is None:
        raise NoWhiteImageError(
            f"no white images for camera {serial or '(serial unknown)'}: connect the camera so the "
            "service pulls them, or upload them with POST /api/v1/calibrations")
    return load_calibration(calibration_dir, metadata, serial=serial, cache_dir=cache_dir)


def _coordinates(metric_dir: str | None, metadata: dict, serial: str | None):
    """The exposure's target calibration from the service's folder of them; None (the metadata's thin
    lens) while the folder holds none."""
    from analysis.calibration.metric_files import coordinates_for

    if metric_dir is None or not any(Path(metric_dir).glob("*/*.json")):
        return None
    return coordinates_for(metric_dir, metadata, serial=serial)


def _params(parameters: dict | None):
    from analysis.pipeline.params import PipelineParams

    return PipelineParams.from_dict(parameters) if parameters else PipelineParams()


def _view_slices(stack: np.ndarray, alphas: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    # A few slices, shrunk and scaled to 8 bits with one common scale so brightness
    # compares between slices.
    step = max(1, int(np.ceil(stack.shape[0] / MAX_VIEW_SLICES)))
    picked = np.arange(0, stack.shape[0], step)
    sub = np.asarray(stack[picked], dtype=np.float32)
    shrink = max(1, int(np.ceil(max(sub.shape[1:]) / MAX_VIEW_SIDE)))
    if shrink > 1:
        h, w = (sub.shape[1] // shrink) * shrink, (sub.shape[2] // shrink) * shrink
        sub = sub[:, :h, :w].reshape(sub.shape[0], h // shrink, shrink, w // shrink, shrink).mean(axis=(2, 4))
    top = float(np.percentile(sub, 99.9)) if sub.size else 0.0
    scaled = np.clip(sub / top * 255.0, 0, 255) if top > 0 else np.zeros_like(sub)
    return scaled.astype(np.uint8), np.asarray(alphas, dtype=np.float64)[picked], shrink


def _worker_cache(directory: Path | None):
    """This worker process's cache of look-up tables (kept across its jobs)."""
    from analysis.cache import Cache

    global _cache
    if _cache is None or _cache.directory != directory:
        _cache = Cache(directory=directory)
    return _cache


_cache = None


def run_task(task: JobTask, progress: Callable[[float, str], None] | None = None) -> JobOutput:
    """Process one exposure and return its particle table and what the dashboard shows.

    Raises
    ------
    analysis.errors.AnalysisError
        For an input the pipeline cannot use (bad file, no white image, ...).
    """
    from analysis.pipeline.process import process

    start = time.perf_counter()
    exposure = read_task_exposure(task)
    calibration = _calibration(task.calibration_dir, task.calibration_cache_dir, exposure.metadata,
                               exposure.serial)
    params = _params(task.parameters)
    cache_dir = Path(task.calibration_cache_dir) if task.calibration_cache_dir else None
    # progress(fraction, stage): the fraction weighted by the stages' cost, and the stage's name.
    report = progress
    coordinates = _coordinates(task.metric_calibration_dir, exposure.metadata, exposure.serial)
    result = process(exposure, calibration, params, keep_stack=task.keep_slices, progress=report,
                     cache=_worker_cache(cache_dir), coordinates=coordinates)
    output = JobOutput(columns={name: np.asarray(col) for name, col in result.particles.items()},
                       parameters=result.params.to_dict(), rejected=dict(result.rejected))
    provenance = result.metadata()
    provenance.pop("alphas", None)
    output.extra["provenance"] = provenance
    if result.curves is not None:
        output.curves = np.asarray(result.curves, dtype=np.float32)
        output.curve_alpha = np.asarray(result.alphas, dtype=np.float64)
    if task.keep_slices and result.stack is not None:
        output.slices, output.slice_alpha, output.slice_binning = _view_slices(np.asarray(result.stack),
                                                                               np.asarray(result.alphas))
    output.seconds = time.perf_counter() - start
    return output


@lru_cache(maxsize=1)
def warm_up() -> float:
    """Import the analysis and compile its kernels once per process; returns seconds taken."""
    from analysis.pipeline.process import warm_up as compile_pipeline

    start = time.perf_counter()
    compile_pipeline()
    return time.perf_counter() - start
