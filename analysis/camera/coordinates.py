"""Physical coordinates: refocus parameter and image position to ``X, Y, Z`` in millimetres.

The camera frame is that of docs/camera-model.md (origin at the main lens, ``Z`` along the axis
toward the scene, ``X`` right and ``Y`` down in the upright output image). Two ways to get there:

* :class:`ThinLensCalibration` - the thin-lens model of the metadata: a point at ``(X, Y, Z)``
  is sharpest at ``alpha = Fp / P`` at lens-plane position ``(X, Y) * P / Z``, so
  ``Z = 1 / (1/f - 1/(alpha P))`` and ``(X, Y) = s * Z / P``.
* :class:`~analysis.camera.target_mapping.MetricCalibration` - fitted to a dot target imaged at
  several stage positions (``plenodust calibrate-target``): the calibration for a real set-up,
  auxiliary lenses and distortion included; ``X, Y, Z`` in the target's frame.
* :class:`UserCalibration` - two numbers a user measures (object-space pixel size at a reference
  plane and depth per unit alpha), or :func:`fit_tilted_layer` to a flat layer tilted at a known
  angle, as in the paper's 13 degree check. Real F01 zoom lenses and added optics do not follow
  the thin lens at ``P``, so this is the calibration to trust in the lab.

:func:`validate_plane` reports how flat a layer came out, as the paper did.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Union

import numpy as np
from scipy.spatial import cKDTree

from .model import Optics
from analysis.errors import ParameterError
from .image_grid import ImageGrid
from .target_mapping import MetricCalibration


@dataclass(frozen=True)
class ThinLensCalibration:
    """Depth and scale from the thin main lens of the metadata (docs/camera-model.md).

    The fallback: real zoom lenses and added optics do not follow it. ``fallback_reason`` says why
    it stands in for a target calibration that was looked for (a warning in the result).
    """

    optics: Optics
    fallback_reason: str | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "thin-lens", **{f"optics.{k}": v for k, v in asdict(self.optics).items()},
                "note": "the metadata's thin-lens model, not a target calibration: real set-ups need one "
                        "(plenodust calibrate-target)" + (f"; {self.fallback_reason}" if self.fallback_reason else "")}


@dataclass(frozen=True)
class UserCalibration:
    """A linear calibration measured by the user.

    ``X = (x - centre_x_px) * pixel_size_mm``, likewise ``Y``, and
    ``Z = reference_z_mm + (alpha - reference_alpha) * depth_per_alpha_mm``, with ``x, y`` in
    output-image pixels.

    Attributes
    ----------
    pixel_size_mm : float
        Object-space size of one output pixel at the reference plane.
    depth_per_alpha_mm : float
        Change of ``Z`` per unit of alpha; negative for an ordinary lens (a larger alpha
        focuses nearer).
    reference_alpha : float
        The alpha whose plane is at ``reference_z_mm``.
    reference_z_mm : float
        Distance of the reference plane; 0 gives depths relative to it.
    centre_x_px, centre_y_px : float
        Output-image pixel on the optical axis; NaN means the centre of the image.
    """

    pixel_size_mm: float
    depth_per_alpha_mm: float
    reference_alpha: float = 1.0
    reference_z_mm: float = 0.0
    centre_x_px: float = math.nan
    centre_y_px: float = math.nan

    def __post_init__(self) -> None:
        if not (math.isfinite(self.pixel_size_mm) and self.pixel_size_mm > 0):
            raise ParameterError(f"pixel_size_mm must be a positive number, got {self.pixel_size_mm}")
        if not (math.isfinite(self.depth_per_alpha_mm) and self.depth_per_alpha_mm != 0):
            raise ParameterError(f"depth_per_alpha_mm must be a non-zero number, got {self.depth_per_alpha_mm}")

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "user", **asdict(self)}


Calibration3D = Union[ThinLensCalibration, UserCalibration, MetricCalibration]


def to_physical(x_px: np.ndarray, y_px: np.ndarray, alpha: np.ndarray, grid: ImageGrid,
                calibration: Calibration3D) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Camera-frame ``X, Y, Z`` in mm of particles at output pixel ``(x, y)`` and refocus ``alpha``.

    Parameters
    ----------
    x_px, y_px : ndarray of shape (n,)
        Position in output-image pixels (integer values are pixel centres, as in
        :class:`~analysis.camera.image_grid.ImageGrid`).
    alpha : ndarray of shape (n,)
        Refocus parameter of each particle.
    grid : ImageGrid
        The grid of the refocused images.
    calibration : ThinLensCalibration, UserCalibration or MetricCalibration

    Returns
    -------
    X, Y, Z : ndarrays of shape (n,), float64, mm

    Raises
    ------
    MetadataError
        With a thin-lens calibration whose metadata has no usable exit-pupil distance.
    """
    x_px = np.asarray(x_px, dtype=np.float64)
    y_px = np.asarray(y_px, dtype=np.float64)
    alpha = np.asarray(alpha, dtype=np.float64)
    if isinstance(calibration, ThinLensCalibration):
        optics = calibration.optics
        z = np.asarray(optics.z_of_alpha(alpha), dtype=np.float64)
        p = optics._require_finite_p()
        sx, sy = grid.to_lens_plane(x_px, y_px)
        return sx * z / p, sy * z / p, z
    if isinstance(calibration, UserCalibration):
        cx = (grid.width - 1) / 2 if math.isnan(calibration.centre_x_px) else calibration.centre_x_px
        cy = (grid.height - 1) / 2 if math.isnan(calibration.centre_y_px) else calibration.centre_y_px
        z = calibration.reference_z_mm + (alpha - calibration.reference_alpha) * calibration.depth_per_alpha_mm
        return (x_px - cx) * calibration.pixel_size_mm, (y_px - cy) * calibration.pixel_size_mm, z
    if isinstance(calibration, MetricCalibration):
        sx, sy = grid.to_lens_plane(x_px, y_px)
        return calibration.to_physical(sx, sy, alpha)
    raise ParameterError(f"unknown calibration type {type(calibration).__name__}; "
                         "use ThinLensCalibration, UserCalibration or MetricCalibration")


