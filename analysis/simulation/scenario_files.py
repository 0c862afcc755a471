"""A simulated scenario written as the camera would store it: exposures, white images, truth.

``write_scenario`` renders a cluster (:mod:`analysis.simulation.scenarios`) through the simulated
F01 (:mod:`analysis.simulation.render`), ideal or realistic (:class:`Realism`), and writes the
camera's files, the calibration folder and the truth table (layout of docs/interfaces.md).
"""

from __future__ import annotations

import csv
import io
import json
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable

import numpy as np
from scipy.spatial import cKDTree

from analysis.camera.front_optics import FrontOptics
from analysis.camera.model import CameraModel
from analysis.errors import ParameterError
from analysis.formats.atomic_write import write_atomic
from analysis.formats.exposure import Exposure, write_lfp, write_raw_pair
from analysis.formats.whites import WhiteImage, write_white_pair
from .camera import (DEFAULT_LENS, DEFAULT_SERIAL, ELECTRONS_PER_DN, F01_SIZE, LASER_532_RESPONSE, OTHER_ZOOM_LENS,
    READ_NOISE_DN, WHITE_RESPONSE, SimulatedLens, simulated_camera_metadata, simulated_private_metadata,
    white_normalized_responses)
from .camera_effects import CameraEffects
from .chamber import ChamberLight
from .dynamics import Motion, moved_scenario, simulate_motion
from .realism import Realism
from .render import (BLUR_SIGMA_PX, ParticleTruth, channel_response_map, in_view, particle_truth, read_out,
    render_exposure, white_coverage)
from .scenarios import Particles, Scenario, make_scenario
from .target import TARGET, DotTarget, default_target, target_sidecar

log = logging.getLogger(__name__)

