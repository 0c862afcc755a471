"""The Cramér-Rao bound of a particle's position and depth from its raw pixels.

How precisely could any estimator place a particle, given what the simulated camera records of
it? The Fisher information of the expected raw image, with the sensor's shot and read noise,
over the particle's position ``X, Y, Z`` and brightness (a nuisance parameter), inverted: the
square roots of its diagonal are the smallest standard errors an unbiased estimate can have.

The bound is that of an **isolated** particle near the optical axis, rendered through the
simulator's optics (:func:`analysis.simulation.render.accumulate_particles`, its blur and Bayer
response) on a small sensor crop: neighbours, saturation, glow gradients and a forward model that
differs from the camera only add to it. Derivatives are central differences of renders that share
their ray samples (the same seed), so the sampling of the aperture does not show as signal.

It tells how far a pipeline's errors are from what the pixels allow, and how much of an
optical effect's cost is physics: for the off-focus ball, a 0.8 px blur instead of the ideal
0.5 px raises the bound 1.2-1.35x, a 1.2 px blur 1.4-1.7x.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from analysis.camera.model import CameraModel
from analysis.errors import ParameterError

from .camera import ELECTRONS_PER_DN, LASER_532_RESPONSE, READ_NOISE_DN, simulated_camera_metadata
from .camera_effects import CameraEffects
from .realism import IDEAL_BLUR_PX
from .render import accumulate_particles, blur, channel_response_map
from .scenarios import Particles

#: Central-difference steps (mm) in X, Y and Z: large enough that the rays' landing points move
#: across many pixels' worth of sampling, small against the bound's scale of micrometres to tens.
STEPS_MM = (0.002, 0.002, 0.01)


@dataclass(frozen=True)
class PositionBound:
    """Smallest standard errors (mm) of ``X, Y, Z`` per particle, arrays of shape ``(n,)``."""

    sigma_x_mm: np.ndarray
    sigma_y_mm: np.ndarray
    sigma_z_mm: np.ndarray


def position_bound(z_mm: np.ndarray, brightness_dn: np.ndarray, *, blur_px: float = IDEAL_BLUR_PX,
                   background_dn: float = 0.0, size: int = 512, samples_per_side: int = 300,
                   seed: int = 0) -> PositionBound:
    """The Cramér-Rao bound of isolated particles at depths ``z_mm`` with ``brightness_dn``.

    Parameters
    ----------
    z_mm, brightness_dn : ndarray of shape (n,)
        Depth (mm, camera frame) and brightness (as :class:`analysis.simulation.scenarios.Particles`).
    blur_px : float
        The optics' point spread (sigma, px).
    background_dn : float
        Diffuse glow under each pixel (DN), which adds shot noise.
    size : int
        Side of the simulated sensor crop (px); each particle is placed a little off its centre.
    samples_per_side, seed
        Ray sampling of the aperture (as :func:`analysis.simulation.render.render_exposure`).

    Returns
    -------
    PositionBound

    Raises
    ------
    ParameterError
        For arrays of different lengths, non-positive brightness or a negative glow.
    """
    z_mm = np.atleast_1d(np.asarray(z_mm, float))
    brightness_dn = np.atleast_1d(np.asarray(brightness_dn, float))
    if z_mm.shape != brightness_dn.shape:
        raise ParameterError("z_mm and brightness_dn must have the same length")
    if np.any(brightness_dn <= 0) or background_dn < 0:
        raise ParameterError("brightness must be positive and the background not negative")
    model = CameraModel.from_metadata(simulated_camera_metadata(size=size))
    camera = CameraEffects(blur_px=blur_px)
    response = channel_response_map(model.height, model.width, LASER_532_RESPONSE).astype(np.float64)
    out = np.full((z_mm.size, 3), np.nan)
    # Off the crop's centre by a fraction of a lens, so the particles do not all sit on one
    # lens's axis (a special case of the light's split between lenses).
    offsets = np.random.default_rng(seed).uniform(-0.02, 0.02, (z_mm.size, 2))
    for i, (z, b) in enumerate(zip(z_mm, brightness_dn)):

        def expected(x: float, y: float, zz: float) -> np.ndarray:
            one = Particles(np.array([x]), np.array([y]), np.array([zz]), np.array([b]))
            light = accumulate_particles(model, one, rng=np.random.default_rng(seed),
                                         samples_per_side=samples_per_side, camera=camera)
            return blur(light, blur_px).astype(np.float64) * response

        x0, y0 = offsets[i]
        mean = expected(x0, y0, z)
        derivatives = []
        for axis, h in enumerate(STEPS_MM):
            step = np.zeros(3)
            step[axis] = h
            plus = expected(x0 + step[0], y0 + step[1], z + step[2])
            minus = expected(x0 - step[0], y0 - step[1], z - step[2])
            derivatives.append(((plus - minus) / (2 * h)).ravel())
        derivatives.append(mean.ravel() / b)
        d = np.stack(derivatives)
        variance = READ_NOISE_DN ** 2 + (mean.ravel() + background_dn) / ELECTRONS_PER_DN
        fisher = (d / variance) @ d.T
        try:
            cov = np.linalg.inv(fisher)
        except np.linalg.LinAlgError:
            continue  # the crop holds none of its light
        out[i] = np.sqrt(np.clip(np.diag(cov)[:3], 0.0, None))
    return PositionBound(out[:, 0], out[:, 1], out[:, 2])
