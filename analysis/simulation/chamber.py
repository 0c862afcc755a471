"""Light from the plasma chamber other than the particles: a glow with a gradient and out-of-focus
laser reflections (a band off the lower electrode, round glints).

Sources are placed in object space (mm, camera frame of camera-model.md) at their own depth, far
from the focus, and rendered through the same optics as the particles (second stop, micro-lens
transmission and pixel response of the camera included): :func:`render_reflections` follows the
ray of each point of each pixel back through its micro-lens and the main lens to the source.
Their positions come from the scene's seed (a stream of their own), never from the camera's.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from analysis.camera.model import CameraModel, Lattice
from .camera import DEFAULT_LENS, F01_PIXEL_PITCH_M, F01_SIZE
from .camera_effects import CameraEffects
from .realism import Realism
from .realism_kernels import BAND, GLINT, trace_extended_sources

# Points per pixel side, and points per micro-lens cell (in lens pitches from its centre: a
# triangle about the centre), of the backward ray tracing.
_PIXEL_SUPERSAMPLE = 2
_CELL_POINTS = ((0.0, -0.3), (0.26, 0.15), (-0.26, 0.15))


@dataclass(frozen=True)
class ExtendedSource:
    """A diffuse light source on a plane at depth ``z_mm``, radiance in DN of a fully lit green pixel.

    ``kind`` "band": a line through ``(x_mm, y_mm)`` at ``angle_rad`` to the X axis, Gaussian across
    (``sigma_mm``), its radiance modulated along it by ``1 + amplitude cos(2 pi along / period_mm +
    phase_rad)``. ``kind`` "glint": a round Gaussian spot.
    """

    kind: str
    z_mm: float
    x_mm: float
    y_mm: float
    sigma_mm: float
    level_dn: float
    angle_rad: float = 0.0
    amplitude: float = 0.0
    period_mm: float = 1.0
    phase_rad: float = 0.0

    def row(self, model: CameraModel) -> list[float]:
        """The kernel's source row (see :func:`trace_extended_sources`)."""
        optics = model.optics
        fp = float(optics.image_distance_m(self.z_mm))
        return [BAND if self.kind == "band" else GLINT, fp / optics.exit_pupil_m, self.z_mm / fp,
                self.x_mm, self.y_mm, self.sigma_mm, self.level_dn, self.angle_rad, self.amplitude,
                self.period_mm, self.phase_rad, math.cos(self.angle_rad), math.sin(self.angle_rad)]

    def footprint_px(self, model: CameraModel) -> tuple[float, float, float]:
        """Where its light falls on the sensor: ``(x, y)`` of its centre (chief ray through the lens
        centre) in sensor pixels, and the half-width (band) or radius (glint) in pixels that holds
        it all: the defocus blur radius plus four sigmas, plus a pitch."""
        optics = model.optics
        p_m = optics.exit_pupil_m
        to_px = p_m / self.z_mm * optics.projection_factor / optics.pixel_pitch_m  # mm -> sensor px
        fp = float(optics.image_distance_m(self.z_mm))
        blur_m = optics.aperture_diameter_m * abs(fp - p_m) / fp / 2
        reach = blur_m * optics.projection_factor / optics.pixel_pitch_m + 4 * self.sigma_mm * to_px
        return (model.lattice.origin_x + self.x_mm * to_px, model.lattice.origin_y + self.y_mm * to_px,
                reach + model.lattice.pitch_px)

    def covers(self, model: CameraModel, x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
        """Which sensor points ``(x_px, y_px)`` lie in this source's `footprint_px`."""
        cx, cy, reach = self.footprint_px(model)
        dx = np.asarray(x_px, dtype=np.float64) - cx
        dy = np.asarray(y_px, dtype=np.float64) - cy
        if self.kind == "band":
            across = -dx * math.sin(self.angle_rad) + dy * math.cos(self.angle_rad)
            return np.abs(across) <= reach
        return np.hypot(dx, dy) <= reach

    def box(self, model: CameraModel) -> tuple[int, int, int, int]:
        """Rows and columns ``(r0, r1, c0, c1)`` of the sensor its light can reach (may be empty)."""
        cx, cy, reach = self.footprint_px(model)
        w, h = model.width, model.height
        if self.kind == "band":
            slope = math.tan(self.angle_rad)
            ys = [cy + (x - cx) * slope for x in (0.0, float(w))]
            half = reach / max(math.cos(self.angle_rad), 1e-6)
            r0, r1, c0, c1 = min(ys) - half, max(ys) + half, 0.0, float(w)
        else:
            r0, r1, c0, c1 = cy - reach, cy + reach, cx - reach, cx + reach
        return (max(int(math.floor(r0)), 0), min(int(math.ceil(r1)), h),
                max(int(math.floor(c0)), 0), min(int(math.ceil(c1)), w))

    @classmethod
    def from_dict(cls, doc: dict) -> "ExtendedSource":
        """Inverse of `to_dict` (its ``footprint_px`` is recomputed, not read)."""
        return cls(**{k: v for k, v in doc.items() if k != "footprint_px"})

    def to_dict(self, model: CameraModel | None = None) -> dict:
        doc = asdict(self)
        if model is not None:
            cx, cy, reach = self.footprint_px(model)
            doc["footprint_px"] = {"x": cx, "y": cy, "reach": reach}
        return doc


@dataclass(frozen=True)
class ChamberLight:
    """The chamber's light besides the particles.

    ``glow_gradient`` is the plasma glow at the bottom edge of the field over that at the top
    (the glow at the centre is the scene's ``background_dn``); ``sources`` are laser reflections.
    """

    glow_gradient: float = 1.0
    sources: tuple[ExtendedSource, ...] = field(default_factory=tuple)

    @classmethod
    def build(cls, realism: Realism, *, seed: int, focus_distance_mm: float = DEFAULT_LENS.focus_distance_mm
              ) -> "ChamberLight":
        """The chamber of ``realism`` for scene ``seed``.

        The band is the laser sheet's reflection off the lower electrode: below the cluster in the
        upright image (``Y`` 4.5 ... 6.5 mm), 4 ... 10 mm behind the focus, nearly level, its
        radiance rippling by 25 % along it. Glints lie anywhere in the field, 5 ... 12 mm in front of
        or behind the focus, each 0.5 ... 1.5 times ``glint_dn``.
        """
        rng = np.random.default_rng([int(seed), 0xC4A3])
        sources = []
        if realism.reflection_dn > 0:
            sources.append(ExtendedSource(
                kind="band", z_mm=focus_distance_mm + float(rng.uniform(4.0, 10.0)),
                x_mm=0.0, y_mm=float(rng.uniform(4.5, 6.5)), sigma_mm=float(rng.uniform(0.15, 0.3)),
                level_dn=realism.reflection_dn, angle_rad=math.radians(float(rng.uniform(-3.0, 3.0))),
                amplitude=0.25, period_mm=float(rng.uniform(1.5, 4.0)), phase_rad=float(rng.uniform(0, 2 * math.pi))))
        for _ in range(realism.glints):
            z = focus_distance_mm + float(rng.choice([-1.0, 1.0]) * rng.uniform(5.0, 12.0))
            half_field = 0.8 * F01_SIZE / 2 * F01_PIXEL_PITCH_M * z / DEFAULT_LENS.lens_to_mla_m
            sources.append(ExtendedSource(
                kind="glint", z_mm=z, x_mm=float(rng.uniform(-half_field, half_field)),
                y_mm=float(rng.uniform(-half_field, half_field)), sigma_mm=float(rng.uniform(0.08, 0.3)),
                level_dn=float(realism.glint_dn * rng.uniform(0.5, 1.5))))
        return cls(glow_gradient=realism.glow_gradient, sources=tuple(sources))

    def glow_profile(self, model: CameraModel, x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
        """Glow relative to the centre's at sensor points: ``gradient ** (y / height)`` about the
        centre row, so bottom over top is ``glow_gradient``."""
        # Over the full sensor's height, so a (centred) crop shows its part of the full frame's gradient.
        y_rel = (np.asarray(y_px, dtype=np.float64) - model.height / 2) / F01_SIZE
        return np.broadcast_to(self.glow_gradient ** y_rel, np.broadcast(y_rel, np.asarray(x_px)).shape)

    def on_reflection(self, model: CameraModel, x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
        """Which sensor points lie where a reflection's light falls (any source's footprint)."""
        x_px = np.asarray(x_px, dtype=np.float64)
        hit = np.zeros(x_px.shape, dtype=bool)
        for source in self.sources:
            hit |= source.covers(model, x_px, y_px)
        return hit

    def to_dict(self, model: CameraModel | None = None) -> dict:
        """JSON-ready (``scenario.json``); with ``model``, each source's footprint on its sensor."""
        return {"glow_gradient": self.glow_gradient, "sources": [s.to_dict(model) for s in self.sources]}

    @classmethod
    def from_dict(cls, doc: dict) -> "ChamberLight":
        """Inverse of `to_dict`: the chamber recorded in a ``scenario.json``."""
        return cls(glow_gradient=float(doc.get("glow_gradient", 1.0)),
                   sources=tuple(ExtendedSource.from_dict(s) for s in doc.get("sources", ())))


def render_reflections(model: CameraModel, lattice: Lattice, chamber: ChamberLight, camera: CameraEffects | None
                       ) -> np.ndarray:
    """Irradiance of the chamber's reflections on the sensor before the point spread (DN as for a green
    site), float32 (H, W).

    Parameters
    ----------
    model : CameraModel
        Sensor, optics and the optical axis (its lattice origin).
    lattice : Lattice
        The micro-lens lattice the light passes (the exposure's, drifted or not).
    chamber : ChamberLight
    camera : CameraEffects or None
        The camera's second stop, lens transmission and pixel response (None: ideal).
    """
    out = np.zeros((model.height, model.width), dtype=np.float32)
    if not chamber.sources:
        return out
    optics = model.optics
    stop = camera.second_stop(model) if camera is not None else None
    half_n = camera.half_n if camera is not None else 0.0
    transmission = camera.transmission if camera is not None else None
    gain = transmission.gain if transmission is not None else np.ones((1, 1))
    gi0, gj0 = (transmission.i0, transmission.j0) if transmission is not None else (0, 0)
    params = np.array([optics.exit_pupil_m, optics.mla_to_sensor_m, optics.pixel_pitch_m, optics.projection_factor,
                       optics.aperture_diameter_m / 2, stop.shift_per_m if stop else 0.0,
                       stop.radius_m if stop else np.inf, optics.pixel_pitch_m / optics.mla_to_sensor_m, half_n])
    cell = np.array(_CELL_POINTS) * optics.lens_pitch_m
    basis = np.ascontiguousarray(lattice.basis)
    inverse = np.ascontiguousarray(np.linalg.inv(basis))
    for source in chamber.sources:
        r0, r1, c0, c1 = source.box(model)
        if r1 <= r0 or c1 <= c0:
            continue
        trace_extended_sources(out, r0, r1, c0, c1, lattice.origin_x, lattice.origin_y, basis, inverse,
                               model.lattice.origin_x, model.lattice.origin_y, params, gain, gi0, gj0,
                               np.ascontiguousarray(cell[:, 0]), np.ascontiguousarray(cell[:, 1]),
                               np.array([source.row(model)]), _PIXEL_SUPERSAMPLE)
    return out
