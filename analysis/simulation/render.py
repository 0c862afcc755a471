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

import csv
import io
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import cv2
import numpy as np
from scipy.spatial import cKDTree

from .kernels import paint_disks
from analysis.formats.atomic_write import write_atomic
from analysis.camera.model import CameraModel, Optics
from analysis.errors import ParameterError
from analysis.formats.exposure import Exposure, write_lfp, write_raw_pair
from .scenarios import Particles, make_scenario
from .camera import (DEFAULT_LENS, DEFAULT_SERIAL, ELECTRONS_PER_DN, F01_SIZE, LASER_532_RESPONSE,
    OTHER_ZOOM_LENS, READ_NOISE_DN, WHITE_RESPONSE, SimulatedLens, chief_ray_cos4, simulated_camera_metadata,
    simulated_private_metadata, white_normalized_responses)
from analysis.formats.whites import WhiteImage, write_white_pair

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
    >>> from analysis.simulation.camera import simulated_camera_metadata
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
    optics = model.optics
    if optics.exit_pupil_m is None:
        raise ParameterError("the camera model has no finite exit-pupil distance (exitPupilOffset.z), so rays "
                             "cannot be traced; build it from simulated_camera_metadata()")
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
                         samples_per_side: int = 160) -> np.ndarray:
    """Trace each particle's light through the optics and sum it per pixel, before blur and mosaic.

    For aperture points ``(u, v)`` (stratified over the disk), the ray meets the MLA at
    ``s = uv + (img - uv) P / Fp``, enters the lens ``k`` whose physical centre is nearest, and
    lands at ``q = c_k + (c_k - uv) d / P`` (camera-model.md steps 1-3). Each ray carries its
    aperture cell's share of the particle's light, times its lens's chief-ray ``cos^4``.
    Only the pixels a particle reaches are touched (a window per particle).

    Returns
    -------
    ndarray of shape (H, W), float32
        Expected signal in DN (as for a green site) before the optics' blur.
    """
    optics = _require_thin_lens(model, particles)
    p_m, d_m, pix = optics.exit_pupil_m, optics.mla_to_sensor_m, optics.pixel_pitch_m
    radius_m = optics.aperture_diameter_m / 2
    lat = model.lattice
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
        li, lj = lat.nearest(lat.origin_x + sx * to_px, lat.origin_y + sy * to_px)
        mx, my = lat.centre(li, lj)
        qx = mx - u * ap_to_px
        qy = my - v * ap_to_px
        on = (qx >= 0) & (qx < model.width) & (qy >= 0) & (qy < model.height)
        if not on.any():
            continue
        qx, qy, li, lj = qx[on], qy[on], li[on], lj[on]
        weight = particles.brightness_dn[k] * cell_area_px * lens_vignetting(model, li, lj)
        col = qx.astype(np.int64)
        row = qy.astype(np.int64)
        c0, r0 = col.min(), row.min()
        w = col.max() - c0 + 1
        h = row.max() - r0 + 1
        window = np.bincount((row - r0) * w + (col - c0), weights=weight, minlength=h * w)
        out[r0:r0 + h, c0:c0 + w] += window.reshape(h, w).astype(np.float32)
    return out


def render_exposure(model: CameraModel, particles: Particles, *, seed: int, background_dn: float = 0.0,
                    noise: bool = True, samples_per_side: int = 160,
                    responses: dict[str, float] | None = None) -> np.ndarray:
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
    expected = blur(accumulate_particles(model, particles, rng=rng, samples_per_side=samples_per_side))
    expected *= channel_response_map(model.height, model.width, responses)
    if background_dn > 0:
        glow = white_coverage(model)
        glow *= channel_response_map(model.height, model.width, WHITE_RESPONSE)
        glow *= np.float32(background_dn)
        expected += glow
    return read_out(expected, black=model.black_level, white=model.white_level,
                    rng=rng if noise else None)


# ---------------------------------------------------------------------------------------------
# Files: a scenario written as the camera would store it.

