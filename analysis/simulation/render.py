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

A realistic camera (``camera=CameraEffects``, see :mod:`analysis.simulation.realism`) adds, in
white images and exposures alike: a wider point spread, a pixel response falling toward each
micro-image's rim (per ray, by the ray's angle to its micro-image's chief ray), a transmission per
micro-lens, a second stop that cuts rays off axis (cat's-eye micro-images), and hot and dead
pixels after the read-out; exposures also see the micro-lens lattice drifted from the white
images'. A chamber (``chamber=ChamberLight``) adds a glow gradient and out-of-focus reflections.
Without them the ideal camera is rendered exactly as before, byte for byte.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from .kernels import paint_disks
from analysis.camera.model import CameraModel, Lattice, Optics
from analysis.errors import ParameterError
from .scenarios import Particles
from .camera import ELECTRONS_PER_DN, LASER_532_RESPONSE, READ_NOISE_DN, WHITE_RESPONSE, chief_ray_cos4
from .camera_effects import CameraEffects
from .chamber import ChamberLight, render_reflections
from .realism import IDEAL_BLUR_PX
from .realism_kernels import paint_micro_images

# Stands for diffraction and pixel-to-pixel spread (camera-model.md step 4).
BLUR_SIGMA_PX = IDEAL_BLUR_PX
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


def blur(image: np.ndarray, sigma_px: float = BLUR_SIGMA_PX) -> np.ndarray:
    """The optics' Gaussian point spread (``BLUR_SIGMA_PX`` for the ideal camera) on a float32 image."""
    return cv2.GaussianBlur(image, (0, 0), sigmaX=sigma_px, sigmaY=sigma_px,
                            borderType=cv2.BORDER_REFLECT_101)


def point_spread(image: np.ndarray, camera: CameraEffects) -> np.ndarray:
    """The realistic camera's point spread on a float32 image: the Gaussian of ``camera.blur_px``,
    with ``camera.psf_halo`` of the light in the wider Gaussian halo of ``camera.psf_halo_px``."""
    core = blur(image, camera.blur_px)
    if camera.psf_halo <= 0:
        return core
    core *= np.float32(1.0 - camera.psf_halo)
    core += np.float32(camera.psf_halo) * blur(image, camera.psf_halo_px)
    return core


def read_out(expected_dn: np.ndarray, *, black: float, white: float, rng: np.random.Generator | None,
             rows_per_block: int = 256) -> np.ndarray:
    """Sensor readout of an expected signal (DN above black): shot and read noise, black level,
    12-bit clip and rounding. ``rng=None`` gives the noiseless rounded image.

    Works in blocks of rows, so the float64 temporaries stay small on a full frame.

    Returns
    -------
    ndarray of shape (H, W), uint16, values in ``0 ... white``.
    """
    out = np.empty(expected_dn.shape, dtype=np.uint16)
    for r0 in range(0, expected_dn.shape[0], rows_per_block):
        block = expected_dn[r0:r0 + rows_per_block]
        if rng is None:
            values = block.astype(np.float64) + black
        else:
            electrons = rng.poisson(np.maximum(block, 0.0).astype(np.float64) * ELECTRONS_PER_DN)
            values = electrons / ELECTRONS_PER_DN
            values += rng.standard_normal(block.shape) * READ_NOISE_DN
            values += black
        np.rint(values, out=values)
        np.clip(values, 0, white, out=values)
        out[r0:r0 + rows_per_block] = values
    return out


def lens_vignetting(model: CameraModel, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """``cos^4`` of the chief ray of lenses ``(i, j)`` (aperture centre to physical lens centre)."""
    s, t = model.lens_plane_position_m(i, j)
    return np.asarray(chief_ray_cos4(np.hypot(s, t), model.optics.exit_pupil_m), dtype=np.float64)


def white_coverage(model: CameraModel, *, camera: CameraEffects | None = None) -> np.ndarray:
    """Noise-free white-light irradiance in units of a fully lit on-axis pixel, float32 (H, W).

    Each micro-image is the aperture disk of radius ``(D/2) d / P`` around its lattice centre,
    integrated over each pixel, times its chief-ray ``cos^4``, then blurred by the optics.
    With ``camera``, the realistic camera's micro-images instead (`camera_coverage`).
    """
    if camera is not None:
        return camera_coverage(model, camera)
    radius = model.optics.micro_image_radius_px
    ij, centres = model.lattice.centres(model.width, model.height, margin_px=-(radius + 2.0))
    vignette = lens_vignetting(model, ij[:, 0], ij[:, 1])
    out = np.zeros((model.height, model.width), dtype=np.float32)
    paint_disks(out, np.ascontiguousarray(centres[:, 0]), np.ascontiguousarray(centres[:, 1]),
                vignette, float(radius), _RIM_SUPERSAMPLE)
    return blur(out)


def camera_coverage(model: CameraModel, camera: CameraEffects, *, lattice: Lattice | None = None,
                    chamber: ChamberLight | None = None) -> np.ndarray:
    """Diffuse light through the realistic camera: irradiance in units of a fully lit on-axis pixel,
    float32 (H, W), after the camera's point spread.

    Each micro-image is the aperture seen through the second stop (the intersection of two disks
    for lenses off axis), times the pixel response toward its rim, its lens's transmission and
    chief-ray ``cos^4``, and with ``chamber`` the chamber's glow profile at the lens.

    Parameters
    ----------
    model : CameraModel
        Sensor, optics, and the optical axis (its lattice's origin).
    camera : CameraEffects
    lattice : Lattice, optional
        The micro-lens lattice the light passes; ``model``'s (the white images') by default.
    chamber : ChamberLight, optional
        Its glow profile at each micro-image's centre scales the micro-image (plasma glow).
    """
    optics = _require_finite_p(model)
    lattice = model.lattice if lattice is None else lattice
    radius = optics.micro_image_radius_px
    ij, centres = lattice.centres(model.width, model.height, margin_px=-(radius + 2.0))
    cx = np.ascontiguousarray(centres[:, 0])
    cy = np.ascontiguousarray(centres[:, 1])
    sx, sy = _lens_plane_m(model, cx, cy)
    value = chief_ray_cos4(np.hypot(sx, sy), optics.exit_pupil_m) * camera.lens_gain(ij[:, 0], ij[:, 1])
    if chamber is not None:
        value = value * chamber.glow_profile(model, cx, cy)
    stop = camera.second_stop(model)
    to_px = optics.mla_to_sensor_m / (optics.exit_pupil_m * optics.pixel_pitch_m)  # aperture m -> px
    if stop is None:
        stop_dx = stop_dy = np.zeros_like(cx)
        radius2 = np.inf
    else:
        stop_dx = np.ascontiguousarray(stop.shift_per_m * sx * to_px)
        stop_dy = np.ascontiguousarray(stop.shift_per_m * sy * to_px)
        radius2 = stop.radius_m * to_px
    out = np.zeros((model.height, model.width), dtype=np.float32)
    paint_micro_images(out, cx, cy, np.ascontiguousarray(value, dtype=np.float64), float(radius), stop_dx, stop_dy,
                       float(radius2), optics.pixel_pitch_m / optics.mla_to_sensor_m, camera.half_n,
                       _RIM_SUPERSAMPLE)
    return point_spread(out, camera)


def _lens_plane_m(model: CameraModel, cx: np.ndarray, cy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Physical lens centres on the MLA (metres from the optical axis) of micro-image centres ``(cx, cy)``.

    The optical axis meets the sensor at ``model``'s lattice origin, whatever lattice the centres
    come from (a drifted one moves the lenses, not the axis).
    """
    k = model.optics.pixel_pitch_m / model.optics.projection_factor
    return (np.asarray(cx) - model.lattice.origin_x) * k, (np.asarray(cy) - model.lattice.origin_y) * k


def _require_finite_p(model: CameraModel) -> Optics:
    if model.optics.exit_pupil_m is None:
        raise ParameterError("the camera model has no finite exit-pupil distance (exitPupilOffset.z), so rays "
                             "cannot be traced; build it from simulated_camera_metadata()")
    return model.optics


def render_white_image(model: CameraModel, *, level: float = 2400.0, seed: int = 0, noise: bool = True,
                       responses: dict[str, float] | None = None, camera: CameraEffects | None = None
                       ) -> np.ndarray:
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
    camera : CameraEffects, optional
        A realistic camera (its micro-images and its sensor defects); the ideal one by default.

    Returns
    -------
    ndarray of shape (H, W), uint16
        Raw 12-bit values including the black level.

    Examples
    --------
    >>> from analysis.simulation.camera import simulated_camera_metadata
    >>> model = CameraModel.from_metadata(simulated_camera_metadata(size=64))
    >>> render_white_image(model, seed=1).shape
    (64, 64)
    """
    if not (0.0 <= level <= 1e5):
        raise ParameterError(f"white level {level} DN is out of range; use 0 ... 4095 for an unsaturated image")
    responses = WHITE_RESPONSE if responses is None else responses
    expected = white_coverage(model, camera=camera)
    expected *= channel_response_map(model.height, model.width, responses)
    expected *= np.float32(level)
    rng = np.random.default_rng(seed) if noise else None
    raw = read_out(expected, black=model.black_level, white=model.white_level, rng=rng)
    return raw if camera is None else camera.with_defects(raw, model)



@dataclass(frozen=True)
class ParticleTruth:
    """What the optics make of each particle: the quantities the pipeline is judged against.

    Attributes
    ----------
    alpha : ndarray (N,)
        ``Fp / P``: the refocus parameter that brings the particle into focus.
    x_px, y_px : ndarray (N,)
        Where the particle's chief ray (through the lens centre) meets the MLA, expressed in
        sensor pixels of the micro-image lattice: ``origin + s (P + d) / (P p)``, upright frame.
        At ``alpha = 1`` the particle lights the lens whose micro-image centre is nearest this.
    blur_pitches : ndarray (N,)
        Diameter of its defocus blur disk on the MLA, ``D |Fp - P| / Fp``, in lens pitches.
    """

    alpha: np.ndarray
    x_px: np.ndarray
    y_px: np.ndarray
    blur_pitches: np.ndarray


def particle_truth(model: CameraModel, particles: Particles) -> ParticleTruth:
    """Ideal image quantities of each particle under ``model``'s thin lens (camera-model.md)."""
    optics = _require_thin_lens(model, particles)
    p_m = optics.exit_pupil_m
    fp = np.asarray(optics.image_distance_m(particles.z_mm), dtype=np.float64)
    # Chief ray: s = (X, Y) * P / Z on the MLA plane (metres), whatever the focus.
    scale = p_m / particles.z_mm * optics.projection_factor / optics.pixel_pitch_m  # X/Z is unitless
    x_px = model.lattice.origin_x + particles.x_mm * scale
    y_px = model.lattice.origin_y + particles.y_mm * scale
    blur = optics.aperture_diameter_m * np.abs(fp - p_m) / fp / optics.lens_pitch_m
    return ParticleTruth(alpha=fp / p_m, x_px=x_px, y_px=y_px, blur_pitches=blur)


def _require_thin_lens(model: CameraModel, particles: Particles) -> Optics:
    """The model's optics, if rays can be traced through them to these particles."""
    optics = _require_finite_p(model)
    if len(particles) and np.min(particles.z_mm) <= optics.focal_length_m * 1e3:
        raise ParameterError(f"particles nearer than the focal length ({optics.focal_length_m * 1e3:.2f} mm) form "
                             "no real image; place them near the focus distance "
                             f"({optics.focus_distance_mm:.1f} mm)")
    return optics


def _aperture_samples(rng: np.random.Generator, radius_m: float, per_side: int) -> tuple[np.ndarray, np.ndarray]:
    """Stratified points on the aperture disk: one random point in each cell of a square grid."""
    cell = 2 * radius_m / per_side
    idx = np.arange(per_side)
    gu, gv = np.meshgrid(idx, idx, indexing="xy")
    u = (gu.ravel() + rng.random(gu.size)) * cell - radius_m
    v = (gv.ravel() + rng.random(gv.size)) * cell - radius_m
    inside = u * u + v * v <= radius_m * radius_m
    return u[inside], v[inside]


def accumulate_particles(model: CameraModel, particles: Particles, *, rng: np.random.Generator,
                         samples_per_side: int = 160, camera: CameraEffects | None = None) -> np.ndarray:
    """Trace each particle's light through the optics and sum it per pixel, before blur and mosaic.

    For aperture points ``(u, v)`` (stratified over the disk), the ray meets the MLA at
    ``s = uv + (img - uv) P / Fp``, enters the lens ``k`` whose physical centre is nearest, and
    lands at ``q = c_k + (c_k - uv) d / P`` (camera-model.md steps 1-3). Each ray carries its
    aperture cell's share of the particle's light, times its lens's chief-ray ``cos^4``.
    Only the pixels a particle reaches are touched (a window per particle).

    With a realistic ``camera``, the lenses sit on the exposure's (drifted) lattice, rays that the
    second stop blocks (``|uv + k s| > R2``, at the ray's own ``s``) are dropped, and each ray is
    weighted by its lens's transmission and the pixel response ``cos(theta)^n`` at its angle to
    the micro-image's chief ray (``tan(theta) = |uv| / P``).

    Returns
    -------
    ndarray of shape (H, W), float32
        Expected signal in DN (as for a green site) before the optics' blur.
    """
    optics = _require_thin_lens(model, particles)
    p_m, d_m, pix = optics.exit_pupil_m, optics.mla_to_sensor_m, optics.pixel_pitch_m
    radius_m = optics.aperture_diameter_m / 2
    lat = model.lattice if camera is None else camera.exposure_lattice(model.lattice)
    axis_x, axis_y = model.lattice.origin_x, model.lattice.origin_y
    stop = None if camera is None else camera.second_stop(model)
    to_px = optics.projection_factor / pix       # MLA metres -> micro-image lattice pixels
    ap_to_px = d_m / (p_m * pix)                 # aperture metres -> pixels within a micro-image
    cell_area_px = (2 * radius_m / samples_per_side * ap_to_px) ** 2
    fp_all = np.asarray(optics.image_distance_m(particles.z_mm), dtype=np.float64)
    out = np.zeros((model.height, model.width), dtype=np.float32)
    for k in range(len(particles)):
        u, v = _aperture_samples(rng, radius_m, samples_per_side)
        fp = fp_all[k]
        img_x = particles.x_mm[k] * fp / particles.z_mm[k]   # metres: X * Fp / Z
        img_y = particles.y_mm[k] * fp / particles.z_mm[k]
        t = p_m / fp
        sx = u + (img_x - u) * t
        sy = v + (img_y - v) * t
        li, lj = lat.nearest(axis_x + sx * to_px, axis_y + sy * to_px)
        mx, my = lat.centre(li, lj)
        qx = mx - u * ap_to_px
        qy = my - v * ap_to_px
        on = (qx >= 0) & (qx < model.width) & (qy >= 0) & (qy < model.height)
        if stop is not None:
            on &= (u + stop.shift_per_m * sx) ** 2 + (v + stop.shift_per_m * sy) ** 2 <= stop.radius_m ** 2
        if not on.any():
            continue
        qx, qy, li, lj = qx[on], qy[on], li[on], lj[on]
        if camera is None:
            weight = particles.brightness_dn[k] * cell_area_px * lens_vignetting(model, li, lj)
        else:
            lx, ly = _lens_plane_m(model, *lat.centre(li, lj))
            weight = (particles.brightness_dn[k] * cell_area_px * chief_ray_cos4(np.hypot(lx, ly), p_m)
                      * camera.lens_gain(li, lj) * camera.pixel_response(np.hypot(u[on], v[on]) / p_m * d_m / pix,
                                                                         model))
        col = qx.astype(np.int64)
        row = qy.astype(np.int64)
        c0, r0 = col.min(), row.min()
        w = col.max() - c0 + 1
        h = row.max() - r0 + 1
        window = np.bincount((row - r0) * w + (col - c0), weights=weight, minlength=h * w)
        out[r0:r0 + h, c0:c0 + w] += window.reshape(h, w).astype(np.float32)
    return out


def render_exposure(model: CameraModel, particles: Particles, *, seed: int, background_dn: float = 0.0,
                    noise: bool = True, samples_per_side: int = 160, responses: dict[str, float] | None = None,
                    camera: CameraEffects | None = None, chamber: ChamberLight | None = None) -> np.ndarray:
    """Raw F01 exposure of point particles that scatter 532 nm laser light.

    Parameters
    ----------
    model : CameraModel
        Thin-lens camera (``simulated_camera_metadata``); particles' light is traced through it.
    particles : Particles
        Positions (mm, camera frame) and brightness (DN above black at a fully lit green pixel).
    seed : int
        Seeds the ray sampling and the noise: same seed, same bytes.
    background_dn : float
        Diffuse plasma glow: a white image of this level under white-light responses.
    noise : bool
        False gives the expected values, rounded.
    samples_per_side : int
        Rays per particle: a ``samples_per_side`` square grid over the aperture, cells in the disk.
    responses : dict, optional
        Bayer responses to the particles' light; 532 nm by default (green full, red/blue a few %).
    camera : CameraEffects, optional
        A realistic camera: its point spread, micro-images, second stop, sensor defects, and the
        lattice drifted from ``model``'s (the white images'). The ideal camera by default.
    chamber : ChamberLight, optional
        The chamber's glow gradient (scaling ``background_dn`` over the field) and its laser
        reflections (532 nm light, as the particles'). A uniform glow by default.

    Returns
    -------
    ndarray of shape (H, W), uint16
        Raw 12-bit values including the black level.

    Examples
    --------
    >>> from analysis.simulation.camera import simulated_camera_metadata
    >>> model = CameraModel.from_metadata(simulated_camera_metadata(size=64))
    >>> one = Particles(*(np.array([v]) for v in (0.0, 0.0, 60.0, 2000.0)))
    >>> int(render_exposure(model, one, seed=0, noise=False).max()) > 2000
    True
    """
    if samples_per_side < 8:
        raise ParameterError(f"samples_per_side={samples_per_side} is too few rays; use 8 or more (160 default)")
    if background_dn < 0:
        raise ParameterError("background_dn must not be negative")
    rng = np.random.default_rng(seed)
    responses = LASER_532_RESPONSE if responses is None else responses
    if camera is None and chamber is None:
        expected = blur(accumulate_particles(model, particles, rng=rng, samples_per_side=samples_per_side))
        expected *= channel_response_map(model.height, model.width, responses)
        if background_dn > 0:
            glow = white_coverage(model)
            glow *= channel_response_map(model.height, model.width, WHITE_RESPONSE)
            glow *= np.float32(background_dn)
            expected += glow
        return read_out(expected, black=model.black_level, white=model.white_level,
                        rng=rng if noise else None)
    camera = CameraEffects(blur_px=BLUR_SIGMA_PX) if camera is None else camera
    lattice = camera.exposure_lattice(model.lattice)
    light = accumulate_particles(model, particles, rng=rng, samples_per_side=samples_per_side, camera=camera)
    if chamber is not None and chamber.sources:
        light += render_reflections(model, lattice, chamber, camera)
    expected = point_spread(light, camera)
    expected *= channel_response_map(model.height, model.width, responses)
    if background_dn > 0:
        glow = camera_coverage(model, camera, lattice=lattice, chamber=chamber)
        glow *= channel_response_map(model.height, model.width, WHITE_RESPONSE)
        glow *= np.float32(background_dn)
        expected += glow
    raw = read_out(expected, black=model.black_level, white=model.white_level, rng=rng if noise else None)
    return camera.with_defects(raw, model)


def in_view(model: CameraModel, truth: ParticleTruth) -> np.ndarray:
    """Particles whose whole blur disk (plus one pitch) lies on the sensor: the ones a crop keeps."""
    reach = (truth.blur_pitches / 2 + 1.0) * model.lattice.pitch_px
    return ((truth.x_px - reach >= 0) & (truth.x_px + reach <= model.width)
            & (truth.y_px - reach >= 0) & (truth.y_px + reach <= model.height))
