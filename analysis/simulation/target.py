"""A calibration target for the simulator: a plate of dots at known stage positions.

Labs calibrate 3D particle-tracking cameras with a plate of dots of known pitch that a translation
stage moves through the measurement volume (Soloff, Adrian & Liu 1997). :class:`DotTarget` is that
plate: a square grid of bright compact dots (like particles), ``pitch_mm`` apart over a square
``extent_mm`` wide, the dot in the middle at ``offset_mm`` from the optical axis, the plate turned
by ``rotation_deg`` about the axis and tilted by ``tilt_deg`` about its rows; the stage moves it
along the optical axis to each of ``positions_mm``.

The frame a target calibration measures in is the target's own (docs/camera-model.md keeps the
camera frame): ``X`` along the rows of dots (columns increase with it), ``Y`` down the columns,
``Z`` the stage position; the origin is the middle dot at stage position 0. For the default
untilted, unturned plate on the axis this is the camera frame.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from analysis.camera.front_optics import FrontOptics, sensor_reference_tan
from analysis.errors import ParameterError
from .camera import DEFAULT_LENS, F01_PIXEL_PITCH_M, F01_SIZE
from .scenarios import Particles

#: The scenario name of a target (``plenodust simulate --scenario target``).
TARGET = "target"
#: What ``--scenario target`` renders by default: 5 stage positions across 8 mm about the focus.
DEFAULT_POSITIONS = 5
DEFAULT_DEPTH_SPAN_MM = 8.0


@dataclass(frozen=True)
class DotTarget:
    """A plate of dots of known pitch at a list of stage positions.

    Attributes
    ----------
    positions_mm : tuple of float
        Stage positions: the depth (mm, along the optical axis from the main lens) of the middle dot
        in each exposure.
    pitch_mm : float
        Distance between neighbouring dots.
    extent_mm : float
        Side of the square the dots fill (a dot on the middle row and column at its centre).
    tilt_deg : float
        Tilt of the plate about its rows (``X``): its normal leaves the stage axis by this angle.
    rotation_deg : float
        Turn of the rows about the optical axis, from the image's ``x``.
    offset_mm : tuple of 2 floats
        Lateral position of the middle dot (from the optical axis).
    brightness_dn : float
        Median dot brightness (DN above black of a fully lit green pixel), spread by 3 %.
    """

    positions_mm: tuple[float, ...]
    pitch_mm: float = 1.0
    extent_mm: float = 12.0
    tilt_deg: float = 0.0
    rotation_deg: float = 0.0
    offset_mm: tuple[float, float] = (0.0, 0.0)
    brightness_dn: float = 1800.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "positions_mm", tuple(float(z) for z in self.positions_mm))
        object.__setattr__(self, "offset_mm", tuple(float(v) for v in self.offset_mm))
        if not self.positions_mm or min(self.positions_mm) <= 0:
            raise ParameterError(f"target positions must be positive depths in mm, got {list(self.positions_mm)}")
        if len(set(self.positions_mm)) != len(self.positions_mm):
            raise ParameterError(f"target positions must differ from each other, got {list(self.positions_mm)}")
        if not (0.05 <= self.pitch_mm <= 20):
            raise ParameterError(f"dot pitch {self.pitch_mm} mm is outside 0.05 ... 20 mm")
        if not (self.pitch_mm <= self.extent_mm <= 200):
            raise ParameterError(f"target extent {self.extent_mm} mm must be at least one pitch and at most 200 mm")
        if not (-60 < self.tilt_deg < 60):
            raise ParameterError(f"target tilt {self.tilt_deg} degrees is outside -60 ... 60")
        if len(self.offset_mm) != 2:
            raise ParameterError("offset_mm takes X and Y")
        if self.brightness_dn <= 0:
            raise ParameterError("brightness_dn must be positive")

    @classmethod
    def about(cls, centre_z_mm: float, *, count: int = DEFAULT_POSITIONS, span_mm: float = DEFAULT_DEPTH_SPAN_MM,
              **plate: Any) -> "DotTarget":
        """A target at ``count`` stage positions evenly across ``span_mm`` about ``centre_z_mm``."""
        if count < 1:
            raise ParameterError(f"give at least one target position, got {count}")
        offsets = np.linspace(-span_mm / 2, span_mm / 2, count) if count > 1 else np.zeros(1)
        return cls(positions_mm=tuple(round(centre_z_mm + float(d), 6) for d in offsets), **plate)

    def dot_indices(self) -> tuple[np.ndarray, np.ndarray]:
        """Row and column of every dot (the middle dot is ``(0, 0)``), row-major."""
        n = int(math.floor(self.extent_mm / 2 / self.pitch_mm + 1e-9))
        rows, cols = np.meshgrid(np.arange(-n, n + 1), np.arange(-n, n + 1), indexing="ij")
        return rows.ravel(), cols.ravel()

    def _rotation(self) -> np.ndarray:
        t, r = math.radians(self.tilt_deg), math.radians(self.rotation_deg)
        tilt = np.array([[1.0, 0.0, 0.0], [0.0, math.cos(t), -math.sin(t)], [0.0, math.sin(t), math.cos(t)]])
        turn = np.array([[math.cos(r), -math.sin(r), 0.0], [math.sin(r), math.cos(r), 0.0], [0.0, 0.0, 1.0]])
        return turn @ tilt

    def camera_positions(self, z_mm: float) -> np.ndarray:
        """Every dot in the camera frame (mm) with the plate at stage position ``z_mm``: (3, n)."""
        rows, cols = self.dot_indices()
        plate = np.stack([cols * self.pitch_mm, rows * self.pitch_mm, np.zeros(rows.size)])
        return self._rotation() @ plate + np.array([self.offset_mm[0], self.offset_mm[1], z_mm])[:, None]

    def target_frame(self, z_mm: float) -> np.ndarray:
        """Every dot in the target's own frame (``X, Y`` on the plate, ``Z`` the stage position): (3, n)."""
        rows, cols = self.dot_indices()
        return np.stack([cols * self.pitch_mm, rows * self.pitch_mm, np.full(rows.size, float(z_mm))])

    def particles(self, z_mm: float, rng: np.random.Generator) -> Particles:
        """The dots at stage position ``z_mm`` as point sources."""
        x, y, z = self.camera_positions(z_mm)
        brightness = self.brightness_dn * np.exp(rng.normal(0.0, 0.03, size=x.size))
        return Particles(x, y, z, brightness)

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["positions_mm"] = list(self.positions_mm)
        out["offset_mm"] = list(self.offset_mm)
        return out