TRUTH_COLUMNS = {
    "particle": "index in the scenario",
    "X": "mm, camera frame (camera-model.md): right in the upright image",
    "Y": "mm, down in the upright image",
    "Z": "mm, along the optical axis from the main lens",
    "alpha": "Fp / P, refocus parameter that brings the particle into focus",
    "x": "px, chief ray on the MLA in micro-image lattice pixels (upright sensor frame)",
    "y": "px, as x",
    "blur_pitches": "defocus blur diameter on the MLA in lens pitches",
    "brightness": "DN above black of a fully lit green pixel",
}


@dataclass(frozen=True)
class WhiteSpec:
    """One white image of the calibration folder."""

    lens: SimulatedLens
    level_dn: float
    exposure_s: float


# The camera's C:\T1CALIB\ as simulated: whites at the picture's zoom at three focus steps, one of
# them dark (short exposure; calibration must skip it), and one at another zoom.
def _calibration_plan(lens: SimulatedLens) -> list[WhiteSpec]:
    def at(focus_step: int) -> SimulatedLens:
        return SimulatedLens(lens.lens_to_mla_m, lens.focus_distance_mm, lens.image_f_number,
                             lens.zoom_step, focus_step)
    return [
        WhiteSpec(at(lens.focus_step - 120), 2400.0, 0.02),
        WhiteSpec(at(lens.focus_step), 150.0, 0.0012),
        WhiteSpec(at(lens.focus_step), 2400.0, 0.02),
        WhiteSpec(at(lens.focus_step + 120), 2400.0, 0.02),
        WhiteSpec(OTHER_ZOOM_LENS, 2400.0, 0.02),
    ]


@dataclass
class SimulationFiles:
    """Paths written by `write_scenario` (layout of docs/interfaces.md)."""

    out_dir: Path
    lfp: list[Path] = field(default_factory=list)
    raw: list[Path] = field(default_factory=list)
    txt: list[Path] = field(default_factory=list)
    truth: list[Path] = field(default_factory=list)
    whites: list[Path] = field(default_factory=list)
    scenario_json: Path | None = None

    @property
    def calibration_dir(self) -> Path:
        return self.out_dir / "calibration"


def in_view(model: CameraModel, truth: ParticleTruth) -> np.ndarray:
    """Particles whose whole blur disk (plus one pitch) lies on the sensor: the ones a crop keeps."""
    reach = (truth.blur_pitches / 2 + 1.0) * model.lattice.pitch_px
    return ((truth.x_px - reach >= 0) & (truth.x_px + reach <= model.width)
            & (truth.y_px - reach >= 0) & (truth.y_px + reach <= model.height))


