"""From one raw exposure and its camera's calibration to a table of 3D particle positions.

The composition of the stages (docs/design.md, "The analysis, stage by stage"), with one
parameter object stored with every result::

    table   = get_table(calibration, cache)               # analysis.pipeline.tables
    image   = without_glints(image, table, find_glints(...))  # analysis.lightfield.glints (--no-glints
              # skips it): compact sources far out of focus, beyond the particles' range, taken off
    stack   = refocus_stack(image, table, alphas)         # analysis.lightfield.refocus
    sub     = subaperture_image(image, table, ...)
    product = stack * sub
    peaks   = locate(product, alphas, params, ...)        # analysis.pipeline.candidates: detection
              # per slice, brightness curves and their peaks, the stack's maxima (analysis.detection)
    peaks   = refine_peaks(fitter, peaks, ...)            # analysis.depth.refine: forward-model fit to
              # the raw pixels (analysis.depth.rayfit); hidden particles (probes in front of and
              # behind each); a second pass over the raw image with the found particles' light off
    peaks   = deblend(fitter, peaks, fit)                 # analysis.depth.deblend: neighbours' light off
    peaks   = late_pass(fitter, ..., peaks, fit)          # analysis.pipeline.passes (--no-late-pass skips it): one
              # more detection pass on what the deblended fits leave, all deblended again with it
    peaks   = apply_depth_prior(fitter, peaks, fit)       # analysis.depth.prior: particles on a surface
    peaks   = refit_blurred(fitter, peaks, fit)           # analysis.depth.deblend: blurred ones again,
              # with every neighbour's light as the stages before left it (each fit keeps its prior)
    peaks   = refit_in_glints(glints_behind(fitter, fit, ...))  # analysis.pipeline.hidden_glints: glints
              # seen through the cluster, found where fits show no point's pattern, taken off; the fits in
              # their light refitted, those that were the glint's light dropped
    peaks   = drop_misfits(drop_extended(...))            # analysis.depth.quality: light that does not
              # converge to a point, and the final table's misfit limit (max_fit_residual)
    peaks   = sharpen_blurred(fitter, peaks, fit)         # analysis.depth.deblend: the blurred ones'
              # last estimate, weighed more sharply, pixels modelled as wide as the camera's blur; it moves
              # fits, and fits it brings onto one particle are merged
    X, Y, Z = to_physical(peaks.x, peaks.y, peaks.alpha, grid, ...)  # analysis.camera.coordinates

Each stage is also callable on its own; :func:`process` runs them all and :func:`process_many`
runs a batch that shares the calibration, the look-up tables (in one :class:`analysis.cache.Cache`)
and the compiled kernels.

Example (from a notebook)::

    from analysis.cache import Cache
    from analysis.formats.exposure import read_exposure
    from analysis.calibration.cache import load_calibration
    from analysis.pipeline.params import PipelineParams
    from analysis.pipeline.process import process

    exposure = read_exposure("IMG_0001.lfp")
    calibration = load_calibration(Path("calibration"), exposure.metadata, serial=exposure.serial)
    result = process(exposure, calibration, PipelineParams(n_slices=40), cache=Cache())
    result.to_csv("IMG_0001.csv")
"""

from __future__ import annotations

import dataclasses
import logging
import math
from pathlib import Path
from typing import Callable, Iterable, Iterator

import numpy as np

from analysis.cache import Cache
from analysis.calibration.calibrate import Calibration
from analysis.calibration.drift import LatticeDrift, block_phases, estimate_drift
from analysis.camera.coordinates import Calibration3D, ThinLensCalibration, coordinate_warnings, to_physical
from analysis.camera.image_grid import ImageGrid
from analysis.camera.model import IDEAL_POINT_SPREAD_PX, CameraModel
from analysis.depth.deblend import deblend, refit_blurred, sharpen_blurred, split_shared
from analysis.depth.prior import apply_depth_prior
from analysis.depth.quality import FIT_RESIDUAL_SLACK, drop_extended, drop_misfits, patterned, too_close
from analysis.depth.rayfit import FitGrid, RayFit, aperture_per_lens_plane, fit_rays, render_fits, unexplained_light
from analysis.depth.refine import (COARSE_LATERAL_PITCHES, COARSE_TEMPERATURE, PROBE_RESIDUAL, SAME_DEPTH_SIGMAS,
                                   RayFitter, accept, inside, moved, refine_peaks, within_limits)
