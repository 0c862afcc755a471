"""What a pipeline job hands back to the service: plain arrays, picklable across processes."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class JobTask:
    """Everything a worker needs to process one exposure (paths on a shared file system).

    Attributes
    ----------
    exposure_id : str
        SHA-1 of the stored exposure.
    raw_paths : tuple of str
        The ``.lfp`` file, or the ``.RAW`` and ``.TXT`` pair.
    calibration_dir : str or None
        Folder of white images for the exposure's camera.
    calibration_cache_dir : str or None
        Where the calibration may be cached between jobs.
    metric_calibration_dir : str or None
        Folder of target calibrations; the one of the exposure's camera, zoom and focus gives X, Y, Z.
    parameters : dict or None
        Pipeline parameters (fields of ``PipelineParams``); None for the defaults.
    keep_slices : bool
        Whether to return refocused slices for the dashboard.
    """

    exposure_id: str
    raw_paths: tuple[str, ...]
    calibration_dir: str | None = None
    calibration_cache_dir: str | None = None
    metric_calibration_dir: str | None = None
    parameters: dict | None = None
    keep_slices: bool = False


@dataclass
class JobOutput:
    """A processed exposure.

    Attributes
    ----------
    columns : dict of str to ndarray
        The particle table, one 1-D array of length N per column, in table order.
    parameters : dict
        The pipeline parameters used (stored with every result).
    curve_alpha : ndarray of shape (A,) or None
        The ``alpha`` of each refocused slice.
    curves : ndarray of shape (N, A) or None
        Brightness ``B_i(alpha)`` of each particle.
    slices : ndarray of shape (K, H, W), uint8, or None
        Refocused slices scaled to 8 bits for viewing.
    slice_alpha : ndarray of shape (K,) or None
        The ``alpha`` of each kept slice.
    slice_binning : int
        Output-image pixels per slice pixel along each axis (slices are shrunk for viewing).
    seconds : float
        Time the worker spent on the job.
    rejected : dict of str to ndarray
        Candidates that did not become particles, with the reason (``reason`` column).
    """

    columns: dict[str, np.ndarray]
    parameters: dict
    curve_alpha: np.ndarray | None = None
    curves: np.ndarray | None = None
    slices: np.ndarray | None = None
    slice_alpha: np.ndarray | None = None
    slice_binning: int = 1
    seconds: float = 0.0
    extra: dict = field(default_factory=dict)
    rejected: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def particles(self) -> int:
        if not self.columns:
            return 0
        return int(len(next(iter(self.columns.values()))))