def coordinate_warnings(x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray,
                        calibration: Calibration3D) -> list[str]:
    """What a user should know about the physical coordinates: particles outside a target
    calibration's volume, or a thin-lens fallback where a target calibration was looked for."""
    if isinstance(calibration, MetricCalibration):
        warning = calibration.volume_warning(x_mm, y_mm, z_mm) if np.size(x_mm) else None
        return [] if warning is None else [warning]
    if isinstance(calibration, ThinLensCalibration) and calibration.fallback_reason:
        return [f"X, Y, Z come from the metadata's thin-lens model: {calibration.fallback_reason}"]
    return []


def fit_tilted_layer(x_px: np.ndarray, y_px: np.ndarray, alpha: np.ndarray, *, tilt_deg: float,
                     pixel_size_mm: float, depth_sign: float = -1.0, reference_alpha: float = 1.0,
                     reference_z_mm: float = 0.0) -> UserCalibration:
    """Depth per unit alpha from a flat particle layer tilted by a known angle (the paper's check).

    A plane ``alpha = a + b x + c y`` is fitted to the particles; across the layer, depth changes
    by ``tan(tilt)`` per unit of lateral distance, so
    ``|depth_per_alpha| = tan(tilt) * pixel_size_mm / |(b, c)|``.

    Parameters
    ----------
    x_px, y_px, alpha : ndarray of shape (n,), n >= 3
        Particles found in the tilted layer.
    tilt_deg : float
        Angle between the layer and the image plane, in (0, 90) degrees.
    pixel_size_mm : float
        Object-space size of one output pixel (from a scale in the image).
    depth_sign : {-1, +1}
        Sign of ``dZ/dalpha``: -1 for an ordinary lens, where a larger alpha focuses nearer.

    Returns
    -------
    UserCalibration

    Raises
    ------
    ParameterError
        Too few particles, a tilt out of range, or a layer showing no depth gradient.
    """
    x_px = np.asarray(x_px, dtype=np.float64)
    y_px = np.asarray(y_px, dtype=np.float64)
    alpha = np.asarray(alpha, dtype=np.float64)
    if x_px.size < 3:
        raise ParameterError(f"a plane needs at least 3 particles, got {x_px.size}")
    if not 0 < tilt_deg < 90:
        raise ParameterError(f"tilt_deg must be between 0 and 90 degrees, got {tilt_deg}")
    if depth_sign not in (-1, 1, -1.0, 1.0):
        raise ParameterError(f"depth_sign must be -1 or +1, got {depth_sign}")
    design = np.column_stack([np.ones_like(x_px), x_px, y_px])
    (_, b, c), *_ = np.linalg.lstsq(design, alpha, rcond=None)
    gradient = math.hypot(b, c)
    extent = max(float(np.ptp(x_px)), float(np.ptp(y_px)))
    if not gradient * extent > 1e-9:  # alpha changes by less than rounding across the layer
        raise ParameterError("the particles show no depth gradient across the image; is the layer tilted?")
    depth_per_alpha = depth_sign * math.tan(math.radians(tilt_deg)) * pixel_size_mm / gradient
    return UserCalibration(pixel_size_mm=pixel_size_mm, depth_per_alpha_mm=depth_per_alpha,
                           reference_alpha=reference_alpha, reference_z_mm=reference_z_mm)


