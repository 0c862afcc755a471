"""The realistic camera's own effects, resolved for one camera (its serial) and one lens geometry.

`CameraEffects` turns the camera's part of a `Realism` (blur, micro-image response, lens
transmission, second stop, sensor defects, lattice drift) into what the renderer needs. Fixed
patterns of the camera (the transmission of each micro-lens, the hot and dead pixels) are drawn
from the camera serial, never from the scene's seed, so every frame of one camera shows the same
ones, and a sensor crop shows the full sensor's pattern where it lies (crops are centred).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np

from analysis.camera.model import CameraModel, Lattice
from analysis.camera.second_stop import SecondStop
from analysis.errors import ParameterError
from .camera import DEFAULT_LENS, F01_SIZE
from .realism import Realism

#: Angle (rad) between the chief ray and the marginal ray of a micro-image for the picture's lens:
#: ``atan(D / 2P)``; ``Realism.rim_response`` is the pixel response at this angle.
REFERENCE_RIM_ANGLE_RAD = math.atan(0.5 / DEFAULT_LENS.image_f_number)

# Lens indices of the transmission table: the full F01 sensor holds about -170 ... 170 (i) by
# -200 ... 200 (j) lenses about the optical axis.
_TABLE_HALF = 256


def serial_seed(serial: str, purpose: str) -> int:
    """A stable 64-bit seed from a camera serial and what it seeds (same on every platform)."""
    digest = hashlib.sha256(f"{serial}/{purpose}".encode()).digest()
    return int.from_bytes(digest[:8], "little")


def second_stop_from_field(model: CameraModel, *, corner_cut: float, onset: float) -> SecondStop:
    """The stop that starts to cut the aperture at ``onset`` of the sensor's half-diagonal and cuts
    ``corner_cut`` of its diameter at the corner, for ``model``'s optics."""
    optics = model.optics
    if optics.exit_pupil_m is None:
        raise ParameterError("vignetting by a second stop needs a finite lens-to-MLA distance; build the "
                             "model from simulated_camera_metadata()")
    half_diagonal_m = math.hypot(F01_SIZE, F01_SIZE) / 2 * optics.pixel_pitch_m / optics.projection_factor
    aperture_r = optics.aperture_diameter_m / 2
    k = corner_cut * optics.aperture_diameter_m / (half_diagonal_m * (1.0 - onset))
    return SecondStop(shift_per_m=k, radius_m=aperture_r + k * onset * half_diagonal_m)


@dataclass(frozen=True)
class SensorDefects:
    """Hot, stuck and dead pixels of one sensor, in full-sensor coordinates.

    ``kind`` 0: hot (``level_dn`` added to the read-out value), 1: stuck at the white level,
    2: dead (reads the black level).
    """

    rows: np.ndarray
    cols: np.ndarray
    kind: np.ndarray
    level_dn: np.ndarray

    HOT = 0
    STUCK = 1
    DEAD = 2

    @classmethod
    def draw(cls, serial: str, *, hot_fraction: float, dead_fraction: float) -> "SensorDefects":
        """The defects of camera ``serial``: about 70 % warm (20 ... 600 DN), 20 % hot (600 ...
        4000 DN), 10 % stuck among the hot ones, and the dead ones."""
        rng = np.random.default_rng(serial_seed(serial, "sensor-defects"))
        n_pixels = F01_SIZE * F01_SIZE
        n_hot = int(round(hot_fraction * n_pixels))
        n_dead = int(round(dead_fraction * n_pixels))
        where = rng.choice(n_pixels, size=n_hot + n_dead, replace=False)
        kind = np.full(where.size, cls.DEAD, dtype=np.int8)
        level = np.zeros(where.size)
        roll = rng.random(n_hot)
        kind[:n_hot] = np.where(roll < 0.1, cls.STUCK, cls.HOT)
        warm = roll < 0.8
        level[:n_hot] = np.where(warm, np.exp(rng.uniform(math.log(20), math.log(600), n_hot)),
                                 np.exp(rng.uniform(math.log(600), math.log(4000), n_hot)))
        rows, cols = np.divmod(where, F01_SIZE)
        return cls(rows=rows, cols=cols, kind=kind, level_dn=np.rint(level))

    def on_crop(self, width: int, height: int) -> "SensorDefects":
        """The defects on a centred ``width`` x ``height`` crop, in its coordinates."""
        r0 = (F01_SIZE - height) // 2
        c0 = (F01_SIZE - width) // 2
        keep = (self.rows >= r0) & (self.rows < r0 + height) & (self.cols >= c0) & (self.cols < c0 + width)
        return SensorDefects(self.rows[keep] - r0, self.cols[keep] - c0, self.kind[keep], self.level_dn[keep])

    def apply(self, raw: np.ndarray, *, black: float, white: float) -> np.ndarray:
        """A copy of the read-out ``raw`` (uint16, full sensor or a centred crop) with the defects."""
        height, width = raw.shape
        on = self.on_crop(width, height)
        out = raw.copy()
        values = out[on.rows, on.cols].astype(np.int64)
        values = np.where(on.kind == self.HOT, np.minimum(values + on.level_dn.astype(np.int64), int(white)), values)
        values = np.where(on.kind == self.STUCK, int(white), values)
        values = np.where(on.kind == self.DEAD, int(black), values)
        out[on.rows, on.cols] = values.astype(np.uint16)
        return out


