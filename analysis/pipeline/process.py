"""From one raw exposure and its camera's calibration to a table of 3D particle positions.

The composition of the stages (docs/design.md, "The analysis, stage by stage"), with one
parameter object stored with every result::

    table   = get_table(calibration)                      # look-up table, cached
    stack   = refocus_stack(image, table, alphas)         # analysis.lightfield.refocus
    sub     = subaperture_image(image, table, ...)
    product = stack * sub
    dets    = [detect(s, threshold=t) for s in product]   # analysis.detection.moments
    peaks   = find_depth_peaks(link_tracks(dets), alphas) # analysis.detection.curves
    peaks  += find_maxima(product, alphas, threshold=t)   # analysis.detection.maxima: crowds, merged blobs
    peaks   = refine_peaks(fitter, peaks, ...)            # analysis.depth.refine: forward-model fit to
              # the raw pixels (analysis.depth.rayfit); hidden particles (probes in front of and
              # behind each); a second pass over the raw image with the found particles' light off
    peaks   = deblend(fitter, peaks, fit)                 # refit with the neighbours' light off
    peaks   = apply_depth_prior(fitter, peaks, fit)       # analysis.depth.prior: one-lens particles
    X, Y, Z = to_physical(peaks.x, peaks.y, peaks.alpha, grid, ...)  # analysis.camera.coordinates

Each stage is also callable on its own; :func:`process` runs them all and :func:`process_many`
runs a batch that shares the calibration, the look-up table and the compiled kernels.

Example (from a notebook)::

    from analysis.formats.exposure import read_exposure
    from analysis.calibration.calibrate import load_calibration
    from analysis.pipeline.process import PipelineParams, process

    exposure = read_exposure("IMG_0001.lfp")
    calibration = load_calibration(Path("calibration"), exposure.metadata, serial=exposure.serial)
    result = process(exposure, calibration, PipelineParams(n_slices=40))
    result.to_csv("IMG_0001.csv")
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator, Mapping

import numpy as np
from scipy.spatial import cKDTree

from analysis.calibration.calibrate import Calibration
from analysis.camera.model import CameraModel
from analysis.camera.coordinates import Calibration3D, ThinLensCalibration, UserCalibration, to_physical
from analysis.detection.curves import (Peaks, Tracks, find_depth_peaks, link_tracks, merge_duplicates,
    unique_indices)
from analysis.errors import CameraMismatchError, MetadataError, ParameterError
from analysis.formats.exposure import Exposure
from analysis.camera.image_grid import ImageGrid
from analysis.lightfield.table import (TABLE_FORMAT_VERSION, LightFieldTable, build_table, load_table,
    save_table)
from analysis.detection.maxima import find_maxima
from analysis.detection.moments import detect
from analysis.formats.particle_table import COLUMNS, write_csv, write_hdf5
from analysis.depth.rayfit import RayFit, aperture_per_lens_plane, fit_rays, render_fits, unexplained_light
from analysis.depth.refine import (RayFitter, apply_depth_prior, concat_fits, concat_peaks, deblend, inside,
    refine_peaks, residual_image, split_shared, take_fit)
from analysis.lightfield.refocus import (alphas_for_depth_range, default_alphas, products, refocus_stack,
    select_samples, subaperture_image)

log = logging.getLogger(__name__)


# Above this fraction of saturated green pixels an exposure holds no usable particle image.
_SATURATED_FRAME_FRACTION = 0.2


@dataclass
class PipelineParams:
    """Every setting of the pipeline; stored with each result.

    Attributes
    ----------
    alpha_min, alpha_max, n_slices
        Refocus parameters of the stack (the paper: 40 over 0.987 ... 1.013).
    depth_range_mm : [near, far] or None
        Derive the alpha range from a depth range with the thin-lens model instead.
    aperture_fraction, blur_sigma_px
        The sub-aperture image: central fraction of the aperture radius, Gaussian blur
        (output pixels).
    grid_oversample
        Output pixels per lens row spacing (1: about one pixel per lens).
    noise_sigmas
        Raw samples within this many noise sigmas of the background are skipped in the refocus.
    threshold
        Absolute detection threshold on the product images; None: ``(threshold_sigma *
        raw noise)**2`` (:func:`product_threshold`).
    threshold_sigma, min_pixels
        Detection (:func:`analysis.detection.moments.detect`).
    link_radius_px, max_gap
        Linking across slices (:func:`analysis.detection.curves.link_tracks`), output pixels.
    min_prominence, fit_half_width
        Peaks of the brightness curves (:func:`analysis.detection.curves.find_depth_peaks`).
    refine, refine_alpha_range
        Refine each peak's position and depth by fitting the forward model to the raw pixels
        around it (:func:`analysis.depth.rayfit.fit_rays`), searching ``alpha +- refine_alpha_range``.
    shadow_probe
        After the fit, where light is left over around a particle, look for a hidden one this far
        in alpha in front of and behind it; after deblending, try splitting unusually bright fits
        into two particles that far apart (:func:`analysis.depth.refine.split_shared`). 0 turns both off.
    maxima_half_slices
        Also take the local maxima of the product stack over (alpha, y, x) as candidates
        (:func:`analysis.detection.maxima.find_maxima`, footprint +-this many slices and +-1 pixel) where no
        brightness-curve peak accounts for them: crowds, where neighbours' blobs merge into one
        component. -1 turns it off.
    fit_depths, fit_lateral
        The depth fit's coarse grid (:func:`analysis.depth.rayfit.fit_rays`): depths, and positions
        per side over +-0.4 pitch. Near focus depth and position are coupled (how the light splits
        between lenses), so positions every 0.2 pitch beat more depths. The fine pass around the
        coarse estimate is :data:`analysis.depth.refine.FINE_GRID`.
    deblend
        Refit every particle with its neighbours' fitted light taken off its pixels
        (:func:`deblend`): in crowds their blurs overlap and pull each other's fits.
    depth_prior
        Where a particle's pixels leave its depth open (its light falls in one micro-lens) and its
        neighbours lie on one surface, take the depth that surface predicts as a prior
        (:func:`apply_depth_prior`, :mod:`analysis.depth.prior`); in a 3D crowd no surface fits and
        it does nothing. Turn it off to measure out-of-surface motion from the pixels alone.
    merge_slices
        Refined particles closer than ``link_radius_px`` in the image and this many slices in alpha
        are one particle (the brighter kept): candidates of one particle converge there.
    passes
        Detection passes: each after the first looks again at the raw image with the light of the
        particles found so far taken off (crowded clusters, where blobs merge). 1: a single pass.
    min_intensity_sigma, max_fit_residual
        Refined particles whose fitted pixel intensity is below this many raw-noise sigmas, or
        whose forward-model misfit per pixel exceeds this fraction of that intensity, are
        dropped: noise, or a particle whose depth lies outside the alpha range.
    pixel_size_mm, depth_per_alpha_mm, reference_alpha, reference_z_mm
        A user calibration of the physical coordinates (:class:`UserCalibration`); when
        ``pixel_size_mm`` and ``depth_per_alpha_mm`` are None the thin-lens model of the
        exposure's metadata is used.
    """

    alpha_min: float = 0.987
    alpha_max: float = 1.013
    n_slices: int = 40
    depth_range_mm: tuple[float, float] | None = None
    aperture_fraction: float = 0.3
    blur_sigma_px: float = 1.0
    grid_oversample: float = 1.0
    noise_sigmas: float | None = 3.0
    threshold: float | None = None
    threshold_sigma: float = 5.0
    min_pixels: int = 2
    link_radius_px: float = 1.5
    max_gap: int = 1
    min_prominence: float = 0.2
    fit_half_width: int = 4
    refine: bool = True
    refine_alpha_range: float = 0.004
    min_intensity_sigma: float = 8.0
    max_fit_residual: float = 0.35
    shadow_probe: float = 0.0065
    passes: int = 2
    maxima_half_slices: int = 2
    merge_slices: float = 4.0
    fit_depths: int = 17
    fit_lateral: int = 5
    deblend: bool = True
    depth_prior: bool = True
    pixel_size_mm: float | None = None
    depth_per_alpha_mm: float | None = None
    reference_alpha: float = 1.0
    reference_z_mm: float = 0.0

    def __post_init__(self) -> None:
        if self.depth_range_mm is not None:
            self.depth_range_mm = tuple(float(v) for v in self.depth_range_mm)  # type: ignore[assignment]
        self.validate()

    def validate(self) -> None:
        """Raise :class:`ParameterError` for a setting out of its range."""
        if not (self.n_slices >= 3):
            raise ParameterError(f"n_slices must be at least 3 to locate a brightness peak, got {self.n_slices}")
        if self.depth_range_mm is None and not (0 < self.alpha_min < self.alpha_max):
            raise ParameterError(f"need 0 < alpha_min < alpha_max, got {self.alpha_min}, {self.alpha_max}")
        if self.depth_range_mm is not None:
            if len(self.depth_range_mm) != 2 or not (0 < self.depth_range_mm[0] < self.depth_range_mm[1]):
                raise ParameterError(f"depth_range_mm must be [near, far] with 0 < near < far, "
                                     f"got {self.depth_range_mm}")
        if self.fit_depths < 3 or self.fit_lateral < 1:
            raise ParameterError(f"need fit_depths >= 3 and fit_lateral >= 1, got {self.fit_depths}, "
                                 f"{self.fit_lateral}")
        if self.merge_slices < 0 or self.maxima_half_slices < -1:
            raise ParameterError(f"need merge_slices >= 0 and maxima_half_slices >= -1 (-1: off), "
                                 f"got {self.merge_slices}, {self.maxima_half_slices}")
        if not (1 <= self.passes <= 5):
            raise ParameterError(f"passes must be 1 ... 5, got {self.passes}")
        if not (0 < self.refine_alpha_range < 0.1):
            raise ParameterError(f"refine_alpha_range must be in (0, 0.1), got {self.refine_alpha_range}")
        if not (0 < self.aperture_fraction <= 1):
            raise ParameterError(f"aperture_fraction must be in (0, 1], got {self.aperture_fraction}")
        if self.blur_sigma_px < 0 or self.grid_oversample <= 0:
            raise ParameterError("blur_sigma_px must be >= 0 and grid_oversample > 0")
        if self.threshold is not None and not math.isfinite(self.threshold):
            raise ParameterError(f"threshold must be a finite number or None, got {self.threshold}")
        if (self.pixel_size_mm is None) != (self.depth_per_alpha_mm is None):
            raise ParameterError("a user calibration needs both pixel_size_mm and depth_per_alpha_mm")
        if self.pixel_size_mm is not None:
            self.user_calibration()  # validates the numbers

    def alphas(self, optics: Any = None) -> np.ndarray:
        """The refocus parameters of the stack (ascending)."""
        if self.depth_range_mm is not None:
            if optics is None:
                raise ParameterError("a depth range needs the exposure's optics to convert it to alphas")
            return alphas_for_depth_range(self.depth_range_mm[0], self.depth_range_mm[1], self.n_slices, optics)
        return default_alphas(self.n_slices, self.alpha_min, self.alpha_max)

    def user_calibration(self) -> UserCalibration | None:
        if self.pixel_size_mm is None or self.depth_per_alpha_mm is None:
            return None
        return UserCalibration(pixel_size_mm=self.pixel_size_mm, depth_per_alpha_mm=self.depth_per_alpha_mm,
                               reference_alpha=self.reference_alpha, reference_z_mm=self.reference_z_mm)

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-able values; ``PipelineParams(**params.to_dict())`` restores it."""
        out = dataclasses.asdict(self)
        if out["depth_range_mm"] is not None:
            out["depth_range_mm"] = list(out["depth_range_mm"])
        return out

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "PipelineParams":
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(values) - known)
        if unknown:
            raise ParameterError(f"unknown pipeline parameter(s) {unknown}; known: {sorted(known)}")
        return cls(**dict(values))