@dataclass(frozen=True)
class PlaneReport:
    """How well a particle layer fits a plane (the paper's flat-layer check).

    Attributes
    ----------
    normal : tuple of 3 floats
        Unit normal of the best plane (total least squares), pointing toward the camera's ``+Z``.
    tilt_deg : float
        Angle between the plane and the image plane (between the normal and the optical axis).
    rms_mm : float
        RMS distance of the particles from the plane.
    nn_mean_mm : float
        Mean 3D nearest-neighbour distance.
    rms_over_nn : float
        ``rms_mm / nn_mean_mm``; the paper reached about 0.07.
    n_particles : int
    """

    normal: tuple[float, float, float]
    tilt_deg: float
    rms_mm: float
    nn_mean_mm: float
    rms_over_nn: float
    n_particles: int

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def validate_plane(x_mm: np.ndarray, y_mm: np.ndarray, z_mm: np.ndarray) -> PlaneReport:
    """Fit a plane to 3D particle positions and report tilt and depth scatter.

    Parameters
    ----------
    x_mm, y_mm, z_mm : ndarray of shape (n,), n >= 4

    Returns
    -------
    PlaneReport

    Raises
    ------
    ParameterError
        With fewer than 4 particles.

    Examples
    --------
    >>> g = np.arange(6.0)
    >>> X, Y = [a.ravel() for a in np.meshgrid(g, g)]
    >>> r = validate_plane(X, Y, 100 + np.tan(np.radians(13)) * Y)
    >>> round(r.tilt_deg, 6), round(r.rms_mm, 9)
    (13.0, 0.0)
    """
    pts = np.column_stack([np.asarray(x_mm, float), np.asarray(y_mm, float), np.asarray(z_mm, float)])
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    n = pts.shape[0]
    if n < 4:
        raise ParameterError(f"a plane check needs at least 4 particles, got {n}")
    centred = pts - pts.mean(axis=0)
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    normal = vt[2] if vt[2, 2] >= 0 else -vt[2]
    distance = centred @ normal
    rms = float(np.sqrt(np.mean(distance**2)))
    nn, _ = cKDTree(pts).query(pts, k=2)
    nn_mean = float(np.mean(nn[:, 1]))
    tilt = math.degrees(math.acos(min(1.0, abs(float(normal[2])))))
    return PlaneReport(normal=(float(normal[0]), float(normal[1]), float(normal[2])), tilt_deg=tilt, rms_mm=rms,
                       nn_mean_mm=nn_mean, rms_over_nn=rms / nn_mean if nn_mean > 0 else math.nan,
                       n_particles=n)