from analysis.depth.sample_noise import SampleNoise
from analysis.detection.curves import Peaks, Tracks
from analysis.detection.rejections import Rejections
from analysis.errors import CameraMismatchError, MetadataError
from analysis.formats.exposure import Exposure, read_exposure
from analysis.formats.frame_metadata import shot_time_s
from analysis.formats.mapped_npz import release_pages
from analysis.lightfield.background import BackgroundMap, estimate_background
from analysis.lightfield.refocus import default_alphas, products, refocus_stack, subaperture_image
from analysis.lightfield.samples import Samples, background_and_noise, select_samples
from analysis.lightfield.drifted_table import shifted_table
from analysis.lightfield.glints import find_glints, without_glints
from analysis.lightfield.table import LightFieldTable

from .candidates import locate, product_threshold
from .depth_range import (LONE_GAP_STEPS, SURVEY_GRID, apart, edge_maxima, fit_limits, lattice_step,
                          range_of_peaks, survey_alphas)
from .hidden_glints import glints_behind, refit_in_glints
from .params import PipelineParams
from .passes import above_noise, late_pass, look_again
from .result import Result
from .stages import Progress, StageClock, trim_heap
from .tables import (drifted_fit_table, get_table, micro_image_model, normalisation_keys, release_table_pages,
                     save_normalisations)

log = logging.getLogger(__name__)

#: Above this fraction of saturated green pixels an exposure holds no usable particle image.
SATURATED_FRAME_FRACTION = 0.2


