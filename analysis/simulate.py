"""Forward model of the F01 (camera-model.md, "How a ray reaches the sensor") and its readout.

White images are rendered per micro-lens analytically (the aperture disk behind each lens,
sub-pixel coverage); exposures of point particles by tracing stratified rays over the aperture.
Both share the readout: a 0.5 px Gaussian (diffraction and pixel integration), the Bayer
responses, shot and read noise, black level and 12-bit quantisation.

Vignetting: each micro-image is scaled by the ``cos^4`` of its chief ray (aperture centre to
lens centre), the same factor in white images and exposures, so dividing an exposure by its
white image removes it exactly and micro-image centroids stay at the lattice centres.
(camera-model.md step 4 takes the angle per ray; within one micro-image the two differ by up
to about 11 % at the rim for this f/2 camera.)
"""

from __future__ import annotations

import logging
import math

import cv2
import numpy as np

from ._sim_kernels import paint_disks
from .camera_model import CameraModel
from .errors import ParameterError
from .sim_camera import ELECTRONS_PER_DN, READ_NOISE_DN, WHITE_RESPONSE, chief_ray_cos4

log = logging.getLogger(__name__)

# Stands for diffraction and pixel-to-pixel spread (camera-model.md step 4).
BLUR_SIGMA_PX = 0.5
_RIM_SUPERSAMPLE = 12


def channel_response_map(height: int, width: int, responses: dict[str, float]) -> np.ndarray:
    """Per-pixel response of the BGGR mosaic, float32 (H, W).

    Even rows read B, G, B, G ...; odd rows G, R, G, R ... (lytro-f01.md 1.5).
    """
    out = np.empty((height, width), dtype=np.float32)
    out[0::2, 0::2] = responses["b"]
    out[0::2, 1::2] = responses["g"]
    out[1::2, 0::2] = responses["g"]
    out[1::2, 1::2] = responses["r"]
    return out


def blur(image: np.ndarray) -> np.ndarray:
    """The optics' small Gaussian (``BLUR_SIGMA_PX``) on a float32 image."""
    return cv2.GaussianBlur(image, (0, 0), sigmaX=BLUR_SIGMA_PX, sigmaY=BLUR_SIGMA_PX,
                            borderType=cv2.BORDER_REFLECT_101)


def read_out(expected_dn: np.ndarray, *, black: float, white: float, rng: np.random.Generator | None) -> np.ndarray:
    """Sensor readout of an expected signal (DN above black): shot and read noise, black level,
    12-bit clip and rounding. ``rng=None`` gives the noiseless rounded image.

    Returns
    -------
    ndarray of shape (H, W), uint16, values in ``0 ... white``.
    """
    if rng is None:
        values = expected_dn.astype(np.float64) + black
    else:
        electrons = rng.poisson(np.maximum(expected_dn, 0.0).astype(np.float64) * ELECTRONS_PER_DN)
        values = electrons / ELECTRONS_PER_DN
        values += rng.standard_normal(expected_dn.shape) * READ_NOISE_DN
        values += black
    np.rint(values, out=values)
    np.clip(values, 0, white, out=values)
    return values.astype(np.uint16)


def lens_vignetting(model: CameraModel, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """``cos^4`` of the chief ray of lenses ``(i, j)`` (aperture centre to physical lens centre)."""
    s, t = model.lens_plane_position_m(i, j)
    return np.asarray(chief_ray_cos4(np.hypot(s, t), model.optics.exit_pupil_m), dtype=np.float64)


def white_coverage(model: CameraModel) -> np.ndarray:
    """Noise-free white-light irradiance in units of a fully lit on-axis pixel, float32 (H, W).

    Each micro-image is the aperture disk of radius ``(D/2) d / P`` around its lattice centre,
    integrated over each pixel, times its chief-ray ``cos^4``, then blurred by the optics.
    """
    radius = model.optics.micro_image_radius_px
    ij, centres = model.lattice.centres(model.width, model.height, margin_px=-(radius + 2.0))
    vignette = lens_vignetting(model, ij[:, 0], ij[:, 1])
    out = np.zeros((model.height, model.width), dtype=np.float32)
    paint_disks(out, np.ascontiguousarray(centres[:, 0]), np.ascontiguousarray(centres[:, 1]),
                vignette, float(radius), _RIM_SUPERSAMPLE)
    return blur(out)


def render_white_image(model: CameraModel, *, level: float = 2400.0, seed: int = 0, noise: bool = True,
                       responses: dict[str, float] | None = None) -> np.ndarray:
    """Raw white (modulation) image of a uniformly lit diffuse scene through ``model``'s optics.

    Parameters
    ----------
    model : CameraModel
        Sensor size, lattice (micro-image centres) and thin-lens optics.
    level : float
        Raw value above black of a fully lit green pixel on the optical axis, in DN.
    seed : int
        Seed of the shot and read noise.
    noise : bool
        False gives the expected values, rounded.
    responses : dict, optional
        Bayer channel responses ``{"r", "g", "b"}``; white light by default.

    Returns
    -------
    ndarray of shape (H, W), uint16
        Raw 12-bit values including the black level.

    Examples
    --------
    >>> from analysis.sim_camera import simulated_camera_metadata
    >>> model = CameraModel.from_metadata(simulated_camera_metadata(size=64))
    >>> render_white_image(model, seed=1).shape
    (64, 64)
    """
    if not (0.0 <= level <= 1e5):
        raise ParameterError(f"white level {level} DN is out of range; use 0 ... 4095 for an unsaturated image")
    responses = WHITE_RESPONSE if responses is None else responses
    expected = white_coverage(model)
    expected *= channel_response_map(model.height, model.width, responses)
    expected *= np.float32(level)
    rng = np.random.default_rng(seed) if noise else None
    return read_out(expected, black=model.black_level, white=model.white_level, rng=rng)


_ = math
