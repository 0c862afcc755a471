"""The regular output image grid of refocused images, in lens-plane metres.

Refocused images (:mod:`analysis.lightfield.refocus`) all share one magnification (the shift-only form of
Ng's refocus), so one grid maps every slice's pixels to positions on the micro-lens-array plane,
measured in metres from the optical axis in the upright frame of docs/camera-model.md.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ImageGrid:
    """A regular grid of output pixels on the lens plane.

    Pixel convention: **integer coordinates are pixel centres.** Output pixel ``(col, row)``
    (``image[row, col]``) is centred on lens-plane position
    ``(x0_m + col * step_m, y0_m + row * step_m)``; it covers ``[col - 0.5, col + 0.5)``.
    ``x`` grows to the right and ``y`` down, as in the upright sensor readout.

    Attributes
    ----------
    width, height : int
        Output image size in pixels.
    x0_m, y0_m : float
        Lens-plane position (m, from the optical axis) of the centre of output pixel (0, 0).
    step_m : float
        Output pixel size in lens-plane metres.
    """

    width: int
    height: int
    x0_m: float
    y0_m: float
    step_m: float

    @property
    def shape(self) -> tuple[int, int]:
        """``(height, width)``, the shape of one image on this grid."""
        return (self.height, self.width)

    def to_lens_plane(self, col: np.ndarray | float, row: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Lens-plane position ``(sx, sy)`` in metres of continuous pixel coordinates ``(col, row)``."""
        col = np.asarray(col, dtype=np.float64)
        row = np.asarray(row, dtype=np.float64)
        return self.x0_m + col * self.step_m, self.y0_m + row * self.step_m

    def to_pixels(self, sx_m: np.ndarray | float, sy_m: np.ndarray | float) -> tuple[np.ndarray, np.ndarray]:
        """Continuous pixel coordinates ``(col, row)`` of lens-plane positions ``(sx_m, sy_m)`` (m)."""
        sx_m = np.asarray(sx_m, dtype=np.float64)
        sy_m = np.asarray(sy_m, dtype=np.float64)
        return (sx_m - self.x0_m) / self.step_m, (sy_m - self.y0_m) / self.step_m

    def scaled(self, factor: float) -> "ImageGrid":
        """The same area with pixels ``factor`` times smaller (``factor=2``: twice as many per axis)."""
        if factor <= 0:
            raise ValueError(f"grid scale factor must be positive, got {factor}")
        step = self.step_m / factor
        # Keep the covered area: the outer pixel edges stay where they were.
        left = self.x0_m - 0.5 * self.step_m
        top = self.y0_m - 0.5 * self.step_m
        width = int(round(self.width * factor))
        height = int(round(self.height * factor))
        return ImageGrid(width=width, height=height, x0_m=left + 0.5 * step, y0_m=top + 0.5 * step, step_m=step)
