"""The one geometry plenodust shares: micro-lens lattice and thin main lens (docs/camera-model.md).

Everything here is derived from the frame metadata JSON of an F01 picture (the camera's ``.TXT``,
or the ``metadataRef`` section of an ``.lfp``). The micro-image lattice built from the metadata is
only a seed: :mod:`analysis.calibration.calibrate` fits the real one to a white image and returns a
:class:`Lattice` of the same form.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Mapping

import numpy as np

from analysis.errors import MetadataError

SQRT3 = math.sqrt(3.0)

#: Sigma (px) of the small Gaussian blur the model gives the sensor image (camera-model.md, "How a
#: ray reaches the sensor", step 4): what the depth fit assumes when no white image says otherwise.
IDEAL_POINT_SPREAD_PX = 0.5

# An exit-pupil distance beyond this (one firmware writes 10000 m) means "telecentric".
_MAX_EXIT_PUPIL_M = 10.0


@dataclass(frozen=True)
class Lattice:
    """Hexagonal lattice of micro-image centres on the sensor, in pixels.

    Lens ``(i, j)`` has its micro-image centre at
    ``origin + R(rotation) @ (i*dX + j*dY/sqrt(3), j*dY)`` with ``dX = pitch*scale_x`` and
    ``dY = pitch*scale_y*sqrt(3)/2`` (row-major hexagonal tiling, each next row half a pitch
    further right). ``origin`` is the centre of lens ``(0, 0)``, where the optical axis meets
    the sensor.
    """

    origin_x: float
    origin_y: float
    pitch_px: float
    rotation_rad: float = 0.0
    scale_x: float = 1.0
    scale_y: float = 1.0

    @property
    def basis(self) -> np.ndarray:
        """ndarray of shape (2, 2): columns are the sensor-pixel steps for ``i + 1`` and ``j + 1``."""
        dx = self.pitch_px * self.scale_x
        dy = self.pitch_px * self.scale_y * SQRT3 / 2
        c, s = math.cos(self.rotation_rad), math.sin(self.rotation_rad)
        rot = np.array([[c, -s], [s, c]])
        return rot @ np.array([[dx, dy / SQRT3], [0.0, dy]])

    @property
    def origin(self) -> np.ndarray:
        return np.array([self.origin_x, self.origin_y])

    def centre(self, i: np.ndarray | float, j: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Micro-image centre ``(x, y)`` in pixels of lens ``(i, j)`` (broadcasts)."""
        b = self.basis
        i = np.asarray(i, dtype=np.float64)
        j = np.asarray(j, dtype=np.float64)
        return (self.origin_x + b[0, 0] * i + b[0, 1] * j,
                self.origin_y + b[1, 0] * i + b[1, 1] * j)

    def fractional_index(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Continuous lattice coordinates ``(i, j)`` of sensor points ``(x, y)``."""
        inv = np.linalg.inv(self.basis)
        dx = np.asarray(x, dtype=np.float64) - self.origin_x
        dy = np.asarray(y, dtype=np.float64) - self.origin_y
        return inv[0, 0] * dx + inv[0, 1] * dy, inv[1, 0] * dx + inv[1, 1] * dy

    def nearest(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Integer index ``(i, j)`` of the lens whose centre is nearest to each ``(x, y)``.

        The nearest hex site is one of the four corners of the lattice cell that contains the
        point, so all four are tried.
        """
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        fi, fj = self.fractional_index(x, y)
        i0, j0 = np.floor(fi), np.floor(fj)
        best_i, best_j = i0.copy(), j0.copy()
        best_d = np.full(np.broadcast(x, y).shape, np.inf)
        for di in (0.0, 1.0):
            for dj in (0.0, 1.0):
                cx, cy = self.centre(i0 + di, j0 + dj)
                d = (cx - x) ** 2 + (cy - y) ** 2
                closer = d < best_d
                best_d = np.where(closer, d, best_d)
                best_i = np.where(closer, i0 + di, best_i)
                best_j = np.where(closer, j0 + dj, best_j)
        return best_i.astype(np.int64), best_j.astype(np.int64)

    def lens_indices(self, width: int, height: int, *, margin_px: float = 0.0) -> np.ndarray:
        """All lenses whose centre lies on the sensor, at least ``margin_px`` from its edges.

        Returns
        -------
        ndarray of shape (N, 2), int64, columns ``(i, j)``, row-major (by ``j``, then ``i``).
        """
        corners_x = np.array([0.0, width, 0.0, width])
        corners_y = np.array([0.0, 0.0, height, height])
        fi, fj = self.fractional_index(corners_x, corners_y)
        i_range = np.arange(math.floor(fi.min()) - 1, math.ceil(fi.max()) + 2)
        j_range = np.arange(math.floor(fj.min()) - 1, math.ceil(fj.max()) + 2)
        jj, ii = np.meshgrid(j_range, i_range, indexing="ij")
        cx, cy = self.centre(ii, jj)
        keep = ((cx >= margin_px) & (cx < width - margin_px)
                & (cy >= margin_px) & (cy < height - margin_px))
        return np.stack([ii[keep], jj[keep]], axis=1).astype(np.int64)

    def centres(self, width: int, height: int, *, margin_px: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Indices (N, 2) and micro-image centres (N, 2) in pixels of every lens on the sensor."""
        ij = self.lens_indices(width, height, margin_px=margin_px)
        cx, cy = self.centre(ij[:, 0], ij[:, 1])
        return ij, np.stack([cx, cy], axis=1)

    def with_changes(self, **changes: float) -> "Lattice":
        return replace(self, **changes)


@dataclass(frozen=True)
class Optics:
    """Thin main lens in front of a micro-lens array (docs/camera-model.md, "Main lens").

    Lengths in metres. ``exit_pupil_m`` is ``P``, the lens-to-MLA distance; ``None`` means
    telecentric micro-images (metadata absent, zero or absurd).
    """

    focal_length_m: float
    f_number: float
    exit_pupil_m: float | None
    mla_to_sensor_m: float
    pixel_pitch_m: float
    lens_pitch_m: float

    @property
    def telecentric(self) -> bool:
        return self.exit_pupil_m is None

    @property
    def aperture_diameter_m(self) -> float:
        return self.focal_length_m / self.f_number

    @property
    def projection_factor(self) -> float:
        """``(P + d) / P``: micro-image centres are lens centres scaled by this from the axis."""
        if self.exit_pupil_m is None:
            return 1.0
        return (self.exit_pupil_m + self.mla_to_sensor_m) / self.exit_pupil_m

    @property
    def micro_image_pitch_px(self) -> float:
        return self.lens_pitch_m * self.projection_factor / self.pixel_pitch_m

    @property
    def micro_image_radius_px(self) -> float:
        """Radius of the aperture's image behind each micro-lens, ``(D/2) d / P``, in pixels.

        For telecentric metadata the aperture is taken to fill the micro-image (half a pitch).
        """
        if self.exit_pupil_m is None:
            return 0.5 * self.micro_image_pitch_px
        return 0.5 * self.aperture_diameter_m * self.mla_to_sensor_m / self.exit_pupil_m / self.pixel_pitch_m

    @property
    def aperture_m_per_px(self) -> float:
        """Main-lens aperture metres per sensor pixel of offset from a micro-image centre.

        The paper's ``u = beta * dx``: ``beta = P / d`` times the pixel pitch. With telecentric
        metadata, the micro-image radius is mapped onto the aperture radius instead.
        """
        if self.exit_pupil_m is None:
            return 0.5 * self.aperture_diameter_m / self.micro_image_radius_px
        return self.exit_pupil_m / self.mla_to_sensor_m * self.pixel_pitch_m

    def _require_finite_p(self) -> float:
        if self.exit_pupil_m is None:
            raise MetadataError(
                "the metadata gives no usable exit-pupil distance (devices.lens.exitPupilOffset.z), "
                "so the thin-lens depth model is undefined; supply a user calibration "
                "(pixel size and depth per unit alpha) instead")
        return self.exit_pupil_m

    @property
    def focus_distance_mm(self) -> float:
        """``Z0``: object distance in focus on the MLA, ``1 / (1/f - 1/P)``, in mm."""
        return self.z_of_alpha(1.0)

    def z_of_alpha(self, alpha: np.ndarray | float) -> np.ndarray | float:
        """Object distance in mm in focus at refocus parameter ``alpha``: ``1/(1/f - 1/(alpha P))``."""
        p = self._require_finite_p()
        alpha = np.asarray(alpha, dtype=np.float64)
        z = 1.0 / (1.0 / self.focal_length_m - 1.0 / (alpha * p)) * 1e3
        return z if z.ndim else float(z)

    def alpha_of_z(self, z_mm: np.ndarray | float) -> np.ndarray | float:
        """Refocus parameter that brings object distance ``z_mm`` into focus (inverse of `z_of_alpha`)."""
        p = self._require_finite_p()
        image_m = self.image_distance_m(z_mm)
        return image_m / p

    def image_distance_m(self, z_mm: np.ndarray | float) -> np.ndarray | float:
        """``Fp = 1 / (1/f - 1/Z)``: where a point at depth ``z_mm`` images behind the lens."""
        z_m = np.asarray(z_mm, dtype=np.float64) * 1e-3
        fp = 1.0 / (1.0 / self.focal_length_m - 1.0 / z_m)
        return fp if fp.ndim else float(fp)


@dataclass(frozen=True)
class CameraModel:
    """Sensor, micro-lens lattice and main lens of one exposure (or one white image)."""

    width: int
    height: int
    lattice: Lattice
    optics: Optics
    black_level: float = 168.0
    white_level: float = 4095.0
    zoom_step: int | None = None
    focus_step: int | None = None

    @classmethod
    def from_metadata(cls, metadata: Mapping[str, Any]) -> "CameraModel":
        """Build the model from F01 frame metadata (``image``, ``devices``, ... at top level).

        Raises
        ------
        MetadataError
            If a required field is missing or not a number, naming the field.
        """
        def get(path: str, default: Any = _REQUIRED) -> Any:
            node: Any = metadata
            for key in path.split("."):
                if not isinstance(node, Mapping) or key not in node:
                    if default is _REQUIRED:
                        raise MetadataError(f"frame metadata lacks '{path}'; is this an F01 picture's metadata?")
                    return default
                node = node[key]
            return node

        def num(path: str, default: Any = _REQUIRED) -> float:
            value = get(path, default)
            if value is None:
                return None  # type: ignore[return-value]
            try:
                return float(value)
            except (TypeError, ValueError):
                raise MetadataError(f"frame metadata field '{path}' is {value!r}, not a number") from None

        tiling = get("devices.mla.tiling", "hexUniformRowMajor")
        if tiling != "hexUniformRowMajor":
            raise MetadataError(f"micro-lens tiling '{tiling}' is not supported (only hexUniformRowMajor, the F01's)")
        width = int(num("image.width"))
        height = int(num("image.height"))
        p = num("devices.sensor.pixelPitch")
        d = num("devices.mla.sensorOffset.z")
        exit_pupil = num("devices.lens.exitPupilOffset.z", None)
        if exit_pupil is not None and not (0.0 < exit_pupil <= _MAX_EXIT_PUPIL_M):
            exit_pupil = None
        optics = Optics(
            focal_length_m=num("devices.lens.focalLength"),
            f_number=num("devices.lens.fNumber"),
            exit_pupil_m=exit_pupil,
            mla_to_sensor_m=d,
            pixel_pitch_m=p,
            lens_pitch_m=num("devices.mla.lensPitch"),
        )
        lattice = Lattice(
            # camera-model.md: plenodust adds sensorOffset; a fitted white image overrides it.
            origin_x=width / 2 + num("devices.mla.sensorOffset.x") / p,
            origin_y=height / 2 + num("devices.mla.sensorOffset.y") / p,
            pitch_px=optics.micro_image_pitch_px,
            rotation_rad=num("devices.mla.rotation"),
            scale_x=num("devices.mla.scaleFactor.x", 1.0),
            scale_y=num("devices.mla.scaleFactor.y", 1.0),
        )
        fmt = get("image.rawDetails.pixelFormat", {})
        black = _channel_level(fmt.get("black"), 168.0)
        white = _channel_level(fmt.get("white"), 4095.0)
        zoom = get("devices.lens.zoomStep", None)
        focus = get("devices.lens.focusStep", None)
        return cls(width=width, height=height, lattice=lattice, optics=optics,
                   black_level=black, white_level=white,
                   zoom_step=None if zoom is None else int(zoom),
                   focus_step=None if focus is None else int(focus))

    def with_lattice(self, lattice: Lattice) -> "CameraModel":
        return replace(self, lattice=lattice)

    def micro_image_offsets(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """For sensor points, the nearest lens ``(i, j)`` and the offset ``(dx, dy)`` in pixels
        from that lens's micro-image centre."""
        i, j = self.lattice.nearest(x, y)
        cx, cy = self.lattice.centre(i, j)
        return i, j, np.asarray(x) - cx, np.asarray(y) - cy

    def aperture_coordinates(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Main-lens aperture point ``(u, v)`` in metres seen by sensor points ``(x, y)`` (pixels).

        Each micro-lens images the aperture inverted, so ``(u, v) = -offset * P / d``
        (camera-model.md, the paper's LOT).
        """
        _, _, dx, dy = self.micro_image_offsets(x, y)
        k = self.optics.aperture_m_per_px
        return -dx * k, -dy * k

    def lens_plane_position_m(self, i: np.ndarray, j: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Physical centre ``(s, t)`` in metres on the MLA plane of lens ``(i, j)``, from the optical axis.

        Micro-image centres are physical centres scaled by ``(P + d)/P`` away from the axis.
        """
        cx, cy = self.lattice.centre(i, j)
        k = self.optics.pixel_pitch_m / self.optics.projection_factor
        return (cx - self.lattice.origin_x) * k, (cy - self.lattice.origin_y) * k


_REQUIRED = object()


def _channel_level(levels: Any, default: float) -> float:
    """The green level of a per-channel dict (the laser lights green), or a single number."""
    if levels is None:
        return default
    if isinstance(levels, Mapping):
        for key in ("gr", "gb", "g"):
            if key in levels:
                return float(levels[key])
        return float(next(iter(levels.values())))
    return float(levels)


def green_mask(height: int, width: int) -> np.ndarray:
    """Boolean mask of the green sites of the F01's BGGR mosaic (``(r + c)`` odd)."""
    rows = np.arange(height)[:, None]
    cols = np.arange(width)[None, :]
    return ((rows + cols) % 2) == 1
