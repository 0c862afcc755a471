"""Calibration of one camera at one zoom/focus from a white image: the fitted micro-image lattice
(:mod:`analysis.calibration.lattice_fit`, seeded from the white's own metadata model) and the
devignetting map."""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from analysis.camera.model import CameraModel, Lattice
from analysis.errors import MetadataError
from analysis.formats.whites import WhiteImage

from .lattice_fit import LatticeFit, fit_lattice

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

    @property
    def lattice(self) -> Lattice:
        return self.model.lattice


def calibrate(white: WhiteImage, *, fallback_metadata: dict | None = None) -> Calibration:
    """Fit the lattice to a white image and keep its devignetting map.

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
        If the lattice fit fails.
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
    log.info("white image %s: lattice %s, fit rms %.4f px over %d blocks, %d lenses (centroid rms %.3f px)",
             white.name, fit.lattice, fit.rms_px, fit.n_blocks, fit.n_lenses, fit.centroid_rms_px)
    devignetting = raw.astype(np.float32)
    devignetting -= np.float32(model.black_level)
    devignetting *= np.float32(1.0 / (model.white_level - model.black_level))
    return Calibration(serial=white.serial, white_name=white.name, white_sha1=white.sha1,
                       zoom_step=white.zoom_step, focus_step=white.focus_step,
                       model=model.with_lattice(fit.lattice), devignetting=devignetting,
                       fit_rms_px=fit.rms_px, fit_n_lenses=fit.n_lenses,
                       fit_centroid_rms_px=fit.centroid_rms_px)