@dataclass
class Result:
    """The particles of one exposure, with everything needed to reproduce and inspect them.

    Attributes
    ----------
    particles : dict of str to ndarray
        The particle table by column (:data:`COLUMNS`): ``particle`` (0..n-1), ``x, y``
        (output-image pixels, integer values at pixel centres), ``alpha``, ``X, Y, Z`` (mm,
        camera frame; NaN without a usable depth model), ``brightness`` (mean intensity per
        pixel in the slice nearest ``alpha``), ``peak_height`` / ``peak_width`` (the fitted
        brightness maximum; width in alpha), ``residual`` (RMS misfit of the forward-model fit per
        pixel as a fraction of ``intensity``; without refinement, of the brightness-curve fit in
        ``log B``), ``prominence`` (fraction of the curve's maximum; below 1 for the lesser
        particles of a shadowing group), ``alpha_std`` (spread of alpha over the candidates the
        raw pixels allow: large where one lens holds all the light) and ``intensity`` (fitted DN
        of a lit pixel).
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

    def __len__(self) -> int:
        return int(self.particles["particle"].size)

    def to_columns(self) -> dict[str, list]:
        """The particle table as plain lists, by column."""
        return {name: self.particles[name].tolist() for name in COLUMNS}

    def to_csv(self, path: str | Path) -> Path:
        """Write the particle table as CSV (header row, one row per particle)."""
        return write_csv(self.particles, path)

    def to_hdf5(self, path: str | Path) -> Path:
        """Write a NeXus-style HDF5 file (``/entry`` NXentry, ``/entry/data`` NXdata with the
        columns, ``/entry/process`` NXprocess with the parameters as attributes), plus the
        stack, sub-aperture image and curves when they were kept."""
        return write_hdf5([self], path)

    def metadata(self) -> dict[str, Any]:
        """Provenance as JSON-able values: parameters, calibration, timings, warnings."""
        return {"params": self.params.to_dict(), "coordinates": self.coordinates, "timings": self.timings,
                "warnings": self.warnings, "exposure_name": self.exposure_name,
                "exposure_sha1": self.exposure_sha1, "serial": self.serial, "white_sha1": self.white_sha1,
                "threshold": self.threshold, "alphas": self.alphas.tolist(),
                "grid": dataclasses.asdict(self.grid)}


# --- the look-up table, cached per calibration -------------------------------------------------

_TABLES: dict[tuple, LightFieldTable] = {}
_TABLES_MAX = 4
#: The depth fit's table keeps the micro-image rims (half a pixel beyond the aperture's image).
FIT_TABLE_RIM_PX = -0.5
_FIT_TABLE_MIN_WEIGHT = 0.05


def table_cache_path(cache_dir: Path, calibration: Calibration, grid_oversample: float, rim_px: float = 1.0) -> Path:
    """Where the look-up table of a calibration is kept, beside the calibration cache."""
    serial = calibration.serial or "unknown-serial"
    return (Path(cache_dir) / serial
            / f"{calibration.white_sha1}.lut.v{TABLE_FORMAT_VERSION}.o{grid_oversample:g}.r{rim_px:g}.npz")


def get_table(calibration: Calibration, *, grid_oversample: float = 1.0,
              cache_dir: Path | None = None, rim_px: float = 1.0) -> LightFieldTable:
    """The look-up table of a calibration: from memory, else from ``cache_dir``, else built.

    A table built here is written to ``cache_dir`` (when given); :func:`process` writes it
    again once it holds the refocus normalisations of new alphas. ``rim_px`` as in
    :func:`analysis.lightfield.table.build_table` (the depth fit uses ``FIT_TABLE_RIM_PX``, which
    keeps the rims of the micro-images).
    """
    key = (calibration.serial, calibration.white_sha1, float(grid_oversample), float(rim_px))
    table = _TABLES.get(key)
    if table is not None:
        return table
    path = table_cache_path(cache_dir, calibration, grid_oversample, rim_px) if cache_dir is not None else None
    if path is not None and path.is_file():
        try:
            table = load_table(path)
        except Exception as exc:  # a stale or broken cache is rebuilt, never trusted
            log.warning("look-up table cache %s unusable (%s); rebuilding it", path, exc)
            table = None
    if table is None or (table.height, table.width) != (calibration.model.height, calibration.model.width):
        table = build_table(calibration, grid_oversample=grid_oversample, rim_px=rim_px,
                            min_weight=_FIT_TABLE_MIN_WEIGHT if rim_px < 0 else 0.05)
        if path is not None:
            _save_table_quietly(table, path)
    if len(_TABLES) >= _TABLES_MAX:
        _TABLES.pop(next(iter(_TABLES)))
    _TABLES[key] = table
    return table


def _save_table_quietly(table: LightFieldTable, path: Path) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        save_table(table, path)
    except OSError as exc:
        log.warning("could not write look-up table cache %s (%s); continuing without it", path, exc)


# --- checks --------------------------------------------------------------------------------------

def check_same_camera(exposure: Exposure, calibration: Calibration) -> None:
    """Raise :class:`CameraMismatchError` unless the exposure was taken by the calibration's camera.

    Serial numbers decide when both are known; otherwise the sensor size and the factory MLA
    geometry (lens pitch, MLA-to-sensor distance, pixel pitch) must agree.
    """
    exp_serial = exposure.serial
    if exp_serial is not None and calibration.serial is not None and exp_serial != calibration.serial:
        raise CameraMismatchError(
            f"exposure {exposure.name or exposure.sha1} is from camera {exp_serial}, the calibration from "
            f"{calibration.serial}; use the white images of camera {exp_serial}")
    model = CameraModel.from_metadata(exposure.metadata)
    cal = calibration.model
    if (model.height, model.width) != (cal.height, cal.width):
        raise CameraMismatchError(
            f"exposure is {model.width}x{model.height} pixels, the calibration {cal.width}x{cal.height}; "
            "use white images of the same camera and sensor size")
    for name in ("lens_pitch_m", "mla_to_sensor_m", "pixel_pitch_m"):
        a, b = getattr(model.optics, name), getattr(cal.optics, name)
        if not math.isclose(a, b, rel_tol=1e-7, abs_tol=0.0):
            raise CameraMismatchError(
                f"exposure and calibration disagree on the micro-lens array ({name}: {a} vs {b}), so they "
                "come from different cameras; use the white images of the exposure's camera")


def saturated_fraction(image: np.ndarray, white_level: float) -> tuple[float, int]:
    """Fraction and count of green sites (odd rows, even columns: one of the two green phases)
    at or above the white level."""
    greens = np.asarray(image)[1::2, 0::2]
    count = int(np.count_nonzero(greens >= white_level))
    return (count / greens.size if greens.size else 0.0), count


# --- the pipeline -------------------------------------------------------------------------------

def product_threshold(noise_dn: float, params: PipelineParams) -> float:
    """Detection threshold for the product images: ``params.threshold``, or
    ``(threshold_sigma * noise_dn)**2``.

    A product pixel is a refocused value times a sub-aperture value, both in DN per unit white
    weight; it passes when both factors stand ``threshold_sigma`` raw-noise sigmas above the
    background. (The product's own pixel statistics are no guide: most pixels are exactly zero
    once the refocus skips samples in the noise, and the rest are mostly particle light.)
    """
    if params.threshold is not None:
        return float(params.threshold)
    return (params.threshold_sigma * max(noise_dn, 0.5)) ** 2


def locate(product: np.ndarray, alphas: np.ndarray, params: PipelineParams, *, threshold: float,
           timings: dict[str, float] | None = None) -> tuple[Peaks, Tracks]:
    """Detection in every product slice, linking, and the brightness peaks (stages 5 and 6)."""
    timings = {} if timings is None else timings
    t0 = time.perf_counter()
    detections = [detect(s, threshold=threshold, min_pixels=params.min_pixels) for s in product]
    t1 = time.perf_counter()
    tracks = link_tracks(detections, radius_px=params.link_radius_px, max_gap=params.max_gap)
    t2 = time.perf_counter()
    peaks = find_depth_peaks(tracks, alphas, min_prominence=params.min_prominence,
                             fit_half_width=params.fit_half_width)
    step = float(alphas[1] - alphas[0])
    peaks = merge_duplicates(peaks, radius_px=params.link_radius_px, alpha_tolerance=1.5 * step)
    t3 = time.perf_counter()
    if params.maxima_half_slices >= 0:
        peaks, tracks = _add_maxima(product, alphas, params, threshold, peaks, tracks)
    t4 = time.perf_counter()
    timings.update(detect=t1 - t0, link=t2 - t1, peaks=t3 - t2, maxima=t4 - t3)
    return peaks, tracks


def _add_maxima(product: np.ndarray, alphas: np.ndarray, params: PipelineParams, threshold: float,
                peaks: Peaks, tracks: Tracks) -> tuple[Peaks, Tracks]:
    """Add the local maxima of the product stack that no brightness-curve peak accounts for.

    In crowds the blobs of neighbours merge into one component per slice, and their tracks hold
    one peak for several particles; each particle still makes a maximum of its own over (alpha,
    y, x). Each new candidate gets a curve of its own: the product at its pixel, slice by slice.
    """
    m = find_maxima(product, alphas, threshold=threshold, half_slices=params.maxima_half_slices, half_px=1)
    if len(m) == 0:
        return peaks, tracks
    step = float(alphas[1] - alphas[0])
    new = np.ones(len(m), dtype=bool)
    if len(peaks):
        # Within the linking radius and two slices of a peak: the same particle.
        near = cKDTree(np.column_stack([peaks.x, peaks.y])).query_ball_point(
            np.column_stack([m.x, m.y]), r=params.link_radius_px)
        for i, js in enumerate(near):
            if js and np.min(np.abs(peaks.alpha[js] - m.alpha[i])) <= 2 * step:
                new[i] = False
    idx = np.flatnonzero(new)
    n = idx.size
    if n == 0:
        return peaks, tracks
    rows = np.clip(np.rint(m.y[idx]).astype(np.int64), 0, product.shape[1] - 1)
    cols = np.clip(np.rint(m.x[idx]).astype(np.int64), 0, product.shape[2] - 1)
    curve = product[:, rows, cols].T.astype(np.float64)
    curve[curve <= threshold] = np.nan
    extra = Tracks(x=np.repeat(m.x[idx, None], alphas.size, axis=1), y=np.repeat(m.y[idx, None], alphas.size, axis=1),
                   brightness=curve)
    cand = Peaks(track=len(tracks) + np.arange(n, dtype=np.int64), alpha=m.alpha[idx], x=m.x[idx], y=m.y[idx],
                 peak_height=m.brightness[idx], peak_width=np.full(n, np.nan), residual=np.full(n, np.nan),
                 prominence=np.ones(n))
    tracks = Tracks(x=np.vstack([tracks.x, extra.x]), y=np.vstack([tracks.y, extra.y]),
                    brightness=np.vstack([tracks.brightness, extra.brightness]))
    return concat_peaks(peaks, cand), tracks


def process(exposure: Exposure, calibration: Calibration, params: PipelineParams | None = None, *,
            keep_stack: bool = False, progress: Callable[[float], None] | None = None,
            coordinates: Calibration3D | None = None, cache_dir: Path | None = None) -> Result:
    """Particles of one exposure: refocus, detect, link, locate the depth peaks, convert to mm.

    Parameters
    ----------
    exposure : Exposure
        From :func:`analysis.formats.exposure.read_exposure`.
    calibration : Calibration
        Of the exposure's camera, from :func:`analysis.calibration.calibrate.load_calibration`.
    params : PipelineParams, optional
    keep_stack : bool
        Keep the refocused stack and the sub-aperture image in the result.
    progress : callable taking a float in [0, 1], optional
        Called after each stage.
    coordinates : ThinLensCalibration or UserCalibration, optional
        Physical calibration; default: the user calibration in ``params`` if set, else the thin
        lens of the exposure's metadata (X, Y, Z are NaN, with a warning, when the metadata has
        no usable exit-pupil distance).
    cache_dir : Path, optional
        Folder for the look-up table cache (beside the calibration cache).

    Returns
    -------
    Result
        Empty, with a warning, for a frame without particles, a saturated frame, or an alpha range
        that holds no particle's brightest slice.

    Raises
    ------
    CameraMismatchError
        If the exposure is not from the calibration's camera.
    ParameterError
        For settings out of range.
    """
    params = PipelineParams() if params is None else params
    params.validate()
    report = progress or (lambda fraction: None)
    timings: dict[str, float] = {}
    warnings: list[str] = []
    t_start = time.perf_counter()

    check_same_camera(exposure, calibration)
    model = CameraModel.from_metadata(exposure.metadata)
    optics = model.optics
    alphas = params.alphas(optics)
    if coordinates is None:
        coordinates = params.user_calibration() or ThinLensCalibration(optics)

    t = time.perf_counter()
    table = get_table(calibration, grid_oversample=params.grid_oversample, cache_dir=cache_dir)
    norms_before = table.normalisation_keys
    grid = table.grid
    timings["table"] = time.perf_counter() - t
    report(0.05)

    def finish(peaks: Peaks, tracks: Tracks | None, stack: np.ndarray | None, sub: np.ndarray | None,
               threshold: float, fit: RayFit | None = None) -> Result:
        t = time.perf_counter()
        particles, curves = _particle_table(peaks, tracks, alphas, grid, coordinates, warnings, fit)
        timings["coordinates"] = time.perf_counter() - t
        if cache_dir is not None and table.normalisation_keys != norms_before:
            _save_table_quietly(table, table_cache_path(cache_dir, calibration, params.grid_oversample))
        timings["total"] = time.perf_counter() - t_start
        report(1.0)
        return Result(particles=particles, params=params, alphas=alphas, grid=grid,
                      coordinates=coordinates.to_dict(), timings=timings, warnings=warnings,
                      exposure_name=exposure.name, exposure_sha1=exposure.sha1, serial=exposure.serial,
                      white_sha1=calibration.white_sha1, curves=curves,
                      stack=stack if keep_stack else None, subaperture=sub if keep_stack else None,
                      threshold=threshold)

    fraction, count = saturated_fraction(exposure.image, model.white_level)
    if fraction > _SATURATED_FRAME_FRACTION:
        warnings.append(f"the exposure is saturated ({100 * fraction:.0f} % of green pixels at the white level); "
                        "no particles can be told apart: shorten the exposure or lower the laser power")
        return finish(_no_peaks(), None, None, None, math.nan)
    if count:
        warnings.append(f"{count} green pixels are saturated; the brightest particles' brightness is clipped")

    t = time.perf_counter()
    samples = select_samples(exposure.image, table, noise_sigmas=params.noise_sigmas)
    timings["samples"] = time.perf_counter() - t
    t = time.perf_counter()
    stack = refocus_stack(exposure.image, table, alphas, grid=grid, samples=samples)
    timings["refocus"] = time.perf_counter() - t
    report(0.5)
    t = time.perf_counter()
    sub = subaperture_image(exposure.image, table, fraction=params.aperture_fraction,
                            blur_sigma_px=params.blur_sigma_px, grid=grid, samples=samples)
    timings["subaperture"] = time.perf_counter() - t
    t = time.perf_counter()
    product = products(stack, sub, out=None if keep_stack else stack)
    threshold = product_threshold(samples.sigma, params)
    timings["products"] = time.perf_counter() - t
    report(0.6)

    peaks, tracks = locate(product, alphas, params, threshold=threshold, timings=timings)
    report(0.8)
    fit = None
    if params.refine and len(peaks):
        fitter = RayFitter(
            exposure.image, get_table(calibration, cache_dir=cache_dir, rim_px=FIT_TABLE_RIM_PX), grid,
            background=samples.background, aperture_per_lens_plane=aperture_per_lens_plane(optics),
            alpha_half_range=params.refine_alpha_range, fit_depths=params.fit_depths,
            fit_lateral=params.fit_lateral, min_intensity=params.min_intensity_sigma * max(samples.sigma, 0.5),
            max_residual=params.max_fit_residual, merge_radius_px=params.link_radius_px,
            merge_alpha=params.merge_slices * float(alphas[1] - alphas[0]))
        t = time.perf_counter()
        peaks, fit = inside(*refine_peaks(fitter, peaks, shadow_probe=params.shadow_probe), alphas)
        timings["refine"] = time.perf_counter() - t
        t = time.perf_counter()
        for _ in range(params.passes - 1):
            found = _look_again(fitter, table, params, alphas, threshold, peaks, tracks, fit)
            if found is None:
                break
            peaks, tracks, fit = found
        timings["more_passes"] = time.perf_counter() - t
        if params.deblend and len(peaks) > 1:
            t = time.perf_counter()
            peaks, fit = deblend(fitter, peaks, fit)
            timings["deblend"] = time.perf_counter() - t
            if params.shadow_probe > 0:
                t = time.perf_counter()
                peaks, fit = split_shared(fitter, peaks, fit, shadow_probe=params.shadow_probe)
                timings["split"] = time.perf_counter() - t
        if params.depth_prior and len(peaks) > 1:
            t = time.perf_counter()
            peaks, fit = apply_depth_prior(fitter, peaks, fit)
            timings["depth_prior"] = time.perf_counter() - t
    report(0.9)
    if len(peaks) == 0:
        if len(tracks):
            warnings.append("particles were seen, but none is brightest inside the alpha range "
                            f"{alphas[0]:.4f} ... {alphas[-1]:.4f}; widen the range")
        else:
            warnings.append("no particles found above the noise; check the exposure and the threshold")
    return finish(peaks, tracks, stack, sub, threshold, fit)


def _look_again(fitter: RayFitter, table: LightFieldTable, params: PipelineParams, alphas: np.ndarray,
                threshold: float, peaks: Peaks, tracks: Tracks, fit: RayFit) -> tuple[Peaks, Tracks, RayFit] | None:
    """One more detection pass on the raw image with the found particles' light taken off.

    Crowded clusters: blobs of neighbours merge in the product images. Returns the particles with
    the new ones added, or None when the pass finds none.
    """
    if len(peaks) == 0:
        return None
    explained = fitter.render(fit)
    residual = residual_image(fitter.image, fitter.table, explained)
    rs = select_samples(residual, table, noise_sigmas=params.noise_sigmas)
    rstack = refocus_stack(residual, table, alphas, grid=fitter.grid, samples=rs)
    rsub = subaperture_image(residual, table, fraction=params.aperture_fraction, blur_sigma_px=params.blur_sigma_px,
                             grid=fitter.grid, samples=rs)
    new, new_tracks = locate(products(rstack, rsub, out=rstack), alphas, params, threshold=threshold)
    # Left-over light of imperfectly modelled particles makes weak blobs (a fifth of a typical
    # particle's peak or less); a particle of its own is about as bright as the rest.
    new = new.take(np.flatnonzero(new.peak_height >= 0.3 * np.median(peaks.peak_height)))
    log.debug("another pass: %d candidates", len(new))
    if len(new) == 0:
        return None
    new, new_fit = inside(*refine_peaks(fitter, new, subtract=explained), alphas)
    # As for hidden particles: a new one must fit well and be about as bright as the others
    # (left-over light of imperfectly modelled neighbours is a tenth of theirs or less).
    good = np.flatnonzero((new_fit.residual <= 0.2) & (new_fit.intensity >= 0.35 * np.median(fit.intensity)))
    new, new_fit = new.take(good), take_fit(new_fit, good)
    if len(new) == 0:
        return None
    # The new peaks' curves are tracks of the residual's stack: append them to the first pass's,
    # so each particle's track index still points at its own curve.
    both = dataclasses.replace(concat_peaks(peaks, new), track=np.r_[peaks.track, new.track + len(tracks)])
    both_fit = concat_fits(fit, new_fit)
    kept = unique_indices(both, radius_px=fitter.merge_radius_px, alpha_tolerance=fitter.merge_alpha,
                          priority=np.r_[fit.intensity + 1e12, new_fit.intensity])
    if kept.size == len(peaks):
        return None
    tracks = Tracks(x=np.vstack([tracks.x, new_tracks.x]), y=np.vstack([tracks.y, new_tracks.y]),
                    brightness=np.vstack([tracks.brightness, new_tracks.brightness]))
    return both.take(kept), tracks, take_fit(both_fit, kept)


def _particle_table(peaks: Peaks, tracks: Tracks | None, alphas: np.ndarray, grid: ImageGrid,
                    coordinates: Calibration3D, warnings: list[str], fit: RayFit | None = None
                    ) -> tuple[dict[str, np.ndarray], np.ndarray]:
    n = len(peaks)
    # Order particles by image position (row, then column) so tables compare between runs.
    order = np.lexsort((peaks.x, peaks.y)) if n else np.empty(0, dtype=np.int64)
    peaks = peaks.take(order)
    if fit is not None:
        fit = take_fit(fit, order)
        alpha_std, intensity = fit.alpha_spread, fit.intensity
    else:
        alpha_std, intensity = np.full(n, np.nan), np.full(n, np.nan)
    try:
        X, Y, Z = to_physical(peaks.x, peaks.y, peaks.alpha, grid, coordinates)
    except MetadataError as exc:
        warnings.append(f"no physical coordinates: {exc}")
        X = Y = Z = np.full(n, np.nan)
    if tracks is not None and n:
        curves = tracks.brightness[peaks.track].astype(np.float32)
        step = float(alphas[1] - alphas[0])
        nearest = np.clip(np.rint((peaks.alpha - alphas[0]) / step).astype(np.int64), 0, alphas.size - 1)
        brightness = tracks.brightness[peaks.track, nearest]
    else:
        curves = np.empty((n, alphas.size), dtype=np.float32)
        brightness = np.empty(n)
    particles = {"particle": np.arange(n, dtype=np.int64), "x": peaks.x, "y": peaks.y, "alpha": peaks.alpha,
                 "X": np.asarray(X, float), "Y": np.asarray(Y, float), "Z": np.asarray(Z, float),
                 "brightness": np.asarray(brightness, float), "peak_height": peaks.peak_height,
                 "peak_width": peaks.peak_width, "residual": peaks.residual, "prominence": peaks.prominence,
                 "alpha_std": np.asarray(alpha_std, float), "intensity": np.asarray(intensity, float)}
    return particles, curves


def _no_peaks() -> Peaks:
    f = np.empty(0)
    return Peaks(track=np.empty(0, dtype=np.int64), alpha=f, x=f.copy(), y=f.copy(), peak_height=f.copy(),
                 peak_width=f.copy(), residual=f.copy(), prominence=f.copy())


def process_many(exposures: Iterable[Exposure | str | Path],
                 calibration: Calibration | Callable[[Exposure], Calibration],
                 params: PipelineParams | None = None, *, keep_stack: bool = False,
                 coordinates: Calibration3D | None = None, cache_dir: Path | None = None,
                 progress: Callable[[int, float], None] | None = None) -> Iterator[Result]:
    """Process a batch (a run), sharing the calibration, look-up table and compiled kernels.

    Parameters
    ----------
    exposures : iterable of Exposure or paths
        Paths are read with :func:`analysis.formats.exposure.read_exposure` one at a time, so memory stays
        that of one exposure.
    calibration : Calibration, or a callable giving the calibration of an exposure
        A callable lets a batch span zoom settings (e.g. ``lambda e: load_calibration(dir,
        e.metadata, serial=e.serial, cache_dir=cache)``, which caches on disk).
    progress : callable (index, fraction), optional

    Yields
    ------
    Result
        One per exposure, in order.
    """
    from analysis.formats.exposure import read_exposure

    for index, item in enumerate(exposures):
        exposure = item if isinstance(item, Exposure) else read_exposure(item)
        cal = calibration(exposure) if callable(calibration) else calibration
        report = None if progress is None else (lambda f, i=index: progress(i, f))
        yield process(exposure, cal, params, keep_stack=keep_stack, progress=report,
                      coordinates=coordinates, cache_dir=cache_dir)


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel of the pipeline on a tiny sensor crop."""
    from analysis.simulation.camera import simulated_camera_metadata

    from analysis.lightfield.table import build_table_from_model

    model = CameraModel.from_metadata(simulated_camera_metadata(size=64))
    table = build_table_from_model(model)
    image = np.full((64, 64), int(model.black_level) + 10, dtype=np.uint16)
    image[30:34, 30:34] += 200
    alphas = default_alphas(3)
    stack = refocus_stack(image, table, alphas)
    sub = subaperture_image(image, table)
    product = products(stack, sub)
    locate(product, alphas, PipelineParams(n_slices=3), threshold=float(product.max()) / 2)
    optics_ratio = aperture_per_lens_plane(model.optics)
    fit = fit_rays(image, table, np.zeros(1), np.zeros(1), np.ones(1), background=0.0,
                   aperture_per_lens_plane=optics_ratio)
    explained = render_fits(table, fit, aperture_per_lens_plane=optics_ratio)
    unexplained_light(image, table, np.zeros(1), np.zeros(1), np.full(1, 1e-4), background=0.0,
                      explained=explained, floor=0.0)
