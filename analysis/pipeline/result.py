"""What :func:`analysis.pipeline.process.process` returns: the particle table of one exposure,
with everything needed to reproduce and inspect it."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from analysis.camera.image_grid import ImageGrid
from analysis.formats.particle_table import COLUMNS, combine, write_csv, write_hdf5

from .params import PipelineParams

if TYPE_CHECKING:
    import pandas as pd


@dataclass
class Result:
    """The particles of one exposure, with everything needed to reproduce and inspect them.

    Attributes
    ----------
    particles : dict of str to ndarray
        The particle table by column (:data:`COLUMNS`): ``index`` (0..n-1, by image position; a
        trajectory id, trackpy's ``particle``, comes with linking: :mod:`analysis.tracking`), ``x, y``
        (output-image pixels, integer values at pixel centres), ``alpha``, ``X, Y, Z`` (mm,
        camera frame; NaN without a usable depth model), ``brightness`` (mean intensity per
        pixel in the slice nearest ``alpha``), ``peak_height`` / ``peak_width`` (the fitted
        brightness maximum; width in alpha), ``residual`` (RMS misfit of the forward-model fit per
        pixel as a fraction of ``intensity``; without refinement, of the brightness-curve fit in
        ``log B``), ``prominence`` (fraction of the curve's maximum; below 1 for the lesser
        particles of a shadowing group), ``alpha_std`` (spread of alpha over the candidates the
        raw pixels and the depth prior allow: large where one lens holds all the light and no
        prior settles it), ``prior_std`` (width in alpha of the neighbours' depth prior the final
        fit weighed, :mod:`analysis.depth.prior`; NaN where the pixels alone decide),
        ``intensity`` (fitted DN of a lit pixel), ``n_lit`` (raw samples the fit lights),
        ``blur_pitches`` (diameter of the particle's blur disk on the micro-lens array in lens
        pitches: below about 1, one lens may hold all its light and its depth is open within the
        range that lens allows) and ``leftover`` (share of the light around it no fit explains).
    params : PipelineParams
    alphas : ndarray of shape (n_slices,)
    grid : ImageGrid
        Output grid of the product images (pixels to lens-plane metres).
    coordinates : dict
        The physical calibration used (thin lens or user).
    timings : dict of str to float
        Seconds per stage.
    warnings : list of str
        What a user should know: nothing found, saturation, peaks outside the alpha range.
    exposure_name, exposure_sha1, serial, white_sha1 : str or None
    curves : ndarray of shape (n_particles, n_slices), float32
        Each particle's brightness curve ``B(alpha)`` (NaN where not detected); particles of one
        shadowing group share their curve.
    stack, subaperture : ndarray or None
        The refocused images (A, H, W) and the sub-aperture image (H, W), when kept.
    threshold : float
        Detection threshold applied to the product images.
    rejected : dict of str to ndarray
        The candidates that did not become particles (``x, y, alpha, X, Y, Z, intensity,
        residual, reason``; the reasons: :data:`analysis.detection.rejections.REASONS`).
    shot_time : float or None
        When the exposure was taken (s since 1970, UTC, from the metadata's clock); None without one.
    drift : dict or None
        How far the micro-lens lattice had moved since the white image, as the exposure showed it
        (:class:`analysis.calibration.drift.LatticeDrift`); None where it showed too little.
    """

    particles: dict[str, np.ndarray]
    params: PipelineParams
    alphas: np.ndarray
    grid: ImageGrid
    coordinates: dict[str, Any]
    timings: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    exposure_name: str | None = None
    exposure_sha1: str | None = None
    serial: str | None = None
    white_sha1: str | None = None
    curves: np.ndarray | None = None
    stack: np.ndarray | None = None
    subaperture: np.ndarray | None = None
    threshold: float = math.nan
    rejected: dict[str, np.ndarray] = field(default_factory=dict)
    drift: dict | None = None
    shot_time: float | None = None

    def __len__(self) -> int:
        return int(self.particles["index"].size)

    def to_columns(self) -> dict[str, list]:
        """The particle table as plain lists, by column."""
        return {name: self.particles[name].tolist() for name in COLUMNS}

    def to_dataframe(self, *, frame: int = 0, t: float = 0.0) -> "pd.DataFrame":
        """The particle table as a pandas DataFrame in trackpy's conventions: ``frame`` and ``t``
        (s) first, then the columns of :data:`COLUMNS`, so that ``trackpy.link`` and
        :func:`analysis.tracking.trajectories.link` take a concatenation of shots as it is.

        Examples
        --------
        >>> import pandas as pd                                        # doctest: +SKIP
        >>> run = pd.concat([r.to_dataframe(frame=k, t=k * 1.0) for k, r in enumerate(results)])  # doctest: +SKIP
        """
        import pandas as pd

        n = len(self)
        return pd.DataFrame({"frame": np.full(n, frame, np.int64), "t": np.full(n, float(t)),
                             **{name: np.asarray(values) for name, values in self.particles.items()}})

    def to_csv(self, path: str | Path) -> Path:
        """Write the particle table as CSV (header row, one row per particle)."""
        return write_csv(self.particles, path)

    def to_hdf5(self, path: str | Path) -> Path:
        """Write a NeXus-style HDF5 file (``/entry`` NXentry, ``/entry/data`` NXdata with the
        columns, ``/entry/process`` NXprocess with the parameters as attributes), plus the
        stack, sub-aperture image and curves when they were kept."""
        return write_results_hdf5([self], path)

    def nexus_frame(self) -> dict[str, Any]:
        """This exposure's extras for :func:`analysis.formats.particle_table.write_hdf5`."""
        return {"metadata": self.metadata(), "alpha": self.alphas, "curves": self.curves, "stack": self.stack,
                "subaperture": self.subaperture, "rejected": self.rejected or None}

    def metadata(self) -> dict[str, Any]:
        """Provenance as JSON-able values: parameters, calibration, timings, warnings."""
        return {"params": self.params.to_dict(), "coordinates": self.coordinates, "timings": self.timings,
                "warnings": self.warnings, "exposure_name": self.exposure_name,
                "exposure_sha1": self.exposure_sha1, "serial": self.serial, "white_sha1": self.white_sha1,
                "threshold": self.threshold, "alphas": self.alphas.tolist(),
                "grid": dataclasses.asdict(self.grid), "drift": self.drift, "shot_time": self.shot_time}


def write_results_hdf5(results: Sequence[Result], path: str | Path) -> Path:
    """One NeXus file of one exposure's particles, or a batch's (with a ``frame`` column), with each
    exposure's provenance, curves and, when kept, stack and sub-aperture image."""
    columns = dict(results[0].particles) if len(results) == 1 else combine(
        (r.particles for r in results), times=[r.shot_time for r in results])
    return write_hdf5(path, columns, parameters=results[0].params.to_dict() if results else {},
                      frames=[r.nexus_frame() for r in results])
