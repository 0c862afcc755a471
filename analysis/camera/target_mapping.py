"""A metric calibration from a dot target: ``(sx, sy, alpha) -> (X, Y, Z)`` in the target's frame.

The inputs are where the pipeline found a particle: its lens-plane position ``sx, sy`` (metres from
the optical axis, :class:`~analysis.camera.image_grid.ImageGrid`; independent of the output grid's
resolution) and its refocus parameter ``alpha``. The output is millimetres in the frame the target
defined: ``X`` along its rows of dots, ``Y`` down its columns, ``Z`` the stage position, origin at
the dot that was nearest the optical axis (docs/interfaces.md, "Metric calibration files").

Two mappings (fitted by :mod:`analysis.camera.mapping_fit`):

* :class:`PolynomialMapping` - each of ``X, Y, Z`` a polynomial in ``sx, sy`` (up to
  ``lateral_degree``) times ``alpha`` (up to ``alpha_degree``): the image-to-object form of the
  polynomial mapping of Soloff, Adrian & Liu (Meas. Sci. Technol. 8, 1441, 1997), which PIV/PTV
  systems use; it knows no optics, so it holds for any lens inside the volume it was fitted over.
* :class:`PhysicalMapping` - the main lens as the metadata give it (thin lens, docs/camera-model.md),
  an auxiliary thin lens and radial distortion (:class:`~analysis.camera.front_optics.FrontOptics`),
  and where the target's frame lies (a rotation, a translation, the stage's direction).

:class:`MetricCalibration` holds the one that predicted held-back target positions best, the other
for the record, the volume the target covered and the residuals; it is stored as JSON
(:mod:`analysis.camera.metric_files`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Union

import numpy as np

from analysis.errors import MetricCalibrationError
from .front_optics import FrontOptics


def polynomial_terms(lateral_degree: int, alpha_degree: int) -> list[tuple[int, int, int]]:
    """Exponents ``(i, j, k)`` of ``u^i v^j w^k`` with ``i + j <= lateral_degree``, ``k <= alpha_degree``."""
    return [(i, d - i, k) for k in range(alpha_degree + 1) for d in range(lateral_degree + 1) for i in range(d, -1, -1)]


@dataclass(frozen=True)
class PolynomialMapping:
    """``X, Y, Z`` each a polynomial in the normalised ``u = sx / scale_m``, ``v = sy / scale_m``,
    ``w = (alpha - alpha_centre) / alpha_scale``.

    Attributes
    ----------
    lateral_degree, alpha_degree : int
    scale_m, alpha_centre, alpha_scale : float
        Normalisation of the inputs (keeps the design well conditioned).
    coefficients : ndarray of shape (n_terms, 3)
        Columns for ``X, Y, Z``, rows in the order of :func:`polynomial_terms`.
    """

    lateral_degree: int
    alpha_degree: int
    scale_m: float
    alpha_centre: float
    alpha_scale: float
    coefficients: np.ndarray

    kind = "polynomial"

    def design(self, sx_m: np.ndarray, sy_m: np.ndarray, alpha: np.ndarray) -> np.ndarray:
        """The terms at each point: (n, n_terms)."""
        u = np.asarray(sx_m, dtype=np.float64) / self.scale_m
        v = np.asarray(sy_m, dtype=np.float64) / self.scale_m
        w = (np.asarray(alpha, dtype=np.float64) - self.alpha_centre) / self.alpha_scale
        return np.column_stack([u ** i * v ** j * w ** k
                                for i, j, k in polynomial_terms(self.lateral_degree, self.alpha_degree)])

    def __call__(self, sx_m: np.ndarray, sy_m: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, ...]:
        out = self.design(sx_m, sy_m, alpha) @ self.coefficients
        return out[:, 0], out[:, 1], out[:, 2]

    @property
    def name(self) -> str:
        return f"polynomial (degree {self.lateral_degree} in sx, sy; {self.alpha_degree} in alpha)"

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "lateral_degree": self.lateral_degree, "alpha_degree": self.alpha_degree,
                "scale_m": self.scale_m, "alpha_centre": self.alpha_centre, "alpha_scale": self.alpha_scale,
                "terms": [list(t) for t in polynomial_terms(self.lateral_degree, self.alpha_degree)],
                "coefficients": {axis: self.coefficients[:, a].tolist() for a, axis in enumerate("XYZ")}}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "PolynomialMapping":
        coefficients = np.column_stack([np.asarray(values["coefficients"][axis], dtype=np.float64) for axis in "XYZ"])
        out = cls(int(values["lateral_degree"]), int(values["alpha_degree"]), float(values["scale_m"]),
                  float(values["alpha_centre"]), float(values["alpha_scale"]), coefficients)
        if coefficients.shape[0] != len(polynomial_terms(out.lateral_degree, out.alpha_degree)):
            raise MetricCalibrationError("the polynomial mapping's coefficients do not match its degrees; the file "
                                         "is damaged: run plenodust calibrate-target again")
        return out


def rotation_matrix(rotvec: np.ndarray) -> np.ndarray:
    """Rotation by ``|rotvec|`` radians about ``rotvec`` (Rodrigues)."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = float(np.linalg.norm(rotvec))
    if angle < 1e-15:
        return np.eye(3)
    k = rotvec / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(angle) * kx + (1 - math.cos(angle)) * kx @ kx