def simulated_front_optics(aux_focal_mm: float | None = None, aux_distance_mm: float = 20.0, *,
                           distortion: float = 0.0) -> FrontOptics | None:
    """The simulated camera's front optics: an auxiliary lens (None: none) and radial distortion given
    as the fractional displacement at the corner of the full F01 sensor. None when there are neither."""
    if aux_focal_mm is None and distortion == 0.0:
        return None
    corner = sensor_reference_tan(F01_SIZE, F01_SIZE, F01_PIXEL_PITCH_M, DEFAULT_LENS.lens_to_mla_m)
    return FrontOptics.with_lens(aux_focal_mm, aux_distance_mm, distortion=distortion, reference_tan=corner)


def default_target(front: FrontOptics | None = None, **plate: Any) -> DotTarget:
    """The default target: 5 positions across 8 mm about where the camera focuses through ``front``."""
    focus = DEFAULT_LENS.focus_distance_mm
    centre = focus if front is None or front.is_identity else front.object_distance_mm(focus)
    return DotTarget.about(round(centre, 3), **plate)


def target_sidecar(target: DotTarget, names: list[str], front: FrontOptics | None) -> dict[str, Any]:
    """``target.json``: the positions of each exposure and which dot each truth row is.

    ``positions_mm[k]`` is the stage position of ``exposures[k]``; truth row ``i`` of every
    exposure is the dot at ``rows[i], cols[i]``; ``target_frame`` says how its coordinates relate to
    the camera frame.
    """
    rows, cols = target.dot_indices()
    return {"format": "plenodust.target-positions", "version": 1,
            "exposures": list(names), "positions_mm": list(target.positions_mm), "pitch_mm": target.pitch_mm,
            "target": target.to_dict(), "rows": rows.tolist(), "cols": cols.tolist(),
            "front_optics": None if front is None else front.to_dict(),
            "target_frame": "X along the rows of dots, Y down the columns, Z the stage position; origin: the "
                            "middle dot (row 0, column 0) at stage position 0"}