def process(exposure: Exposure, calibration: Calibration, params: PipelineParams | None = None, *,
            keep_stack: bool = False, progress: Progress | None = None,
            coordinates: Calibration3D | None = None, cache: Cache | None = None) -> Result:
    """Particles of one exposure: refocus, detect, link, locate the depth peaks, convert to mm.

    Parameters
    ----------
    exposure : Exposure
        From :func:`analysis.formats.exposure.read_exposure`.
    calibration : Calibration
        Of the exposure's camera, from :func:`analysis.calibration.cache.load_calibration`.
    params : PipelineParams, optional
    keep_stack : bool
        Keep the refocused stack and the sub-aperture image in the result.
    progress : callable ``(fraction, stage)``, optional
        Called as each stage starts (fraction of the work done, weighted by the stages' typical
        cost, and the stage's name) and once with ``(1.0, "done")``.
    coordinates : ThinLensCalibration, UserCalibration or MetricCalibration, optional
        Physical calibration (a target calibration: :func:`analysis.calibration.metric_files.coordinates_for`);
        default: the user calibration in ``params`` if set, else the thin
        lens of the exposure's metadata (X, Y, Z are NaN, with a warning, when the metadata has
        no usable exit-pupil distance).
    cache : Cache, optional
        Look-up tables and what is derived from them; pass the same one to every call of a batch
        (with a directory, the tables are also kept on disk). Default: a new one for this call.

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
    cache = Cache() if cache is None else cache
    clock = StageClock(progress)
    warnings: list[str] = []
    rejected = Rejections()

    check_same_camera(exposure, calibration)
    model = CameraModel.from_metadata(exposure.metadata)
    optics = model.optics
    if coordinates is None:
        coordinates = params.user_calibration() or ThinLensCalibration(optics)

    drift = None
    with clock.stage("table"):
        table = get_table(calibration, cache, grid_oversample=params.grid_oversample)
    norms_before = normalisation_keys(table, cache)
    grid = table.grid
    alphas = params.alphas(optics)
    if alphas is None:
        alphas = survey_alphas(table)  # until the survey has found the range

    def finish(peaks: Peaks, tracks: Tracks | None, stack: np.ndarray | None, sub: np.ndarray | None,
               threshold: float, fit: RayFit | None = None, quality: dict | None = None) -> Result:
        with clock.stage("coordinates"):
            particles, curves = _particle_table(peaks, tracks, alphas, table, coordinates, warnings, fit, quality)
            dropped = rejected.table()
            dropped.update(zip("XYZ", _physical(dropped["x"], dropped["y"], dropped["alpha"], grid, coordinates)))
        save_normalisations(table, calibration, cache, grid_oversample=params.grid_oversample, before=norms_before)
        return Result(particles=particles, params=params, alphas=alphas, grid=grid,
                      coordinates=coordinates.to_dict(), timings=clock.finish(), warnings=warnings,
                      exposure_name=exposure.name, exposure_sha1=exposure.sha1, serial=exposure.serial,
                      white_sha1=calibration.white_sha1, curves=curves,
                      stack=stack if keep_stack else None, subaperture=sub if keep_stack else None,
                      threshold=threshold, rejected=dropped, drift=None if drift is None else drift.to_dict(),
                      shot_time=shot_time_s(exposure.metadata))

    fraction, count = saturated_fraction(exposure.image, model.white_level)
    if fraction > SATURATED_FRAME_FRACTION:
        warnings.append(f"the exposure is saturated ({100 * fraction:.0f} % of green pixels at the white level); "
                        "no particles can be told apart: shorten the exposure or lower the laser power")
        return finish(_no_peaks(), None, None, None, math.nan)
    if count:
        warnings.append(f"{count} green pixels are saturated; the brightest particles' brightness is clipped")

    with clock.stage("drift"):
        noise_dn = background_and_noise(exposure.image, table)[1]
        drift = _lattice_drift(exposure, calibration, cache, noise_dn)
        fit_table = drifted_fit_table(calibration, cache, drift)
    with clock.stage("samples"):
        background, samples, noise = _samples(exposure.image, table, fit_table, noise_dn, params, cache)
        threshold = product_threshold(samples.sigma, params)
    with clock.stage("subaperture"):
        sub = subaperture_image(exposure.image, table, fraction=params.aperture_fraction,
                                blur_sigma_px=params.blur_sigma_px, grid=grid, samples=samples, cache=cache)
    fitter = RayFitter(
        exposure.image, fit_table, grid, background=background.per_sample(fit_table),
        aperture_per_lens_plane=aperture_per_lens_plane(optics),
        alpha_half_range=params.refine_alpha_range,
        coarse=FitGrid(depths=params.fit_depths, lateral_pitches=COARSE_LATERAL_PITCHES,
                       positions=params.fit_lateral, pixel_points=1, temperature=COARSE_TEMPERATURE),
        min_intensity=params.min_intensity_sigma * max(samples.sigma, 0.5),
        max_residual=FIT_RESIDUAL_SLACK * params.max_fit_residual, merge_radius_px=params.link_radius_px,
        merge_alpha=params.merge_slices * (float(alphas[1] - alphas[0]) if params.user_range
                                           else lattice_step(params.n_slices)),
        cache=cache, rejected=rejected, saturation=model.white_level,
        blur_px=calibration.blur_px, response_slope=calibration.response_slope,
        second_stop=calibration.second_stop) if params.refine else None
    # How much noisier than the typical ones each fit-table lens's samples are (extended light).
    lens_noise = samples.variance_ratio(background.per_lens(fit_table))
    # The background read the fit's table; the stacks below do not: where it is mapped from the disk
    # cache, its pages go back until the fits read them again (a drifted F01 table: 90 MB).
    release_table_pages(fit_table, cache)
    if not params.user_range:
        with clock.stage("survey"):
            found, lone = _survey(exposure.image, table, background, alphas, params, threshold, cache, fitter,
                                  lens_noise)
        if lone.size:
            warnings.append(f"{lone.size} point source(s) at alpha {', '.join(f'{a:.4f}' for a in lone)} lie far in "
                            f"depth from all the others (over {LONE_GAP_STEPS:g} survey steps) and were left out of "
                            "the range: a compact glint looks so, and so would a lone particle; give the alpha "
                            "range to include them")
        if found is None:
            warnings.append(f"no particles found above the noise anywhere in alpha {alphas[0]:.4f} ... "
                            f"{alphas[-1]:.4f}; check the exposure and the threshold")
            return finish(_no_peaks(), None, None, sub, threshold)
        limits, alphas = fit_limits(found, alphas), found
        trim_heap()  # the survey's stack
    else:
        limits = (alphas[0], alphas[-1])
    image, glints = exposure.image, []
    if params.glints and fitter is not None:
        with clock.stage("glints"):
            glints = find_glints(image, fit_table, background.per_lens(fit_table),
                                 particle_c=(1.0 - 1.0 / limits[0], 1.0 - 1.0 / limits[1]), saturation=model.white_level)
            if glints:
                # Everything from the background on sees the exposure without their light.
                warnings.append(f"{len(glints)} glint(s) far out of focus (alpha "
                                f"{', '.join(f'{g.alpha:.4f}' for g in glints)}) taken off the image")
                image = without_glints(image, fit_table, glints, saturation=model.white_level)
                samples = sub = None  # let go before they are made again (a frame's peak)
                background, samples, noise = _samples(image, table, fit_table, noise_dn, params, cache)
                sub = subaperture_image(image, table, fraction=params.aperture_fraction,
                                        blur_sigma_px=params.blur_sigma_px, grid=grid, samples=samples, cache=cache)
                fitter = dataclasses.replace(fitter, image=image, background=background.per_sample(fit_table))
                lens_noise = samples.variance_ratio(background.per_lens(fit_table))
    release_table_pages(fit_table, cache)  # read by the glints' stage
    with clock.stage("refocus"):
        stack = refocus_stack(image, table, alphas, grid=grid, samples=samples, cache=cache)
    with clock.stage("products"):
        product = products(stack, sub, out=None if keep_stack else stack)

    peaks, tracks = locate(product, alphas, params, threshold=threshold, clock=clock)
    # The depth stages read the raw image, not the stack or the samples: let them go (an F01's
    # fine stack and samples, 30 MB more at the peak of the next pass's own).
    samples = product = None
    if not keep_stack:
        stack = None
    release_table_pages(table, cache)  # until another detection pass refocuses (below)
    trim_heap()
    if params.user_range:
        low, high = edge_maxima(tracks.brightness)
        if low.size + high.size:
            rejected.add(_edge_candidates(tracks, alphas, low, high), "edge_of_range")
            warnings.append(f"{low.size + high.size} particle(s) look brightest at the edge of the alpha range "
                            f"{alphas[0]:.4f} ... {alphas[-1]:.4f} ({low.size} at its start, {high.size} at its "
                            "end) and may lie outside it: widen the range, or leave it out so the pipeline finds it")
    fit, quality = None, {}
    if fitter is not None and len(peaks):
        with clock.stage("refine"):
            peaks = above_noise(fitter, peaks, lens_noise, threshold)
            peaks, fit = inside(fitter, *refine_peaks(fitter, peaks, shadow_probe=params.shadow_probe), limits)
        with clock.stage("more_passes"):
            for _ in range(params.passes - 1):
                found = look_again(fitter, table, background, params, alphas, limits, threshold, peaks, tracks, fit,
                                   lens_noise)
                if found is None:
                    break
                peaks, tracks, fit = found
            trim_heap()
        if params.deblend and len(peaks) > 1:
            with clock.stage("deblend"):
                peaks, fit = deblend(fitter, peaks, fit)
            if params.shadow_probe > 0:
                with clock.stage("split"):
                    peaks, fit = split_shared(fitter, peaks, fit, shadow_probe=params.shadow_probe)
            if params.late_pass:
                with clock.stage("late_pass"):
                    peaks, tracks, fit = late_pass(fitter, table, background, params, alphas, limits, threshold,
                                                   peaks, tracks, fit, lens_noise)
            else:
                clock.skip("late_pass")  # turned off: progress should not wait for it
        if params.depth_prior and len(peaks) > 1:
            with clock.stage("depth_prior"):
                peaks, fit = apply_depth_prior(fitter, peaks, fit)
        if params.deblend and len(peaks) > 1:
            with clock.stage("refit"):
                peaks, fit = refit_blurred(fitter, peaks, fit)
        if params.glints and params.deblend and len(peaks):
            with clock.stage("glints_behind"):
                behind = glints_behind(fitter, fit, background.per_lens(fit_table), limits, glints)
                if behind:
                    warnings.append(f"{len(behind)} glint(s) far out of focus seen through the cluster (alpha "
                                    f"{', '.join(f'{g.alpha:.4f}' for g in behind)}) taken off the image")
                    image = without_glints(fitter.image, fit_table, behind, saturation=model.white_level)
                    release_table_pages(fit_table, cache)  # the background reads it all again
                    # The glow estimated again: where it held some of the glint's light, the fits
                    # would miss that light (kept, 7 of 20 frames with such a glint lost 1-5 particles).
                    if params.weigh_noise:  # the fits' noise comes from the samples
                        background, _, noise = _samples(image, table, fit_table, noise_dn, params, cache)
                    else:
                        background = estimate_background(image, fit_table, noise_dn=noise_dn)
                    fitter = dataclasses.replace(fitter, image=image, background=background.per_sample(fit_table))
                    peaks, fit = refit_in_glints(fitter, peaks, fit, behind, max_residual=params.max_fit_residual)
        with clock.stage("quality"):
            # The refits since the refine stage's merge can bring two fits onto one particle, or
            # move one out of the range (held-out seed 26: three of a compact glint's tiling fits).
            peaks, fit = inside(fitter, *fitter.unique(peaks, fit, max_sigmas=SAME_DEPTH_SIGMAS), limits)
            peaks, fit = _separated(fitter, peaks, fit, grid, coordinates, params.min_separation)
            peaks, fit, share = drop_extended(fitter, peaks, fit)
            peaks, fit, share = drop_misfits(fitter, peaks, fit, share, limit=params.max_fit_residual)
            quality = {"leftover": share}
        if params.deblend and len(peaks):
            with clock.stage("sharpen"):
                peaks, fit = sharpen_blurred(fitter, peaks, fit, noise)
                # Refitted with the others' light off, a ghost can land on the particle beside it;
                # and a fit held at its window's edge by light from beyond the range (a compact
                # glint far out of focus) has its depth profile's vertex out there.
                kept = fitter.merge_rows(peaks, fit, max_sigmas=SAME_DEPTH_SIGMAS)
                kept = kept[within_limits(fitter, peaks.take(kept), fit.take(kept), limits)]
                peaks, fit, quality = peaks.take(kept), fit.take(kept), {"leftover": share[kept]}
    if len(peaks) == 0:
        if len(tracks):
            warnings.append("particles were seen, but none is brightest inside the alpha range "
                            f"{alphas[0]:.4f} ... {alphas[-1]:.4f}; widen the range")
        else:
            warnings.append("no particles found above the noise; check the exposure and the threshold")
    return finish(peaks, tracks, stack, sub, threshold, fit, quality)


def _samples(image: np.ndarray, table: LightFieldTable, fit_table: LightFieldTable, noise_dn: float,
             params: PipelineParams, cache: Cache) -> tuple[BackgroundMap, Samples, SampleNoise | None]:
    """The extended light behind the image (on the depth fit's table), the refocus table's samples
    above it, and their noise for the fits when ``params.weigh_noise``."""
    background = estimate_background(image, fit_table, noise_dn=noise_dn)
    release_table_pages(fit_table, cache)  # not held while the samples read the refocus table
    samples = select_samples(image, table, background=background, noise_sigmas=params.noise_sigmas)
    return background, samples, SampleNoise(*samples.noise, samples.background) if params.weigh_noise else None


def _lattice_drift(exposure: Exposure, calibration: Calibration, cache: Cache, noise_dn: float) -> LatticeDrift | None:
    """How far the exposure's micro-images moved from the white image's (None: too little light to
    tell; the white image's lattice then stands)."""
    lattice = calibration.model.lattice

    def white_phases() -> tuple[np.ndarray, np.ndarray]:
        phases = block_phases(calibration.devignetting, lattice)
        release_pages(calibration.devignetting)
        return phases
    white = cache.get_or_make(("white_phases", calibration.white_sha1), white_phases)
    return estimate_drift(exposure.image, lattice, white, noise_dn=noise_dn)


def _survey(image: np.ndarray, table: LightFieldTable, background: BackgroundMap, survey: np.ndarray,
            params: PipelineParams, threshold: float, cache: Cache, fitter: RayFitter | None,
            lens_noise: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """The fine stack's alphas from a coarse stack over the whole range (``survey``), None when it
    shows no particle; and the alphas of the point fits left out of it as lying apart from the others
    (:func:`analysis.pipeline.depth_range.apart`; recorded as ``apart``).

    Far from focus the shift-and-add lines a particle's samples up again on the lattice (ghosts at
    ``c +- pitch / (aperture metres per pixel)``, about 0.016 in alpha here), so only peaks whose
    light the forward model explains as a point at their depth, and whose lenses show a point's
    pattern (:func:`analysis.depth.quality.patterned`), set the range.

    Its samples are cut by one noise model for the frame (``select_samples(local=False)``), harder
    over glow than each lens's own noise would: the range needs the clear particles only, and the
    faint outskirts of compact glints' blurred disks, which the lower cut lets in, then outshine
    particles on their lines of sight in the coarse stack (nine such particles lost, the range set
    at the glints). Where that cut leaves no point source, the survey looks again with each lens's
    own noise: the frame's model follows the light the background leaves unexplained (a reflection
    under a wider blur: 4x the variance per DN of light that the same frame shows under the ideal
    blur), and a target far from focus, its dots blurred over 17 pitches, then showed none."""
    found, lone = _survey_once(image, table, background, survey, params, threshold, cache, fitter, lens_noise,
                               local=False)
    if found is None:
        found, lone = _survey_once(image, table, background, survey, params, threshold, cache, fitter, lens_noise,
                                   local=True)
    return found, lone


def _survey_once(image: np.ndarray, table: LightFieldTable, background: BackgroundMap, survey: np.ndarray,
                 params: PipelineParams, threshold: float, cache: Cache, fitter: RayFitter | None,
                 lens_noise: np.ndarray, *, local: bool) -> tuple[np.ndarray | None, np.ndarray]:
    samples = select_samples(image, table, background=background, noise_sigmas=params.noise_sigmas, local=local)
    sub = subaperture_image(image, table, fraction=params.aperture_fraction, blur_sigma_px=params.blur_sigma_px,
                            grid=table.grid, samples=samples, cache=cache)
    stack = refocus_stack(image, table, survey, grid=table.grid, samples=samples, cache=cache)
    del samples
    # Its table's pages and normalisations, read in again for the fine stack, are not held through
    # the fits below (held-out seed 34's realistic off-focus ball: 574 -> 537 MB at this stage).
    release_table_pages(table, cache)
    coarse = dataclasses.replace(params, maxima_half_slices=-1)  # the range, not every particle
    peaks, _ = locate(products(stack, sub, out=stack), survey, coarse, threshold=threshold)
    if fitter is not None:
        peaks = above_noise(fitter, peaks, lens_noise, threshold, record=False)  # not the particles' candidates
    alpha, lone = peaks.alpha, np.empty(0)
    if fitter is not None and len(peaks):
        sx, sy = table.grid.to_lens_plane(peaks.x, peaks.y)
        fit = fitter.fit(sx, sy, peaks.alpha, fine=SURVEY_GRID, wide_fine=SURVEY_GRID)
        # As strict as for hidden particles: a ghost or an edge of extended light that the model
        # half explains would stretch the range, and every slice added costs candidates to fit
        # (a glint on the far side of focus, set as the range's end, brought 500 fits of ghosts of
        # real particles there: 3x the time, 9 particles fewer). Such a glint fits as a blurred
        # point; the light in its lenses shows that it is none.
        peaks, fit = fitter.unique(*accept(fitter, peaks, fit, min(fitter.max_residual, PROBE_RESIDUAL),
                                               record=False), record=False)
        point = patterned(fitter, fit, fitter.render(fit))
        log.debug("survey: %d peaks over alpha %.4f ... %.4f, %d explained, %d of them as points", len(peaks),
                  survey[0], survey[-1], len(fit), point.sum())
        peaks, fit = moved(table.grid, peaks, fit).take(point), fit.take(point)
        far = apart(fit.alpha, survey)
        fitter.reject(peaks.take(far), fit.take(far), "apart")
        alpha, lone = fit.alpha[~far], np.sort(fit.alpha[far])
    return range_of_peaks(alpha, survey, n_slices=params.n_slices), lone


def _separated(fitter: RayFitter, peaks: Peaks, fit: RayFit, grid: ImageGrid, coordinates: Calibration3D,
               fraction: float) -> tuple[Peaks, RayFit]:
    """``peaks`` without those closer to a brighter one than particles come (recorded as ``too_close``)."""
    xyz = np.column_stack(_physical(peaks.x, peaks.y, peaks.alpha, grid, coordinates))
    close = too_close(xyz, fit.intensity, fraction)
    fitter.reject(peaks.take(close), fit.take(close), "too_close")
    return peaks.take(~close), fit.take(~close)


def _particle_table(peaks: Peaks, tracks: Tracks | None, alphas: np.ndarray, table: LightFieldTable,
                    coordinates: Calibration3D, warnings: list[str], fit: RayFit | None = None,
                    quality: dict[str, np.ndarray] | None = None) -> tuple[dict[str, np.ndarray], np.ndarray]:
    n = len(peaks)
    # Order particles by image position (row, then column) so tables compare between runs.
    order = np.lexsort((peaks.x, peaks.y)) if n else np.empty(0, dtype=np.int64)
    peaks = peaks.take(order)
    nan = np.full(n, np.nan)
    quality = {name: np.asarray(v, float)[order] for name, v in (quality or {}).items()}
    fit = None if fit is None else fit.take(order)
    X, Y, Z = _physical(peaks.x, peaks.y, peaks.alpha, table.grid, coordinates)
    warnings.extend(coordinate_warnings(X, Y, Z, coordinates))
    if n and not np.isfinite(Z).any():
        warnings.append("no physical coordinates: the metadata give no usable exit-pupil distance; "
                        "give a user calibration (pixel size and depth per alpha)")
    if tracks is not None and n:
        curves = tracks.brightness[peaks.track].astype(np.float32)
        step = float(alphas[1] - alphas[0])
        nearest = np.clip(np.rint((peaks.alpha - alphas[0]) / step).astype(np.int64), 0, alphas.size - 1)
        brightness = tracks.brightness[peaks.track, nearest]
    else:
        curves = np.empty((n, alphas.size), dtype=np.float32)
        brightness = np.empty(n)
    pitch = float(np.hypot(*table.basis_m[:, 0]))
    particles = {"index": np.arange(n, dtype=np.int64), "x": peaks.x, "y": peaks.y, "alpha": peaks.alpha,
                 "X": X, "Y": Y, "Z": Z, "brightness": np.asarray(brightness, float), "peak_height": peaks.peak_height,
                 "peak_width": peaks.peak_width, "residual": peaks.residual, "prominence": peaks.prominence,
                 "alpha_std": nan if fit is None else fit.alpha_spread,
                 # The width of the neighbours' depth prior the final fit weighed (NaN: the pixels alone).
                 "prior_std": nan if fit is None else fit.prior_sigma,
                 "intensity": nan if fit is None else fit.intensity,
                 "n_lit": nan if fit is None else fit.n_lit.astype(float),
                 # Diameter of the blur disk on the micro-lens array, in lens pitches (as the
                 # simulator's truth tables give it): below 1 one lens may hold all the light.
                 "blur_pitches": 2.0 * np.abs(1.0 - 1.0 / peaks.alpha) * table.aperture_radius_m / pitch,
                 "leftover": quality.get("leftover", nan)}
    return particles, curves


def _edge_candidates(tracks: Tracks, alphas: np.ndarray, low: np.ndarray, high: np.ndarray) -> Peaks:
    """Curves brightest on the first (``low``) or last (``high``) slice, as candidates there."""
    rows = np.r_[low, high]
    col = np.r_[np.zeros(low.size, np.int64), np.full(high.size, alphas.size - 1)]
    n = rows.size
    return Peaks(track=rows, alpha=alphas[col], x=tracks.x[rows, col], y=tracks.y[rows, col],
                 peak_height=tracks.brightness[rows, col], peak_width=np.full(n, np.nan), residual=np.full(n, np.nan),
                 prominence=np.full(n, np.nan))


def _physical(x: np.ndarray, y: np.ndarray, alpha: np.ndarray, grid: ImageGrid,
              coordinates: Calibration3D) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``X, Y, Z`` (mm), NaN without a usable depth model."""
    try:
        return tuple(np.asarray(v, float) for v in to_physical(x, y, alpha, grid, coordinates))  # type: ignore[return-value]
    except MetadataError:
        return np.full(len(x), np.nan), np.full(len(x), np.nan), np.full(len(x), np.nan)


def _no_peaks() -> Peaks:
    f = np.empty(0)
    return Peaks(track=np.empty(0, dtype=np.int64), alpha=f, x=f.copy(), y=f.copy(), peak_height=f.copy(),
                 peak_width=f.copy(), residual=f.copy(), prominence=f.copy())


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


def process_many(exposures: Iterable[Exposure | str | Path],
                 calibration: Calibration | Callable[[Exposure], Calibration],
                 params: PipelineParams | None = None, *, keep_stack: bool = False,
                 coordinates: Calibration3D | None = None, cache: Cache | None = None,
                 progress: Callable[[int, float, str], None] | None = None) -> Iterator[Result]:
    """Process a batch (a run), sharing the calibration, look-up tables and compiled kernels.

    Parameters
    ----------
    exposures : iterable of Exposure or paths
        Paths are read with :func:`analysis.formats.exposure.read_exposure` one at a time, so memory
        stays that of one exposure.
    calibration : Calibration, or a callable giving the calibration of an exposure
        A callable lets a batch span zoom settings (e.g. ``lambda e: load_calibration(dir,
        e.metadata, serial=e.serial, cache_dir=cache)``, which caches on disk).
    cache : Cache, optional
        Shared by the whole batch; default: a new one for the batch.
    progress : callable ``(index, fraction, stage)``, optional

    Yields
    ------
    Result
        One per exposure, in order.
    """
    cache = Cache() if cache is None else cache
    for index, item in enumerate(exposures):
        exposure = item if isinstance(item, Exposure) else read_exposure(item)
        cal = calibration(exposure) if callable(calibration) else calibration
        report = None if progress is None else (lambda f, stage, i=index: progress(i, f, stage))
        yield process(exposure, cal, params, keep_stack=keep_stack, progress=report,
                      coordinates=coordinates, cache=cache)


def warm_up() -> None:
    """Compile (or load from numba's cache) every kernel of the pipeline on a tiny sensor crop."""
    from analysis.lightfield.table import build_table_from_model
    from analysis.simulation.camera import simulated_camera_metadata

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
    optics = model.optics
    white = np.ones(image.shape, np.float32)
    white.flags.writeable = False  # as a calibration read from its cache maps it
    shifted_table(table, white, np.full((table.n_lenses, 2), 0.1),
                  m_per_px=optics.pixel_pitch_m / optics.projection_factor,
                  template=micro_image_model(IDEAL_POINT_SPREAD_PX, optics.micro_image_radius_px, 1.0),
                  defects=np.zeros(image.shape, bool))