def truth_csv_bytes(particles: Particles, truth: ParticleTruth, index: np.ndarray) -> bytes:
    """The truth table: one row per particle, columns `TRUTH_COLUMNS`."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(TRUTH_COLUMNS)
    for row in range(len(particles)):
        writer.writerow([int(index[row]),
                         f"{particles.x_mm[row]:.6f}", f"{particles.y_mm[row]:.6f}", f"{particles.z_mm[row]:.6f}",
                         f"{truth.alpha[row]:.8f}", f"{truth.x_px[row]:.4f}", f"{truth.y_px[row]:.4f}",
                         f"{truth.blur_pitches[row]:.4f}", f"{particles.brightness_dn[row]:.2f}"])
    return buf.getvalue().encode("ascii")


def mean_nn_distance_mm(particles: Particles) -> float:
    """Mean 3D nearest-neighbour distance, the unit in which depth errors are judged."""
    xyz = np.stack([particles.x_mm, particles.y_mm, particles.z_mm], axis=1)
    if len(xyz) < 2:
        return float("nan")
    dist, _ = cKDTree(xyz).query(xyz, k=2)
    return float(dist[:, 1].mean())


def write_scenario(out_dir: str | Path, scenario_name: str, seed: int, *, count: int = 1, size: int = F01_SIZE,
                   brightness_dn: float = 1800.0, background_dn: float = 40.0, serial: str = DEFAULT_SERIAL,
                   centre_z_mm: float | None = None, progress: Callable[[str], None] | None = None
                   ) -> SimulationFiles:
    """Simulate a scenario and write it as the camera's files, with its truth.

    Writes ``IMG_nnnn.lfp``, ``IMG_nnnn.RAW`` + ``.TXT`` and ``IMG_nnnn.truth.csv`` for each of
    ``count`` exposures (the cluster moves a little between them), ``calibration/MOD_nnnn.RAW`` +
    ``.TXT`` white images, and ``scenario.json`` (docs/interfaces.md).

    Parameters
    ----------
    out_dir : path
        Folder to write into (created).
    scenario_name : {"tilted-layer", "shadowing", "ball"}
    seed : int
        Same seed, same bytes.
    count : int
        Number of exposures.
    size : int
        Sensor size in pixels: 3280 for a full F01 frame, less for a centred crop (a multiple
        of 4, so the Bayer phase is kept). A crop keeps only particles whose blur disk is on it.
    brightness_dn, background_dn : float
        Median particle brightness and plasma glow (see `make_scenario`).
    serial : str
        Camera serial written into every file's private metadata.
    centre_z_mm : float, optional
        Distance of the cluster's centre from the lens (see `make_scenario`; default: the focus
        distance, give or take 0.3 mm). Placing it a few mm off focus keeps every particle's
        blur above a lens pitch, so none lights a single micro-lens.
    progress : callable, optional
        Called with a line of text before each long step.

    Returns
    -------
    SimulationFiles
    """
    if count < 1 or count > 9999:
        raise ParameterError(f"count={count}: give 1 ... 9999 exposures")
    if size % 4:
        raise ParameterError(f"size={size} must be a multiple of 4 (keeps the crop's Bayer phase BGGR)")
    say = progress or (lambda line: log.info("%s", line))
    out = Path(out_dir)
    (out / "calibration").mkdir(parents=True, exist_ok=True)
    private = simulated_private_metadata(serial)
    scenario = make_scenario(scenario_name, seed, brightness_dn=brightness_dn, background_dn=background_dn,
                             centre_z_mm=centre_z_mm)
    metadata = simulated_camera_metadata(lens=DEFAULT_LENS, size=size)
    model = CameraModel.from_metadata(metadata)
    files = SimulationFiles(out_dir=out)
    frames = []
    for k in range(1, count + 1):
        frame_rng = np.random.default_rng([seed, k])
        current = scenario if k == 1 else scenario.jittered(frame_rng)
        truth = particle_truth(model, current.particles)
        keep = np.flatnonzero(in_view(model, truth))
        shown = current.particles.subset(keep)
        name = f"IMG_{k:04d}"
        say(f"{name}: rendering {len(shown)} of {len(current.particles)} particles on {size}x{size} px")
        image = render_exposure(model, shown, seed=int(frame_rng.integers(2 ** 63)),
                                background_dn=current.background_dn)
        minute, second = divmod((k - 1) % 3600, 60)  # one exposure per second from 09:00
        frame_meta = simulated_camera_metadata(lens=DEFAULT_LENS, size=size,
                                               zulu_time=f"2021-06-01T09:{minute:02d}:{second:02d}.000Z")
        exposure = Exposure(image=image, metadata=frame_meta, private_metadata=private, name=name)
        say(f"{name}: writing .lfp, .RAW + .TXT, truth")
        files.lfp.append(write_lfp(exposure, out / f"{name}.lfp"))
        raw_path, txt_path = write_raw_pair(exposure, out / f"{name}.RAW")
        files.raw.append(raw_path)
        files.txt.append(txt_path)
        shown_truth = ParticleTruth(*(np.asarray(a)[keep] for a in (truth.alpha, truth.x_px, truth.y_px,
                                                                     truth.blur_pitches)))
        files.truth.append(write_atomic(out / f"{name}.truth.csv", truth_csv_bytes(shown, shown_truth, keep)))
        frames.append({"name": name, "sha1": exposure.sha1, "particles_in_view": int(keep.size),
                       "alpha_range": [float(shown_truth.alpha.min()), float(shown_truth.alpha.max())]
                       if keep.size else None,
                       "mean_nn_distance_mm": mean_nn_distance_mm(shown)})
    whites = _write_calibration(out / "calibration", seed=seed, size=size, private=private, say=say)
    files.whites.extend(whites["paths"])
    doc = {
        "scenario": scenario.name, "seed": int(seed), "count": int(count), "size": int(size), "serial": serial,
        "particles": len(scenario.particles), "background_dn": scenario.background_dn,
        "brightness_dn": float(brightness_dn),
        "parameters": scenario.parameters,
        "optics": _optics_doc(model, DEFAULT_LENS),
        "exposures": frames, "calibration": whites["doc"], "truth_columns": TRUTH_COLUMNS,
        "noise": {"electrons_per_dn": ELECTRONS_PER_DN, "read_noise_dn": READ_NOISE_DN,
                  "blur_sigma_px": BLUR_SIGMA_PX, "laser_532_response": LASER_532_RESPONSE},
    }
    files.scenario_json = write_atomic(out / "scenario.json", (json.dumps(doc, indent=2) + "\n").encode())
    say(f"wrote {out}")
    return files


def _optics_doc(model: CameraModel, lens: SimulatedLens) -> dict:
    o = model.optics
    lat = model.lattice
    return {"focal_length_m": o.focal_length_m, "f_number": o.f_number, "lens_to_mla_m": o.exit_pupil_m,
            "aperture_diameter_m": o.aperture_diameter_m, "focus_distance_mm": lens.focus_distance_mm,
            "magnification": o.exit_pupil_m / (lens.focus_distance_mm * 1e-3),
            "mla_to_sensor_m": o.mla_to_sensor_m, "lens_pitch_m": o.lens_pitch_m, "pixel_pitch_m": o.pixel_pitch_m,
            "micro_image_pitch_px": lat.pitch_px, "micro_image_radius_px": o.micro_image_radius_px,
            "lattice": {"origin_x": lat.origin_x, "origin_y": lat.origin_y, "pitch_px": lat.pitch_px,
                        "rotation_rad": lat.rotation_rad, "scale_x": lat.scale_x, "scale_y": lat.scale_y},
            "zoom_step": lens.zoom_step, "focus_step": lens.focus_step}


def _write_calibration(folder: Path, *, seed: int, size: int, private: dict,
                       say: Callable[[str], None]) -> dict:
    """White images ``MOD_nnnn`` of `_calibration_plan`; one coverage map per distinct geometry."""
    plan = _calibration_plan(DEFAULT_LENS)
    coverage: dict[tuple, np.ndarray] = {}
    paths: list[Path] = []
    doc = []
    for index, spec in enumerate(plan):
        name = f"MOD_{index:04d}"
        meta = simulated_camera_metadata(lens=spec.lens, size=size, exposure_s=spec.exposure_s)
        meta["devices"]["sensor"]["normalizedResponses"] = white_normalized_responses()
        model = CameraModel.from_metadata(meta)
        key = (model.lattice, model.optics)
        if key not in coverage:
            say(f"calibration: rendering white images at zoomStep {spec.lens.zoom_step}")
            cov = white_coverage(model)
            cov *= channel_response_map(model.height, model.width, WHITE_RESPONSE)
            coverage[key] = cov
        rng = np.random.default_rng([seed, 1000 + index])
        image = read_out(coverage[key] * np.float32(spec.level_dn), black=model.black_level,
                         white=model.white_level, rng=rng)
        raw_path, txt_path = write_white_pair(WhiteImage.from_image(name, image, meta, private), folder)
        paths.extend([raw_path, txt_path])
        doc.append({"name": name, "zoom_step": spec.lens.zoom_step, "focus_step": spec.lens.focus_step,
                    "exposure_s": spec.exposure_s, "level_dn": spec.level_dn, "dark": spec.level_dn < 500})
    return {"paths": paths, "doc": doc}


__all__ = ["BLUR_SIGMA_PX", "ParticleTruth", "Particles", "SimulationFiles", "TRUTH_COLUMNS", "accumulate_particles",
           "channel_response_map", "in_view", "make_scenario", "mean_nn_distance_mm", "particle_truth", "read_out",
           "render_exposure", "render_white_image", "simulated_camera_metadata", "truth_csv_bytes",
           "white_coverage", "write_scenario"]
