"""Every setting of the pipeline, in one object that is stored with each result."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from analysis.camera.coordinates import UserCalibration
from analysis.errors import ParameterError
from analysis.lightfield.refocus import alphas_for_depth_range, default_alphas


@dataclass
class PipelineParams:
    """Every setting of the pipeline; stored with each result.

    Attributes
    ----------
    alpha_min, alpha_max, n_slices
        Refocus parameters of the stack (the paper: 40 over 0.987 ... 1.013). ``alpha_min`` and
        ``alpha_max`` None (the default): the range that holds the exposure's particles, found by
        a survey (:mod:`analysis.pipeline.depth_range`), at ``n_slices`` slices per 0.026 of alpha
        (and at least ``n_slices``).
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
        into two particles that far apart (:func:`analysis.depth.deblend.split_shared`). 0 turns both off.
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
    late_pass
        With ``deblend``: once the particles are deblended, one more detection pass with their
        light taken off, and all of them deblended again with what it finds (faint particles
        blurred over many pitches among brighter ones, whose refocused spots merged with theirs).
        On realistic off-focus balls and clouds not tuned on (seeds 33-36) it raised the recall
        from 92.2 to 94.5 % and from 94.0 to 95.7 %, with 4 false particles more (10 of the 2098
        found), none on a reflection; it costs about 1.3x the time: turn it off where speed
        matters more.
    depth_prior
        Where a particle's neighbours lie on one surface, take the depth that surface predicts as a
        prior, weighed with the pixels (:func:`apply_depth_prior`, :mod:`analysis.depth.prior`): it
        decides where they leave the depth open (the light falls in one micro-lens); in a 3D crowd
        no surface fits and it does nothing. Turn it off to measure out-of-surface motion from the
        pixels alone.
    glints
        Find compact sources far out of focus (glints: laser light scattered off electrodes or
        windows) beyond the particles' range, fit each as a source spread over the lens plane, and
        take their light off the raw image before the particles are looked for
        (:mod:`analysis.lightfield.glints`); otherwise the tests of extended light drop particles
        in a glint's disk. Once the particles are fitted, glints seen through the cluster are
        looked for too, where fits show no point's pattern, and taken off
        (:mod:`analysis.pipeline.hidden_glints`).
    weigh_noise
        The last refit of the strongly blurred particles (``sharpen``) weighs each sample by its
        noise (:class:`analysis.depth.sample_noise.SampleNoise`), not all alike. Off by default: it
        helps where the forward model matches the camera (depth error through ideal optics 14-27 %
        lower on tuning seed 27 and fresh seeds 70-71, with vignetting alone 3-19 % lower on
        fresh 70-71), but with every effect together it was mixed on tuning seed 27 (ball 3.8 ->
        4.0 %, cloud 4.9 -> 4.1 % of NN) and worse on fresh off-focus balls 70-71 (pooled 3.1 ->
        3.9 %). With the pixel response modelled (stop 42), which removed the +2.5 % depth bias of
        the wider blur and the response together, it was still no better with every effect
        (tuning 27-28: ball 27 3.7 -> 4.2 %, cloud 28 4.9 -> 5.3 %, the other two unchanged).
        It takes that refit 1.3-1.9x its time (tuning ball 27 and cloud 27).
    min_separation
        A prior of the physics: particles in a plasma repel one another, so none comes much closer
        to another than about half their typical spacing. Of two particles closer than this
        fraction of the median nearest-neighbour distance (3D, physical coordinates) the fainter
        is one particle's light fitted twice and is dropped (``too_close``); 0 turns it off. On the
        realism bench's frames of seeds 1-2 and 25-28 real pairs stood at least 0.47 of it apart
        (the shadowing partners, placed 0.5 apart on purpose), 5 of the 24 false particles 0.09-0.28.
    merge_slices
        Refined particles closer than ``link_radius_px`` in the image and this many slices in alpha
        are one particle (the brighter kept): candidates of one particle converge there.
    passes
        Detection passes: each after the first looks again at the raw image with the light of the
        particles found so far taken off (crowded clusters, where blobs merge). 1: a single pass.
    min_intensity_sigma, max_fit_residual
        Refined particles whose fitted pixel intensity is below this many raw-noise sigmas, or
        whose forward-model misfit per pixel exceeds this fraction of that intensity, are
        dropped: noise, a particle whose depth lies outside the alpha range, or light a brighter
        neighbour's model leaves. The fits on the way, which still carry their neighbours' light,
        may misfit 1.4 times as much (:data:`analysis.depth.quality.FIT_RESIDUAL_SLACK`).
    pixel_size_mm, depth_per_alpha_mm, reference_alpha, reference_z_mm
        A user calibration of the physical coordinates (:class:`UserCalibration`); when
        ``pixel_size_mm`` and ``depth_per_alpha_mm`` are None the thin-lens model of the
        exposure's metadata is used.
    """

    alpha_min: float | None = None
    alpha_max: float | None = None
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
    max_fit_residual: float = 0.25
    shadow_probe: float = 0.0065
    passes: int = 2
    maxima_half_slices: int = 2
    merge_slices: float = 4.0
    fit_depths: int = 17
    fit_lateral: int = 5
    deblend: bool = True
    late_pass: bool = True
    depth_prior: bool = True
    glints: bool = True
    weigh_noise: bool = False
    min_separation: float = 0.3
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
        if (self.alpha_min is None) != (self.alpha_max is None):
            raise ParameterError("give both alpha_min and alpha_max, or neither (the range is then found from "
                                 "the exposure)")
        if self.alpha_min is not None and not (0 < self.alpha_min < self.alpha_max):
            raise ParameterError(f"need 0 < alpha_min < alpha_max, got {self.alpha_min}, {self.alpha_max}")
        if self.depth_range_mm is not None and self.alpha_min is not None:
            raise ParameterError("give an alpha range or a depth range, not both")
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
        if not (0 <= self.min_separation < 1):
            raise ParameterError(f"min_separation must be in [0, 1) (of the median nearest-neighbour distance), "
                                 f"got {self.min_separation}")
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

    @property
    def user_range(self) -> bool:
        """Whether the user gave the refocus range (else the pipeline finds it)."""
        return self.depth_range_mm is not None or self.alpha_min is not None

    def alphas(self, optics: Any = None) -> np.ndarray | None:
        """The refocus parameters of the stack (ascending) that the user asked for; None when the
        pipeline is to find the range from the exposure."""
        if self.depth_range_mm is not None:
            if optics is None:
                raise ParameterError("a depth range needs the exposure's optics to convert it to alphas")
            return alphas_for_depth_range(self.depth_range_mm[0], self.depth_range_mm[1], self.n_slices, optics)
        if self.alpha_min is None:
            return None
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
