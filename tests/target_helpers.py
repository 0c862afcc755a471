"""Synthetic target observations with known truth, traced forward through the simulated optics.

Written forward (object -> apparent position -> thin main lens -> lens plane and alpha), apart from
the inverse the mappings implement, so a mapping that fits these and predicts held-back positions
has the optics right.
"""

from __future__ import annotations

import math

import numpy as np

from analysis.camera.front_optics import FrontOptics
from analysis.camera.mapping_fit import MainLens, TargetObservations
from analysis.camera.target_mapping import rotation_matrix
from analysis.simulation.camera import DEFAULT_LENS
from analysis.simulation.target import simulated_front_optics

F_MM = DEFAULT_LENS.focal_length_m * 1e3
P_MM = DEFAULT_LENS.lens_to_mla_m * 1e3
#: The paper's set-up: a 174 mm lens 20 mm in front, 1 % distortion at the sensor's corner.
PAPER_FRONT = simulated_front_optics(174.0, 20.0, distortion=0.01)


def main_lens() -> MainLens:
    return MainLens(focal_length_mm=F_MM, lens_to_mla_mm=P_MM, reference_tan=PAPER_FRONT.reference_tan)


def seen(front: FrontOptics, xyz_mm: np.ndarray, *, field_curvature_mm: float = 0.0
         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lens-plane ``sx, sy`` (m) and ``alpha`` where the pipeline would see camera-frame points (3, n).

    ``field_curvature_mm`` shifts the apparent depth by that much at the reference field (times the
    field tangent squared): an effect no thin lens has.
    """
    x, y, z = front.apparent(*xyz_mm)
    t2 = (x * x + y * y) / (z * z)
    z = z + field_curvature_mm * t2 / front.reference_tan ** 2
    image_mm = 1.0 / (1.0 / F_MM - 1.0 / z)
    return x / z * P_MM * 1e-3, y / z * P_MM * 1e-3, image_mm / P_MM


def observations(front: FrontOptics = PAPER_FRONT, *, positions=(48.5, 50.5, 52.5, 54.5, 56.5), pitch: float = 1.0,
                 half: int = 6, rotation=(0.0, 0.0, 0.0), origin=(0.0, 0.0, 0.0), stage_slope=(0.0, 0.0),
                 noise_s_m: float = 0.0, noise_alpha: float = 0.0, field_curvature_mm: float = 0.0,
                 shift=(0.0, 0.0), seed: int = 0) -> TargetObservations:
    """A square target of ``2 half + 1`` dots a side at each stage position, as the pipeline sees it
    (``shift``: every dot moved by that much on the plate, in the target's frame)."""
    rng = np.random.default_rng(seed)
    rows, cols = (a.ravel() for a in np.meshgrid(np.arange(-half, half + 1), np.arange(-half, half + 1),
                                                 indexing="ij"))
    rot = rotation_matrix(np.asarray(rotation, dtype=np.float64))
    stage = np.array([stage_slope[0], stage_slope[1], 1.0])
    stage /= np.linalg.norm(stage)
    sx, sy, alpha, world, position = [], [], [], [], []
    for k, z in enumerate(positions):
        w = np.stack([cols * pitch + shift[0], rows * pitch + shift[1], np.full(rows.size, float(z))])
        cam = np.asarray(origin, float)[:, None] + rot[:, :1] * w[0] + rot[:, 1:2] * w[1] + stage[:, None] * w[2]
        a, b, c = seen(front, cam, field_curvature_mm=field_curvature_mm)
        sx.append(a + rng.normal(0, noise_s_m, a.size) if noise_s_m else a)
        sy.append(b + rng.normal(0, noise_s_m, b.size) if noise_s_m else b)
        alpha.append(c + rng.normal(0, noise_alpha, c.size) if noise_alpha else c)
        world.append(w.T)
        position.append(np.full(rows.size, k))
    return TargetObservations(np.concatenate(sx), np.concatenate(sy), np.concatenate(alpha), np.vstack(world),
                              np.concatenate(position), np.asarray(positions, dtype=np.float64))


def between(obs_positions=(49.5, 51.5, 53.5, 55.5), **kwargs) -> TargetObservations:
    """Dots at positions between those calibrated (offset half a pitch laterally too): particles."""
    return observations(positions=obs_positions, shift=(0.5, 0.5), half=5, **kwargs)


def tilt_of(deg: float) -> tuple[float, float, float]:
    """Rotation vector of a plate tilted by ``deg`` about its rows."""
    return (math.radians(deg), 0.0, 0.0)