@dataclass(frozen=True)
class LensTransmission:
    """Transmission of each micro-lens ``(i, j)`` (1 on average), indices about the optical axis."""

    gain: np.ndarray
    i0: int
    j0: int

    @classmethod
    def draw(cls, serial: str, *, spread: float) -> "LensTransmission":
        rng = np.random.default_rng(serial_seed(serial, "lens-transmission"))
        size = 2 * _TABLE_HALF
        gain = 1.0 + spread * np.clip(rng.standard_normal((size, size)), -4.0, 4.0)
        return cls(gain=gain, i0=-_TABLE_HALF, j0=-_TABLE_HALF)

    def __call__(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Transmission of lenses ``(i, j)`` (1 outside the table)."""
        gi = np.asarray(i) - self.i0
        gj = np.asarray(j) - self.j0
        h, w = self.gain.shape
        inside = (gi >= 0) & (gi < w) & (gj >= 0) & (gj < h)
        return np.where(inside, self.gain[np.clip(gj, 0, h - 1), np.clip(gi, 0, w - 1)], 1.0)


@dataclass(frozen=True)
class CameraEffects:
    """What the realistic camera does to light, for one serial (build with :meth:`build`).

    Attributes
    ----------
    blur_px : float
        Sigma of the Gaussian point spread on the sensor, px.
    psf_halo, psf_halo_px : float
        Fraction of the point spread's light in a wider Gaussian halo, and its sigma (px).
    half_n : float
        Half the exponent ``n`` of the pixel response ``cos(theta)^n`` (0: flat).
    transmission : LensTransmission or None
    vignetting_corner_cut, vignetting_onset : float
        The second stop (`second_stop_from_field`); no stop when the cut is 0.
    defects : SensorDefects or None
    drift_px : tuple of float
        Shift of the lattice in exposures relative to the white images.
    drift_rad : float
        Rotation of the lattice in exposures relative to the white images.
    """

    blur_px: float
    psf_halo: float = 0.0
    psf_halo_px: float = 3.0
    half_n: float = 0.0
    transmission: LensTransmission | None = None
    vignetting_corner_cut: float = 0.0
    vignetting_onset: float = 0.5
    defects: SensorDefects | None = None
    drift_px: tuple[float, float] = (0.0, 0.0)
    drift_rad: float = 0.0

    @classmethod
    def build(cls, realism: Realism, *, serial: str) -> "CameraEffects":
        """Resolve the camera's part of ``realism`` for the camera ``serial``."""
        half_n = 0.0
        if realism.rim_response < 1.0:
            half_n = 0.5 * math.log(realism.rim_response) / math.log(math.cos(REFERENCE_RIM_ANGLE_RAD))
        transmission = (LensTransmission.draw(serial, spread=realism.lens_transmission_spread)
                        if realism.lens_transmission_spread > 0 else None)
        defects = None
        if realism.hot_pixel_fraction > 0 or realism.dead_pixel_fraction > 0:
            defects = SensorDefects.draw(serial, hot_fraction=realism.hot_pixel_fraction,
                                         dead_fraction=realism.dead_pixel_fraction)
        return cls(blur_px=realism.blur_px, psf_halo=realism.psf_halo, psf_halo_px=realism.psf_halo_px,
                   half_n=half_n, transmission=transmission,
                   vignetting_corner_cut=realism.vignetting_corner_cut, vignetting_onset=realism.vignetting_onset,
                   defects=defects, drift_px=realism.lattice_drift_px, drift_rad=realism.lattice_drift_rad)

    def second_stop(self, model: CameraModel) -> SecondStop | None:
        """The second stop for ``model``'s optics, or None."""
        if self.vignetting_corner_cut <= 0:
            return None
        return second_stop_from_field(model, corner_cut=self.vignetting_corner_cut, onset=self.vignetting_onset)

    def lens_gain(self, i: np.ndarray, j: np.ndarray) -> np.ndarray:
        """Transmission of lenses ``(i, j)``; ones without a transmission spread."""
        if self.transmission is None:
            return np.ones(np.broadcast(np.asarray(i), np.asarray(j)).shape)
        return self.transmission(i, j)

    def pixel_response(self, offset_px: np.ndarray, model: CameraModel) -> np.ndarray:
        """Response of pixels ``offset_px`` (distance from their micro-image centre) under ``model``."""
        if self.half_n == 0.0:
            return np.ones_like(np.asarray(offset_px, dtype=np.float64))
        t = model.optics.pixel_pitch_m / model.optics.mla_to_sensor_m
        return (1.0 + (np.asarray(offset_px, dtype=np.float64) * t) ** 2) ** (-self.half_n)

    def exposure_lattice(self, lattice: Lattice) -> Lattice:
        """The lattice of an exposure: the white images' one, shifted and turned by the drift."""
        if self.drift_px == (0.0, 0.0) and self.drift_rad == 0.0:
            return lattice
        return lattice.with_changes(origin_x=lattice.origin_x + self.drift_px[0],
                                    origin_y=lattice.origin_y + self.drift_px[1],
                                    rotation_rad=lattice.rotation_rad + self.drift_rad)

    def with_defects(self, raw: np.ndarray, model: CameraModel) -> np.ndarray:
        """The read-out ``raw`` with the sensor's defects (unchanged without any)."""
        if self.defects is None:
            return raw
        return self.defects.apply(raw, black=model.black_level, white=model.white_level)
