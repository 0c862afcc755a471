"""What lies between the scene and the thin main lens: an auxiliary thin lens and radial distortion.

The paper's set-up put a convex lens (f = 174 mm) in front of the camera to shorten the working
distance; real main lenses also bend straight lines (radial distortion). Neither is in the camera's
metadata. Both are modelled here as a map from where a point *is* (camera frame of
docs/camera-model.md, mm) to where the thin main lens *sees* it (its apparent position), and back:

1. **Auxiliary thin lens** of power ``phi = 1/f`` at ``L`` mm in front of the main lens, on its axis.
   A point at object distance ``s = Z - L`` from it images at ``L + s / (1 - phi s)`` (a virtual
   image farther away for ``s < f``, the close-up lens case; a real, inverted one between the
   lenses beyond ``f``), magnified laterally by ``m = 1 / (1 - phi s)``. Depth is stretched by
   ``m^2``, so lateral and depth scales change with depth.
2. **Radial distortion** of the main lens: the apparent field tangent ``t = r / Z`` moves to
   ``t (1 + k1 q^2 + k2 q^4)`` with ``q = t / reference_tan``; ``k1`` is the fractional radial
   displacement at the reference field (the sensor's corner for the simulator), so ``k1 = 0.01``
   is "1 % distortion". Depth is unchanged: distortion bends the chief ray, not the focus.

The simulator renders particles at their apparent positions (exact for ideal thin lenses); the
physical model of :mod:`analysis.camera.mapping_fit` fits ``phi, L, k1, k2`` to a target.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Mapping

import numpy as np

from analysis.errors import ParameterError

#: Newton steps to undo the distortion polynomial (converges to 1e-15 in 3-4 for |k| < 0.2).
_UNDISTORT_STEPS = 8


@dataclass(frozen=True)
class FrontOptics:
    """An auxiliary thin lens in front of the main lens, and the main lens's radial distortion.

    Attributes
    ----------
    aux_power_per_mm : float
        ``1 / f`` of the auxiliary lens in 1/mm (positive: convex); 0 means no auxiliary lens.
    aux_distance_mm : float
        Distance from the main lens to the auxiliary lens along the axis (``L``).
    k1, k2 : float
        Radial distortion: fractional displacement of the field tangent at ``reference_tan``
        (``k1``) and its fourth-order companion. Positive: pincushion; negative: barrel.
    reference_tan : float
        Field tangent (radius over depth) at which ``k1`` is the displacement.

    Examples
    --------
    >>> front = FrontOptics.with_lens(174.0, 20.0)
    >>> x, y, z = front.apparent(np.array([1.0]), np.array([0.0]), np.array([52.5]))
    >>> back = front.physical(x, y, z)
    >>> [round(float(v[0]), 9) for v in back]
    [1.0, 0.0, 52.5]
    """

    aux_power_per_mm: float = 0.0
    aux_distance_mm: float = 0.0
    k1: float = 0.0
    k2: float = 0.0
    reference_tan: float = 0.2

    def __post_init__(self) -> None:
        for name in ("aux_power_per_mm", "aux_distance_mm", "k1", "k2", "reference_tan"):
            if not math.isfinite(getattr(self, name)):
                raise ParameterError(f"front optics: {name} must be a finite number, got {getattr(self, name)}")
        if self.aux_distance_mm < 0:
            raise ParameterError(f"the auxiliary lens must sit in front of the main lens (distance >= 0 mm), "
                                 f"got {self.aux_distance_mm} mm")
        if self.reference_tan <= 0:
            raise ParameterError(f"reference_tan must be positive, got {self.reference_tan}")
        if abs(self.k1) > 0.3 or abs(self.k2) > 0.3:
            raise ParameterError(f"radial distortion k1={self.k1}, k2={self.k2} is beyond +-30 %; give it as a "
                                 "fraction (0.01 for 1 %)")

    @classmethod
    def with_lens(cls, focal_length_mm: float | None, distance_mm: float = 0.0, *, distortion: float = 0.0,
                  reference_tan: float = 0.2) -> "FrontOptics":
        """An auxiliary lens of focal length ``focal_length_mm`` (None: none) ``distance_mm`` in front."""
        if focal_length_mm is not None and not (math.isfinite(focal_length_mm) and focal_length_mm != 0):
            raise ParameterError(f"auxiliary focal length must be a non-zero number of mm, got {focal_length_mm}")
        power = 0.0 if focal_length_mm is None else 1.0 / focal_length_mm
        return cls(aux_power_per_mm=power, aux_distance_mm=float(distance_mm), k1=float(distortion),
                   reference_tan=float(reference_tan))

    @property
    def is_identity(self) -> bool:
        """No auxiliary lens and no distortion: apparent positions are the true ones."""
        return self.aux_power_per_mm == 0.0 and self.k1 == 0.0 and self.k2 == 0.0

    @property
    def aux_focal_mm(self) -> float | None:
        return None if self.aux_power_per_mm == 0.0 else 1.0 / self.aux_power_per_mm

    def apparent(self, x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Where the main lens sees points at ``(x, y, z)`` (mm, camera frame): the auxiliary lens's
        image of them, then distorted.

        Raises
        ------
        ParameterError
            For points at or behind the auxiliary lens, or whose image through it would not lie in
            front of the main lens.
        """
        x, y, z = (np.asarray(a, dtype=np.float64) for a in (x_mm, y_mm, z_mm))
        s = z - self.aux_distance_mm
        if self.aux_power_per_mm != 0.0:
            if np.any(s <= 0):
                raise ParameterError(f"points must lie in front of the auxiliary lens ({self.aux_distance_mm} mm "
                                     "from the main lens); move them farther or the lens nearer")
            denom = 1.0 - self.aux_power_per_mm * s
            zi = self.aux_distance_mm + s / denom
            if np.any(zi <= 0) or np.any(denom == 0):
                raise ParameterError("the auxiliary lens images these points behind the main lens (they lie beyond "
                                     f"its focal length {self.aux_focal_mm:.1f} mm); move them nearer the lens")
            m = 1.0 / denom
            x, y, z = x * m, y * m, zi
        scale = self._distortion_scale(np.hypot(x, y) / z)
        return x * scale, y * scale, z

    def physical(self, x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inverse of :meth:`apparent`: true positions of points the main lens sees at ``(x, y, z)``.

        Points whose apparent depth the auxiliary lens cannot produce come out NaN.
        """
        x, y, z = (np.asarray(a, dtype=np.float64) for a in (x_mm, y_mm, z_mm))
        tan_d = np.hypot(x, y) / z
        tan_u = self.undistort_tan(tan_d)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.where(tan_d > 0, tan_u / tan_d, 1.0)
        x, y = x * ratio, y * ratio
        if self.aux_power_per_mm == 0.0:
            return x, y, z
        v = z - self.aux_distance_mm
        m = 1.0 + self.aux_power_per_mm * v
        with np.errstate(divide="ignore", invalid="ignore"):
            s = np.where(m != 0, v / m, np.nan)  # m < 0: a real, inverted image between the lenses
            return x / m, y / m, self.aux_distance_mm + s

    def _distortion_scale(self, tan_u: np.ndarray) -> np.ndarray:
        q2 = (tan_u / self.reference_tan) ** 2
        return 1.0 + self.k1 * q2 + self.k2 * q2 * q2

    def undistort_tan(self, tan_d: np.ndarray) -> np.ndarray:
        """Field tangent before distortion of one seen at ``tan_d`` (Newton's method)."""
        tan_d = np.asarray(tan_d, dtype=np.float64)
        if self.k1 == 0.0 and self.k2 == 0.0:
            return tan_d.copy()
        t = tan_d.copy()
        r2 = self.reference_tan ** 2
        for _ in range(_UNDISTORT_STEPS):
            q2 = t * t / r2
            f = t * (1.0 + self.k1 * q2 + self.k2 * q2 * q2) - tan_d
            df = 1.0 + 3.0 * self.k1 * q2 + 5.0 * self.k2 * q2 * q2
            t = t - f / df
        return t

    def object_distance_mm(self, apparent_z_mm: float) -> float:
        """True depth (on axis) of a point the main lens sees at ``apparent_z_mm``: e.g. where the
        main lens's focus lies in the scene."""
        return float(self.physical(np.zeros(1), np.zeros(1), np.array([apparent_z_mm]))[2][0])

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        out["aux_focal_mm"] = self.aux_focal_mm
        return out

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "FrontOptics":
        known = {"aux_power_per_mm", "aux_distance_mm", "k1", "k2", "reference_tan"}
        return cls(**{k: float(v) for k, v in values.items() if k in known})


def sensor_reference_tan(width_px: int, height_px: int, pixel_pitch_m: float, lens_to_mla_m: float) -> float:
    """Field tangent of the sensor's corner seen from the main lens: ``half-diagonal / P``."""
    return 0.5 * math.hypot(width_px, height_px) * pixel_pitch_m / lens_to_mla_m
