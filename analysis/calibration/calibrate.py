"""Calibration of one camera at one zoom/focus from a white image: the fitted micro-image lattice
(:mod:`analysis.calibration.lattice_fit`, seeded from the white's own metadata model), the
devignetting map, and the optical blur and micro-image response fitted to its micro-images
(:mod:`analysis.calibration.profile`). The camera's defective pixels, found from all its calibration
frames, join it in :func:`analysis.calibration.cache.load_calibration`."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np

from analysis.camera.model import IDEAL_POINT_SPREAD_PX, CameraModel, Lattice
from analysis.camera.second_stop import SecondStop
from analysis.errors import CalibrationError, MetadataError
from analysis.formats.whites import WhiteImage

from .defects import DefectMap
from .lattice_fit import LatticeFit, fit_lattice
from .profile import MicroImageProfile, fit_micro_image_profile
from .second_stop_fit import fit_second_stop

#: The point spread (sigma, px) the depth fit models when the white image gives none: the ideal
#: optics' (camera-model.md step 4).
DEFAULT_BLUR_PX = IDEAL_POINT_SPREAD_PX

log = logging.getLogger(__name__)


@dataclass(frozen=True, eq=False)
class Calibration:
    """Micro-image lattice and devignetting map of one camera at one zoom/focus.

    Attributes
    ----------
    serial : str or None
        Camera serial number of the white image (``None`` if its metadata has none).
    white_name, white_sha1 : str
        The white image used (e.g. ``MOD_0012``) and the SHA-1 of its packed raw bytes.
    zoom_step, focus_step : int or None
        Lens stepper positions of the white image.
    model : CameraModel
        The white image's metadata model with the fitted lattice. For an exposure, combine
        the exposure's optics with this lattice:
        ``CameraModel.from_metadata(meta).with_lattice(calibration.model.lattice)``.
    devignetting : ndarray of shape (H, W), float32
        ``(white - black) / (white_level - black)`` per pixel, not smoothed or clipped: the
        gaps between micro-images are near (or, by noise, below) zero, so divide only where it
        is above a floor.
    fit_rms_px : float
        RMS of the lattice-fit residuals in pixels.
    fit_n_lenses : int
        Lenses whose centroid agreed with the fitted lattice (within 1 px).
    fit_centroid_rms_px : float
        RMS distance between micro-image centroids and fitted centres (a check on the fit;
        centroids are noisier than the fit).
    from_cache : bool
        True when this calibration was read from the cache instead of fitted.
    profile : MicroImageProfile or None
        The optical blur, the aperture image's radius and the pixel response toward the rim, fitted
        to the white image's micro-images; None when the white image allowed no fit (then the depth
        fit models the ideal optics' blur, :data:`DEFAULT_BLUR_PX`).
    defects : DefectMap or None
        Hot, stuck and dead pixels of the camera, from all its calibration frames
        (:func:`analysis.calibration.cache.load_calibration`); the look-up tables leave them out.
        None when not searched.
    second_stop : SecondStop or None
        The main lens's second stop, from how the white image's micro-images shrink toward the
        corners (:func:`analysis.calibration.second_stop_fit.fit_second_stop`); None when they do not.
    """

    serial: str | None
    white_name: str
    white_sha1: str
    zoom_step: int | None
    focus_step: int | None
    model: CameraModel
    devignetting: np.ndarray
    fit_rms_px: float
    fit_n_lenses: int
    fit_centroid_rms_px: float
    from_cache: bool = False
    profile: MicroImageProfile | None = None
    defects: DefectMap | None = None
    second_stop: SecondStop | None = None

    @property
    def lattice(self) -> Lattice:
        return self.model.lattice

    @property
    def blur_px(self) -> float:
        """Sigma (px) of the camera's point spread for the depth fit: the white image's, else the default."""
        return DEFAULT_BLUR_PX if self.profile is None else self.profile.blur_px

    @property
    def response_slope(self) -> float:
        """The pixel response within a micro-image for the depth fit, ``ln(response)`` per squared
        pixel of offset from its centre: the white image's (``rim_response ** (r / radius_px) ** 2``),
        else 0 (flat)."""
        if self.profile is None:
            return 0.0
        return math.log(self.profile.rim_response) / self.profile.radius_px ** 2

    @property
    def defect_mask(self) -> np.ndarray | None:
        """ndarray (H, W) bool of the defective pixels, or None when there are none (or no search)."""
        return None if self.defects is None or len(self.defects) == 0 else self.defects.mask

    @property
    def defects_key(self) -> str:
        """What the look-up tables built with this calibration's defect map are filed under ("" for none)."""
        return "" if self.defects is None or len(self.defects) == 0 else self.defects.key


def calibrate(white: WhiteImage, *, fallback_metadata: dict | None = None) -> Calibration:
    """Fit the lattice and the micro-image profile to a white image and keep its devignetting map.

    Parameters
    ----------
    white : WhiteImage
    fallback_metadata : dict, optional, keyword-only
        Frame metadata to seed the lattice from if the white's own metadata cannot (e.g. the
        picture's metadata, same camera).

    Raises
    ------
    MetadataError
        If neither metadata gives a camera model.
    CalibrationError
        If the lattice fit fails (a failed profile fit is logged and leaves ``profile`` None).
    """
    try:
        model = CameraModel.from_metadata(white.metadata)
    except MetadataError:
        if fallback_metadata is None:
            raise
        log.warning("white image %s: metadata gives no camera model; seeding from the picture's", white.name)
        model = CameraModel.from_metadata(fallback_metadata)
    raw = white.image()
    fit: LatticeFit = fit_lattice(raw, model.lattice, black_level=model.black_level)
    log.info("white image %s: lattice %s, fit rms %.4f px over %d blocks (%d left out, holding cut micro-images), "
             "%d lenses (centroid rms %.3f px)", white.name, fit.lattice, fit.rms_px, fit.n_blocks, fit.n_cut_blocks,
             fit.n_lenses, fit.centroid_rms_px)
    try:
        profile: MicroImageProfile | None = fit_micro_image_profile(
            raw, fit.lattice, black_level=model.black_level, white_level=model.white_level,
            radius_px=model.optics.micro_image_radius_px)
    except CalibrationError as exc:
        log.warning("white image %s: no micro-image profile (%s); the depth fit models the default blur of %.2f px",
                    white.name, exc, DEFAULT_BLUR_PX)
        profile = None
    devignetting = raw.astype(np.float32)
    devignetting -= np.float32(model.black_level)
    devignetting *= np.float32(1.0 / (model.white_level - model.black_level))
    calibration = Calibration(serial=white.serial, white_name=white.name, white_sha1=white.sha1,
                              zoom_step=white.zoom_step, focus_step=white.focus_step,
                              model=model.with_lattice(fit.lattice), devignetting=devignetting,
                              fit_rms_px=fit.rms_px, fit_n_lenses=fit.n_lenses,
                              fit_centroid_rms_px=fit.centroid_rms_px, profile=profile)
    radius = model.optics.micro_image_radius_px if profile is None else profile.radius_px
    return replace(calibration, second_stop=fit_second_stop(raw, calibration.model, radius_px=radius,
                                                            response_slope=calibration.response_slope,
                                                            blur_px=calibration.blur_px))