#: Effect groups rendered by the camera, by the chamber, and by the scene.
CAMERA_EFFECTS = ("blur", "micro-images", "vignetting", "hot-pixels", "drift")
CHAMBER_EFFECTS = ("glow", "reflections")


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
#: Columns a run's truth tables (``--count`` above 1) add: the particle's velocity and shell.
MOTION_COLUMNS = {
    "vX": "mm/s, camera frame", "vY": "mm/s", "vZ": "mm/s",
    "shell": "shell of a ball the particle's cage lies on (0 innermost); -1 for other clusters",
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
    target_json: Path | None = None

    @property
    def calibration_dir(self) -> Path:
        return self.out_dir / "calibration"


def truth_csv_bytes(particles: Particles, truth: ParticleTruth, index: np.ndarray,
                    velocity: np.ndarray | None = None, shell: np.ndarray | None = None) -> bytes:
    """The truth table: one row per particle, columns `TRUTH_COLUMNS` (and `MOTION_COLUMNS` given
    the velocities (n, 3) and shells of a moving cluster)."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(list(TRUTH_COLUMNS) + (list(MOTION_COLUMNS) if velocity is not None else []))
    for row in range(len(particles)):
        motion = [] if velocity is None else [f"{v:.6f}" for v in velocity[row]] + [int(shell[row])]
        writer.writerow([int(index[row]),
                         f"{particles.x_mm[row]:.6f}", f"{particles.y_mm[row]:.6f}", f"{particles.z_mm[row]:.6f}",
                         f"{truth.alpha[row]:.8f}", f"{truth.x_px[row]:.4f}", f"{truth.y_px[row]:.4f}",
                         f"{truth.blur_pitches[row]:.4f}", f"{particles.brightness_dn[row]:.2f}"] + motion)
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
                   centre_z_mm: float | None = None, realism: Realism | None = None,
                   motion: Motion | None = None, progress: Callable[[str], None] | None = None,
                   front_optics: FrontOptics | None = None, target: DotTarget | None = None) -> SimulationFiles:
    """Simulate a scenario and write it as the camera's files, with its truth.

    Writes ``IMG_nnnn.lfp``, ``IMG_nnnn.RAW`` + ``.TXT`` and ``IMG_nnnn.truth.csv`` for each of
    ``count`` exposures (the cluster moves between them as ``motion`` says, one shot per
    ``motion.interval_s`` on the metadata clock; the truth then has velocities and shells),
    ``calibration/MOD_nnnn.RAW`` +
    ``.TXT`` white images, and ``scenario.json`` (docs/interfaces.md).

    Parameters
    ----------
    out_dir : path
        Folder to write into (created).
    scenario_name : {"tilted-layer", "shadowing", "ball", "cloud", "target"}
        ``target``: a plate of dots (``target``, default :func:`default_target`), one exposure per
        stage position (``count`` is ignored), the positions in ``target.json``.
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
    realism : Realism, optional
        Effects of a real camera and chamber (`Realism`; ideal by default, which writes exactly
        the ideal simulator's bytes). The camera's effects appear in the white images too; the
        metadata stay the ideal camera's, so the pipeline is told none of them. The parameters,
        and what they resolve to (second stop, defects on this sensor, reflections), go into
        ``scenario.json`` under ``realism``.
    motion : Motion, optional
        How the cluster moves between exposures (:class:`analysis.simulation.dynamics.Motion`,
        default ``Motion()``); recorded in ``scenario.json`` with the shell hops it made.
    progress : callable, optional
        Called with a line of text before each long step.
    front_optics : FrontOptics, optional
        An auxiliary lens in front of the camera and the main lens's distortion: everything is
        rendered where the main lens sees it; the truth keeps the true ``X, Y, Z`` (its ``alpha``,
        ``x, y`` and blur are the apparent position's). By default the cluster (or target) is
        placed where the camera focuses through it.

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
    realism = Realism() if realism is None else realism
    on = set(realism.effects_on())
    front = None if front_optics is None or front_optics.is_identity else front_optics
    if scenario_name == TARGET:
        target = target or default_target(front, brightness_dn=brightness_dn)
        count = len(target.positions_mm)
        scenario = Scenario(TARGET, int(seed), target.particles(target.positions_mm[0], np.random.default_rng(seed)),
                            background_dn, {"target": target.to_dict()})
    else:
        if centre_z_mm is None and front is not None:
            nominal = DEFAULT_LENS.focus_distance_mm - (2.6 if scenario_name == "cloud" else 0.0)
            centre_z_mm = round(front.object_distance_mm(nominal), 3)
        scenario = make_scenario(scenario_name, seed, brightness_dn=brightness_dn, background_dn=background_dn,
                                 centre_z_mm=centre_z_mm, varied=realism.varied_scene,
                                 brightness_spread=realism.brightness_spread or None)
    metadata = simulated_camera_metadata(lens=DEFAULT_LENS, size=size)
    model = CameraModel.from_metadata(metadata)
    camera = CameraEffects.build(realism, serial=serial) if on & set(CAMERA_EFFECTS) else None
    chamber = ChamberLight.build(realism, seed=seed) if on & set(CHAMBER_EFFECTS) else None
    files = SimulationFiles(out_dir=out)
    frames = []
    motion = Motion() if motion is None else motion
    moving = count > 1 and target is None  # a target's plate stands still at each stage position
    shots, hops = simulate_motion(scenario, motion, count, seed=[seed, 0x40710]) if moving else ([], [])
    start = np.datetime64("2021-06-01T09:00:00.000")
    for k in range(1, count + 1):
        frame_rng = np.random.default_rng([seed, k])
        current = moved_scenario(scenario, shots[k - 1]) if shots else scenario
        if target is not None:
            current = replace(scenario, particles=target.particles(target.positions_mm[k - 1], frame_rng))
        seen = current.particles if front is None else Particles(
            *front.apparent(current.particles.x_mm, current.particles.y_mm, current.particles.z_mm),
            current.particles.brightness_dn)
        truth = particle_truth(model, seen)
        keep = np.flatnonzero(in_view(model, truth))
        shown = current.particles.subset(keep)
        name = f"IMG_{k:04d}"
        say(f"{name}: rendering {len(shown)} of {len(current.particles)} particles on {size}x{size} px")
        image = render_exposure(model, seen.subset(keep), seed=int(frame_rng.integers(2 ** 63)),
                                background_dn=current.background_dn, camera=camera, chamber=chamber)
        t_s = shots[k - 1].t_s if shots else 0.0  # from 09:00, one shot per motion.interval_s
        stamp = start + np.timedelta64(int(round(t_s * 1000)), "ms")
        frame_meta = simulated_camera_metadata(lens=DEFAULT_LENS, size=size, zulu_time=f"{stamp}Z")
        exposure = Exposure(image=image, metadata=frame_meta, private_metadata=private, name=name)
        say(f"{name}: writing .lfp, .RAW + .TXT, truth")
        files.lfp.append(write_lfp(exposure, out / f"{name}.lfp"))
        raw_path, txt_path = write_raw_pair(exposure, out / f"{name}.RAW")
        files.raw.append(raw_path)
        files.txt.append(txt_path)
        shown_truth = ParticleTruth(*(np.asarray(a)[keep] for a in (truth.alpha, truth.x_px, truth.y_px,
                                                                     truth.blur_pitches)))
        motion_truth = {} if not shots else {"velocity": shots[k - 1].velocity_mm_s[keep],
                                             "shell": shots[k - 1].shell[keep]}
        files.truth.append(write_atomic(out / f"{name}.truth.csv",
                                        truth_csv_bytes(shown, shown_truth, keep, **motion_truth)))
        frames.append({"name": name, "sha1": exposure.sha1, "t_s": t_s, "particles_in_view": int(keep.size),
                       "alpha_range": [float(shown_truth.alpha.min()), float(shown_truth.alpha.max())]
                       if keep.size else None,
                       "mean_nn_distance_mm": mean_nn_distance_mm(shown)})
    whites = _write_calibration(out / "calibration", seed=seed, size=size, private=private, say=say, camera=camera)
    files.whites.extend(whites["paths"])
    if target is not None:
        sidecar = target_sidecar(target, [f["name"] for f in frames], front)
        files.target_json = write_atomic(out / "target.json", (json.dumps(sidecar, indent=2) + "\n").encode())
    doc = {
        "scenario": scenario.name, "seed": int(seed), "count": int(count), "size": int(size), "serial": serial,
        "particles": len(scenario.particles), "background_dn": scenario.background_dn,
        "brightness_dn": float(brightness_dn),
        "parameters": scenario.parameters,
        "optics": _optics_doc(model, DEFAULT_LENS),
        "front_optics": None if front is None else front.to_dict(),
        "exposures": frames, "calibration": whites["doc"], "truth_columns": TRUTH_COLUMNS,
        "noise": {"electrons_per_dn": ELECTRONS_PER_DN, "read_noise_dn": READ_NOISE_DN,
                  "blur_sigma_px": BLUR_SIGMA_PX, "laser_532_response": LASER_532_RESPONSE},
    }
    if shots:
        doc["motion"] = {**motion.to_dict(), "hops": hops}
        doc["truth_columns"] = {**TRUTH_COLUMNS, **MOTION_COLUMNS}
    if not realism.is_ideal:
        doc["realism"] = _realism_doc(realism, model, camera, chamber)
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


def _realism_doc(realism: Realism, model: CameraModel, camera: CameraEffects | None,
                 chamber: ChamberLight | None) -> dict:
    """``scenario.json``'s record of the realism: its parameters and what they resolved to."""
    doc: dict = {"parameters": realism.to_dict()}
    if camera is not None:
        stop = camera.second_stop(model)
        defects = camera.defects.on_crop(model.width, model.height) if camera.defects is not None else None
        drifted = camera.exposure_lattice(model.lattice)
        doc["camera"] = {
            "blur_sigma_px": camera.blur_px,
            "halo": ({"fraction": camera.psf_halo, "sigma_px": camera.psf_halo_px} if camera.psf_halo > 0
                     else None),
            "pixel_response_exponent": 2 * camera.half_n,
            "second_stop": None if stop is None else {"shift_per_m": stop.shift_per_m, "projected_radius_m": stop.radius_m,
                                                      **stop.physical(model.optics.exit_pupil_m)},
            "hot_pixels": None if defects is None else {
                "hot": int(np.sum(defects.kind == defects.HOT)), "stuck": int(np.sum(defects.kind == defects.STUCK)),
                "dead": int(np.sum(defects.kind == defects.DEAD)), "seeded_by": "camera serial"},
            "exposure_lattice": {"origin_x": drifted.origin_x, "origin_y": drifted.origin_y,
                                 "rotation_rad": drifted.rotation_rad},
        }
    if chamber is not None:
        doc["chamber"] = chamber.to_dict(model)
    return doc


def _write_calibration(folder: Path, *, seed: int, size: int, private: dict,
                       say: Callable[[str], None], camera: CameraEffects | None = None) -> dict:
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
            cov = white_coverage(model, camera=camera)
            cov *= channel_response_map(model.height, model.width, WHITE_RESPONSE)
            coverage[key] = cov
        rng = np.random.default_rng([seed, 1000 + index])
        image = read_out(coverage[key] * np.float32(spec.level_dn), black=model.black_level,
                         white=model.white_level, rng=rng)
        if camera is not None:
            image = camera.with_defects(image, model)
        raw_path, txt_path = write_white_pair(WhiteImage.from_image(name, image, meta, private), folder)
        paths.extend([raw_path, txt_path])
        doc.append({"name": name, "zoom_step": spec.lens.zoom_step, "focus_step": spec.lens.focus_step,
                    "exposure_s": spec.exposure_s, "level_dn": spec.level_dn, "dark": spec.level_dn < 500})
    return {"paths": paths, "doc": doc}