@dataclass(frozen=True)
class PhysicalMapping:
    """The optics traced back: main thin lens, auxiliary lens and distortion, then the target's frame.

    A point sharp at ``alpha`` on lens-plane ``(sx, sy)`` is seen by the main lens at
    ``Z'' = 1 / (1/f - 1/(alpha P))``, ``(X'', Y'') = (sx, sy) Z'' / P``; ``front.physical`` gives its
    camera-frame position ``c``; its target-frame coordinates solve
    ``c = origin_mm + X plate_x + Y plate_y + Z stage`` (``plate_x, plate_y`` the first two columns of
    ``rotation_matrix(rotation)``, ``stage`` the unit vector along ``(stage_slope_x, stage_slope_y, 1)``).

    Attributes
    ----------
    focal_length_mm, lens_to_mla_mm : float
        The main lens as calibrated (the metadata's thin lens).
    front : FrontOptics
    rotation : tuple of 3 floats
        Rotation vector (radians) of the target's plate in the camera frame.
    origin_mm : tuple of 3 floats
        Camera-frame position of the target frame's origin.
    stage_slope : tuple of 2 floats
        Direction of the stage's travel in the camera frame: ``(dX/dZ, dY/dZ)``.
    """

    focal_length_mm: float
    lens_to_mla_mm: float
    front: FrontOptics
    rotation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    origin_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    stage_slope: tuple[float, float] = (0.0, 0.0)

    kind = "physical"

    @property
    def name(self) -> str:
        f = self.front.aux_focal_mm
        lens = "no auxiliary lens" if f is None else f"auxiliary lens f = {f:.1f} mm at {self.front.aux_distance_mm:.1f} mm"
        return f"physical (thin main lens, {lens}, distortion k1 = {self.front.k1:+.4f})"

    def frame_matrix(self) -> np.ndarray:
        """Columns: the camera-frame vectors of one mm along the target's ``X``, ``Y`` and stage ``Z``."""
        rot = rotation_matrix(np.asarray(self.rotation))
        stage = np.array([self.stage_slope[0], self.stage_slope[1], 1.0])
        return np.column_stack([rot[:, 0], rot[:, 1], stage / np.linalg.norm(stage)])

    def camera_points(self, sx_m: np.ndarray, sy_m: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, ...]:
        """True camera-frame positions (mm) of points sharp at ``alpha`` on lens-plane ``(sx, sy)``."""
        alpha = np.asarray(alpha, dtype=np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = 1.0 / (1.0 / self.focal_length_mm - 1.0 / (alpha * self.lens_to_mla_mm))
        scale = z / (self.lens_to_mla_mm * 1e-3)
        return self.front.physical(np.asarray(sx_m, float) * scale, np.asarray(sy_m, float) * scale, z)

    def __call__(self, sx_m: np.ndarray, sy_m: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, ...]:
        c = np.stack(self.camera_points(sx_m, sy_m, alpha))
        world = np.linalg.solve(self.frame_matrix(), c - np.asarray(self.origin_mm)[:, None])
        return world[0], world[1], world[2]

    def to_dict(self) -> dict[str, Any]:
        return {"kind": self.kind, "focal_length_mm": self.focal_length_mm, "lens_to_mla_mm": self.lens_to_mla_mm,
                "front_optics": self.front.to_dict(), "rotation": list(self.rotation),
                "origin_mm": list(self.origin_mm), "stage_slope": list(self.stage_slope)}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "PhysicalMapping":
        return cls(float(values["focal_length_mm"]), float(values["lens_to_mla_mm"]),
                   FrontOptics.from_dict(values["front_optics"]),
                   tuple(float(v) for v in values["rotation"]), tuple(float(v) for v in values["origin_mm"]),
                   tuple(float(v) for v in values["stage_slope"]))


Mapping3D = Union[PolynomialMapping, PhysicalMapping]


def mapping_from_dict(values: Mapping[str, Any]) -> Mapping3D:
    """A mapping from its :meth:`to_dict` form."""
    kind = values.get("kind")
    if kind == PolynomialMapping.kind:
        return PolynomialMapping.from_dict(values)
    if kind == PhysicalMapping.kind:
        return PhysicalMapping.from_dict(values)
    raise MetricCalibrationError(f"unknown mapping kind {kind!r} (known: polynomial, physical); is the file from a "
                                 "newer plenodust?")


@dataclass(frozen=True)
class CalibratedVolume:
    """Where the target's dots were: the volume a mapping may be trusted in (target frame, mm)."""

    x_mm: tuple[float, float]
    y_mm: tuple[float, float]
    z_mm: tuple[float, float]
    alpha: tuple[float, float]
    margin_mm: float = 0.0

    def outside(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
        """Which points lie outside the volume (by more than ``margin_mm``); NaN counts as outside."""
        m = self.margin_mm
        inside = np.ones(np.shape(x), dtype=bool)
        for value, (lo, hi) in ((x, self.x_mm), (y, self.y_mm), (z, self.z_mm)):
            value = np.asarray(value, dtype=np.float64)
            inside &= (value >= lo - m) & (value <= hi + m)
        return ~inside

    def describe(self) -> str:
        return (f"X {self.x_mm[0]:.2f} ... {self.x_mm[1]:.2f}, Y {self.y_mm[0]:.2f} ... {self.y_mm[1]:.2f}, "
                f"Z {self.z_mm[0]:.2f} ... {self.z_mm[1]:.2f} mm")

    def to_dict(self) -> dict[str, Any]:
        return {"x_mm": list(self.x_mm), "y_mm": list(self.y_mm), "z_mm": list(self.z_mm), "alpha": list(self.alpha),
                "margin_mm": self.margin_mm}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "CalibratedVolume":
        pair = lambda key: tuple(float(v) for v in values[key])  # noqa: E731
        return cls(pair("x_mm"), pair("y_mm"), pair("z_mm"), pair("alpha"), float(values.get("margin_mm", 0.0)))


@dataclass(frozen=True)
class CameraKey:
    """The camera and lens setting a metric calibration belongs to."""

    serial: str | None
    zoom_step: int | None
    focus_step: int | None

    def describe(self) -> str:
        return f"camera {self.serial or '(serial unknown)'} at zoomStep {self.zoom_step}, focusStep {self.focus_step}"

    def to_dict(self) -> dict[str, Any]:
        return {"serial": self.serial, "zoom_step": self.zoom_step, "focus_step": self.focus_step}

    @classmethod
    def from_dict(cls, values: Mapping[str, Any]) -> "CameraKey":
        def integer(v: Any) -> int | None:
            return None if v is None else int(v)
        return cls(values.get("serial"), integer(values.get("zoom_step")), integer(values.get("focus_step")))


@dataclass(frozen=True)
class MetricCalibration:
    """A fitted target calibration, as applied to particles and stored per camera.

    Attributes
    ----------
    mapping : PolynomialMapping or PhysicalMapping
        The mapping used: the one that predicted held-back target positions best.
    camera : CameraKey
    volume : CalibratedVolume
    alternatives : dict of str to mapping
        The other mappings fitted (for the record and for comparison).
    report : dict
        Residuals per position and axis (fit and held back, micrometres), the comparison of the
        mappings, the target and its exposures (JSON-able; see docs/interfaces.md).
    white_sha1 : str or None
        The white image whose lattice gave the lens-plane positions.
    created_utc : str
    sha1 : str or None
        SHA-1 of the file it was read from (None until saved or read).
    """

    mapping: Mapping3D
    camera: CameraKey
    volume: CalibratedVolume
    alternatives: dict[str, Mapping3D] = field(default_factory=dict)
    report: dict[str, Any] = field(default_factory=dict)
    white_sha1: str | None = None
    created_utc: str = ""
    sha1: str | None = None

    def to_physical(self, sx_m: np.ndarray, sy_m: np.ndarray, alpha: np.ndarray) -> tuple[np.ndarray, ...]:
        """Target-frame ``X, Y, Z`` (mm) of points sharp at ``alpha`` on lens-plane ``(sx, sy)`` (m)."""
        return tuple(np.asarray(v, dtype=np.float64) for v in self.mapping(sx_m, sy_m, alpha))

    def volume_warning(self, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> str | None:
        """A warning when particles lie outside the calibrated volume (None when all are inside)."""
        out = self.volume.outside(x, y, z)
        if not out.any():
            return None
        return (f"{int(out.sum())} of {out.size} particles lie outside the volume the target calibration covered "
                f"({self.volume.describe()}); their coordinates are extrapolated: calibrate over a volume that "
                "holds the cluster")

    def to_dict(self) -> dict[str, Any]:
        """What a result records: the calibration used, not its whole report."""
        held = self.report.get("comparison", {}).get(self.mapping.kind, {})
        return {"kind": "target", "model": self.mapping.kind, "mapping": self.mapping.name,
                "sha1": self.sha1, "created_utc": self.created_utc, **self.camera.to_dict(),
                "held_out_rms_um": held.get("held_out_rms_um"), "volume": self.volume.to_dict(),
                "frame": "target: X along its rows of dots, Y down its columns, Z the stage position (mm)"}
